"""Experiment: where a voxel model's crown projection area error comes from.

The study finds that the 0.25 m fixed voxels underestimate the crown projection area (CPA) and
that the CPA error grows with the voxel size. Two causes lower a simulated CPA: the
simulation does not see the whole crown (occlusion: by the opaque cubes above and by the
neighbours), and a crown base placed too high (the CPA is the hull of the points above the
CBH, so a higher CBH drops the lower crown). One cause raises it: a cube of side ``a`` reaches
up to ``a`` beyond the TLS points that filled its cell, so the model's outline is wider than
the crown the TLS saw. This experiment measures each of them on a finished run, per target
tree, method and scenario, from the files the run wrote:

``cpa_ref``
    the reference cloud's CPA at its own CBH (the reference value of the errors);
``cpa_model``
    the CPA of the model itself: the convex hull of the xy corners of the tree's cubes whose
    top lies at or above the reference's crown base (what a simulation that saw every cube
    would give);
``cpa_seen``
    the simulated cloud's CPA at the *reference's* crown base;
``cpa_sim``
    the simulated cloud's CPA at its own CBH (the simulated value of the errors).

Their differences add up exactly to the CPA error ``cpa_sim − cpa_ref``:

* ``outline = cpa_model − cpa_ref``: the model's crown outline against the reference's;
* ``unseen = cpa_seen − cpa_model``: what the simulation does not see of that outline (≤ 0
  up to the beam's footprint);
* ``base = cpa_sim − cpa_seen``: the simulated crown base's own effect (a CBH above the
  reference's drops the crown below it).

The crown base height (CBH) error ``cbh_sim − cbh_ref`` splits the same way, with

``cbh_model``
    the CBH of the model itself: the paper's rule (the first 0.1 m slice wider than 1.5 m)
    applied to the tree's cubes, each cube standing for its whole extent in every slice it
    reaches (:func:`model_crown_base`);

into ``own_base = cbh_model − cbh_ref`` (where the model's own crown starts against the
reference's) and ``seen_base = cbh_sim − cbh_model`` (what the simulation sees of it).

Every CPA and CBH is :mod:`vlsforest.metrics`' (``crown_projection_area``, ``tree_metrics``),
with the target's ground height of the run's targets table, as the run's metrics are.
"""

from __future__ import annotations

import math

import numpy as np

from vlsforest.errors import ConfigError
from vlsforest.experiments.run_outputs import cloud_points, mean_se, method_files, plot_files, targets
from vlsforest.io.las import read_las
from vlsforest.io.voxel_model import VoxelModel
from vlsforest.metrics import CBH_SLICE, crown_projection_area, tree_metrics

__all__ = ["CBH_TERMS", "TERMS", "model_crown_base", "model_outline_area", "run_crown_outline"]

#: the parts of the CPA error, in the order they add up to it
TERMS = ("outline", "unseen", "base")
#: the parts of the CBH error, in the order they add up to it
CBH_TERMS = ("own_base", "seen_base")


def model_outline_area(model: VoxelModel, cbh: float, ground_z: float) -> float:
    """CPA of a voxel model itself: the hull of the xy corners of its cubes above the crown base.

    Parameters
    ----------
    model : VoxelModel
        One tree's cubes.
    cbh : float
        Crown base height above ``ground_z`` (m); cubes whose top lies below it are left out.
    ground_z : float
        Terrain height at the stem.

    Returns
    -------
    float
        The area (m²), by :func:`vlsforest.metrics.crown_projection_area` of the corners (placed
        at their cube's top); 0.0 for a model without cubes.
    """
    if model.n_voxels == 0:
        return 0.0
    c = model.centres()
    h = 0.5 * model.sides()
    top = c[:, 2] + h
    corners = np.concatenate([np.column_stack([c[:, 0] + sx * h, c[:, 1] + sy * h, top])
                              for sx in (-1.0, 1.0) for sy in (-1.0, 1.0)])
    return crown_projection_area(corners, cbh, ground_z=ground_z)


def model_crown_base(model: VoxelModel, ground_z: float) -> float:
    """CBH of a voxel model itself: the paper's rule applied to the solid cubes.

    Each cube contributes the four xy corners of its footprint to every 0.1 m slice (the
    slices of :func:`vlsforest.metrics.tree_metrics`, counted from ``ground_z``) that its
    vertical extent reaches; the CBH is then that of :func:`~vlsforest.metrics.tree_metrics`
    on those points: the centre of the first slice whose xy diameter exceeds 1.5 m.

    Parameters
    ----------
    model : VoxelModel
        One tree's cubes.
    ground_z : float
        Terrain height at the stem.

    Returns
    -------
    float
        The CBH above ``ground_z`` (m); NaN for a model without cubes.
    """
    if model.n_voxels == 0:
        return math.nan
    c = model.centres()
    h = 0.5 * model.sides()
    lo = np.floor(np.round((c[:, 2] - h - ground_z) / CBH_SLICE, 9)).astype(np.int64)
    hi = np.ceil(np.round((c[:, 2] + h - ground_z) / CBH_SLICE, 9)).astype(np.int64) - 1
    n = np.maximum(hi - lo + 1, 1)
    cube = np.repeat(np.arange(len(c)), n)
    k = lo[cube] + (np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n))
    z = ground_z + (k + 0.5) * CBH_SLICE
    pts = np.concatenate([np.column_stack([c[cube, 0] + sx * h[cube], c[cube, 1] + sy * h[cube], z])
                          for sx in (-1.0, 1.0) for sy in (-1.0, 1.0)])
    return _cbh(pts, ground_z)


def _cbh(xyz, ground_z) -> float:
    return float(tree_metrics(xyz, ground_z=ground_z)["cbh"]) if len(xyz) else math.nan


def run_crown_outline(manifest, methods, scenarios, *, option: str = "--inputs-json", progress=None) -> dict:
    """Split each method's CPA error into the model's outline, the unseen part and the crown base.

    Parameters
    ----------
    manifest : mapping
        The run's files by plot (:mod:`vlsforest.experiments.run_outputs`): each plot's
        ``targets``, ``reference`` tree clouds by scenario, and per method its ``voxels`` and
        ``trees`` by scenario.
    methods : sequence of str
        The voxel methods to take apart.
    scenarios : sequence of str
        The scenarios.
    option : str
        The name of the manifest in error messages.
    progress : callable, optional
        Called with a line of text after each plot.

    Returns
    -------
    dict
        ``methods``, ``scenarios``, ``plots``; ``summary`` (method → scenario → ``error`` and
        each of :data:`TERMS` as mean, standard error and count over the trees, in m²; ``cbh``:
        the CBH error and its terms ``own_base`` and ``seen_base``, in m, likewise);
        ``trees`` (one row per tree, method and scenario: ``plot``, ``tree_id``, ``group``, the
        CBHs and the four CPAs of the module docstring).

    Raises
    ------
    ConfigError
        No method or scenario, or a file the manifest does not name.
    InputDataError
        A file that cannot be read (names it).
    """
    methods, scenarios = [str(m) for m in methods], [str(s) for s in scenarios]
    if not methods or not scenarios:
        raise ConfigError("crown outline: needs at least one method and one scenario")
    plots = plot_files(manifest, option)
    rows = []
    for plot, entry in plots.items():
        trees = targets(plot, entry)
        models = {m: VoxelModel.load(method_files(plot, entry, m, "voxels", option=option)) for m in methods}
        own, own_cbh = {}, {}  # (target, method) → the tree's cubes and their own CBH
        for t in trees:
            for m in methods:
                own[t.target_id, m] = models[m].subset(models[m].owner == t.segment_id)
                own_cbh[t.target_id, m] = model_crown_base(own[t.target_id, m], t.ground_z)
        for sc in scenarios:
            ref_path = (entry.get("reference") or {}).get(sc)
            if not isinstance(ref_path, str):
                raise ConfigError(f"{option}: plot {plot!r} does not name the reference trees of scenario {sc}")
            ref = read_las(ref_path, require=("tree_id",), allow_empty=True)
            sims = {m: read_las(method_files(plot, entry, m, "trees", sc, option), require=("tree_id",),
                                allow_empty=True) for m in methods}
            for t in trees:
                r_xyz = cloud_points(ref, t.target_id)
                cbh_ref = _cbh(r_xyz, t.ground_z)
                cpa_ref = crown_projection_area(r_xyz, cbh_ref, ground_z=t.ground_z) if len(r_xyz) else math.nan
                for m in methods:
                    s_xyz = cloud_points(sims[m], t.target_id)
                    ok = len(r_xyz) > 0 and len(s_xyz) > 0
                    cbh_sim = _cbh(s_xyz, t.ground_z)
                    rows.append({
                        "plot": plot, "tree_id": t.target_id, "group": t.group, "method": m, "scenario": sc,
                        "cbh_ref": cbh_ref, "cbh_sim": cbh_sim,
                        "cbh_model": own_cbh[(t.target_id, m)] if ok else math.nan, "cpa_ref": cpa_ref,
                        "cpa_model": model_outline_area(own[(t.target_id, m)], cbh_ref, t.ground_z) if ok else math.nan,
                        "cpa_seen": crown_projection_area(s_xyz, cbh_ref, ground_z=t.ground_z) if ok else math.nan,
                        "cpa_sim": crown_projection_area(s_xyz, cbh_sim, ground_z=t.ground_z) if ok else math.nan,
                    })
        if progress is not None:
            progress(f"{plot}: {len(trees)} target trees")
    summary = {}
    for m in methods:
        summary[m] = {}
        for sc in scenarios:
            rs = [r for r in rows if r["method"] == m and r["scenario"] == sc]
            parts = {
                "error": [r["cpa_sim"] - r["cpa_ref"] for r in rs],
                "outline": [r["cpa_model"] - r["cpa_ref"] for r in rs],
                "unseen": [r["cpa_seen"] - r["cpa_model"] for r in rs],
                "base": [r["cpa_sim"] - r["cpa_seen"] for r in rs],
            }
            summary[m][sc] = {k: mean_se(v) for k, v in parts.items()}
            summary[m][sc]["cbh"] = {
                "error": mean_se([r["cbh_sim"] - r["cbh_ref"] for r in rs]),
                "own_base": mean_se([r["cbh_model"] - r["cbh_ref"] for r in rs]),
                "seen_base": mean_se([r["cbh_sim"] - r["cbh_model"] for r in rs]),
            }
            summary[m][sc]["reference_m2"] = mean_se([r["cpa_ref"] for r in rs])["mean"]
    return {"experiment": "crown_outline", "methods": methods, "scenarios": scenarios, "plots": list(plots),
            "method": ("per target tree: the reference's CPA at its CBH, the model's own outline (its cubes' "
                       "corners above the reference's crown base), the simulated cloud's CPA at the reference's "
                       "and at its own crown base; error = outline + unseen + base; the CBH of the model's own "
                       "cubes; CBH error = own_base + seen_base"),
            "summary": summary, "trees": rows}
