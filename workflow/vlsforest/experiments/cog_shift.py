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

__all__ = ["PREDICTED", "carried_returns", "run_cog_shift", "surface_displacement"]

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
    from scipy.spatial import cKDTree

    xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
    margin_m = 0.5 * base.size if margin_m is None else margin_m
    moved, on = xyz.copy(), np.zeros(len(xyz), bool)
    if base.n_voxels == 0 or len(xyz) == 0:
        return moved, on
    c0 = base.centres()
    dist, idx = cKDTree(c0).query(xyz, p=np.inf)
    on = dist <= 0.5 * base.sides()[idx] + margin_m
    moved[on] += (shifted.centres() - c0)[idx[on]]
    return moved, on


def surface_displacement(base: VoxelModel, shifted: VoxelModel) -> tuple[float, float]:
    """Mean vertical displacement (m) of the top cube of each column, and of all cubes."""
    if base.n_voxels == 0:
        return math.nan, math.nan
    dz = shifted.centres()[:, 2] - base.centres()[:, 2]
    order = np.lexsort((base.ijk[:, 2], base.ijk[:, 1], base.ijk[:, 0]))
    ij = base.ijk[order, :2]
    last = np.r_[np.any(ij[1:] != ij[:-1], axis=1), True]  # the highest cell of each (i, j) column
    return float(dz[order[last]].mean()), float(dz.mean())


def _same_cells(base: VoxelModel, shifted: VoxelModel, names) -> None:
    if not (np.array_equal(base.ijk, shifted.ijk) and np.array_equal(base.owner, shifted.owner)
            and np.allclose(base.sides(), shifted.sides(), rtol=0, atol=1e-9)):
        raise ConfigError(f"CoG shift: the {names[0]} and {names[1]} models do not hold the same cells and cubes")


def run_cog_shift(manifest, base: str, shifted: str, scenarios, *, margin_m: float | None = None,
                  option: str = "--inputs-json", progress=None) -> dict:
    """Each target tree's predicted and simulated change under the CoG shift, per scenario.

    Parameters
    ----------
    manifest : mapping
        The run's files by plot (:mod:`vlsforest.experiments.run_outputs`): each plot's
        ``targets``, both methods' ``voxels`` and ``metrics`` by scenario and the ``base``
        method's ``trees`` by scenario.
    base, shifted : str
        The unshifted scaled method and its CoG-shift variant.
    scenarios : sequence of str
        The scenarios.
    margin_m : float, optional
        See :func:`carried_returns` (default: half the models' cell).
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
        change)); ``surface`` and ``all_cubes`` (mean, se, n over the trees of the mean vertical
        displacement of the columns' top cubes and of all cubes, m); ``on_cubes`` (scenario → mean,
        se, n over the trees of the share of returns from a cube); ``trees`` (plot, tree id,
        group, the displacements, per scenario the share of returns from a cube and the predicted
        and simulated change of each metric).

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
            clouds[sc] = read_las(method_files(plot, entry, base, "trees", sc, option), require=("tree_id",),
                                  allow_empty=True)
        for t in trees:
            mine = models[0].owner == t.segment_id
            b, s = models[0].subset(mine), models[1].subset(mine)
            top, everywhere = surface_displacement(b, s)
            row = {"plot": plot, "tree_id": t.target_id, "group": t.group, "n_cubes": int(b.n_voxels),
                   "surface_dz_m": top, "all_cubes_dz_m": everywhere, "scenarios": {}}
            for sc in scenarios:
                xyz = cloud_points(clouds[sc], t.target_id)
                moved, on = carried_returns(xyz, b, s, margin_m)
                rec = {"n_returns": int(len(xyz)), "on_cubes": float(on.mean()) if len(on) else math.nan,
                       "predicted": {}, "simulated": {}}
                if len(xyz):
                    before = tree_metrics(xyz, ground_z=t.ground_z)
                    after = tree_metrics(moved, ground_z=t.ground_z)
                    rec["predicted"] = {k: float(after[k] - before[k]) for k in PREDICTED}
                else:
                    rec["predicted"] = dict.fromkeys(PREDICTED, math.nan)
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
            summary[sc][k] = v
    return {"experiment": "cog_shift", "base": base, "shifted": shifted, "scenarios": scenarios,
            "margin_m": float(margin_m) if margin_m is not None else (0.5 * cell if cell else None),
            "cell_m": cell, "plots": list(plots),
            "method": ("per target tree and scenario: the unshifted model's simulated returns carried along with "
                       "the cubes they come from (nearest cube centre in the maximum norm, within margin_m of the "
                       "cube) to the CoG-shifted cubes; predicted change = metric of the carried returns − "
                       "metric of the returns; simulated change = the run's metrics, shifted − unshifted"),
            "summary": summary,
            "surface": mean_se([r["surface_dz_m"] for r in rows]),
            "all_cubes": mean_se([r["all_cubes_dz_m"] for r in rows]),
            "on_cubes": {sc: mean_se([r["scenarios"][sc]["on_cubes"] for r in rows]) for sc in scenarios},
            "trees": rows}
