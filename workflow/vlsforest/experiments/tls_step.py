"""Experiment: how the TLS angular step sets the 0.02 m / scaled voxel ratio.

The study finds ≈ 50× more filled 0.02 m voxels than scaled cubes (one cube per filled 0.25 m
cell). Its TLS scanned at 0.017° steps; the embedded forest's TLS scans at 0.1°, a 5.9× coarser
step and so a 35× sparser cloud. A 0.02 m cell is filled by one point, so the fine count grows
with the point density long after the 0.25 m count has saturated: the step, not the voxel
method, could explain a lower ratio. This experiment tests that by scanning one plot's target
trees at several steps with everything else held fixed, and counting the filled cells.

For every target tree of the plot and every untilted scan position of the recordings
(:func:`vlsforest.synth.record.tls_positions`), the VZ-400 scans the tree's leaf-level truth
scene inside a field of view restricted to a box around the tree seen from the position
(horizontally ± the widest corner, vertically from its lowest to its highest corner, clipped to
the recordings' vertical field of view), with the recordings' TLS settings otherwise. The box is
the tree's bounding box, or, with ``band_m``, a horizontal slab of that height through the
middle of the crown (the study's step multiplies the rays 35-fold; a slab keeps the experiment
short and measures the same density effect). The tree's own returns (its object ids) inside the
box from all positions are pooled, and the cells of a 0.02 m and of a 0.25 m grid (anchored at
the origin) that hold at least one return are counted: the filled voxels of the study's fixed
0.02 m method and the cubes of its scaled methods.

The same returns also give the fixed models of other cell sizes (``cells_m``, e.g. the study's
0.10 and 0.05 m): their *fill*, the share of the 0.25 m cells' volume that the filled cells of
that size occupy (``n_h·h³ / (n_0.25·0.25³)``), says how opaque the fixed model of that size
is: 1 for the 0.25 m model itself, near 0 for a model of isolated small cubes. A finer step fills
more small cells in the same crown, so a fixed model of a given size is more opaque at the
study's step than at the embedded forest's; the fill per species group shows whether the
porosity contrast between conifers and broadleaf trees survives the finer step.

The returns in each filled 0.25 m cell also give the cell's centre of gravity, which the
study's CoG shift moves the cell's scaled cube towards (:func:`vlsforest.voxels.shift_cubes`):
its mean offset from the cell centre, vertically and radially (horizontally, away from the
tree's stem axis), says in which direction the CoG shift moves the crown at either step.

The result (:func:`run_tls_step`) is a JSON document with, per step, the returns and the filled
cells of every grid summed over the trees, the 0.02 / 0.25 m ratio, the fill per cell size and
the centre-of-gravity offset (all trees and per species group), and the same per tree.
"""

from __future__ import annotations

import math

import numpy as np

from vlsforest.domain.species import species_group
from vlsforest.errors import ConfigError
from vlsforest.sim.engine import simulate
from vlsforest.sim.survey import survey_from_dict
from vlsforest.synth.forest import generate_plot_trees, plot_layout
from vlsforest.synth.record import DEFAULT_RECORDING_PHYSICS, plot_scene, synth_settings, tls_positions, tls_survey
from vlsforest.voxels import cell_centroids

__all__ = ["FINE_CELL_M", "COARSE_CELL_M", "FOV_MARGIN_DEG", "cell_key", "check_arguments", "cog_offsets",
           "filled_cells", "fill", "tree_fov", "run_tls_step"]

#: cell of the study's finest fixed voxels (m)
FINE_CELL_M = 0.02
#: cell of the study's scaled cubes, one per filled cell (m)
COARSE_CELL_M = 0.25
#: margin around a tree's bounding box in the restricted field of view (degrees)
FOV_MARGIN_DEG = 1.0
#: the leaf-level scene's object ids of tree ``t``: wood 10·t + 1, foliage 10·t + 2
_PART_IDS = (1, 2)


def filled_cells(xyz: np.ndarray, cell: float) -> np.ndarray:
    """The distinct cells (integer indices, one row each) of a grid anchored at the origin that hold points.

    Parameters
    ----------
    xyz : ndarray (n, 3)
        Points.
    cell : float
        Cell size (m).

    Returns
    -------
    ndarray (k, 3) of int64
        Sorted distinct cell indices.
    """
    if len(xyz) == 0:
        return np.zeros((0, 3), np.int64)
    return np.unique(np.floor(np.asarray(xyz, float) / cell).astype(np.int64), axis=0)


def cell_key(cell: float) -> str:
    """The key of a cell size in the result's ``cells`` and ``fill`` mappings (e.g. ``"0.1"``)."""
    return f"{float(cell):g}"


def fill(n_cells: float, cell: float, n_coarse: float, coarse: float = COARSE_CELL_M) -> float:
    """The share of the coarse cells' volume that ``n_cells`` filled cells of side ``cell`` occupy.

    Parameters
    ----------
    n_cells : float
        Filled cells of side ``cell``.
    cell : float
        Their side (m).
    n_coarse : float
        Filled coarse cells of the same points.
    coarse : float
        The coarse cell's side (m; default the scaled cubes' 0.25 m).

    Returns
    -------
    float
        ``n_cells·cell³ / (n_coarse·coarse³)``: 1 for the coarse grid itself; NaN without coarse cells.
    """
    if not n_coarse:
        return math.nan
    return float(n_cells) * float(cell) ** 3 / (float(n_coarse) * float(coarse) ** 3)


def cog_offsets(xyz: np.ndarray, axis_xy, cell: float = COARSE_CELL_M) -> np.ndarray:
    """Offset of each filled cell's centre of gravity from the cell centre, vertically and radially.

    Parameters
    ----------
    xyz : ndarray (n, 3)
        Points.
    axis_xy : sequence of 2 floats
        Horizontal position of the tree's stem axis.
    cell : float
        Cell size (m) of a grid anchored at the origin.

    Returns
    -------
    ndarray (k, 2)
        Per filled cell (in :func:`filled_cells` order): the vertical offset (m; negative: the
        points lie low in the cell) and the radial one (m; the horizontal offset along the
        direction from the axis to the cell centre; negative: towards the axis). A cell whose
        centre lies on the axis has radial offset 0.
    """
    cells = filled_cells(xyz, cell)
    if len(cells) == 0:
        return np.zeros((0, 2))
    centre = (cells + 0.5) * cell
    d = cell_centroids(xyz, cell, cells) - centre
    out_dir = centre[:, :2] - np.asarray(axis_xy, float)[:2]
    norm = np.hypot(out_dir[:, 0], out_dir[:, 1])
    radial = np.where(norm > 0, (d[:, 0] * out_dir[:, 0] + d[:, 1] * out_dir[:, 1]) / np.where(norm > 0, norm, 1.0),
                      0.0)
    return np.column_stack([d[:, 2], radial])


def tree_fov(position, corners: np.ndarray, v_limits) -> dict | None:
    """Heading and field of view of a scan that covers ``corners`` from ``position``.

    Parameters
    ----------
    position : sequence of 3 floats
        Scanner position.
    corners : ndarray (8, 3)
        Corners of the tree's bounding box.
    v_limits : (float, float)
        The recordings' vertical field of view (degrees), which clips the result.

    Returns
    -------
    dict or None
        ``heading_deg`` (compass azimuth towards the box centre), ``h_half_deg`` and
        ``v_fov_deg``; None when the box lies outside ``v_limits``.
    """
    p = np.asarray(position, float)
    d = corners - p
    c = d.mean(axis=0)
    heading = math.degrees(math.atan2(c[0], c[1])) % 360.0
    az = np.degrees(np.arctan2(d[:, 0], d[:, 1]))
    rel = (az - heading + 180.0) % 360.0 - 180.0
    half = float(np.abs(rel).max()) + FOV_MARGIN_DEG
    # the elevation extremes lie on the corners or at the box's horizontally nearest point
    # (its nearest side, a corner, or the scanner's own column where the box covers it)
    horiz = np.hypot(d[:, 0], d[:, 1])
    gap = np.maximum(np.maximum(d[:, :2].min(axis=0), -d[:, :2].max(axis=0)), 0.0)  # scanner to box, per axis
    near = max(float(np.hypot(*gap)), 0.1)
    el = np.degrees(np.arctan2(d[:, 2], horiz))
    el_near = np.degrees(np.arctan2(d[:, 2], near))
    lo = float(min(el.min(), el_near.min())) - FOV_MARGIN_DEG
    hi = float(max(el.max(), el_near.max())) + FOV_MARGIN_DEG
    lo, hi = max(lo, float(v_limits[0])), min(hi, float(v_limits[1]))
    if hi <= lo:
        return None
    return {"heading_deg": heading, "h_half_deg": min(half, 180.0), "v_fov_deg": [lo, hi]}


def check_arguments(steps, band_m=None, cells_m=(), names=("steps", "band_m", "cells_m")):
    """The steps and the further cell sizes of :func:`run_tls_step`, checked.

    Parameters
    ----------
    steps, band_m, cells_m
        As :func:`run_tls_step` takes them.
    names : (str, str, str)
        What the caller calls ``steps``, ``band_m`` and ``cells_m`` (e.g. a command's options
        ``--steps``, ``--band``, ``--cells``); the messages name them so.

    Returns
    -------
    steps : list of float
    cells : list of float
        ``cells_m`` as floats.

    Raises
    ------
    ConfigError
        No step, a step that is not > 0, a band that is not > 0, or a cell size that is not
        finite and > 0.
    """
    steps_name, band_name, cells_name = names
    if band_m is not None and not band_m > 0:
        raise ConfigError(f"{band_name}: must be > 0 m, got {band_m!r}")
    steps = [float(s) for s in steps]
    if not steps or any(not (s > 0) for s in steps):
        raise ConfigError(f"{steps_name}: every step must be > 0 degrees, got {steps}")
    cells = [float(c) for c in cells_m]
    if any(not (c > 0 and math.isfinite(c)) for c in cells):
        raise ConfigError(f"{cells_name}: every cell size must be > 0 m, got {list(cells_m)}")
    return steps, cells


def _scan(scene, pos, fov, step, tls_cfg, physics, seed):
    """One recordings' TLS scan (:func:`vlsforest.synth.record.tls_survey`) from ``pos``, turned to
    the box of :func:`tree_fov` and at ``step`` degrees."""
    cfg = dict(tls_cfg, h_fov_deg=2.0 * fov["h_half_deg"], v_fov_deg=fov["v_fov_deg"], step_deg=float(step))
    at = {"position": list(pos["position"]), "heading_deg": fov["heading_deg"], "tilt_deg": 0.0}
    survey = survey_from_dict(tls_survey(at, cfg, physics, int(seed)))
    return simulate(scene, survey, workers=1, keep_pulses=False)


def run_tls_step(cfg: dict | None, plot: str, steps, *, seed: int = 0, trees: int | None = None,
                 band_m: float | None = None, cells_m=(), progress=None) -> dict:
    """Scan a plot's target trees at several TLS steps and count the filled cells.

    Parameters
    ----------
    cfg : dict
        Workflow config (its ``forest`` and ``tls`` blocks, as ``vlsforest synth`` reads them).
    plot : str
        The plot.
    steps : sequence of float
        Angular steps (degrees, horizontal and vertical), e.g. ``(0.1, 0.017)``.
    seed : int
        The forest's master seed.
    trees : int, optional
        Only the first ``trees`` target trees (by id).
    band_m : float, optional
        Scan and count only a horizontal slab of this height (m) through the middle of each
        crown (between the lowest foliage and the top); default the whole tree.
    cells_m : sequence of float
        Further cell sizes (m) whose filled cells and fill are counted besides 0.02 and 0.25 m
        (e.g. the configured fixed methods' sizes).
    progress : callable, optional
        Called with a line of text after each tree × step.

    Returns
    -------
    dict
        ``plot``, ``seed``, ``steps`` (per step: ``step_deg``, ``n_returns``, ``cells_fine``,
        ``cells_coarse``, ``ratio``, ``cells`` and ``fill`` per cell size (:func:`cell_key`),
        ``cog_offset`` (the filled 0.25 m cells' mean centre-of-gravity offset, :func:`cog_offsets`:
        ``n_cells``, ``z_m``, ``z_se_m``, ``radial_m``, ``radial_se_m``, the means and their
        standard errors), and ``groups``: per species group its ``n_trees``, ``cells``, ``fill``
        and ``cog_offset``), ``trees`` (per tree its species, group and per step the same but
        ``groups``), ``n_trees``, ``n_positions``, the cell sizes and the method in words.

    Raises
    ------
    ConfigError
        An unknown plot, a plot without target trees, a step or band that is not positive.
    """
    steps, extra = check_arguments(steps, band_m, cells_m)
    sizes = sorted({FINE_CELL_M, COARSE_CELL_M, *extra})
    st = synth_settings(cfg)
    lay = plot_layout(st["forest"], seed, plot)
    geoms = generate_plot_trees(lay)
    targets = sorted(lay.target_ids())
    if trees is not None:
        targets = targets[: int(trees)]
    if not targets:
        raise ConfigError(f"plot {plot}: no target trees")
    tls_cfg = st["tls"]
    physics = DEFAULT_RECORDING_PHYSICS["tls"]
    scene = plot_scene(lay, geoms, "tls", physics)
    positions = [p for p in tls_positions(lay, tls_cfg, geoms) if p["tilt_deg"] == 0.0]
    per_tree = []
    totals = {s: {"n_returns": 0, "cells": dict.fromkeys(map(cell_key, sizes), 0)} for s in steps}
    by_group: dict = {}
    offsets = {s: [] for s in steps}  # per step: the cells' CoG offsets of every tree
    group_offsets: dict = {}
    for tid in targets:
        g = geoms[tid]
        v = g.vertices
        lo, hi = v.min(axis=0).copy(), v.max(axis=0).copy()
        if band_m is not None:
            crown = v[g.faces[g.organ == 2].ravel()] if (g.organ == 2).any() else v
            mid = 0.5 * (float(crown[:, 2].min()) + float(hi[2]))
            lo[2], hi[2] = mid - band_m / 2.0, mid + band_m / 2.0
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        ids = {10 * tid + k for k in _PART_IDS}
        group = species_group(geoms[tid].species, default="other")
        row = {"tree_id": int(tid), "species": geoms[tid].species, "group": group, "steps": []}
        for step in steps:
            pts = []
            for k, pos in enumerate(positions, start=1):
                fov = tree_fov(pos["position"], corners, tls_cfg["v_fov_deg"])
                if fov is None:
                    continue
                res = _scan(scene, pos, fov, step, tls_cfg, physics, seed + 101 * k)
                xyz_k = res.points["xyz"]
                sel = np.isin(res.points["object_id"], list(ids)) & (xyz_k[:, 2] >= lo[2]) & (xyz_k[:, 2] <= hi[2])
                pts.append(xyz_k[sel])
            xyz = np.concatenate(pts) if pts else np.zeros((0, 3))
            cells = {cell_key(c): int(len(filled_cells(xyz, c))) for c in sizes}
            off = cog_offsets(xyz, g.position[:2])
            offsets[step].append(off)
            group_offsets.setdefault(step, {}).setdefault(group, []).append(off)
            rec = _step_record(step, len(xyz), cells)
            rec["cog_offset"] = _offset_summary([off])
            row["steps"].append(rec)
            totals[step]["n_returns"] += rec["n_returns"]
            grp = by_group.setdefault(step, {}).setdefault(group, {"n_trees": 0, "cells": dict.fromkeys(cells, 0)})
            grp["n_trees"] += 1
            for k, n in cells.items():
                totals[step]["cells"][k] += n
                grp["cells"][k] += n
            nf, nc = cells[cell_key(FINE_CELL_M)], cells[cell_key(COARSE_CELL_M)]
            if progress is not None:
                progress(f"tree {tid} at {step:g}°: {rec['n_returns']} returns, {nf} fine / {nc} coarse cells")
        per_tree.append(row)
    out_steps = []
    for s in steps:
        rec = _step_record(s, totals[s]["n_returns"], totals[s]["cells"])
        rec["cog_offset"] = _offset_summary(offsets[s])
        rec["groups"] = {g: {"n_trees": v["n_trees"], "cells": v["cells"], "fill": _fills(v["cells"]),
                             "cog_offset": _offset_summary(group_offsets[s][g])}
                         for g, v in sorted(by_group.get(s, {}).items())}
        out_steps.append(rec)
    return {
        "experiment": "tls_step",
        "plot": plot,
        "seed": int(seed),
        "n_trees": len(targets),
        "n_positions": len(positions),
        "band_m": band_m,
        "cell_fine_m": FINE_CELL_M,
        "cell_coarse_m": COARSE_CELL_M,
        "cells_m": sizes,
        "method": ("each target tree scanned from the recordings' untilted positions inside its bounding box's "
                   "field of view; the tree's own returns pooled; cells holding at least one return counted; "
                   "fill = filled cells' volume / filled 0.25 m cells' volume"),
        "steps": out_steps,
        "trees": per_tree,
    }


def _fills(cells: dict) -> dict:
    """Fill (:func:`fill`) of every cell size of a ``cells`` mapping (keys from :func:`cell_key`)."""
    nc = cells[cell_key(COARSE_CELL_M)]
    return {k: fill(n, float(k), nc) for k, n in cells.items()}


def _step_record(step: float, n_returns: int, cells: dict) -> dict:
    nf, nc = cells[cell_key(FINE_CELL_M)], cells[cell_key(COARSE_CELL_M)]
    return {"step_deg": float(step), "n_returns": int(n_returns), "cells_fine": int(nf), "cells_coarse": int(nc),
            "ratio": nf / nc if nc else math.nan, "cells": dict(cells), "fill": _fills(cells)}


def _offset_summary(parts: list) -> dict:
    """Mean and standard error of the cells' vertical and radial CoG offsets (:func:`cog_offsets`)."""
    off = np.concatenate(parts) if parts else np.zeros((0, 2))
    n = len(off)
    out = {"n_cells": int(n)}
    for k, name in enumerate(("z", "radial")):
        v = off[:, k]
        out[f"{name}_m"] = float(v.mean()) if n else math.nan
        out[f"{name}_se_m"] = float(v.std(ddof=1) / math.sqrt(n)) if n > 1 else math.nan
    return out
