"""Experiment: the CoG shift's vertical and horizontal parts, simulated apart.

The study finds that moving each scaled cube towards the centre of gravity of its cell's TLS
points lowers Hmean, the multiple-return share, the tree height and the CPA slightly. The shift
moves a cube along all three axes at once: down or up within its cell, and sideways, which moves
the cubes of a column apart so that they hide one another less (the CoG-shift experiment,
:mod:`vlsforest.experiments.cog_shift`, measures that cover). Where the whole shift does not
lower a metric, the proposed cause is that its two parts act against each other: the vertical
part lowers the metric and the horizontal one raises it. This experiment tests that by
simulation. Per plot it builds two variants of the unshifted scaled model, each cube moved by
only the vertical component (``vertical``) or only the horizontal components (``horizontal``)
of its CoG displacement, and simulates each with the run's own surveys, seeds and simulation
region, everything else held fixed (the scene's other parts, materials and back ends are those
of the unshifted method's scene file, read with a ``voxel_transform``). The target trees' metrics
come out as the run's do (:func:`vlsforest.experiments.resimulate.simulated_metrics`).

Per scenario and metric the result gives, over the target trees, the change of each part
(part − unshifted) and the change of the whole shift (the run's shifted metrics − the run's
unshifted metrics), each as mean, standard error and count, and the interaction (whole − the two
parts' sum).
"""

from __future__ import annotations

import math
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from vlsforest.errors import InputDataError
from vlsforest.experiments.resimulate import check_simulation, plot_surveys, run_metrics, simulated_metrics
from vlsforest.experiments.run_outputs import mean_se, method_files, plot_files, targets
from vlsforest.io.voxel_model import VoxelModel

__all__ = ["METRICS", "PARTS", "partial_shift", "run_cog_parts"]

#: the metrics of finding F4
METRICS = ("hmean", "multi_return_pct", "height", "cpa")
#: the parts of the shift simulated apart: name → which axes (x, y, z) of the displacement move
PARTS = {"vertical": (0.0, 0.0, 1.0), "horizontal": (1.0, 1.0, 0.0)}


def partial_shift(model: VoxelModel, shifted: VoxelModel, axes: Sequence[float], source: str = "voxels") -> VoxelModel:
    """A voxel model whose cubes move by some components of their displacement to ``shifted``.

    Parameters
    ----------
    model : VoxelModel
        The unshifted cubes (every cell of it must be a cell of ``shifted``, with the same size).
    shifted : VoxelModel
        The same cells with the cubes at other centres (e.g. the CoG shift).
    axes : sequence of 3 floats
        The share of the displacement taken along x, y and z (``(0, 0, 1)``: the vertical part).
    source : str
        Name of ``shifted`` in error messages.

    Returns
    -------
    VoxelModel
        ``model``'s cells, owners, sizes and PAD, the centres ``c + axes · (c_shifted − c)``.

    Raises
    ------
    InputDataError
        When the lattices differ, a cell of ``model`` is not in ``shifted`` or its cube has
        another size there.
    """
    axes = np.asarray(axes, np.float64).reshape(3)
    if not math.isclose(model.size, shifted.size, rel_tol=1e-12):
        raise InputDataError(f"{source}: cell size {shifted.size:g} m, the unshifted model's {model.size:g} m")
    at = _rows_of(shifted.ijk, model.ijk)
    if (at < 0).any():
        raise InputDataError(f"{source}: {int((at < 0).sum())} of the unshifted model's cells are not in it")
    half = model.half if model.half is not None else np.full(model.n_voxels, 0.5 * model.size)
    other = shifted.half[at] if shifted.half is not None else np.full(len(at), 0.5 * shifted.size)
    if not np.allclose(half, other, rtol=0, atol=1e-12):
        raise InputDataError(f"{source}: its cubes are not the unshifted model's sizes (another method?)")
    c = model.centres()
    centre = c + (shifted.centres()[at] - c) * axes
    return VoxelModel(model.size, model.ijk, model.owner, half=model.half, centre=centre, pad=model.pad)


def _rows_of(table: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Row of each ``query`` cell in ``table`` (−1 where it has none)."""
    table, query = np.asarray(table, np.int64).reshape(-1, 3), np.asarray(query, np.int64).reshape(-1, 3)
    if len(table) == 0 or len(query) == 0:
        return np.full(len(query), -1, np.int64)
    lo = np.minimum(table.min(axis=0), query.min(axis=0))
    dims = np.maximum(table.max(axis=0), query.max(axis=0)) - lo + 1
    kt = np.ravel_multi_index((table - lo).T, dims)
    kq = np.ravel_multi_index((query - lo).T, dims)
    order = np.argsort(kt, kind="stable")
    pos = np.searchsorted(kt[order], kq)
    pos = np.minimum(pos, len(kt) - 1)
    found = kt[order][pos] == kq
    return np.where(found, order[pos], -1)


def run_cog_parts(manifest: Mapping, base: str, shifted: str, scenarios: Sequence[str], seeds: Mapping,
                  margin_m: float, tmp_dir, parts: Mapping | None = None, workers: int | None = 1,
                  progress=None) -> dict:
    """Simulate the vertical and horizontal parts of a shift apart, on a finished run's plots.

    Parameters
    ----------
    manifest, scenarios, seeds, margin_m, tmp_dir, workers, progress
        As every experiment that simulates a run again takes them
        (:mod:`vlsforest.experiments.resimulate`); the base method's ``scene`` is simulated and
        both methods need their ``voxels`` and ``metrics``.
    base, shifted : str
        The unshifted scaled method and its shifted variant.
    parts : mapping, optional
        Part name → axes (default :data:`PARTS`).

    Returns
    -------
    dict
        ``base``, ``shifted``, ``parts`` (name → axes), ``trees`` (per target: plot, target id,
        group, and per scenario the metrics of ``base``, ``shifted`` (the run's) and each part),
        ``summary`` (scenario → metric → ``whole``, each part, and ``interaction``: mean, se, n of
        the per-tree changes).
    """
    from vlsforest.sim import Scene, load_survey
    from vlsforest.sim.scene_file import targets_region

    parts = dict(PARTS if parts is None else parts)
    check_simulation(scenarios, seeds, margin_m)
    Path(tmp_dir).mkdir(parents=True, exist_ok=True)
    trees = []
    for plot, entry in plot_files(manifest, "--inputs-json").items():
        tgt = targets(plot, entry)
        scene_yaml = Path(method_files(plot, entry, base, "scene", option="--inputs-json")) / "scene.yaml"
        shifted_path = method_files(plot, entry, shifted, "voxels", option="--inputs-json")
        moved = VoxelModel.load(shifted_path)
        site, paths = plot_surveys(plot, entry, scenarios)
        surveys = {sc: load_survey(path) for sc, path in paths.items()}
        run = {sc: {m: run_metrics(method_files(plot, entry, m, "metrics", sc, option="--inputs-json"), METRICS)
                    for m in (base, shifted)} for sc in scenarios}
        rows = {t.target_id: {"plot": plot, "target_id": t.target_id, "group": t.group,
                              "scenarios": {sc: {"base": run[sc][base].get(t.target_id),
                                                 "shifted": run[sc][shifted].get(t.target_id)} for sc in scenarios}}
                for t in tgt}
        for part, axes in parts.items():
            scene = Scene.from_yaml(scene_yaml, voxel_transform=lambda m, a=axes: partial_shift(m, moved, a, shifted_path))
            region, _ = targets_region(site, float(margin_m), scene.max_voxel_size)
            for sc in scenarios:
                with tempfile.TemporaryDirectory(dir=tmp_dir, prefix=".cog-parts-") as tmp:
                    got = simulated_metrics(scene, surveys[sc], int(seeds[sc]), region, tgt, Path(tmp), METRICS,
                                            workers)
                for tid, row in rows.items():
                    row["scenarios"][sc][part] = got.get(tid)
                if progress:
                    progress(f"cog-parts: {plot} {part} {sc}: {len(got)} target trees")
        trees += list(rows.values())
    return {"base": base, "shifted": shifted, "parts": {k: list(map(float, v)) for k, v in parts.items()},
            "scenarios": list(scenarios), "trees": trees, "summary": _summary(trees, scenarios, list(parts))}


def _summary(trees, scenarios, parts) -> dict:
    def change(row, sc, a, m):
        s = row["scenarios"][sc]
        if s.get(a) is None or s.get("base") is None:
            return math.nan
        return s[a][m] - s["base"][m]

    out = {}
    for sc in scenarios:
        out[sc] = {}
        for m in METRICS:
            entry = {"whole": mean_se([change(r, sc, "shifted", m) for r in trees])}
            for p in parts:
                entry[p] = mean_se([change(r, sc, p, m) for r in trees])
            entry["interaction"] = mean_se([change(r, sc, "shifted", m) - sum(change(r, sc, p, m) for p in parts)
                                            for r in trees])
            out[sc][m] = entry
    return out
