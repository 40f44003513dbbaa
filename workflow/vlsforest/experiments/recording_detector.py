"""Experiment: how the recordings' detector sets their multiple-return share.

The findings compare every simulation with the embedded forest's "real" recordings, and finding
D1 compares those recordings with the study's real data: where the recordings' share of pulses
with multiple returns differs from the real sensors', the voxel methods' penetration verdicts
say more about the recordings than about the methods. The proposed cause is the recordings'
detector (:data:`vlsforest.synth.record.DEFAULT_RECORDING_PHYSICS`: an energy threshold and the
physical peak rule), whose threshold no datasheet gives. This experiment tests it: it records one
plot again with the recording physics unchanged and with detector variants, everything else
held fixed (same forest, flight lines, seeds), and reports the target trees' multiple-return
shares by species group beside the study's real shares.

Each variant replaces keys of the sensor's recording-physics block, e.g.
``{"peak_rule": {"physical": 0}}`` (HELIOS++ 1.0.8's rule) or
``{"detection_threshold": {"min_energy": 40000}}``. A target tree's returns are taken by its
truth object ids (wood and foliage), and its share is :func:`vlsforest.metrics.tree_metrics`'s
``multi_return_pct`` (pulses with more than one return among the pulses with a return on the
tree), as for the reference clouds.

Each flight is traced once: the recording and every variant made only of
:data:`vlsforest.synth.record.DETECTION_CANDIDATES` are detected on that trace
(:func:`vlsforest.sim.redetect`, the points a full simulation gives, bit for bit); a variant
that changes the trace (beam, trajectory) is simulated on its own.
"""

from __future__ import annotations

import copy
import math

import numpy as np

from vlsforest.domain.species import species_group
from vlsforest.errors import ConfigError
from vlsforest.io.las import PointCloud
from vlsforest.metrics import tree_metrics
from vlsforest.sim import beam_geometry, hit_offsets, redetect, simulate, survey_from_dict, trace_hits
from vlsforest.synth.forest import generate_plot_trees, plot_layout
from vlsforest.synth.record import (
    DEFAULT_RECORDING_PHYSICS,
    DETECTION_CANDIDATES,
    airborne_survey,
    plot_scene,
    recording_region,
    restyle_for,
    synth_settings,
    validate_recording_physics,
)

__all__ = ["run_recording_detector"]


def _tree_shares(points, targets, geoms) -> dict:
    oid = np.asarray(points["object_id"], np.int64)
    out = {}
    for tid in targets:
        sel = (oid == 10 * tid + 1) | (oid == 10 * tid + 2)
        if not sel.any():
            out[tid] = math.nan
            continue
        m = tree_metrics(points["xyz"][sel], ground_z=float(geoms[tid].position[2]),
                         number_of_returns=points["number_of_returns"][sel], gps_time=points["gps_time"][sel],
                         point_source_id=points["point_source_id"][sel])
        out[tid] = float(m["multi_return_pct"])
    return out


def run_recording_detector(cfg: dict | None, plot: str, sensor: str, variants: dict, *, seed: int = 0,
                           progress=None) -> dict:
    """Record a plot with the recording physics and with detector variants; the trees' shares.

    Parameters
    ----------
    cfg : dict
        Workflow config (its ``forest`` and ``recordings`` blocks, as ``vlsforest synth`` reads
        them).
    plot : str
        The plot.
    sensor : {"als", "uls"}
        The recording.
    variants : dict
        Variant name → keys that replace the sensor's recording-physics block (validated as
        recording physics). The unchanged recording is always run first, as ``"recording"``.
    seed : int
        The forest's master seed.
    progress : callable, optional
        Called with a line of text after each variant.

    Returns
    -------
    dict
        ``plot``, ``sensor``, ``seed``, ``variants`` (per variant: its ``name``, the replaced
        ``physics`` keys, ``n_points`` and the mean share per group ``conifer``/``broadleaf``
        with ``n`` trees), ``trees`` (per tree: id, species, group, share per variant).

    Raises
    ------
    ConfigError
        An unknown plot or sensor, a plot without target trees, or a variant that is not valid
        recording physics.
    """
    if sensor not in ("als", "uls"):
        raise ConfigError(f"sensor: must be als or uls, got {sensor!r}")
    if not isinstance(variants, dict) or "recording" in variants:
        raise ConfigError("variants: a mapping of names (not 'recording') to recording-physics keys")
    st = synth_settings(cfg)
    lay = plot_layout(st["forest"], seed, plot)
    base = validate_recording_physics(DEFAULT_RECORDING_PHYSICS)
    runs = {"recording": {}}
    for name, keys in variants.items():
        phys = copy.deepcopy(base)
        phys[sensor].update(copy.deepcopy(keys or {}))
        validate_recording_physics(phys, where=f"variants.{name}")
        runs[str(name)] = keys or {}
    geoms = generate_plot_trees(lay)
    targets = sorted(lay.target_ids())
    if not targets:
        raise ConfigError(f"plot {plot}: no target trees")
    region = recording_region(lay)  # as `vlsforest synth` records the plot
    physics = {}
    for name, keys in runs.items():
        physics[name] = copy.deepcopy(base[sensor])
        physics[name].update(copy.deepcopy(keys))
    geometry = plot_scene(lay, geoms, "tls")  # one geometry and BVH, each variant's materials
    scenes = {name: restyle_for(geometry, sensor, physics[name]) for name in runs}
    flights = {name: airborne_survey(lay, sensor, st["recordings"][sensor], physics[name], seed) for name in runs}
    per_tree = {name: {t: [] for t in targets} for name in runs}
    n_points = dict.fromkeys(runs, 0)
    for r, recorded in enumerate(flights["recording"]):
        survey = survey_from_dict(recorded)
        pulses, hits = trace_hits(scenes["recording"], survey, workers=1, region=region)
        ptr, beam = hit_offsets(pulses, hits), beam_geometry(survey.scanner)
        for name, keys in runs.items():
            sv = survey_from_dict(flights[name][r])
            if set(keys) <= DETECTION_CANDIDATES:
                res = redetect(scenes[name].part_table(), pulses, hits, sv, beam=beam, hit_ptr=ptr)
            else:
                res = simulate(scenes[name], sv, workers=1, keep_pulses=False, region=region)
            n_points[name] += len(res.points["xyz"])
            for tid, v in _tree_shares(res.points, targets, geoms).items():
                per_tree[name][tid].append(v)
            del res
        del pulses, hits, ptr
    shares, rows = {}, []
    for name, keys in runs.items():
        # the repeats of a survey are separate flights: a tree's share over all of them
        shares[name] = {t: (float(np.nanmean(v)) if np.isfinite(v).any() else math.nan)
                        for t, v in per_tree[name].items()}
        groups = {}
        for g in ("conifer", "broadleaf"):
            vals = [shares[name][t] for t in targets
                    if species_group(geoms[t].species, default="other") == g and np.isfinite(shares[name][t])]
            groups[g] = {"mean_pct": float(np.mean(vals)) if vals else math.nan, "n": len(vals)}
        rows.append({"name": name, "physics": keys, "n_points": int(n_points[name]), **groups})
        if progress is not None:
            progress(f"{name}: conifer {groups['conifer']['mean_pct']:.1f} %, "
                     f"broadleaf {groups['broadleaf']['mean_pct']:.1f} %")
    trees = [{"tree_id": int(t), "species": geoms[t].species,
              "group": species_group(geoms[t].species, default="other"),
              "shares_pct": {name: shares[name][t] for name in runs}} for t in targets]
    return {"experiment": "recording_detector", "plot": plot, "sensor": sensor, "seed": int(seed),
            "method": ("the plot recorded with the recording physics and with each variant (same forest, "
                       "lines and seeds); target trees' returns by truth object id; shares as "
                       "vlsforest.metrics.tree_metrics computes them"),
            "variants": rows, "trees": trees}
