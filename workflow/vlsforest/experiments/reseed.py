"""Experiment: the run's own noise, by simulating one method again with another seed.

The study finds that the random shift of the scaled cubes changes none of the metrics it
compares (Hmean, the multiple-return share, CBH, CPA). A finding of "no change" holds where the
change's 95 % interval over the target trees lies within the paper's tolerance. Where it does
not, one proposed cause is that the metric is not repeatable to that tolerance at all: a
simulation of the *same* model that differs only in its random draws changes the metric by as
much. This experiment measures that. Per plot it simulates one method's scene again, with the
run's own surveys and simulation region and the scenario's seed plus ``seed_offset`` (the seed
draws the range noise of every return, :func:`vlsforest.sim.waveform.range_noise`; the pulses,
the scene and the detector are those of the run), and measures the target trees as the run does
(:func:`vlsforest.experiments.resimulate.simulated_metrics`). With ``seed_offset`` 0 it
reproduces the run's own metrics digit for digit (a check of the measurement).

Per scenario and metric the result gives, over the target trees, the change ``reseeded − the
run's`` as mean, standard error and count; per tree both values and the change.
"""

from __future__ import annotations

import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path

from vlsforest.errors import ConfigError
from vlsforest.experiments.resimulate import check_simulation, plot_surveys, run_metrics, simulated_metrics
from vlsforest.experiments.run_outputs import mean_se, method_files, plot_files, targets

__all__ = ["METRICS", "changes", "run_reseed"]

#: the metrics of finding F6
METRICS = ("hmean", "multi_return_pct", "cbh", "cpa")


def run_reseed(manifest: Mapping, method: str, scenarios: Sequence[str], seeds: Mapping, margin_m: float,
               tmp_dir, seed_offset: int = 1, workers: int | None = 1, progress=None) -> dict:
    """Simulate one method of a finished run again with other seeds and measure its targets.

    Parameters
    ----------
    manifest, scenarios, seeds, margin_m, tmp_dir, workers, progress
        As every experiment that simulates a run again takes them
        (:mod:`vlsforest.experiments.resimulate`); ``method`` needs its ``scene`` and ``metrics``.
    method : str
        The method simulated again.
    seed_offset : int
        Added to each scenario's seed (0 reproduces the run).

    Returns
    -------
    dict
        ``method``, ``scenarios``, ``seeds`` (scenario → the run's seed and the seed simulated),
        ``trees`` (per target: plot, target id, group, and per scenario the metrics of ``run``
        and ``reseeded`` and their ``change``, reseeded − run, NaN where either is missing),
        ``summary`` (scenario → metric → mean, se, n of the changes).

    Raises
    ------
    ConfigError
        When a scenario, seed, margin or the offset is invalid, or the manifest lacks a file.
    """
    from vlsforest.sim import Scene, load_survey
    from vlsforest.sim.scene_file import targets_region

    check_simulation(scenarios, seeds, margin_m)
    if isinstance(seed_offset, bool) or not isinstance(seed_offset, int):
        raise ConfigError(f"--seed-offset: must be an integer, got {seed_offset!r}")
    low = [sc for sc in scenarios if seeds[sc] + seed_offset < 0]
    if low:
        raise ConfigError(f"--seed-offset: {seed_offset} makes the seed of {', '.join(low)} negative")
    Path(tmp_dir).mkdir(parents=True, exist_ok=True)
    trees = []
    for plot, entry in plot_files(manifest, "--inputs-json").items():
        scene_yaml = Path(method_files(plot, entry, method, "scene", option="--inputs-json")) / "scene.yaml"
        site, surveys = plot_surveys(plot, entry, scenarios)
        tgt = targets(plot, entry)
        scene = Scene.from_yaml(scene_yaml)
        region, _ = targets_region(site, float(margin_m), scene.max_voxel_size)
        rows = {t.target_id: {"plot": plot, "target_id": t.target_id, "group": t.group, "scenarios": {}} for t in tgt}
        for sc in scenarios:
            run = run_metrics(method_files(plot, entry, method, "metrics", sc, option="--inputs-json"), METRICS)
            with tempfile.TemporaryDirectory(dir=tmp_dir, prefix=".reseed-") as tmp:
                got = simulated_metrics(scene, load_survey(surveys[sc]), int(seeds[sc]) + seed_offset, region, tgt,
                                        Path(tmp), METRICS, workers)
            for tid, row in rows.items():
                a, b = got.get(tid), run.get(tid)
                row["scenarios"][sc] = {"run": b, "reseeded": a, "change": {
                    m: float("nan") if a is None or b is None else float(a[m]) - float(b[m]) for m in METRICS}}
            if progress:
                progress(f"reseed: {plot} {method} {sc}: {len(got)} target trees")
        trees += list(rows.values())
    return {"method": method, "scenarios": list(scenarios), "seed_offset": int(seed_offset),
            "seeds": {sc: {"run": int(seeds[sc]), "reseeded": int(seeds[sc]) + seed_offset} for sc in scenarios},
            "trees": trees, "summary": _summary(trees, scenarios)}


def changes(result: Mapping, scenario: str, metric: str) -> list[float]:
    """Per target tree of a result: its ``change`` of ``metric`` (reseeded − run; NaN where missing)."""
    return [float(((row.get("scenarios") or {}).get(scenario) or {}).get("change", {}).get(metric, float("nan")))
            for row in result.get("trees", [])]


def _summary(trees, scenarios) -> dict:
    res = {"trees": trees}
    return {sc: {m: mean_se(changes(res, sc, m)) for m in METRICS} for sc in scenarios}
