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

The result (:func:`run_tls_step`) is a JSON document with, per step, the returns and the filled
cells of both grids summed over the trees and their ratio, and the same per tree.
"""

from __future__ import annotations

import math

import numpy as np

from vlsforest.errors import ConfigError
from vlsforest.sim.engine import simulate
from vlsforest.sim.scanner import PRESETS
from vlsforest.sim.survey import survey_from_dict
from vlsforest.synth.forest import forest_from_config, generate_plot_trees
from vlsforest.synth.record import DEFAULT_RECORDING_PHYSICS, physics_overrides, plot_scene, synth_settings, tls_positions

__all__ = ["FINE_CELL_M", "COARSE_CELL_M", "FOV_MARGIN_DEG", "filled_cells", "tree_fov", "run_tls_step"]

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


def _scan(scene, pos, fov, step, tls_cfg, physics, seed):
    ov = {"tls_h_fov_deg": [-fov["h_half_deg"], fov["h_half_deg"]], "tls_v_fov_deg": fov["v_fov_deg"],
          "tls_h_step_deg": float(step), "tls_v_step_deg": float(step),
          "beam_sample_quality": int(tls_cfg["beam_sample_quality"])}
    pov, _ = physics_overrides(physics, PRESETS["riegl_vz400"].beam.divergence_mrad)
    ov.update(pov)
    survey = survey_from_dict({
        "scanner": "riegl_vz400", "overrides": ov, "seed": int(seed), "detector": {"mode": "physical"},
        "platform": {"type": "static", "positions": [{"position": list(pos["position"]),
                                                      "heading_deg": fov["heading_deg"], "tilt_deg": 0.0}]}})
    return simulate(scene, survey, workers=1, keep_pulses=False)


def run_tls_step(cfg: dict | None, plot: str, steps, *, seed: int = 0, trees: int | None = None,
                 band_m: float | None = None, progress=None) -> dict:
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
    progress : callable, optional
        Called with a line of text after each tree × step.

    Returns
    -------
    dict
        ``plot``, ``seed``, ``steps`` (per step: ``step_deg``, ``n_returns``, ``cells_fine``,
        ``cells_coarse``, ``ratio``), ``trees`` (per tree and step the same), ``n_trees``,
        ``n_positions``, the cell sizes and the method in words.

    Raises
    ------
    ConfigError
        An unknown plot, a plot without target trees, a step or band that is not positive.
    """
    if band_m is not None and not band_m > 0:
        raise ConfigError(f"band_m: must be > 0 m, got {band_m!r}")
    steps = [float(s) for s in steps]
    if not steps or any(not (s > 0) for s in steps):
        raise ConfigError(f"steps: every step must be > 0 degrees, got {steps}")
    st = synth_settings(cfg)
    layouts = {p.name: p for p in forest_from_config(st["forest"], seed)}
    if plot not in layouts:
        raise ConfigError(f"plot: unknown plot {plot!r} (known: {', '.join(layouts)})")
    lay = layouts[plot]
    geoms = generate_plot_trees(lay)
    targets = sorted(t.tree_id for t in lay.trees if t.target)
    if trees is not None:
        targets = targets[: int(trees)]
    if not targets:
        raise ConfigError(f"plot {plot}: no target trees")
    tls_cfg = st["tls"]
    physics = DEFAULT_RECORDING_PHYSICS["tls"]
    scene = plot_scene(lay, geoms, "tls", physics)
    positions = [p for p in tls_positions(lay, tls_cfg, geoms) if p["tilt_deg"] == 0.0]
    per_tree = []
    totals = {s: {"n_returns": 0, "cells_fine": 0, "cells_coarse": 0} for s in steps}
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
        row = {"tree_id": int(tid), "species": geoms[tid].species, "steps": []}
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
            nf, nc = len(filled_cells(xyz, FINE_CELL_M)), len(filled_cells(xyz, COARSE_CELL_M))
            rec = {"step_deg": step, "n_returns": int(len(xyz)), "cells_fine": int(nf), "cells_coarse": int(nc),
                   "ratio": nf / nc if nc else math.nan}
            row["steps"].append(rec)
            for k in ("n_returns", "cells_fine", "cells_coarse"):
                totals[step][k] += rec[k]
            if progress is not None:
                progress(f"tree {tid} at {step:g}°: {rec['n_returns']} returns, {nf} fine / {nc} coarse cells")
        per_tree.append(row)
    out_steps = [{"step_deg": s, **totals[s],
                  "ratio": totals[s]["cells_fine"] / totals[s]["cells_coarse"] if totals[s]["cells_coarse"] else math.nan}
                 for s in steps]
    return {
        "experiment": "tls_step",
        "plot": plot,
        "seed": int(seed),
        "n_trees": len(targets),
        "n_positions": len(positions),
        "band_m": band_m,
        "cell_fine_m": FINE_CELL_M,
        "cell_coarse_m": COARSE_CELL_M,
        "method": ("each target tree scanned from the recordings' untilted positions inside its bounding box's "
                   "field of view; the tree's own returns pooled; cells holding at least one return counted"),
        "steps": out_steps,
        "trees": per_tree,
    }
