"""Benchmark against HELIOS++ on the same machine: the same scenes and surveys run by
``vlsforest simulate`` (``helios_v1`` mode) and by a HELIOS++ binary, as whole processes.

One command, given a HELIOS++ binary::

    python benchmarks/bench_helios.py --helios /path/to/helios

Without ``--helios`` only our side is measured and every row says so (``helios: null``).

Scenes and surveys
------------------
(a) The real Bretten spruce F_BR08_08 (``F_BR08_08_crown_250.vox``, 6,185 fixed 0.25 m voxels,
    and ``F_BR08_08_stem_Poisson.obj``, from ``<repo>/../shared/data/real`` or ``--data DIR``)
    on a 100 m ground square centred on the stem, at the stem base. Two surveys, planned with
    :func:`vlsforest.sim.planning.plan_survey` and the study's scenario settings (HELIOS++
    1.0.8's detector, ``detector: {mode: helios_v1}``, beam sample quality 3):

    - ``als``: RIEGL VQ-780i, 687 m above the ground, 51 m/s, ±30° effective of the ±45°
      polygon, 250 lines/s, window 1.75 ns; one line over the stem, running 250 m beyond the
      ground square at both ends (600 m, 11.8 s: ≈ 7.8 M emitted pulses, most of which miss
      the scene).
    - ``uls``: RIEGL miniVUX-1UAV, 68 m, 5 m/s, window 1.5 ns; a double grid of 2 + 2 lines
      20 m apart over the crown, each running 27 m beyond it (4 × 60 m, 48 s: ≈ 2.4 M emitted
      pulses).

    ``--quick``: a 20 m ground square, the ALS line 5 m and the ULS lines 1 m beyond the crown
    (for tests; seconds).
(b) With ``--study-results DIR``: one plot of a finished study run,
    ``DIR/{plot}/{method}/scene/scene.yaml`` with ``DIR/{plot}/surveys/{als,uls}.yaml`` (those
    that exist; default plot P3, method ``scaled``). The study's simulations trace only the
    pulses that reach the target trees (``--region-from``); here every pulse is traced, as
    HELIOS++ does.

Each scene + survey is exported with ``vlsforest scene helios SCENE --survey SURVEY -o DIR``
(the exporter's refusal is recorded in the row, and HELIOS++ is then not run on that case).

What runs
---------
For each scene × survey × thread count (``--threads``, default one and all CPUs):

- ``vlsforest simulate SCENE SURVEY -o OUT.las --workers T --seed S --quiet --timing T.json``;
- with ``--helios``: ``helios survey.xml --output OUT --seed S -j T --lasOutput --rebuildScene``
  run inside the exported folder; for HELIOS++ ≥ 2 (its ``--version``, or ``--helios-version``)
  also ``--legacyEnergyModel`` (the 1.0.8 energy model that ``helios_v1`` reproduces),
  ``--noSceneWriting``, ``--kdtJobs T`` and ``--assets .``; ``--helios-arg`` appends more.

Each is run ``--repeats`` times (default 3), after ``--warmup`` untimed runs (default 1) of
ours on each case (a first run in a fresh checkout compiles the simulator's kernels into
numba's disk cache, which takes a minute) and of HELIOS++ on the first case; the row holds the
medians. Per process (``os.wait4`` in a small launcher process, so that the figures are the
measured process's and those of its reaped worker processes, not the benchmark's):
``wall_s``; ``cpu_s`` (user + system); ``max_rss_mb`` (``ru_maxrss``: the largest single
process); ``tree_pss_mb`` (the peak of the summed proportional set size of the process and its
descendants, sampled every 50 ms: the memory of the whole tree with shared pages counted
once); ``n_points`` (our LAS read with :func:`vlsforest.io.las.read_las`; HELIOS++'s point files
under its output folder: LAS/LAZ headers via laspy, ``.xyz`` lines); ``pulses_per_cpu_s``.

``n_pulses`` is the survey's emitted pulses as ``vlsforest simulate`` counts them (HELIOS++
emits the same slots; it does not report its count), so both tools' pulses per CPU-second use
it. The ratios: ``speedup_wall`` and ``speedup_cpu`` (HELIOS++'s seconds ÷ ours: above 1 we are
faster; ``speedup_cpu`` is also the ratio of pulses per CPU-second), ``rss_ratio`` (our
``max_rss_mb`` ÷ HELIOS++'s) and ``points_ratio``. Our side also says where its time goes:
``engine_s`` (the simulation itself, ``--timing``'s ``total``) and ``outside_engine_s`` (the
rest of the process: interpreter and library start-up, reading and building the scene, the
LAS write); ``startup_s`` (top-level) is the wall time of a process that only imports the
simulator. Where we are slower the row's ``slower`` names the larger of the two.

On the spruce both tools' points are also compared (``agreement``): per tool the ground
points (object id 1), the tree points (stem 2 and crown 3), the tree's share of pulses with
more than one return (pulses by GPS time and flight line, as :func:`vlsforest.metrics.tree_metrics`
counts them) and its heights above the ground (median and 99th percentile), with the bounds
:data:`AGREEMENT` (ground points within 2 %, tree points within 10 %, the multiple-return share
within 2 percentage points, the heights within 0.15 m) and whether each holds. One flight
samples the crown's voxel lattice at one set of places, and the multiple-return share of a few
hundred ALS pulses moves by a few percentage points with that phase alone; ``--phases N`` flies
the spruce at N pulse phases with both tools (the legs moved within a voxel, :func:`phase_case`)
and adds ``agreement.phases``: per figure the mean difference over the phases, its standard
error, and whether the mean lies within the bound.

Linux only (``/proc``, ``os.wait4``). Rows go to ``benchmarks/results/bench_helios.jsonl``
(``results.rows``, and flat in ``results.table``: one record per scene × survey × thread count,
rendered by ``scripts/gen_reference.py``).

Run: ``python benchmarks/bench_helios.py [--helios PATH] [--study-results results/ [--study-only]]
[--repeats 3] [--threads 1,all] [--surveys als,uls] [--phases N] [--quick] [--workdir DIR]``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shlex
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

import benchresult

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
DATA = REPO.parent / "shared" / "data" / "real"  # <repo>/../shared/data/real
CROWN = "F_BR08_08_crown_250.vox"
STEM = "F_BR08_08_stem_Poisson.obj"
SURVEYS = ("als", "uls")

#: the study's scenarios (config/config.yaml) as flown over the spruce: sensor settings as in
#: the study, flight geometry chosen for one tree (module docstring)
SCENARIOS = {
    "als": {"scanner": "riegl_vq780i", "pattern": "parallel", "altitude_m": 687.0, "speed_mps": 51.0,
            "line_spacing_m": 175.0, "n_lines": 1, "margin_m": 250.0,
            "overrides": {"scan_freq_hz": 250, "window_size_ns": 1.75, "beam_sample_quality": 3},
            "detector": {"mode": "helios_v1"}},
    "uls": {"scanner": "riegl_minivux1uav", "pattern": "double_grid", "altitude_m": 68.0, "speed_mps": 5.0,
            "line_spacing_m": 20.0, "n_lines": 2, "margin_m": 27.0,
            "overrides": {"window_size_ns": 1.5, "beam_sample_quality": 3},
            "detector": {"mode": "helios_v1"}},
}
#: the spruce scene's object ids: the ground plane and the tree (stem, crown)
GROUND_ID, TREE_IDS = 1, (2, 3)
#: the shift of the flight lines between pulse phases (``--phases``): one crown voxel
PHASE_STEP_M = 0.25

#: bounds of the agreement of the two tools' points on the spruce: relative differences of the
#: ground and tree point counts, the tree's multiple-return share (percentage points) and its
#: heights above the ground (m)
AGREEMENT = {"ground_points": 0.02, "tree_points": 0.10, "tree_multi_return_pct": 2.0,
             "tree_height_p50_m": 0.15, "tree_height_p99_m": 0.15}
#: --quick: (ground square side m, {survey: scenario changes})
QUICK = (20.0, {"als": {"margin_m": 5.0}, "uls": {"margin_m": 1.0, "n_lines": 1}})
GROUND_SIDE_M = 100.0


class BenchError(Exception):
    """Bad input to the benchmark: reported as one line, exit 2."""


# ----------------------------------------------------------------------------- measuring
def _tree_pids(pid: int) -> list[int]:
    """``pid`` and its living descendants (from ``/proc/*/task/*/children``)."""
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        try:
            for task in os.listdir(f"/proc/{p}/task"):
                with open(f"/proc/{p}/task/{task}/children") as fh:
                    todo += [int(c) for c in fh.read().split()]
        except OSError:
            continue
    return out


def _pss_kb(pid: int) -> int:
    try:
        with open(f"/proc/{pid}/smaps_rollup") as fh:
            for line in fh:
                if line.startswith("Pss:"):
                    return int(line.split()[1])
    except (OSError, ValueError):
        pass
    return 0


class _PssSampler(threading.Thread):
    """Peak of the summed PSS of a process's descendants, sampled every ``interval`` seconds
    (Linux)."""

    def __init__(self, pid: int, interval: float = 0.05):
        super().__init__(daemon=True)
        self.pid, self.interval, self.peak_kb = pid, interval, 0
        self._halt = threading.Event()

    def run(self):
        while not self._halt.is_set():
            self.peak_kb = max(self.peak_kb, sum(_pss_kb(p) for p in _tree_pids(self.pid)[1:]))
            self._halt.wait(self.interval)

    def stop(self):
        self._halt.set()
        self.join()


#: a small launcher that forks, runs the command and writes its ``wait4`` figures as JSON: the
#: measured process starts from the launcher's few MB, not from a copy of this process (Linux
#: keeps a process's peak RSS across ``exec``, so a child forked from here would report at
#: least this process's resident size)
_LAUNCHER = """
import json, os, sys, time
out, cwd, log, cmd = sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4:]
fd = os.open(log or os.devnull, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
t0 = time.perf_counter()
pid = os.fork()
if pid == 0:
    try:
        if cwd:
            os.chdir(cwd)
        os.dup2(fd, 1)
        os.dup2(fd, 2)
        os.execvp(cmd[0], cmd)
    finally:
        os._exit(127)
_, status, ru = os.wait4(pid, 0)
wall = time.perf_counter() - t0
with open(out, "w") as fh:
    json.dump({"rc": os.waitstatus_to_exitcode(status), "wall_s": wall, "cpu_s": ru.ru_utime + ru.ru_stime,
               "max_rss_mb": ru.ru_maxrss / 1024.0}, fh)
"""


def measure(cmd: list[str], cwd=None, log=None) -> dict:
    """Run ``cmd`` as a child process; its exit code, wall and CPU seconds, peak memory.

    Parameters
    ----------
    cmd : list of str
    cwd : path, optional
    log : path, optional
        File for the child's stdout and stderr (default: discarded).

    Returns
    -------
    dict
        ``rc`` (127: it could not start), ``wall_s``, ``cpu_s`` (user + system of the process
        and its reaped children, ``os.wait4``), ``max_rss_mb`` (``ru_maxrss``: the largest of
        those processes), ``tree_pss_mb`` (sampled peak of the tree's summed PSS; None where
        ``/proc`` has no ``smaps_rollup``).
    """
    with tempfile.TemporaryDirectory(prefix="bench_helios_run_") as tmp:
        out = Path(tmp) / "wait4.json"
        proc = subprocess.Popen([sys.executable, "-S", "-c", _LAUNCHER, str(out), str(cwd or ""), str(log or ""),
                                 *map(str, cmd)])
        sampler = _PssSampler(proc.pid)
        sampler.start()
        proc.wait()
        sampler.stop()
        if proc.returncode != 0 or not out.is_file():
            return {"rc": proc.returncode or 1, "wall_s": None, "cpu_s": None, "max_rss_mb": None,
                    "tree_pss_mb": None}
        res = json.loads(out.read_text())
    res["tree_pss_mb"] = sampler.peak_kb / 1024.0 or None
    return res


def _median_runs(runs: list[dict]) -> dict:
    """Medians of the numeric figures of repeated runs."""
    out = {}
    for key in ("wall_s", "cpu_s", "max_rss_mb", "tree_pss_mb", "engine_s"):
        vals = [r[key] for r in runs if r.get(key) is not None]
        out[key] = round(statistics.median(vals), 3) if vals else None
    return out


def _tail(path: Path, n: int = 3) -> str:
    try:
        lines = [ln for ln in path.read_text(errors="replace").splitlines() if ln.strip()]
    except OSError:
        return ""
    return " / ".join(lines[-n:])


# ----------------------------------------------------------------------------- point counts
def count_points(folder: Path) -> tuple[int, list[str]]:
    """Points of the point files under a HELIOS++ output folder: ``*.las`` / ``*.laz``
    (header point count, laspy) and ``*.xyz`` (non-empty lines that do not start with ``#``);
    trajectory, pulse and full-waveform files are not point files."""
    total, files = 0, []
    for p in sorted(folder.rglob("*")):
        name = p.name.lower()
        if not p.is_file() or any(w in name for w in ("trajectory", "fullwave", "pulse")):
            continue
        if p.suffix.lower() in (".las", ".laz"):
            import laspy

            with laspy.open(p) as fh:
                total += int(fh.header.point_count)
        elif p.suffix.lower() == ".xyz":
            with p.open("rb") as fh:
                total += sum(1 for ln in fh if ln.strip() and not ln.lstrip().startswith(b"#"))
        else:
            continue
        files.append(str(p.relative_to(folder)))
    return total, files


def point_summary(xyz, object_id, number_of_returns, gps_time, line, ground_z: float) -> dict:
    """The figures :data:`AGREEMENT` compares, from one tool's points.

    Parameters
    ----------
    xyz : ndarray (n, 3)
        Points.
    object_id : ndarray (n,)
        The scene part each point hit (:data:`GROUND_ID`, :data:`TREE_IDS`).
    number_of_returns : ndarray (n,)
        The returns of each point's pulse.
    gps_time : ndarray (n,)
        Each point's pulse time.
    line : ndarray (n,)
        Each point's flight line (two lines may share a pulse time).
    ground_z : float
        The ground's height.

    Returns
    -------
    dict
        ``ground_points``, ``tree_points``, ``tree_multi_return_pct`` (of the pulses with a
        return on the tree, the share whose pulse has more than one return),
        ``tree_height_p50_m`` and ``tree_height_p99_m`` (of the tree points above the ground).
    """
    import numpy as np

    oid = np.asarray(object_id).astype(np.int64)
    tree = np.isin(oid, TREE_IDS)
    out = {"ground_points": int((oid == GROUND_ID).sum()), "tree_points": int(tree.sum())}
    if tree.any():
        keys = np.column_stack([np.asarray(line, np.float64)[tree], np.asarray(gps_time, np.float64)[tree]])
        _, pulse = np.unique(keys, axis=0, return_inverse=True)
        multi = np.zeros(pulse.max() + 1, bool)
        np.logical_or.at(multi, pulse.ravel(), np.asarray(number_of_returns)[tree] > 1)
        h = np.asarray(xyz, np.float64)[tree, 2] - ground_z
        out.update(tree_multi_return_pct=round(100.0 * float(multi.mean()), 3),
                   tree_height_p50_m=round(float(np.percentile(h, 50)), 3),
                   tree_height_p99_m=round(float(np.percentile(h, 99)), 3))
    return out


def helios_points(folder: Path, files) -> dict:
    """The LAS/LAZ points of a HELIOS++ output folder: ``xyz``, ``object_id`` (``hitObjectId``),
    ``number_of_returns``, ``gps_time`` and ``line`` (the file's index: one file per leg)."""
    import laspy
    import numpy as np

    parts = {"xyz": [], "object_id": [], "number_of_returns": [], "gps_time": [], "line": []}
    for k, name in enumerate(f for f in files if f.lower().endswith((".las", ".laz"))):
        las = laspy.read(folder / name)
        parts["xyz"].append(np.column_stack([las.x, las.y, las.z]))
        parts["object_id"].append(np.asarray(las["hitObjectId"]))
        parts["number_of_returns"].append(np.asarray(las.number_of_returns))
        parts["gps_time"].append(np.asarray(las.gps_time))
        parts["line"].append(np.full(len(las.x), k))
    if not parts["xyz"]:
        return {}
    return {k: np.concatenate(v) for k, v in parts.items()}


def agreement(ours: dict, helios: dict) -> dict:
    """Both tools' :func:`point_summary` figures, their differences and whether each lies within
    :data:`AGREEMENT` (counts: relative to HELIOS++'s)."""
    out = {"vlsforest": ours, "helios": helios}
    for key, bound in AGREEMENT.items():
        a, b = ours.get(key), helios.get(key)
        if a is None or b is None:
            continue
        diff = (a - b) / b if key.endswith("_points") and b else a - b
        out[f"{key}_diff"] = round(diff, 4)
        out[f"{key}_within"] = bool(abs(diff) <= bound)
    return out


def phase_case(case: dict, k: int, n: int) -> dict:
    """The case flown ``k``-th of ``n`` pulse phases: every leg moved by ``k/n`` of a crown voxel
    (:data:`PHASE_STEP_M`) across x and by the fractional part of ``0.618·k`` of one along y, so
    that the pulses meet the voxel lattice at other places; its own folder and survey file."""
    import yaml

    survey = yaml.safe_load(Path(case["survey_yaml"]).read_text())
    dx, dy = PHASE_STEP_M * k / n, PHASE_STEP_M * ((0.618 * k) % 1.0)
    for leg in survey["platform"]["legs"]:
        for end in ("start", "end"):
            leg[end] = [leg[end][0] + dx, leg[end][1] + dy, leg[end][2]]
    folder = case["folder"] / f"phase_{k}"
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{case['survey']}.yaml"
    path.write_text(yaml.safe_dump(survey, sort_keys=False))
    return dict(case, survey_yaml=path, folder=folder, shift_m=[round(dx, 4), round(dy, 4)])


def phase_agreement(pairs: list[tuple[dict, dict]]) -> dict:
    """Mean and standard error over pulse phases of each :data:`AGREEMENT` difference (ours − HELIOS++;
    counts relative), and whether the mean lies within the bound."""
    import numpy as np

    out = {"n_phases": len(pairs)}
    for key, bound in AGREEMENT.items():
        diffs = []
        for ours, helios in pairs:
            a, b = ours.get(key), helios.get(key)
            if a is not None and b is not None:
                diffs.append((a - b) / b if key.endswith("_points") and b else a - b)
        if len(diffs) >= 2:
            d = np.asarray(diffs)
            mean, se = float(d.mean()), float(d.std(ddof=1) / np.sqrt(len(d)))
            out[key] = {"mean_diff": round(mean, 4), "se": round(se, 4), "diffs": [round(float(x), 4) for x in d],
                        "within": bool(abs(mean) <= bound)}
    return out


# ----------------------------------------------------------------------------- scenes
def _vlsforest(*args) -> list[str]:
    return [sys.executable, "-m", "vlsforest.cli", *map(str, args)]


def spruce_cases(data: Path, work: Path, surveys, quick: bool) -> list[dict]:
    """Scene and surveys of the spruce F_BR08_08 written under ``work``; one case per survey."""
    import yaml

    from vlsforest.io.mesh import read_mesh
    from vlsforest.io.vox import read_vox
    from vlsforest.sim.planning import plan_survey

    crown, stem = data / CROWN, data / STEM
    missing = [p.name for p in (crown, stem) if not p.is_file()]
    if missing:
        raise BenchError(f"the data folder {data} lacks {', '.join(missing)} (--data DIR: the folder with "
                         f"{CROWN} and {STEM})")
    v = read_mesh(stem).vertices
    gz = float(v[:, 2].min())
    cx, cy = (0.5 * float(v[:, i].min() + v[:, i].max()) for i in (0, 1))
    side, changes = (QUICK[0], QUICK[1]) if quick else (GROUND_SIDE_M, {})
    h = side / 2.0
    scene = {"name": "F_BR08_08", "parts": [
        {"id": 1, "type": "plane", "z": gz, "extent": [cx - h, cy - h, cx + h, cy + h], "name": "ground"},
        {"id": 2, "type": "mesh", "path": str(stem.resolve()), "name": "stem"},
        {"id": 3, "type": "vox", "path": str(crown.resolve()), "mode": "fixed", "name": "crown"}]}
    folder = work / "F_BR08_08"
    folder.mkdir(parents=True, exist_ok=True)
    scene_yaml = folder / "scene.yaml"
    scene_yaml.write_text(yaml.safe_dump(scene, sort_keys=False))
    vox = read_vox(crown)
    c = vox.centres()
    lo, hi = c.min(axis=0) - 0.5 * vox.res, c.max(axis=0) + 0.5 * vox.res
    crown_extent = [float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])]
    ground_extent = scene["parts"][0]["extent"]
    cases = []
    for name in surveys:
        scen = dict(SCENARIOS[name], **changes.get(name, {}))
        extent = ground_extent if name == "als" else crown_extent
        path = folder / f"{name}.yaml"
        path.write_text(yaml.safe_dump(plan_survey(scen, extent, gz, where=f"scenario {name}"), sort_keys=False))
        cases.append({"scene": "F_BR08_08" + (" (quick)" if quick else ""), "survey": name,
                      "scene_yaml": scene_yaml, "survey_yaml": path, "folder": folder, "ground_z": gz})
    return cases


def study_cases(results: Path, plot: str, method: str, surveys, work: Path) -> list[dict]:
    """One study plot's scene with those of its surveys that exist."""
    scene_yaml = results / plot / method / "scene" / "scene.yaml"
    if not scene_yaml.is_file():
        raise BenchError(f"no study scene {scene_yaml} (--study-results DIR: a finished run's results/ folder; "
                         "--plot, --method)")
    cases = []
    for name in surveys:
        path = results / plot / "surveys" / f"{name}.yaml"
        if path.is_file():
            folder = work / f"{plot}_{method}"
            folder.mkdir(parents=True, exist_ok=True)
            cases.append({"scene": f"{plot}/{method}", "survey": name, "scene_yaml": scene_yaml,
                          "survey_yaml": path, "folder": folder})
    if not cases:
        raise BenchError(f"no survey {', '.join(f'{s}.yaml' for s in surveys)} under {results / plot / 'surveys'}")
    return cases


def export(case: dict) -> str | None:
    """``vlsforest scene helios`` of a case into ``folder/helios_{survey}``; its error line or None."""
    out = case["folder"] / f"helios_{case['survey']}"
    if out.exists():
        shutil.rmtree(out)
    r = subprocess.run(_vlsforest("scene", "helios", case["scene_yaml"], "--survey", case["survey_yaml"],
                                  "-o", out, "--name", case["survey"]), capture_output=True, text=True)
    case["helios_dir"] = out
    if r.returncode != 0:
        lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
        return lines[-1] if lines else f"exit {r.returncode}"
    return None


# ----------------------------------------------------------------------------- the two tools
def helios_version(binary: str, given: str | None) -> str | None:
    """HELIOS++'s version: ``given``, else the first ``X.Y.Z`` its ``--version`` prints."""
    if given:
        return given
    try:
        r = subprocess.run([binary, "--version"], capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.SubprocessError):
        return None
    m = re.search(r"(\d+)\.(\d+)\.(\d+)", r.stdout + r.stderr)
    return m.group(0) if m else None


def helios_command(binary: str, version: str | None, out: Path, seed: int, threads: int, extra) -> list[str]:
    """The HELIOS++ command line of one run (module docstring)."""
    cmd = [binary, "survey.xml", "--output", str(out), "--seed", str(seed), "-j", str(threads), "--lasOutput",
           "--rebuildScene"]
    major = int(version.split(".")[0]) if version else 1
    if major >= 2:
        cmd += ["--legacyEnergyModel", "--noSceneWriting", "--kdtJobs", str(threads), "--assets", "."]
    return cmd + list(extra)


def run_ours(case: dict, threads: int, seed: int, repeats: int) -> dict:
    """``vlsforest simulate`` of a case, ``repeats`` times; medians and counts."""
    from vlsforest.io.las import read_las

    stem = case["folder"] / f"ours_{case['survey']}_{threads}"
    las, timing, log = stem.with_suffix(".las"), stem.with_suffix(".json"), stem.with_suffix(".log")
    cmd = _vlsforest("simulate", case["scene_yaml"], case["survey_yaml"], "-o", las, "--workers", threads,
                     "--seed", seed, "--quiet", "--timing", timing)
    runs = []
    for _ in range(repeats):
        r = measure(cmd, log=log)
        if r["rc"] != 0:
            return {"error": f"exit {r['rc']}: {_tail(log)}", "command": shlex.join(cmd)}
        t = json.loads(timing.read_text())
        r.update(engine_s=float(t["total"]), n_pulses=int(t["n_pulses"]), n_rays=int(t["n_rays"]),
                 n_points=int(t["n_points"]))
        runs.append(r)
    res = _median_runs(runs)
    cloud = read_las(las, allow_empty=True)
    n_read = len(cloud.xyz)
    if "ground_z" in case and n_read:
        a = cloud.attrs
        res_summary = point_summary(cloud.xyz, a["object_id"], a["number_of_returns"], a["gps_time"],
                                    a["point_source_id"], case["ground_z"])
    else:
        res_summary = None
    res.update(n_points=n_read, n_pulses=runs[-1]["n_pulses"], n_rays=runs[-1]["n_rays"],
               outside_engine_s=round(res["wall_s"] - res["engine_s"], 3),
               pulses_per_cpu_s=round(runs[-1]["n_pulses"] / res["cpu_s"]) if res["cpu_s"] else None,
               command=shlex.join(cmd))
    if n_read != runs[-1]["n_points"] or len({r["n_points"] for r in runs}) > 1:
        res["note"] = (f"point counts differ: LAS {n_read}, timing "
                       f"{sorted({r['n_points'] for r in runs})}")
    if res_summary is not None:
        res["points"] = res_summary
    las.unlink(missing_ok=True)
    return res


def run_helios(case: dict, binary: str, version, threads: int, seed: int, repeats: int, extra) -> dict:
    """HELIOS++ on a case's exported folder, ``repeats`` times; medians and point counts."""
    out = case["folder"] / f"helios_out_{case['survey']}_{threads}"
    log = case["folder"] / f"helios_{case['survey']}_{threads}.log"
    cmd = helios_command(binary, version, out, seed, threads, extra)
    runs, counts, files = [], set(), []
    for _ in range(repeats):
        if out.exists():
            shutil.rmtree(out)
        r = measure(cmd, cwd=case["helios_dir"], log=log)
        if r["rc"] != 0:
            return {"error": f"exit {r['rc']}: {_tail(log)}", "command": shlex.join(cmd)}
        n, files = count_points(out) if out.is_dir() else (0, [])
        if not files:
            return {"error": f"no point file (.las, .laz, .xyz) under {out}", "command": shlex.join(cmd)}
        counts.add(n)
        runs.append(r)
    res = _median_runs(runs)
    res.pop("engine_s")
    res.update(n_points=max(counts), point_files=files, command=shlex.join(cmd))
    if len(counts) > 1:
        res["note"] = f"point counts differ between repeats: {sorted(counts)}"
    if "ground_z" in case:
        pts = helios_points(out, files)
        if pts:
            res["points"] = point_summary(pts["xyz"], pts["object_id"], pts["number_of_returns"],
                                          pts["gps_time"], pts["line"], case["ground_z"])
    shutil.rmtree(out, ignore_errors=True)
    return res


def row_of(case: dict, threads: int, ours: dict, helios: dict | None, helios_note: str | None) -> dict:
    """The result row of one scene × survey × thread count."""
    row = {"scene": case["scene"], "survey": case["survey"], "threads": threads,
           "n_pulses": ours.get("n_pulses"), "vlsforest": ours, "helios": helios}
    if helios is None:
        row["helios_note"] = helios_note
    elif "error" not in helios and "error" not in ours:
        helios["pulses_per_cpu_s"] = round(ours["n_pulses"] / helios["cpu_s"]) if helios["cpu_s"] else None

        def ratio(a, b):
            return round(a / b, 3) if a and b else None

        if ours.get("points") and helios.get("points"):
            row["agreement"] = agreement(ours["points"], helios["points"])
        row.update(speedup_wall=ratio(helios["wall_s"], ours["wall_s"]),
                   speedup_cpu=ratio(helios["cpu_s"], ours["cpu_s"]),
                   rss_ratio=ratio(ours["max_rss_mb"], helios["max_rss_mb"]),
                   points_ratio=ratio(ours["n_points"], helios["n_points"]))
        if min(row["speedup_wall"] or 1, row["speedup_cpu"] or 1) < 1:
            big = "engine_s" if ours["engine_s"] >= ours["outside_engine_s"] else "outside_engine_s"
            row["slower"] = (f"{big} {ours[big]:.2f} s of {ours['wall_s']:.2f} s wall (engine {ours['engine_s']:.2f} s: "
                             f"{ours['n_rays']:,} sub-rays; outside the engine {ours['outside_engine_s']:.2f} s: "
                             "start-up, scene, LAS write)")
    return row


def flat(row: dict) -> dict:
    """A result row with its per-tool figures as ``vlsforest.wall_s`` … columns (for the table)."""
    out = {}
    for k, v in row.items():
        if isinstance(v, dict):
            for kk, vv in v.items():
                if kk == "phases":
                    out[f"{k}.phases.n"] = vv["n_phases"]
                    for key in AGREEMENT:
                        if key in vv:
                            out[f"{k}.phases.{key}_mean_diff"] = vv[key]["mean_diff"]
                            out[f"{k}.phases.{key}_se"] = vv[key]["se"]
                            out[f"{k}.phases.{key}_within"] = vv[key]["within"]
                elif kk not in ("command", "point_files", "points", "vlsforest", "helios"):
                    out[f"{k}.{kk}"] = vv
        else:
            out[k] = v
    return out


# ----------------------------------------------------------------------------- driver
def _threads(spec: str) -> list[int]:
    n_cpu = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    out = []
    for tok in spec.split(","):
        tok = tok.strip()
        n = n_cpu if tok == "all" else int(tok) if tok.isdigit() else 0
        if n < 1:
            raise BenchError(f"--threads takes integers ≥ 1 and 'all', comma separated, got {spec!r}")
        if n not in out:
            out.append(n)
    return out


def _startup_s() -> float | None:
    """Wall seconds of a process that imports the simulator and its CLI."""
    r = measure([sys.executable, "-c", "import vlsforest.cli, vlsforest.sim"])
    return round(r["wall_s"], 3) if r["rc"] == 0 else None


def _table(rows: list[dict]) -> str:
    head = (f"{'scene':<18} {'survey':<6} {'thr':>3} {'pulses':>10} | {'ours s':>7} {'CPU s':>7} {'RSS MB':>7} "
            f"{'points':>9} | {'HELIOS s':>8} {'CPU s':>7} {'RSS MB':>7} {'points':>9} | {'×wall':>6} {'×CPU':>6}")
    lines = [head, "-" * len(head)]
    for r in rows:
        o, h = r["vlsforest"], r["helios"]

        def f(d, k, fmt):
            return format(d[k], fmt) if d and d.get(k) is not None else "-"

        lines.append(f"{r['scene']:<18} {r['survey']:<6} {r['threads']:>3} {f(r, 'n_pulses', ','):>10} | "
                     f"{f(o, 'wall_s', '.2f'):>7} {f(o, 'cpu_s', '.2f'):>7} {f(o, 'max_rss_mb', '.0f'):>7} "
                     f"{f(o, 'n_points', ','):>9} | {f(h, 'wall_s', '.2f'):>8} {f(h, 'cpu_s', '.2f'):>7} "
                     f"{f(h, 'max_rss_mb', '.0f'):>7} {f(h, 'n_points', ','):>9} | "
                     f"{f(r, 'speedup_wall', '.2f'):>6} {f(r, 'speedup_cpu', '.2f'):>6}")
        for who, d in (("vlsforest", o), ("HELIOS++", h)):
            if d and d.get("error"):
                lines.append(f"  {who} failed: {d['error']}")
        if r.get("slower"):
            lines.append(f"  slower: {r['slower']}")
        ag = r.get("agreement")
        if ag:
            parts = []
            for key in AGREEMENT:
                if f"{key}_diff" in ag:
                    d = ag[f"{key}_diff"]
                    txt = f"{100 * d:+.1f} %" if key.endswith("_points") else f"{d:+.2f}"
                    parts.append(f"{key} {ag['vlsforest'][key]} vs {ag['helios'][key]} ({txt}, "
                                 f"{'within' if ag[f'{key}_within'] else 'OUTSIDE'})")
            lines.append("  agreement: " + "; ".join(parts))
            ph = ag.get("phases")
            if ph:
                parts = []
                for key, bound in AGREEMENT.items():
                    if key in ph:
                        m, se = ph[key]["mean_diff"], ph[key]["se"]
                        txt = (f"{100 * m:+.1f} ± {100 * se:.1f} %" if key.endswith("_points") else f"{m:+.2f} ± {se:.2f}")
                        parts.append(f"{key} {txt} ({'within' if ph[key]['within'] else 'OUTSIDE'})")
                lines.append(f"  over {ph['n_phases']} pulse phases (mean ± SE): " + "; ".join(parts))
    lines.append("medians of the repeats; ×wall, ×CPU: HELIOS++'s seconds ÷ ours (above 1: we are faster); "
                 "RSS: the largest process")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--helios", help="HELIOS++ binary (without it only vlsforest is measured)")
    ap.add_argument("--helios-version", help="HELIOS++'s version X.Y.Z (default: what its --version prints)")
    ap.add_argument("--helios-arg", action="append", default=[], help="one more HELIOS++ argument (repeatable)")
    ap.add_argument("--data", type=Path, default=DATA, help=f"folder of {CROWN} and {STEM} (default {DATA})")
    ap.add_argument("--study-results", type=Path, help="a finished study run's results/ folder: also its plot")
    ap.add_argument("--study-only", action="store_true",
                    help="with --study-results: only the study plot, not the spruce")
    ap.add_argument("--plot", default="P3", help="the study plot (default P3)")
    ap.add_argument("--method", default="scaled", help="the study plot's scene method (default scaled)")
    ap.add_argument("--surveys", default=",".join(SURVEYS), help="comma-separated: als, uls (default both)")
    ap.add_argument("--threads", default="1,all", help="thread counts, comma-separated; 'all': every CPU (default 1,all)")
    ap.add_argument("--repeats", type=int, default=3, help="timed runs per measurement, median kept (default 3)")
    ap.add_argument("--warmup", type=int, default=1,
                    help="untimed runs before the timed ones: ours per case, HELIOS++ on the first case (default 1)")
    ap.add_argument("--phases", type=int, default=0,
                    help="on the spruce also fly N−1 more pulse phases (legs shifted within a voxel) with both tools "
                         "and judge the agreement on the mean over all N (default 0: the one flight)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--quick", action="store_true", help="small ground and short surveys of the spruce (tests)")
    ap.add_argument("--workdir", type=Path, help="keep the scenes, exports and logs here (default: a temporary folder)")
    args = ap.parse_args(argv)
    try:
        return _main(args)
    except BenchError as exc:
        print(f"bench_helios: error: {exc}", file=sys.stderr)
        return 2


def _main(args) -> int:
    surveys = [s.strip() for s in args.surveys.split(",") if s.strip()]
    if not surveys or set(surveys) - set(SURVEYS):
        raise BenchError(f"--surveys takes {', '.join(SURVEYS)}, got {args.surveys!r}")
    threads = _threads(args.threads)
    if args.repeats < 1 or args.warmup < 0 or args.phases < 0 or args.phases == 1:
        raise BenchError("--repeats must be ≥ 1, --warmup ≥ 0 and --phases 0 or ≥ 2")
    binary = None
    if args.helios:
        binary = shutil.which(args.helios) or args.helios
        if not (os.path.isfile(binary) and os.access(binary, os.X_OK)):
            raise BenchError(f"--helios {args.helios}: not an executable file")
        binary = str(Path(binary).resolve())
    if args.study_only and not args.study_results:
        raise BenchError("--study-only needs --study-results DIR")
    if not args.data.is_dir() and not args.study_only:
        raise BenchError(f"no data folder {args.data} (--data DIR: the folder with {CROWN} and {STEM})")
    with tempfile.TemporaryDirectory(prefix="bench_helios_") as tmp:
        work = args.workdir or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        cases = [] if args.study_only else spruce_cases(args.data, work, surveys, args.quick)
        if args.study_results:
            cases += study_cases(args.study_results, args.plot, args.method, surveys, work)
        version = helios_version(binary, args.helios_version) if binary else None
        for case in cases:
            case["export_error"] = export(case)
        print(f"bench_helios: {len(cases)} case(s), threads {threads}, {args.repeats} repeat(s); HELIOS++: "
              + (f"{binary} (version {version or 'unknown'})" if binary else "none (--helios PATH), our side only"))
        for case in cases:
            if case["export_error"]:
                print(f"  {case['scene']} {case['survey']}: HELIOS++ export refused: {case['export_error']}")
        startup = _startup_s()
        rows = []
        warm_helios = args.warmup
        for case in cases:
            # untimed: every case (its voxels may go to another back end, whose compiled
            # kernels are loaded into the disk cache by its first run); HELIOS++ once
            for _ in range(args.warmup):
                run_ours(case, max(threads), args.seed, 1)
            if binary and not case["export_error"]:
                for _ in range(warm_helios):
                    run_helios(case, binary, version, max(threads), args.seed, 1, args.helios_arg)
                warm_helios = 0
            for t in threads:
                ours = run_ours(case, t, args.seed, args.repeats)
                helios, note = None, None
                if not binary:
                    note = "no HELIOS++ binary given (--helios PATH): vlsforest only"
                elif case["export_error"]:
                    note = f"the HELIOS++ export refused this survey: {case['export_error']}"
                else:
                    helios = run_helios(case, binary, version, t, args.seed, args.repeats, args.helios_arg)
                rows.append(row_of(case, t, ours, helios, note))
                print(f"  done: {case['scene']} {case['survey']} threads {t}", flush=True)
            last = rows[-1]
            if args.phases and "ground_z" in case and last.get("agreement"):
                pairs = [(last["agreement"]["vlsforest"], last["agreement"]["helios"])]
                shifts = [[0.0, 0.0]]
                for k in range(1, args.phases):
                    pc = phase_case(case, k, args.phases)
                    if export(pc) is None:
                        o = run_ours(pc, max(threads), args.seed, 1)
                        h = run_helios(pc, binary, version, max(threads), args.seed, 1, args.helios_arg)
                        if o.get("points") and h.get("points"):
                            pairs.append((o["points"], h["points"]))
                            shifts.append(pc["shift_m"])
                last["agreement"]["phases"] = dict(phase_agreement(pairs), shifts_m=shifts)
                print(f"  done: {case['scene']} {case['survey']} {len(pairs)} pulse phases", flush=True)
    print()
    print(f"Summary ({len(os.sched_getaffinity(0))} CPUs usable; startup of the simulator "
          f"{startup if startup is not None else '-'} s)")
    print(_table(rows))
    print("Reproduce: python benchmarks/bench_helios.py" + (" --helios PATH" if binary else "")
          + (" --quick" if args.quick else ""))
    benchresult.record(helios_binary=binary, helios_version=version, repeats=args.repeats, warmup=args.warmup,
                       threads=threads, quick=args.quick, startup_s=startup, seed=args.seed, rows=rows,
                       table=[flat(r) for r in rows])
    failed = [r for r in rows if "error" in r["vlsforest"] or (r["helios"] or {}).get("error")]
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(benchresult.run("bench_helios", main))
