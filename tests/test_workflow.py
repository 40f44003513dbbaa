"""The Snakemake workflow: default target, config schema, end-to-end quick run, incremental
behaviour (nothing changed, PADmax changed, ULS window changed), determinism, every study method
on the quick plot, SLURM dry run and lint.

Every run uses a temporary working directory with the repository's ``Snakefile``; nothing is
written into the repository. The end-to-end runs use ``config/quick.yaml`` (the quick virtual
forest: one plot with 4 targets, four voxel methods, ALS and ULS; about 2.5 min per run on 2
cores).
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import time
from pathlib import Path

import jsonschema
import laspy
import numpy as np
import pandas as pd
import pytest
import yaml
from wfrun import QUICK, REPO, SNAKEFILE, run_quick, snakemake_cli

DEFAULT = REPO / "config" / "config.yaml"
SCHEMA = REPO / "config" / "schema.yaml"
SLURM_PROFILE = REPO / "profiles" / "slurm"

#: the statistics the stats rule writes
STATS_FILES = ("findings.md", "errors.csv", "summary_by_species.csv", "tests.csv", "multireturn_ttest.csv",
               "table5.csv", "findings.csv")

#: what a run may create in its working directory
ALLOWED_TOP_LEVEL = {"results", "logs", ".snakemake"}

#: LAS header bytes 90–93: file creation day of year and year (uint16 each), set to "today"


# ---------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------
def _load(path):
    return yaml.safe_load(Path(path).read_text())


def _snakemake(*args, cwd, timeout=300):
    """Run the Snakemake CLI on the repository's Snakefile in ``cwd``."""
    return snakemake_cli(*args, cwd=cwd, timeout=timeout)


def _expected_outputs(cfg):
    """Every output the default target builds for config ``cfg``."""
    virtual = [p for p, block in cfg["plots"].items() if block.get("kind", "virtual") == "virtual"]
    out = {f"results/forest/{d}/{p}" for p in virtual for d in ("plots", "truth")}
    if virtual:
        out |= {f"results/forest/truth/{f}" for f in ("trees.csv", "synth_settings.yaml", "recording_physics.yaml")}
    out |= {f"results/summary/{f}" for f in ("tree_metrics.csv", "voxel_counts.csv", "sim_times.csv",
                                             "pad_validation.csv", "pad_validation.png", "figures")}
    out |= {f"results/summary/stats/{f}" for f in STATS_FILES}
    out |= {f"results/experiments/{name}.json" for name, block in (cfg.get("experiments") or {}).items()
            if block.get("enabled")}
    diag = cfg.get("diagnosis") or {}
    if diag.get("enabled"):
        for scenario in diag.get("scenarios", cfg["scenarios"]):
            out |= {f"results/diagnosis/{scenario}.{ext}" for ext in ("sim.yaml", "json", "png")}
    for plot in cfg["plots"]:
        out |= {f"results/{plot}/{f}" for f in ("segment", "targets.csv", "site.json", "stems", "crowns.npz",
                                                "pad/pad.vox", "pad/validation.csv", "pad/validation.png")}
        for scenario in cfg["scenarios"]:
            out |= {f"results/{plot}/surveys/{scenario}.yaml",
                    f"results/{plot}/reference/{scenario}/trees.laz",
                    f"results/{plot}/reference/{scenario}/metrics.csv"}
        for method in cfg["methods"]:
            out |= {f"results/{plot}/{method}/voxels.npz", f"results/{plot}/{method}/scene"}
            for scenario in cfg["scenarios"]:
                out |= {f"results/{plot}/{method}/{scenario}/{f}"
                        for f in ("sim.laz", "timing.json", "trees.laz", "metrics.csv")}
    return out


def _run_file_experiments(cfg, methods, scenarios=None):
    """The enabled experiments that read the run's files of any of ``methods`` (crown outline:
    the fixed and unshifted scaled methods' tree clouds; shift room, CoG shift and CoG parts: the
    scaled methods' metrics; reseed: its method's, by default the first unshifted scaled one)."""
    ms, exps = cfg["methods"], cfg.get("experiments") or {}
    unshifted = [m for m, e in ms.items() if e["kind"] == "scaled" and e.get("shift", "none") == "none"]
    reads = {"crown_outline": [m for m, e in ms.items()
                               if e["kind"] == "fixed" or (e["kind"] == "scaled" and e.get("shift", "none") == "none")],
             "shift_room": [m for m, e in ms.items() if e["kind"] == "scaled" and e.get("shift", "none") in ("none", "random")],
             "cog_shift": [m for m, e in ms.items() if e["kind"] == "scaled" and e.get("shift", "none") in ("none", "cog")],
             "cog_parts": [m for m, e in ms.items() if e["kind"] == "scaled" and e.get("shift", "none") in ("none", "cog")],
             "reseed": [(exps.get("reseed") or {}).get("method") or unshifted[0]] if unshifted else []}
    out = {f"results/experiments/{name}.json" for name, used in reads.items()
           if (exps.get(name) or {}).get("enabled") and set(used) & set(methods)}
    # the CoG-parts and reseed experiments read only their own scenarios' files
    for name in ("cog_parts", "reseed"):
        if scenarios is not None and not set(scenarios) & set((exps.get(name) or {}).get("scenarios")
                                                              or cfg["scenarios"]):
            out.discard(f"results/experiments/{name}.json")
    return out


def _downstream_of_sims(cfg, pairs):
    """Outputs of the simulation branch for (method, scenario) pairs, plus the summaries and the
    experiments that read those simulations."""
    out = {"results/summary/tree_metrics.csv", "results/summary/sim_times.csv", "results/summary/figures"}
    out |= {f"results/summary/stats/{f}" for f in STATS_FILES}
    out |= _run_file_experiments(cfg, {m for m, _ in pairs}, {s for _, s in pairs})
    for plot in cfg["plots"]:
        for method, scenario in pairs:
            out |= {f"results/{plot}/{method}/{scenario}/{f}"
                    for f in ("sim.laz", "timing.json", "trees.laz", "metrics.csv")}
    return out


def _api_dry_run(workdir, configfile=None, config=None):
    """Dry run of the default target through the Snakemake Python API.

    Returns the set of outputs that would be (re)built. The API changes the working directory
    (and with --sdm conda the Snakefile would set PATH/PYTHONPATH): both are restored.
    """
    from snakemake.api import SnakemakeApi
    from snakemake.settings.types import (
        ConfigSettings,
        DAGSettings,
        ExecutionSettings,
        OutputSettings,
        ResourceSettings,
        StorageSettings,
    )

    cwd, env = os.getcwd(), dict(os.environ)
    updated: list[str] = []
    # the workflow's scheduler patch stays out of this test process (a dry run schedules nothing;
    # tests/test_scheduler_patch.py checks Snakemake's own method in the same process)
    os.environ["VLSFOREST_SCHEDULER_PATCH"] = "0"
    try:
        with SnakemakeApi(OutputSettings(dryrun=True)) as api:
            wf = api.workflow(
                resource_settings=ResourceSettings(cores=1),
                config_settings=ConfigSettings(
                    configfiles=[Path(configfile)] if configfile else [], config=config or {}
                ),
                storage_settings=StorageSettings(),
                snakefile=SNAKEFILE,
                workdir=Path(workdir),
            )
            wf.dag(DAGSettings()).execute_workflow(
                executor="dryrun", execution_settings=ExecutionSettings(), updated_files=updated
            )
    finally:
        os.chdir(cwd)
        os.environ.clear()
        os.environ.update(env)
    return set(updated)


def _run_quick(workdir):
    """Run the quick config to completion in ``workdir``; return (process, seconds)."""
    return run_quick(workdir)


# ---------------------------------------------------------------------------------------------
# dry runs and configuration
# ---------------------------------------------------------------------------------------------
def test_default_target_schedules_every_quick_output(tmp_path):
    """A dry run with no target builds exactly the quick config's scenes, surveys, clouds, pulse
    tables and the summary (rule all is the default target)."""
    updated = _api_dry_run(tmp_path, QUICK)
    assert updated == _expected_outputs(_load(QUICK))
    assert not any(tmp_path.joinpath(d).exists() for d in ("results", "logs"))


def test_configfile_replaces_the_default_config(tmp_path):
    """--configfile replaces config/config.yaml instead of being merged into it: a scenario of
    the default config must not creep into a study that does not list it."""
    cfg = _load(QUICK)
    del cfg["scenarios"]["uls"]
    path = tmp_path / "only_als.yaml"
    path.write_text(yaml.safe_dump(cfg))
    updated = _api_dry_run(tmp_path, path)
    assert updated == _expected_outputs(cfg)
    assert not any("/uls/" in f for f in updated)


def test_plain_cli_dry_run_uses_default_config(tmp_path):
    """`snakemake -n` with no target and no --configfile, from another directory, schedules the
    default config's jobs (repository config/config.yaml as fallback)."""
    proc = _snakemake("-n", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    cfg = _load(DEFAULT)
    n_sims = len(cfg["plots"]) * len(cfg["methods"]) * len(cfg["scenarios"])
    stats = {}
    for line in proc.stdout.splitlines():
        parts = line.split()
        if len(parts) == 2 and parts[1].isdigit():
            stats[parts[0]] = int(parts[1])
    assert stats.get("simulate") == n_sims and stats.get("all") == 1, proc.stdout[-2000:]
    assert not tmp_path.joinpath("results").exists()


def _mutate(cfg, what):
    if what == "negative_radius":
        cfg["scenarios"]["als"]["extraction_radius_m"] = -5
    elif what == "unknown_scanner":
        cfg["scenarios"]["uls"]["scanner"] = "riegl_nonexistent"
    elif what == "missing_scenarios":
        del cfg["scenarios"]
    elif what == "misspelt_key":
        cfg["scenarios"]["als"]["recordings"] = cfg["scenarios"]["als"].pop("recording")
    elif what == "unknown_override":
        cfg["scenarios"]["als"]["overrides"]["scan_frequency"] = 100
    elif what == "bad_override_value":
        cfg["scenarios"]["uls"]["overrides"]["beam_sample_quality"] = 11
    elif what == "bad_pad_max":
        cfg["pad"]["groups"]["conifer"]["pad_max"] = 0
    elif what == "bad_voxel_size":
        cfg["methods"]["fixed_0.25"]["voxel_size"] = 0
    elif what == "bad_lad":
        cfg["pad"]["groups"]["broadleaf"]["lad"] = "flat"
    elif what == "unknown_method_kind":
        cfg["methods"]["fixed_0.25"]["kind"] = "voxelz"
    elif what == "misspelt_segment_key":
        cfg["segment"] = {"stem_bridges": 20}
    elif what == "negative_realisations":
        cfg.setdefault("diagnosis", {})["realisations"] = -1
    elif what == "unknown_diagnosis_method":
        cfg["diagnosis"] = {"enabled": True, "method": "scaled_typo"}
    elif what == "unknown_reseed_method":
        cfg["experiments"]["reseed"]["method"] = "scaled_typo"
    elif what == "unknown_cog_shift_base":
        cfg["experiments"]["cog_shift"]["base"] = "fixed_typo"
    elif what == "real_plot_without_scans":
        cfg["plots"]["R1"] = {"kind": "real", "tls": ["a.laz"], "plot_json": "p.json"}
    return cfg


BAD_CONFIGS = [
    ("negative_radius", "scenarios.als.extraction_radius_m", "less than or equal to the minimum of 0"),
    ("unknown_scanner", "scenarios.uls.scanner", "'riegl_nonexistent' is not one of"),
    ("missing_scenarios", "(top level)", "'scenarios' is a required property"),
    ("misspelt_key", "scenarios.als", "'recordings' was unexpected"),
    ("unknown_override", "scenarios.als.overrides", "scan_frequency is not a scanner setting; allowed: prf_hz, "),
    ("bad_override_value", "scenarios.uls.overrides", "beam_sample_quality must be between 1 and 10 (got 11)"),
    ("bad_pad_max", "pad.groups.conifer.pad_max", "less than or equal to the minimum of 0"),
    ("bad_voxel_size", "methods.fixed_0.25.voxel_size", "less than or equal to the minimum of 0"),
    ("bad_lad", "pad.groups.broadleaf.lad", "'flat' is not one of"),
    ("real_plot_without_scans", "plots.R1", "'scans' is a required property"),
    ("unknown_method_kind", "methods.fixed_0.25.kind", "unknown kind 'voxelz'"),
    ("misspelt_segment_key", "segment", "'stem_bridges' was unexpected"),
    ("negative_realisations", "diagnosis.realisations", "-1 is less than the minimum of 0"),
    ("unknown_diagnosis_method", "diagnosis.method", "'scaled_typo' is not a configured method"),
    ("unknown_reseed_method", "experiments.reseed.method", "'scaled_typo' is not a configured method"),
    ("unknown_cog_shift_base", "experiments.cog_shift.base", "'fixed_typo' is not a configured method"),
]


@pytest.mark.parametrize("what, key, reason", BAD_CONFIGS)
def test_bad_config_fails_naming_the_key(tmp_path, what, key, reason):
    """Through the API: the schema check raises before the DAG is built, naming the key."""
    from snakemake.exceptions import WorkflowError

    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(_mutate(_load(QUICK), what)))
    with pytest.raises(WorkflowError) as info:
        _api_dry_run(tmp_path, path)
    assert f"Invalid configuration at '{key}': " in str(info.value)
    assert reason in str(info.value)


def test_bad_config_cli_message_and_no_job_runs(tmp_path):
    """What a user sees: a real (not dry) run stops before any job with a one-line message."""
    what, key, reason = BAD_CONFIGS[0]
    assert what == "negative_radius"
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(_mutate(_load(QUICK), what)))
    proc = _snakemake("--cores", 1, "--configfile", path, cwd=tmp_path)
    assert proc.returncode != 0
    msg = proc.stderr + proc.stdout
    line = next((ln for ln in msg.splitlines() if ln.startswith("Invalid configuration")), "")
    assert line.startswith(f"Invalid configuration at '{key}': ") and reason in line, msg[-2000:]
    assert not tmp_path.joinpath("results").exists() and not tmp_path.joinpath("logs").exists()


def test_schema_lists_match_the_library():
    """The schema's scanner names are the library's airborne presets, so the schema neither
    rejects valid nor admits unknown names; the override keys it leaves to the library (the
    workflow checks them with vlsforest.sim.scanner when it reads the config)."""
    from vlsforest.sim.scanner import PRESETS

    scen = _load(SCHEMA)["properties"]["scenarios"]["additionalProperties"]["properties"]
    airborne = {name for name, s in PRESETS.items() if s.deflector.kind != "tls"}
    assert set(scen["scanner"]["enum"]) == airborne
    assert scen["overrides"] == {"type": "object", "description": scen["overrides"]["description"]}
    # the segment block lists exactly SegmentConfig's settings
    from vlsforest.segment import SegmentConfig

    seg = _load(SCHEMA)["properties"]["segment"]
    assert seg["additionalProperties"] is False
    assert set(seg["properties"]) == {f.name for f in dataclasses.fields(SegmentConfig)}


def test_shipped_configs_are_valid():
    """config.yaml and quick.yaml pass the schema."""
    schema = _load(SCHEMA)
    for path in (DEFAULT, QUICK):
        jsonschema.Draft202012Validator(schema).validate(_load(path))


# ---------------------------------------------------------------------------------------------
# end to end
# ---------------------------------------------------------------------------------------------
def test_quick_run_end_to_end(quick_run):
    workdir, proc, seconds = quick_run
    cfg = _load(QUICK)
    for f in _expected_outputs(cfg):
        assert (workdir / f).exists(), f
    forest = workdir / "results" / "forest"
    assert (forest / "truth" / "trees.csv").is_file() and (forest / "plots" / "Q1" / "uls.laz").is_file()
    assert {p.name for p in workdir.iterdir()} <= ALLOWED_TOP_LEVEL
    metrics = pd.read_csv(workdir / "results" / "summary" / "tree_metrics.csv")
    n_targets = sum(len(pd.read_csv(workdir / f"results/{p}/targets.csv")) for p in cfg["plots"])
    assert n_targets == 4
    sources = set(cfg["methods"]) | {"reference"}
    assert set(metrics.method) == sources and set(metrics.scenario) == set(cfg["scenarios"])
    assert len(metrics) == n_targets * len(sources) * len(cfg["scenarios"])
    # every target tree has points in every simulation and reference, heights above its stem base
    assert (metrics.n_points > 50).all(), metrics[metrics.n_points <= 50][["tree_id", "method", "scenario", "n_points"]]
    assert metrics.height.between(10, 40).all()
    counts = pd.read_csv(workdir / "results" / "summary" / "voxel_counts.csv")
    assert set(counts.method) == set(cfg["methods"]) and (counts.n_voxels > 0).all()
    for scenario in cfg["scenarios"]:
        for plot in cfg["plots"]:
            for method in cfg["methods"]:
                las = laspy.read(workdir / f"results/{plot}/{method}/{scenario}/sim.laz")
                cls = np.asarray(las.classification)
                assert (cls == 2).sum() > 1000, f"{scenario}: too few ground returns"
                assert (cls == 5).sum() > 100, f"{scenario}: too few crown returns"
                assert (workdir / f"logs/simulate/{plot}_{method}_{scenario}.log").is_file()
                assert (workdir / f"logs/benchmarks/simulate/{plot}_{method}_{scenario}.tsv").is_file()
    assert (workdir / "results" / "summary" / "stats" / "findings.md").read_text().strip()


def test_second_run_is_a_noop(quick_run):
    workdir, _, _ = quick_run
    lazs = sorted(workdir.glob("results/**/*.laz"))
    before = {p: p.stat().st_mtime_ns for p in lazs}
    t0 = time.perf_counter()
    proc = _snakemake("--cores", 2, "--configfile", QUICK, cwd=workdir)
    print(f"\nno-op rerun: {time.perf_counter() - t0:.1f} s")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "Nothing to be done" in proc.stdout + proc.stderr
    assert {p: p.stat().st_mtime_ns for p in lazs} == before


def test_unchanged_config_rebuilds_nothing(quick_run):
    """(a) nothing changed → no job."""
    workdir, _, _ = quick_run
    assert _api_dry_run(workdir, QUICK) == set()


def test_changed_conifer_pad_max_rebuilds_only_scaled_branches(quick_run):
    """(b) PADmax of conifers changed → only the PAD-scaled methods' voxels, scenes, simulations,
    metrics and the summaries, statistics and figures."""
    workdir, _, _ = quick_run
    cfg = _load(QUICK)
    groups = cfg["pad"]["groups"]
    groups["conifer"]["pad_max"] = 9.0
    updated = _api_dry_run(workdir, QUICK, config={"pad": {**cfg["pad"], "groups": groups}})
    scaled = [m for m, e in cfg["methods"].items() if e["kind"] == "scaled"]
    expected = _downstream_of_sims(cfg, [(m, s) for m in scaled for s in cfg["scenarios"]])
    for plot in cfg["plots"]:
        expected |= {f"results/{plot}/{m}/{f}" for m in scaled for f in ("voxels.npz", "scene")}
    expected.add("results/summary/voxel_counts.csv")  # the scaled models' counts are summarised there
    assert updated == expected


def test_changed_uls_window_rebuilds_only_uls_simulations(quick_run):
    """(d) the ULS window size changed → only the ULS surveys, simulations and their dependants."""
    workdir, _, _ = quick_run
    cfg = _load(QUICK)
    uls = cfg["scenarios"]["uls"]
    uls["overrides"]["window_size_ns"] = 2.0
    updated = _api_dry_run(workdir, QUICK, config={"scenarios": {**cfg["scenarios"], "uls": uls}})
    expected = _downstream_of_sims(cfg, [(m, "uls") for m in cfg["methods"]])
    expected |= {f"results/{p}/surveys/uls.yaml" for p in cfg["plots"]}
    assert updated == expected


def _slurm_rerun_available():
    """True where tests/test_slurm_cluster.py re-runs the quick study from scratch (through a real
    SLURM cluster) and compares every result file byte for byte with the ``quick_run`` fixture."""
    from slurm_cluster import missing_requirements

    return missing_requirements() is None


@pytest.mark.skipif(_slurm_rerun_available(), reason=(
    "the from-scratch rerun is done by tests/test_slurm_cluster.py (same bytes through SLURM); "
    "a second local rerun would only add ~3 min"))
def test_rerun_from_scratch_is_byte_identical(quick_run, tmp_path):
    """Same config and seed in a fresh directory → identical files (LAS: byte-identical except
    the header's creation date, which laspy sets to the day of writing; pulse tables: identical
    arrays, the .npz zip entries carry write times). Where a local SLURM cluster can be started,
    the SLURM test does this rerun (and the same comparison) instead."""
    first, _, _ = quick_run
    _, seconds = _run_quick(tmp_path)
    print(f"\nsecond quick run: {seconds:.1f} s")
    # wall-clock timings differ between runs by nature; everything else is compared
    files = sorted(str(p.relative_to(first)) for p in (first / "results").rglob("*")
                   if p.is_file() and p.name not in ("timing.json", "sim_times.csv", "table5.csv"))
    assert any(f.endswith("uls.laz") for f in files) and any("truth" in f for f in files)
    assert any(f.endswith("voxels.npz") for f in files) and any(f.endswith(".png") for f in files)
    for f in files:
        assert (first / f).read_bytes() == (tmp_path / f).read_bytes(), f


# ---------------------------------------------------------------------------------------------
# cluster profile and lint
# ---------------------------------------------------------------------------------------------
def _dry_run_jobs(out: str) -> list[dict]:
    """The jobs of a dry run's output: rule, wildcards, threads and priority of each."""
    jobs = []
    for block in out.split("\nrule ")[1:]:
        lines = block.splitlines()
        job = {"rule": lines[0].rstrip(":"), "threads": 1, "priority": None, "wildcards": ""}
        for line in lines[1:]:
            key, _, value = line.strip().partition(": ")
            if key == "threads":
                job["threads"] = int(value)
            elif key == "priority":
                job["priority"] = value
            elif key == "wildcards":
                job["wildcards"] = value
            elif not line.startswith(" "):
                break
        jobs.append(job)
    return jobs


def test_local_profile_runs_one_cpu_jobs_side_by_side_and_the_diagnosis_first(tmp_path):
    """The default (local) profile counts simulations and the diagnosis as one thread each, and
    gives the diagnosis and exactly the jobs it needs the highest priority; without the
    diagnosis nothing is prioritized."""
    proc = _snakemake("-n", "--cores", 2, cwd=tmp_path)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-3000:]
    assert "profiles/default" in out
    jobs = _dry_run_jobs(out)
    cfg = _load(DEFAULT)
    sims = [j for j in jobs if j["rule"] == "simulate"]
    assert len(sims) == len(cfg["plots"]) * len(cfg["methods"]) * len(cfg["scenarios"])
    assert {j["threads"] for j in sims} == {1}
    assert [j["threads"] for j in jobs if j["rule"] == "diagnose"] == [1]
    # one synthesis job per plot, the 2 cores shared by the 6 plots: one worker each, side by side
    synth = [j for j in jobs if j["rule"] == "synth_plot"]
    assert sorted(j["wildcards"] for j in synth) == sorted(f"plot={p}" for p in cfg["plots"])
    assert {j["threads"] for j in synth} == {1}
    first = {(j["rule"], j["wildcards"]) for j in jobs if j["priority"] == "highest"}
    d = cfg["diagnosis"]
    plot, method, scenario = d["plots"][0], d["method"], d["scenarios"][0]
    assert len(d["plots"]) == 1 and len(d["scenarios"]) == 1
    assert first == {
        ("synth_plot", f"plot={plot}"), ("segment", f"plot={plot}"), ("targets", f"plot={plot}"), ("stems", f"plot={plot}"),
        ("crowns", f"plot={plot}"), ("pad_virtual", f"plot={plot}"),
        ("voxels", f"plot={plot}, method={method}"), ("scene", f"plot={plot}, method={method}"),
        ("survey", f"plot={plot}, scenario={scenario}"), ("diagnose", f"scenario={scenario}")}
    proc = _snakemake("-n", "--cores", 2, "--configfile", DEFAULT, REPO / "config" / "no-diagnosis.yaml",
                      cwd=tmp_path)
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-3000:]
    jobs = _dry_run_jobs(proc.stdout + proc.stderr)
    assert jobs and not any(j["priority"] for j in jobs) and "diagnose" not in {j["rule"] for j in jobs}


def test_diagnosis_method_defaults_to_the_unshifted_scaled_method(tmp_path):
    """Without diagnosis.method the diagnosis simulates the first scaled method without a shift,
    whatever its name."""
    cfg = _load(DEFAULT)
    cfg["methods"] = {("pad_cubes" if k == "scaled" else k): v for k, v in cfg["methods"].items()}
    del cfg["diagnosis"]["method"]
    path = tmp_path / "renamed.yaml"
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    proc = _snakemake("-n", "--cores", 2, "--configfile", path, cwd=tmp_path)
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-3000:]
    first = {(j["rule"], j["wildcards"]) for j in _dry_run_jobs(proc.stdout + proc.stderr) if j["priority"] == "highest"}
    plot = cfg["diagnosis"]["plots"][0]
    assert ("scene", f"plot={plot}, method=pad_cubes") in first
    assert not any("method=scaled_" in w for _, w in first)


def test_slurm_profile_dry_run(tmp_path):
    """`-n` with profiles/slurm (executor slurm) plans every job without sbatch. Where conda is
    missing, `--sdm env-modules` switches the profile's conda deployment off (no rule uses
    envmodules), since even a dry run with --sdm conda calls `conda info`."""
    import snakemake_executor_plugin_slurm  # noqa: F401  (pinned in envs/requirements.txt)

    extra = [] if shutil.which("conda") else ["--sdm", "env-modules"]
    proc = _snakemake("-n", "--workflow-profile", SLURM_PROFILE, "--configfile", QUICK, *extra, cwd=tmp_path)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-3000:]
    assert "profiles/slurm" in out
    q = _load(QUICK)
    n_sims = len(q["scenarios"]) * len(q["methods"]) * len(q["plots"])
    assert out.count("rule simulate:") == n_sims
    prof = _load(SLURM_PROFILE / "profile.yaml")
    assert prof["executor"] == "slurm" and "conda" in prof["software-deployment-method"]
    # the profile's per-rule resources reach the simulation jobs (threads: a dry run caps them
    # at --cores, which defaults to 1 there)
    res = prof["set-resources"]["simulate"]  # expressions of `attempt`, 1 in a first run
    mem_mb, runtime = (int(eval(str(res[k]), {"attempt": 1})) for k in ("mem_mb", "runtime"))
    assert out.count(f"mem_mb={mem_mb},") == n_sims
    assert out.count(f"runtime={runtime}") == n_sims


def test_default_profile_has_no_software_deployment():
    prof = _load(REPO / "profiles" / "default" / "profile.yaml")
    assert "software-deployment-method" not in prof and "sdm" not in prof
    assert "executor" not in prof


def test_lint_passes(tmp_path):
    proc = _snakemake("--lint", cwd=tmp_path)
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-3000:]
    assert "Congratulations" in proc.stdout + proc.stderr


def test_every_study_method_simulates_on_the_quick_plot(quick_run, tmp_path):
    """Each of the study's seven methods (config/config.yaml) builds a voxel model from the quick
    plot's crown points and PAD grid, assembles into a scene and simulates without error; every
    target crown returns points under its own object id; voxel counts grow as the cells shrink
    and the scaled models never outnumber the 0.25 m cells."""
    from vlsforest.domain.labels import object_ids
    from vlsforest.scene import assemble_scene
    from vlsforest.sim import Scene, simulate
    from vlsforest.sim.survey import survey_from_dict
    from vlsforest.voxels import ModelInputs, PadGrid, build_model

    workdir, _, _ = quick_run
    plot = workdir / "results" / "Q1"
    methods = _load(DEFAULT)["methods"]
    assert len(methods) == 7
    z = np.load(plot / "crowns.npz")
    targets = pd.read_csv(plot / "targets.csv")
    site = json.loads((plot / "site.json").read_text())
    inputs = ModelInputs(z["xyz"], z["owner"], dict(zip(targets.tree_id, targets.group)),
                         PadGrid.from_vox(plot / "pad" / "pad.vox"), 0)
    stems = {int(t): plot / "stems" / str(int(t)) / "stem.obj" for t in targets.tree_id}
    x0, y0, x1, y1 = site["targets_extent"]
    zf = site["ground_z"] + 70.0
    survey = survey_from_dict({"scanner": "riegl_minivux1uav", "overrides": {"beam_sample_quality": 1},
                               "platform": {"type": "linear", "speed_mps": 5.0,
                                            "legs": [{"start": [x0 - 5, 0.5 * (y0 + y1), zf],
                                                      "end": [x1 + 5, 0.5 * (y0 + y1), zf]}]}})
    counts = {}
    for name, entry in methods.items():
        model = build_model(entry, inputs, name)
        counts[name] = model.n_voxels
        yaml_path = assemble_scene(tmp_path / name / "scene.yaml", model, targets, stems, site["ground_z"],
                                   site["extent"], method=name)
        res = simulate(Scene.from_yaml(yaml_path), survey, seed=0, workers=1, progress=False,
                       region=[x0 - 5, y0 - 5, x1 + 5, y1 + 5])
        oid = set(np.unique(res.points["object_id"]).tolist())
        for t in targets.tree_id:
            assert object_ids(int(t))[1] in oid, (name, t)
    print("\nvoxel counts on the quick plot:", counts)
    assert counts["fixed_0.25"] < counts["fixed_0.10"] < counts["fixed_0.05"] < counts["fixed_0.02"]
    for name in ("scaled", "scaled_random_shift", "scaled_cog_shift"):
        assert counts[name] <= counts["fixed_0.25"]


@pytest.mark.parametrize("scenario,backend", [("uls", "grid"), ("uls", "embree"), ("als", "grid")])
def test_one_metre_region_margin_keeps_every_target_return(quick_run, scenario, backend):
    """The simulations trace only pulses whose beam reaches the targets' extent ±
    `simulation.region_margin_m` (default 1 m). The target clouds are taken by object id, and a
    target's voxels and stem lie within its TLS points ± one cell, so with 1 m the target points
    are those of a trace 10 m wider, bit for bit (a return's range noise depends on its pulse
    and return number alone), from fewer
    traced sub-rays. Checked on the coarsest fixed cells (0.25 m), which reach furthest beyond
    the points, with each voxel back-end: `auto` may route a lattice to the other back-end
    for fewer rays, and the two differ on rays that graze a cube edge (docs/simulator.md, "Scenes and back ends")."""
    from vlsforest.domain.labels import object_ids
    from vlsforest.sim import Scene, load_survey, simulate

    workdir, _, _ = quick_run
    plot = workdir / "results" / "Q1"
    assert _load(DEFAULT)["simulation"]["region_margin_m"] == 1
    x0, y0, x1, y1 = json.loads((plot / "site.json").read_text())["targets_extent"]
    targets = pd.read_csv(plot / "targets.csv")
    ids = np.array(sorted(o for t in targets.tree_id for o in object_ids(int(t))))
    path = plot / "fixed_0.25" / "scene" / "scene.yaml"
    scene = Scene.from_dict(dict(_load(path), voxel_backend=backend), base_dir=path.parent, source=str(path))
    survey = load_survey(plot / "surveys" / f"{scenario}.yaml")
    runs = {}
    for m in (10.0, 1.0):
        res = simulate(scene, survey, workers=2, progress=False, keep_pulses=False,
                       region=[x0 - m, y0 - m, x1 + m, y1 + m])
        keep = np.isin(res.points["object_id"], ids)
        runs[m] = ({k: np.asarray(v)[keep] for k, v in res.points.items()}, res.timings["n_rays"])
    (wide, rays_wide), (near, rays_near) = runs[10.0], runs[1.0]
    assert len(wide["xyz"]) > 1000
    assert set(np.unique(wide["object_id"])) >= {object_ids(int(t))[1] for t in targets.tree_id}
    assert wide.keys() == near.keys()
    for k in wide:
        np.testing.assert_array_equal(wide[k], near[k], err_msg=k)
    assert rays_near < 0.8 * rays_wide, (rays_near, rays_wide)


def test_report_html_embeds_every_figure_with_data(quick_run, tmp_path):
    """`snakemake --report` writes one self-contained HTML; every PNG the workflow marks for the
    report is embedded as a data URI that decodes to a non-blank image, and the tables are in it
    (tests/test_report_browser.py opens the same report in headless Chromium)."""
    import base64
    import io
    import re

    import matplotlib.image as mpimg

    workdir, _, _ = quick_run
    report = tmp_path / "report.html"  # outside the shared run's results/ (compared by other tests)
    proc = _snakemake("--configfile", QUICK, "--report", report, cwd=workdir)
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-3000:]
    html = report.read_text()
    pngs = sorted((workdir / "results" / "summary").rglob("*.png"))
    names = {p.name for p in pngs}
    assert {"fig07_percentile_curves.png", "fig10_multireturn.png", "fig11_cbh_cpa_errors.png",
            "fig12_height_errors.png", "pad_validation.png"} <= names
    uris = re.findall(r'"data_uri": "(data:image/png;[^"]*?base64,([A-Za-z0-9+/=]+))"', html)
    embedded = {}
    for full, b64 in uris:
        fname = re.search(r"filename=([^;]+);", full)
        embedded[fname.group(1) if fname else f"#{len(embedded)}"] = base64.b64decode(b64)
    assert names <= set(embedded), sorted(names - set(embedded))
    for name in names:
        data = embedded[name]
        assert data[:8] == b"\x89PNG\r\n\x1a\n", name
        img = mpimg.imread(io.BytesIO(data), format="png")
        assert img.shape[0] > 100 and img.shape[1] > 100, name
        assert float(img[..., :3].std()) > 0.01, f"{name} is blank"
    for table in ("tree_metrics.csv", "voxel_counts.csv", "findings.md"):
        assert table in html


def test_method_added_as_rule_file_flows_through_the_study(tmp_path):
    """The example method of workflow/rules/methods/ (kind linear_pad), added by a config entry
    only, is scheduled through voxels → scene → simulations → tree clouds → metrics → summaries,
    statistics and figures (dry run)."""
    cfg = _load(QUICK)
    cfg["methods"]["linear_pad"] = {"kind": "linear_pad"}
    path = tmp_path / "with_linear_pad.yaml"
    path.write_text(yaml.safe_dump(cfg))
    updated = _api_dry_run(tmp_path, path)
    assert updated == _expected_outputs(cfg)
    for f in ("voxels.npz", "scene", "als/sim.laz", "uls/metrics.csv"):
        assert f"results/Q1/linear_pad/{f}" in updated


def test_linear_pad_method_function(quick_run):
    """The example method's function: PAD-scaled cubes with side ∝ PAD/PADmax (α = 1), so each
    cube is no larger than the study's α = 0.5 cube of the same cell."""
    import importlib.util

    from vlsforest.voxels import ModelInputs, PadGrid, build_model

    spec = importlib.util.spec_from_file_location("linear_pad", REPO / "workflow" / "rules" / "methods" / "linear_pad.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    workdir, _, _ = quick_run
    plot = workdir / "results" / "Q1"
    z = np.load(plot / "crowns.npz")
    targets = pd.read_csv(plot / "targets.csv")
    inputs = ModelInputs(z["xyz"], z["owner"], dict(zip(targets.tree_id, targets.group)),
                         PadGrid.from_vox(plot / "pad" / "pad.vox"), 0)
    groups = _load(QUICK)["pad"]["groups"]
    lin = mod.linear_pad_model(inputs, groups=groups)
    sq = build_model({"kind": "scaled", "groups": groups}, inputs)
    assert np.array_equal(lin.ijk, sq.ijk)
    pmax = np.where(np.isin(lin.owner, targets.tree_id[targets.group == "conifer"]), 8.0, 5.0)
    assert np.allclose(2 * lin.half, 0.25 * lin.pad / pmax)
    assert (lin.half <= sq.half + 1e-12).all() and (lin.half < sq.half).any()


def test_added_plot_rebuilds_only_that_plot_and_the_summaries(quick_run):
    """(c) one plot added → only that plot's jobs and the summaries. The added plot is a
    ``kind: real`` plot naming files (here the quick forest's own recordings of Q1), which also
    exercises the real-data inputs of every rule."""
    workdir, _, _ = quick_run
    cfg = _load(QUICK)
    base = "results/forest/plots/Q1"
    tls = sorted(str(p.relative_to(workdir)) for p in (workdir / base / "tls").glob("scan_*.laz"))
    real = {"kind": "real", "tls": tls, "scans": f"{base}/tls/scans.csv", "plot_json": f"{base}/plot.json",
            "als": f"{base}/als.laz", "uls": f"{base}/uls.laz",
            "trajectory_als": f"{base}/trajectory_als.csv", "trajectory_uls": f"{base}/trajectory_uls.csv"}
    plots = {**cfg["plots"], "R1": real}
    updated = _api_dry_run(workdir, QUICK, config={"plots": plots})
    expected = {f for f in _expected_outputs({**cfg, "plots": {"R1": real}}) if f.startswith("results/R1/")}
    expected -= {"results/R1/pad/validation.csv", "results/R1/pad/validation.png"}  # no truth for real data
    expected |= {f"results/summary/{f}" for f in ("tree_metrics.csv", "voxel_counts.csv", "sim_times.csv", "figures")}
    expected |= {f"results/summary/stats/{f}" for f in STATS_FILES}
    expected |= _run_file_experiments(cfg, cfg["methods"])  # they read every plot
    assert updated == expected
