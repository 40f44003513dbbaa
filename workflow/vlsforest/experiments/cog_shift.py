"""Experiment: what the centre-of-gravity shift does to the cubes the returns come from.

The study finds that moving each scaled cube to the centre of gravity of its cell's TLS points
lowers Hmean, the multiple-return share, the tree height and the CPA slightly. The shift moves
a cube towards its cell's centre of gravity, within the room the cell leaves
(:func:`vlsforest.voxels.shift_cubes`); a simulated height or area changes through the cubes
the returns come from: Hmean and the height fall where those cubes move down, the CPA where
the outermost ones move in. The proposed cause of a metric that does not fall is that the cubes
its returns lie on do not move that way. This experiment tests it on a finished run, per target
tree and scenario, to first order: each return of the unshifted model's simulation is carried
along with the cube it comes from (the cube whose centre is nearest in the maximum norm, when the
return lies within ``margin_m`` of that cube, by default half a cell: the beam's footprint and
the range noise place a return off the surface that made it) by that cube's displacement in the
shifted model; returns far from every cube (stem, ground) stay. The
*predicted change* of a metric is its value on the carried returns less its value on the
returns (:func:`vlsforest.metrics.tree_metrics`, the tree's ground height as in the run's
metrics); set beside it is the *simulated change*, the shifted model's metric less the
unshifted one's (the run's metrics), and their difference per tree: where it is not significant,
the simulations follow the cubes, and a simulated change whose interval still reaches zero is a
change smaller than the trees' spread resolves. The multiple-return share belongs to pulses, not
to return positions, and has no such prediction.

A simulated change that departs from the prediction comes from what the pulses reach: the
shifted model's returns, carried back the same way to where the unshifted cubes lie, hold the
shifted simulation's choice of cubes (and of faces) at the unshifted cubes' places. The
*reached change*, their metric less the unshifted returns', is the part of the simulated change
that does not come from the cubes' own displacement (the rest, simulated less reached, is the
displacement of the cubes the shifted model's returns lie on). Beside it the result gives the
share of each model's returns that lie on the top cube of their column (how many pulses end at
the crown's surface) and the area the cubes cover in vertical view (the union of their
horizontal squares, on a raster of ``pixel_m``): the shift moves the cubes of a column apart,
so that they hide one another less.

Per tree the result also gives the cubes' mean vertical displacement over all cubes and over
the top cube of each column (the crown's surface): the direction the shift moves the crown itself.
"""

from __future__ import annotations

import math

import numpy as np

from vlsforest.errors import ConfigError
from vlsforest.experiments.run_outputs import cloud_points, mean_se, method_files, plot_files, targets
from vlsforest.experiments.shift_room import line_fit
from vlsforest.io.csvfile import read_csv_table
from vlsforest.io.las import read_las
from vlsforest.io.voxel_model import VoxelModel
from vlsforest.metrics import tree_metrics

__all__ = ["PREDICTED", "carried_returns", "column_tops", "cover_area", "run_cog_shift", "surface_displacement"]

#: the metrics a change of the return positions predicts (the multiple-return share has no prediction)
PREDICTED = ("hmean", "height", "cpa")


def carried_returns(xyz: np.ndarray, base: VoxelModel, shifted: VoxelModel, margin_m: float | None = None):
    """Returns carried along with the cubes they lie on, from one model to its shifted variant.

    Parameters
    ----------
    xyz : ndarray (n, 3)
        Returns of a simulation of ``base``.
    base, shifted : VoxelModel
        The same cells and cube sizes, the cubes at different centres.
    margin_m : float, optional
        A return comes from the cube whose centre is nearest in the maximum norm when it is
        within that cube's half side plus this (m; default half the cell).

    Returns
    -------
    moved : ndarray (n, 3)
        The returns, those on a cube moved by its displacement.
    on_cube : ndarray of bool (n,)
        Which returns come from a cube.
    """
    xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
    idx, on = _return_cubes(xyz, base, margin_m)
    moved = xyz.copy()
    if on.any():
        moved[on] += (shifted.centres() - base.centres())[idx[on]]
    return moved, on


def _return_cubes(xyz: np.ndarray, model: VoxelModel, margin_m: float | None):
    """Each return's cube (nearest centre in the maximum norm) and whether it lies on it."""
    from scipy.spatial import cKDTree

    margin_m = 0.5 * model.size if margin_m is None else margin_m
    idx, on = np.zeros(len(xyz), np.int64), np.zeros(len(xyz), bool)
    if model.n_voxels == 0 or len(xyz) == 0:
        return idx, on
    dist, idx = cKDTree(model.centres()).query(xyz, p=np.inf)
    on = dist <= 0.5 * model.sides()[idx] + margin_m
    return idx, on


def column_tops(model: VoxelModel) -> np.ndarray:
    """Which cubes are the highest of their (i, j) column of cells (the crown's surface seen from above)."""
    top = np.zeros(model.n_voxels, bool)
    if model.n_voxels:
        order = np.lexsort((model.ijk[:, 2], model.ijk[:, 1], model.ijk[:, 0]))
        ij = model.ijk[order, :2]
        top[order[np.r_[np.any(ij[1:] != ij[:-1], axis=1), True]]] = True
    return top


def surface_displacement(base: VoxelModel, shifted: VoxelModel) -> tuple[float, float]:
    """Mean vertical displacement (m) of the top cube of each column, and of all cubes."""
    if base.n_voxels == 0:
        return math.nan, math.nan
    dz = shifted.centres()[:, 2] - base.centres()[:, 2]
    return float(dz[column_tops(base)].mean()), float(dz.mean())


def cover_area(model: VoxelModel, pixel_m: float | None = None) -> float:
    """Area (m²) the cubes cover in vertical view: the union of their horizontal squares.

    Counted on a raster of ``pixel_m`` (default a fiftieth of the cell): a pixel is covered when
    its centre lies inside a square, so that each square's edge is placed to half a pixel.
    """
    if model.n_voxels == 0:
        return 0.0
    pixel_m = model.size / 50.0 if pixel_m is None else float(pixel_m)
    if not (math.isfinite(pixel_m) and pixel_m > 0):
        raise ConfigError(f"CoG shift: pixel_m must be > 0, got {pixel_m!r}")
    c, h = model.centres()[:, :2], 0.5 * model.sides()
    lo = (c - h[:, None]).min(axis=0)
    # the pixels whose centre (lo + (k + 0.5)·pixel) lies in [c − h, c + h]
    first = np.ceil((c - h[:, None] - lo) / pixel_m - 0.5).astype(np.int64)
    stop = np.floor((c + h[:, None] - lo) / pixel_m - 0.5).astype(np.int64) + 1
    grid = np.zeros(tuple(np.maximum(stop.max(axis=0), 1)), bool)
    for (i0, j0), (i1, j1) in zip(first, stop):
        grid[i0:i1, j0:j1] = True
    return float(grid.sum()) * pixel_m ** 2


def _top_share(xyz: np.ndarray, model: VoxelModel, tops: np.ndarray, margin_m: float | None) -> float:
    """Share of the returns that lie on the top cube of their column (NaN without returns)."""
    if len(xyz) == 0:
        return math.nan
    idx, on = _return_cubes(np.asarray(xyz, np.float64).reshape(-1, 3), model, margin_m)
    return float((on & tops[idx]).mean()) if model.n_voxels else 0.0


def _same_cells(base: VoxelModel, shifted: VoxelModel, names) -> None:
    if not (np.array_equal(base.ijk, shifted.ijk) and np.array_equal(base.owner, shifted.owner)
            and np.allclose(base.sides(), shifted.sides(), rtol=0, atol=1e-9)):
        raise ConfigError(f"CoG shift: the {names[0]} and {names[1]} models do not hold the same cells and cubes")


def run_cog_shift(manifest, base: str, shifted: str, scenarios, *, margin_m: float | None = None,
                  pixel_m: float | None = None, option: str = "--inputs-json", progress=None) -> dict:
    """Each target tree's predicted and simulated change under the CoG shift, per scenario.

    Parameters
    ----------
    manifest : mapping
        The run's files by plot (:mod:`vlsforest.experiments.run_outputs`): each plot's
        ``targets``, both methods' ``voxels``, and ``metrics`` and ``trees`` by scenario.
    base, shifted : str
        The unshifted scaled method and its CoG-shift variant.
    scenarios : sequence of str
        The scenarios.
    margin_m : float, optional
        See :func:`carried_returns` (default: half the models' cell).
    pixel_m : float, optional
        See :func:`cover_area` (default: a fiftieth of the models' cell).
    option : str
        The name of the manifest in error messages.
    progress : callable, optional
        Called with a line of text after each plot.

    Returns
    -------
    dict
        ``base``, ``shifted``, ``scenarios``, ``margin_m``, ``cell_m``; ``summary`` (scenario →
        metric → ``simulated`` (mean, se, n of the trees' simulated changes), and for
        :data:`PREDICTED` ``predicted`` (the same of the predicted changes), ``difference`` (the
        same of each tree's simulated less predicted change) and ``fit``
        (:func:`~vlsforest.experiments.shift_room.line_fit` of the simulated on the predicted
        change), and ``reached`` (the same of the reached changes: the shifted model's returns
        carried back to the unshifted cubes, less the unshifted model's returns)); ``surface`` and
        ``all_cubes`` (mean, se, n over the trees of the mean vertical displacement of the
        columns' top cubes and of all cubes, m); ``on_cubes`` (scenario → mean, se, n over the
        trees of the share of returns from a cube); ``top_share`` (scenario → ``base``,
        ``shifted`` and ``change``: mean, se, n over the trees of the share of returns on the top
        cube of their column, and its change); ``cover`` (``base_m2``, ``shifted_m2``: mean, se,
        n over the trees of the area the cubes cover in vertical view; ``change_pct``: the same
        of its relative change, %); ``trees`` (plot, tree id, group, the displacements, the
        covered areas, per scenario the share of returns from a cube, both models' shares on
        the columns' top cubes and the predicted, reached and simulated change of each metric).

    Raises
    ------
    ConfigError
        The same method twice, no scenario, a file the manifest does not name, or models that
        do not hold the same cells and cube sizes.
    InputDataError
        A file that cannot be read or lacks a metric column (names it).
    """
    if base == shifted:
        raise ConfigError("CoG shift: the base and the shifted method must differ")
    scenarios = [str(s) for s in scenarios]
    if not scenarios:
        raise ConfigError("CoG shift: needs at least one scenario")
    if margin_m is not None and not (math.isfinite(margin_m) and margin_m >= 0):
        raise ConfigError(f"CoG shift: margin_m must be ≥ 0, got {margin_m!r}")
    if pixel_m is not None and not (math.isfinite(pixel_m) and pixel_m > 0):
        raise ConfigError(f"CoG shift: pixel_m must be > 0, got {pixel_m!r}")
    metrics = (*PREDICTED, "multi_return_pct")
    plots = plot_files(manifest, option)
    rows, cell = [], None
    for plot, entry in plots.items():
        trees = targets(plot, entry)
        models = [VoxelModel.load(method_files(plot, entry, m, "voxels", option=option)) for m in (base, shifted)]
        _same_cells(*models, (base, shifted))
        if cell is not None and models[0].size != cell:
            raise ConfigError(f"CoG shift: the {base} models have different cells ({cell} and {models[0].size} m)")
        cell = models[0].size
        tables, clouds = {}, {}
        for sc in scenarios:
            for m in (base, shifted):
                path = method_files(plot, entry, m, "metrics", sc, option)
                tables[m, sc] = read_csv_table(path, "metrics table", metrics, ids=("tree_id",)).set_index("tree_id")
                clouds[m, sc] = read_las(method_files(plot, entry, m, "trees", sc, option), require=("tree_id",),
                                         allow_empty=True)
        for t in trees:
            mine = models[0].owner == t.segment_id
            b, s = models[0].subset(mine), models[1].subset(mine)
            top, everywhere = surface_displacement(b, s)
            tops = column_tops(b)
            cover = (cover_area(b, pixel_m), cover_area(s, pixel_m))
            row = {"plot": plot, "tree_id": t.target_id, "group": t.group, "n_cubes": int(b.n_voxels),
                   "surface_dz_m": top, "all_cubes_dz_m": everywhere, "cover_m2": list(cover), "scenarios": {}}
            for sc in scenarios:
                xyz = cloud_points(clouds[base, sc], t.target_id)
                xyz_s = cloud_points(clouds[shifted, sc], t.target_id)
                moved, on = carried_returns(xyz, b, s, margin_m)
                back, _ = carried_returns(xyz_s, s, b, margin_m)
                rec = {"n_returns": int(len(xyz)), "on_cubes": float(on.mean()) if len(on) else math.nan,
                       "top_share": [_top_share(xyz, b, tops, margin_m), _top_share(xyz_s, s, tops, margin_m)],
                       "predicted": {}, "reached": {}, "simulated": {}}
                before = tree_metrics(xyz, ground_z=t.ground_z) if len(xyz) else None
                for key, pts in (("predicted", moved), ("reached", back)):
                    if before is not None and len(pts):
                        after = tree_metrics(pts, ground_z=t.ground_z)
                        rec[key] = {k: float(after[k] - before[k]) for k in PREDICTED}
                    else:
                        rec[key] = dict.fromkeys(PREDICTED, math.nan)
                a, z = tables[base, sc], tables[shifted, sc]
                rec["simulated"] = {k: (float(z.at[t.target_id, k] - a.at[t.target_id, k])
                                        if t.target_id in a.index and t.target_id in z.index else math.nan)
                                    for k in metrics}
                row["scenarios"][sc] = rec
            rows.append(row)
        if progress is not None:
            progress(f"{plot}: {len(trees)} target trees")
    summary = {}
    for sc in scenarios:
        summary[sc] = {}
        for k in metrics:
            sim = [r["scenarios"][sc]["simulated"][k] for r in rows]
            v = {"simulated": mean_se(sim)}
            if k in PREDICTED:
                pred = [r["scenarios"][sc]["predicted"][k] for r in rows]
                v["predicted"] = mean_se(pred)
                v["difference"] = mean_se(np.subtract(sim, pred))
                v["fit"] = line_fit(pred, sim)
                v["reached"] = mean_se([r["scenarios"][sc]["reached"][k] for r in rows])
            summary[sc][k] = v
    shares = {sc: np.array([r["scenarios"][sc]["top_share"] for r in rows], np.float64).reshape(-1, 2)
              for sc in scenarios}
    covers = np.array([r["cover_m2"] for r in rows], np.float64).reshape(-1, 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        cover_change = 100.0 * (covers[:, 1] / covers[:, 0] - 1.0)
    return {"experiment": "cog_shift", "base": base, "shifted": shifted, "scenarios": scenarios,
            "margin_m": float(margin_m) if margin_m is not None else (0.5 * cell if cell else None),
            "cell_m": cell, "plots": list(plots),
            "method": ("per target tree and scenario: the unshifted model's simulated returns carried along with "
                       "the cubes they come from (nearest cube centre in the maximum norm, within margin_m of the "
                       "cube) to the CoG-shifted cubes; predicted change = metric of the carried returns − "
                       "metric of the returns; simulated change = the run's metrics, shifted − unshifted; reached "
                       "change = metric of the shifted model's returns carried back the same way to the unshifted "
                       "cubes − metric of the unshifted model's returns"),
            "pixel_m": float(pixel_m) if pixel_m is not None else (cell / 50.0 if cell else None),
            "summary": summary,
            "surface": mean_se([r["surface_dz_m"] for r in rows]),
            "all_cubes": mean_se([r["all_cubes_dz_m"] for r in rows]),
            "on_cubes": {sc: mean_se([r["scenarios"][sc]["on_cubes"] for r in rows]) for sc in scenarios},
            "top_share": {sc: {"base": mean_se(v[:, 0]), "shifted": mean_se(v[:, 1]),
                               "change": mean_se(v[:, 1] - v[:, 0])} for sc, v in shares.items()},
            "cover": {"base_m2": mean_se(covers[:, 0]), "shifted_m2": mean_se(covers[:, 1]),
                      "change_pct": mean_se(cover_change)},
            "trees": rows}
