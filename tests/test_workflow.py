"""The Snakemake workflow: default target, config schema, end-to-end quick run, incremental
behaviour, determinism, the simulated ground point density, SLURM dry run and lint.

Every run uses a temporary working directory with the repository's ``Snakefile``; nothing is
written into the repository. The end-to-end runs use ``config/quick.yaml`` (one demo tree,
one ALS and one ULS flight line each; about 15 s per run on 2 cores).
"""

from __future__ import annotations

import dataclasses
import math
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import laspy
import numpy as np
import pandas as pd
import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
SNAKEFILE = REPO / "Snakefile"
QUICK = REPO / "config" / "quick.yaml"
DEFAULT = REPO / "config" / "config.yaml"
SCHEMA = REPO / "config" / "schema.yaml"
SLURM_PROFILE = REPO / "profiles" / "slurm"

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
    cmd = [sys.executable, "-m", "snakemake", "--snakefile", str(SNAKEFILE), *map(str, args)]
    return subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=timeout, env=dict(os.environ))


def _expected_outputs(cfg):
    """Every output the default target builds for config ``cfg`` (rules synth, scene, survey,
    simulate, simulation_summary)."""
    out = {"results/summary/simulations.csv", "results/forest"}
    for plot in cfg["plots"]:
        for method in cfg["methods"]:
            out |= {f"results/{plot}/{method}/scene/{f}" for f in ("scene.yaml", "stem.obj", "crown.csv")}
            for scenario in cfg["scenarios"]:
                out |= {f"results/{plot}/{method}/{scenario}/{f}" for f in ("survey.yaml", "sim.laz", "pulses.npz")}
    return out


def _api_dry_run(workdir, configfile=None, config=None):
    """Dry run of the default target through the Snakemake Python API.

    Returns the set of outputs that would be (re)built. The API changes the working directory
    and the Snakefile sets PATH/PYTHONPATH: both are restored.
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
    t0 = time.perf_counter()
    proc = _snakemake("--cores", 2, "--configfile", QUICK, cwd=workdir)
    dt = time.perf_counter() - t0
    assert proc.returncode == 0, proc.stderr[-4000:]
    return proc, dt


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    """One completed end-to-end run of config/quick.yaml (shared by the tests below)."""
    workdir = tmp_path_factory.mktemp("quick")
    proc, seconds = _run_quick(workdir)
    print(f"\nquick end-to-end run: {seconds:.1f} s")
    return workdir, proc, seconds


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
    if what == "negative_altitude":
        cfg["scenarios"]["als"]["altitude_m"] = -5
    elif what == "unknown_scanner":
        cfg["scenarios"]["uls"]["scanner"] = "riegl_nonexistent"
    elif what == "missing_scenarios":
        del cfg["scenarios"]
    elif what == "misspelt_key":
        cfg["scenarios"]["als"]["altitud_m"] = cfg["scenarios"]["als"].pop("altitude_m")
    elif what == "unknown_override":
        cfg["scenarios"]["als"]["overrides"]["scan_frequency"] = 100
    return cfg


BAD_CONFIGS = [
    ("negative_altitude", "scenarios.als.altitude_m", "less than or equal to the minimum of 0"),
    ("unknown_scanner", "scenarios.uls.scanner", "'riegl_nonexistent' is not one of"),
    ("missing_scenarios", "(top level)", "'scenarios' is a required property"),
    ("misspelt_key", "scenarios.als", "'altitud_m' was unexpected"),
    ("unknown_override", "scenarios.als.overrides", "'scan_frequency' is not one of"),
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
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(_mutate(_load(QUICK), what)))
    proc = _snakemake("--cores", 1, "--configfile", path, cwd=tmp_path)
    assert proc.returncode != 0
    msg = proc.stderr + proc.stdout
    line = next((ln for ln in msg.splitlines() if ln.startswith("Invalid configuration")), "")
    assert line.startswith(f"Invalid configuration at '{key}': ") and reason in line, msg[-2000:]
    assert not tmp_path.joinpath("results").exists() and not tmp_path.joinpath("logs").exists()


def test_schema_lists_match_the_library():
    """The schema's scanner and override names are the library's (airborne presets; every
    overridable ScannerSettings field), so the schema neither rejects valid nor admits unknown
    names."""
    from vlsforest.sim.scanner import PRESETS, ScannerSettings

    scen = _load(SCHEMA)["properties"]["scenarios"]["additionalProperties"]["properties"]
    airborne = {name for name, s in PRESETS.items() if s.deflector != "tls"}
    assert set(scen["scanner"]["enum"]) == airborne
    overridable = {f.name for f in dataclasses.fields(ScannerSettings)} - {"name", "deflector"}
    assert set(scen["overrides"]["propertyNames"]["enum"]) == overridable


def test_shipped_configs_are_valid():
    """config.yaml and quick.yaml pass the schema."""
    jsonschema = pytest.importorskip("jsonschema")
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
    summary = pd.read_csv(workdir / "results" / "summary" / "simulations.csv")
    assert set(summary["scenario"]) == set(cfg["scenarios"])
    for scenario in cfg["scenarios"]:
        for plot in cfg["plots"]:
            for method in cfg["methods"]:
                las = laspy.read(workdir / f"results/{plot}/{method}/{scenario}/sim.laz")
                cls = np.asarray(las.classification)
                assert len(las.points) > 1000
                assert (cls == 2).sum() > 1000, f"{scenario}: too few ground returns"
                assert (cls == 5).sum() > 100, f"{scenario}: too few crown returns"
                row = summary[(summary["scenario"] == scenario) & (summary["plot"] == plot)]
                assert int(row["n_points"].iloc[0]) == len(las.points)
                assert (workdir / f"logs/simulate/{plot}_{method}_{scenario}.log").is_file()
                assert (workdir / f"logs/benchmarks/simulate/{plot}_{method}_{scenario}.tsv").is_file()


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


def test_changed_scenario_param_rebuilds_only_its_branch(quick_run):
    """A changed scenario value (tracked through params) reruns that scenario's survey and
    simulation and the summary, nothing else."""
    workdir, _, _ = quick_run
    cfg = _load(QUICK)
    new_alt = cfg["scenarios"]["uls"]["altitude_m"] + 2
    updated = _api_dry_run(workdir, QUICK, config={"scenarios": {"uls": {"altitude_m": new_alt}}})
    prefix = "results/{}/{}/uls/".format(next(iter(cfg["plots"])), next(iter(cfg["methods"])))
    assert updated == {prefix + f for f in ("survey.yaml", "sim.laz", "pulses.npz")} | {
        "results/summary/simulations.csv"
    }


def _taper(u, a, b):
    """1 for u ≤ a, 0 for u ≥ b, cos² in between (continuous slope)."""
    t = np.clip((np.asarray(u) - a) / (b - a), 0.0, 1.0)
    return np.cos(0.5 * np.pi * t) ** 2


def _scene_points(scene_dir):
    """Crown voxel centres and stem vertices of the demo scene (for its shadow on the ground)."""
    crown = np.loadtxt(scene_dir / "crown.csv", delimiter=",", skiprows=1, ndmin=2)
    verts = [list(map(float, ln.split()[1:4])) for ln in (scene_dir / "stem.obj").read_text().splitlines()
             if ln.startswith("v ")]
    return np.vstack([crown, np.asarray(verts)])


@pytest.mark.parametrize("scenario", ["als", "uls"])
def test_ground_point_density_matches_the_scan_pattern(quick_run, scenario):
    """Ground returns (classification 2) per m² equal the analytic density of the scan pattern.

    A line scanner emitting PRF pulses per second, evenly over a sweep of Φ radians per scan line,
    flown at speed v and height h, lays PRF / (v · h · Φ) · cos²θ pulses per m² on flat ground
    at off-nadir angle θ (along-track line spacing v/f; across-track spacing h·dθ/cos²θ).
    Φ = 2 × the polygon facet half-sweep, or 2π for the rotating mirror. Flight lines add up.

    The counts use a smooth window over the ground plane, away from its edges (beam footprints
    straddling the edge) and outside the tree's shadow (radius from the crown/stem points and the
    steepest ray). With a smooth window, summing over a regular pulse lattice equals the
    integral of density × window to far better than 0.1 % (the aliasing terms of a C¹ window
    ≥ 1 m wide on a ≤ 0.25 m lattice are negligible), so a 1 % tolerance tests the physics: PRF,
    sweep, speed, altitude, cos²θ and that every pulse reaching the ground yields one return.
    """
    from vlsforest.sim.scanner import scanner_from_preset

    workdir, _, _ = quick_run
    cfg = _load(QUICK)
    plot, method = next(iter(cfg["plots"])), next(iter(cfg["methods"]))
    base = workdir / "results" / plot / method
    scene = _load(base / "scene" / "scene.yaml")
    (plane,) = [p for p in scene["parts"] if p["type"] == "plane"]
    x0, y0, x1, y1 = map(float, plane["extent"])
    ground_z = float(plane["z"])
    assert math.isclose(x1 - x0, y1 - y0) and math.isclose(x0 + x1, 0) and math.isclose(y0 + y1, 0)
    half = 0.5 * (x1 - x0)

    survey = _load(base / scenario / "survey.yaml")
    scanner = scanner_from_preset(survey["scanner"], survey.get("overrides"))
    if scanner.deflector == "polygon":
        sweep = 2.0 * math.radians(scanner.max_scan_angle_deg)
    elif scanner.deflector == "rotating":
        sweep = 2.0 * math.pi
    else:  # pragma: no cover - the schema admits only these airborne scanners
        pytest.fail(f"no analytic density for a {scanner.deflector} scanner")
    speed = float(survey["platform"]["speed_mps"])
    legs = [leg for leg in survey["platform"]["legs"] if leg["active"]]

    # window: edges taper over [half − 2, half − 0.5] (beam footprints straddling the plane's
    # edge are left out); the tree's shadow is cut out up to r0, tapering in over [r0, r0 + 1]
    edge_a, edge_b = half - 2.0, half - 0.5
    n = 1601
    u = np.linspace(-half, half, n)
    gx, gy = np.meshgrid(u, u)
    square = (np.abs(gx) < edge_b) & (np.abs(gy) < edge_b)
    geometry = []
    for leg in legs:
        p, q = np.asarray(leg["start"][:2], float), np.asarray(leg["end"][:2], float)
        d = (q - p) / np.linalg.norm(q - p)
        h = float(leg["start"][2]) - ground_z
        along = (gx - p[0]) * d[0] + (gy - p[1]) * d[1]
        across = np.abs((gx - p[0]) * d[1] - (gy - p[1]) * d[0])
        # the line runs over the whole counting square, whose ground lies inside the emitted sweep
        assert along[square].min() >= 0 and along[square].max() <= np.linalg.norm(q - p)
        assert np.degrees(np.arctan(across[square].max() / h)) < scanner.scan_angle_deg
        geometry.append((h, across))
    # shadow radius: a crown voxel or stem vertex at height z shades ground up to z·tanθ away
    # (steepest ray over the square), plus half a voxel diagonal and the beam footprint radius
    tan_max = max(across[square].max() / h for h, across in geometry)
    footprint = max(h for h, _ in geometry) * math.tan(0.5e-3 * max(scanner.beam_divergence_mrad))
    objs = _scene_points(base / "scene")
    voxel = float(cfg["methods"][method]["voxel_size"])
    r0 = float(np.max(np.hypot(objs[:, 0], objs[:, 1]) + (objs[:, 2] - ground_z) * tan_max))
    r0 += 0.5 * voxel * math.sqrt(3.0) + footprint
    assert r0 + 1.0 < edge_a, "the tree's shadow leaves no ground to count"

    def window(x, y):
        return _taper(np.abs(x), edge_a, edge_b) * _taper(np.abs(y), edge_a, edge_b) * (
            1.0 - _taper(np.hypot(x, y), r0, r0 + 1.0)
        )

    las = laspy.read(base / scenario / "sim.laz")
    ground = np.asarray(las.classification) == 2
    measured = float(window(np.asarray(las.x)[ground], np.asarray(las.y)[ground]).sum())

    density = np.zeros_like(gx)
    for h, across in geometry:
        density += scanner.prf_hz * np.cos(np.arctan(across / h)) ** 2 / (speed * h * sweep)
    expected = float((window(gx, gy) * density).sum() * (u[1] - u[0]) ** 2)

    print(f"\n{scenario}: windowed ground returns {measured:.1f}, analytic {expected:.1f}")
    assert expected > 500  # enough ground returns in the window for a 1 % comparison
    assert measured == pytest.approx(expected, rel=0.01), (scenario, measured, expected)


def test_rerun_from_scratch_is_byte_identical(quick_run, tmp_path):
    """Same config and seed in a fresh directory → identical files (LAS: byte-identical except
    the header's creation date, which laspy sets to the day of writing; pulse tables: identical
    arrays, the .npz zip entries carry write times)."""
    first, _, _ = quick_run
    _, seconds = _run_quick(tmp_path)
    print(f"\nsecond quick run: {seconds:.1f} s")
    files = sorted(f for f in _expected_outputs(_load(QUICK)) if f != "results/forest")
    files += sorted(str(p.relative_to(first)) for p in (first / "results" / "forest").rglob("*") if p.is_file())
    assert any(f.endswith("uls.laz") for f in files) and any("truth" in f for f in files)
    for f in files:
        assert (first / f).read_bytes() == (tmp_path / f).read_bytes(), f


# ---------------------------------------------------------------------------------------------
# cluster profile and lint
# ---------------------------------------------------------------------------------------------
def test_slurm_profile_dry_run(tmp_path):
    """`-n` with profiles/slurm (executor slurm) plans every job without sbatch. Where conda is
    missing, `--sdm env-modules` switches the profile's conda deployment off (no rule uses
    envmodules), since even a dry run with --sdm conda calls `conda info`."""
    pytest.importorskip("snakemake_executor_plugin_slurm")
    extra = [] if shutil.which("conda") else ["--sdm", "env-modules"]
    proc = _snakemake("-n", "--workflow-profile", SLURM_PROFILE, "--configfile", QUICK, *extra, cwd=tmp_path)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-3000:]
    assert "profiles/slurm" in out
    n_sims = len(_load(QUICK)["scenarios"])
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
