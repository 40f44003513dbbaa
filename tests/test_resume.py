"""Interrupted, read-only and partly failing runs.

- ``kill -9`` of Snakemake and all its jobs in the middle of the quick study, then the resume
  documented in the README (``snakemake --unlock`` with the run's arguments, then the run command
  again): the results are the bytes of an uninterrupted run.
- A read-only checkout: the commands run and write nothing into the package (numba's cache goes
  to the user's cache folder, to ``NUMBA_CACHE_DIR``, or, where neither can be written, to a
  temporary folder that is removed); the workflow plans from a read-only checkout and writes
  only ``.snakemake/`` into its working directory.
- ``vlsforest synth`` recording plots side by side: when one plot fails, no file of the forest
  remains.
"""

from __future__ import annotations

import copy
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
from wfrun import QUICK, REPO, job_env, snakemake_cli, snakemake_command

from vlsforest.cli import main

#: the README's run command for the quick study (after `.venv/bin/snakemake`)
RUN = ("--cores", 2, "--configfile", QUICK)
#: the wall-clock timings, which differ between any two runs; every other file under results/ is compared
TIMING_FILES = {"timing.json", "sim_times.csv", "table5.csv"}

#: the cheapest recording physics (test speed)
CHEAP_PHYSICS = {"als": {"beam_sample_quality": 1}, "uls": {"beam_sample_quality": 1}, "tls": {}}
#: the quick forest with one coarse TLS scan
TINY_SYNTH = {"forest": {"preset": "quick"}, "tls": {"n_positions": 1, "step_deg": 1.0, "n_tilted": 0},
              "recordings": {"uls": {"repeats": 1, "cross_margin_m": 0.0}}}
SCENARIO = {"scanner": "riegl_minivux1uav", "pattern": "double_grid", "altitude_m": 40, "speed_mps": 8,
            "line_spacing_m": 28, "n_lines": 1, "margin_m": 0, "overrides": {"prf_hz": 5000}}


def _files(root: Path) -> dict:
    """Every file under ``root`` (hidden ones included) → its path relative to ``root``."""
    return {str(p.relative_to(root)): p for p in root.rglob("*") if p.is_file()}


# ------------------------------------------------------------------ kill -9, then resume
def _group_gone(pgid: int, timeout: float = 60.0) -> bool:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        try:
            os.killpg(pgid, 0)
        except ProcessLookupError:
            return True
        time.sleep(0.2)
    return False


def test_kill_9_mid_study_then_the_documented_resume_gives_the_uninterrupted_bytes(quick_run, tmp_path):
    """The quick study is killed (SIGKILL to Snakemake's process group: Snakemake and every job)
    once some simulations have written their clouds; its lock is found stale (what
    ``run-study.sh`` removes), and the resume (``--unlock``, then the run command again)
    finishes it. Compared with the uninterrupted run (``quick_run``): the same
    set of files under ``results/`` — so no temporary or partial file is left — and the same
    bytes for each, except the wall-clock timings (``timing.json``, ``sim_times.csv``,
    ``table5.csv``). ``logs/`` and ``.snakemake/`` are not results and are not compared."""
    reference, _, _ = quick_run
    cfg = yaml.safe_load(QUICK.read_text())
    n_sims = len(cfg["plots"]) * len(cfg["methods"]) * len(cfg["scenarios"])
    work = tmp_path / "run"
    work.mkdir()
    with open(tmp_path / "killed.log", "w") as log:
        proc = subprocess.Popen(snakemake_command(*RUN), cwd=work, env=job_env(os.environ), stdout=log,
                                stderr=subprocess.STDOUT, start_new_session=True)
        try:
            t0 = time.monotonic()
            while proc.poll() is None and time.monotonic() - t0 < 1800:
                if list(work.glob("results/*/*/*/sim.laz")):
                    break
                time.sleep(0.5)
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=60)
    assert proc.returncode == -signal.SIGKILL, (tmp_path / "killed.log").read_text()[-3000:]
    assert _group_gone(proc.pid), "jobs of the killed run still run"
    done = list(work.glob("results/*/*/*/sim.laz"))
    assert 1 <= len(done) < n_sims, done
    assert not (work / "results" / "summary" / "tree_metrics.csv").exists()
    # the killed run's lock stays behind, and run-study.sh's check finds it stale
    stale = subprocess.run(["bash", str(REPO / "scripts" / "stale-lock.sh"), str(work)], capture_output=True)
    assert stale.returncode == 0, stale.stderr
    # Snakemake called directly refuses and names the remedy
    again = snakemake_cli(*RUN, cwd=work, timeout=600)
    assert again.returncode != 0 and "--unlock" in again.stdout + again.stderr, again.stderr[-3000:]
    unlock = snakemake_cli("--unlock", *RUN[2:], cwd=work, timeout=600)
    assert unlock.returncode == 0, unlock.stderr[-3000:]
    resumed = snakemake_cli(*RUN, cwd=work, timeout=3600)
    assert resumed.returncode == 0, resumed.stderr[-4000:]

    ours = {f: p for f, p in _files(work / "results").items() if Path(f).name not in TIMING_FILES}
    theirs = {f: p for f, p in _files(reference / "results").items() if Path(f).name not in TIMING_FILES}
    assert sorted(ours) == sorted(theirs)
    assert any(f.endswith("sim.laz") for f in ours) and any(f.endswith("findings.md") for f in ours)
    for f in sorted(ours):
        assert ours[f].read_bytes() == theirs[f].read_bytes(), f


# ------------------------------------------------------------------ read-only checkout
def _unprivileged(cmd: list) -> list:
    """``cmd`` run so that file permissions bind it: as root, without the capabilities that let
    root write into read-only folders (skip where that cannot be done)."""
    if os.geteuid() != 0:
        return cmd
    setpriv = shutil.which("setpriv")
    if setpriv is None:
        pytest.skip("root without setpriv: a read-only folder cannot be made binding")
    return [setpriv, "--bounding-set=-dac_override,-dac_read_search,-fowner,-linux_immutable", *cmd]


def _read_only_copy(dest: Path, parts) -> Path:
    """Copy ``parts`` of the repository (without __pycache__) to ``dest`` and make it read-only."""
    for part in parts:
        src = REPO / part
        if src.is_dir():
            shutil.copytree(src, dest / part, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            (dest / part).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / part)
    _chmod_tree(dest, writable=False)
    return dest


def _chmod_tree(root: Path, writable: bool) -> None:
    for p in [root, *root.rglob("*")]:
        mode = p.stat().st_mode & 0o7777
        os.chmod(p, mode | 0o200 if writable else mode & ~0o222)


def _snapshot(root: Path) -> dict:
    """Every file and folder under ``root`` with its size and modification time."""
    return {str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns) for p in root.rglob("*")}


@pytest.fixture
def checkout(tmp_path):
    """A read-only copy of the library; made writable again afterwards, so it can be removed."""
    root = _read_only_copy(tmp_path / "checkout", ["workflow/vlsforest"])
    yield root
    _chmod_tree(root, writable=True)


def _env(home: Path, checkout: Path, tmpdir: Path, numba_cache=None) -> dict:
    env = {k: v for k, v in os.environ.items()
           if k not in ("NUMBA_CACHE_DIR", "XDG_CACHE_HOME", "PYTHONDONTWRITEBYTECODE")}
    env.update(HOME=str(home), TMPDIR=str(tmpdir), PYTHONPATH=str(checkout / "workflow"))
    if numba_cache is not None:
        env["NUMBA_CACHE_DIR"] = str(numba_cache)
    return env


def _vlsforest(args, cwd, env):
    proc = subprocess.run(_unprivileged([sys.executable, "-m", "vlsforest.cli", *map(str, args)]), cwd=cwd,
                          env=env, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc


@pytest.mark.parametrize("cache", ["home", "NUMBA_CACHE_DIR", "nowhere"])
def test_commands_from_a_read_only_checkout_write_nothing_into_it(checkout, tmp_path, cache):
    """demo, plan and simulate (and, with a writable home, synth) run from a read-only copy of the
    library and add nothing to it. numba's cache goes to ``~/.cache/numba``
    (``cache="home"``), to ``NUMBA_CACHE_DIR`` where it is set, and where neither can be written
    (``"nowhere"``) to a temporary folder that is gone when the command ends. The cloud is the
    same bytes as the one simulated from the writable checkout."""
    home, work, tmpdir, numba_cache = (tmp_path / d for d in ("home", "work", "tmp", "numba"))
    for d in (home, work, tmpdir):
        d.mkdir()
    if cache != "home":
        os.chmod(home, 0o555)
    env = _env(home, checkout, tmpdir, numba_cache if cache == "NUMBA_CACHE_DIR" else None)
    package = checkout / "workflow" / "vlsforest"
    probe = subprocess.run(_unprivileged([sys.executable, "-c", f"open({str(package / 'probe')!r}, 'w')"]),
                           env=env, capture_output=True, text=True)
    assert probe.returncode != 0 and "PermissionError" in probe.stderr, "the copy is not read-only"
    before = _snapshot(checkout)

    (work / "scenario.yaml").write_text(yaml.safe_dump(SCENARIO))
    _vlsforest(["demo", "-o", "scene/scene.yaml", "--seed", "1"], work, env)
    _vlsforest(["plan", "--scene", "scene/scene.yaml", "--scenario", "scenario.yaml", "-o", "survey.yaml"], work, env)
    _vlsforest(["simulate", "scene/scene.yaml", "survey.yaml", "-o", "sim.laz", "--workers", "1", "--quiet"],
               work, env)
    if cache == "home":
        (work / "tiny.yaml").write_text(yaml.safe_dump(TINY_SYNTH))
        (work / "physics.yaml").write_text(yaml.safe_dump(CHEAP_PHYSICS))
        _vlsforest(["synth", "tiny.yaml", "--recording-physics", "physics.yaml", "-o", "forest", "--quiet",
                    "--workers", "1"], work, env)
        assert (work / "forest" / "plots" / "Q1" / "uls.laz").is_file()

    assert _snapshot(checkout) == before
    cached = {"home": home / ".cache" / "numba", "NUMBA_CACHE_DIR": numba_cache, "nowhere": None}[cache]
    if cached is not None:
        assert list(cached.rglob("*.nbi")), f"numba cached nothing in {cached}"
    else:
        assert not list(tmpdir.iterdir())  # the temporary cache is removed
    # the same cloud as from the writable checkout
    assert main(["demo", "-o", str(tmp_path / "ref" / "scene" / "scene.yaml"), "--seed", "1"]) == 0
    assert main(["simulate", str(tmp_path / "ref" / "scene" / "scene.yaml"), str(work / "survey.yaml"),
                 "-o", str(tmp_path / "ref" / "sim.laz"), "--workers", "1", "--quiet"]) == 0
    assert (work / "sim.laz").read_bytes() == (tmp_path / "ref" / "sim.laz").read_bytes()


def test_the_workflow_plans_from_a_read_only_checkout(tmp_path):
    """Snakemake on the Snakefile of a read-only checkout (the library, rules, configs and
    profiles) plans the quick study; it writes only ``.snakemake/`` into its working directory and
    nothing into the checkout. (The jobs are the ``vlsforest`` commands tested above.)"""
    root = _read_only_copy(tmp_path / "checkout", ["Snakefile", "workflow", "config", "profiles"])
    try:
        work, home = tmp_path / "work", tmp_path / "home"
        work.mkdir()
        home.mkdir()
        before = _snapshot(root)
        env = job_env(_env(home, root, tmp_path))
        cmd = _unprivileged(snakemake_command("-n", *RUN, snakefile=root / "Snakefile"))
        proc = subprocess.run(cmd, cwd=work, env=env, capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, proc.stderr[-3000:]
        assert "synth_plot" in proc.stdout + proc.stderr
        assert _snapshot(root) == before
        assert {p.name for p in work.iterdir()} <= {".snakemake"}
    finally:
        _chmod_tree(root, writable=True)


def test_the_quick_study_runs_from_a_read_only_checkout(quick_run, tmp_path):
    """The whole quick study, run as an unprivileged user from a read-only copy of the checkout
    (library, rules, configs, profiles, environment files), finishes; it writes
    nothing into the copy, only ``results/``, ``logs/`` and ``.snakemake/`` into its working
    directory, and its results are the bytes of the run from the writable checkout (timing files
    aside)."""
    reference, _, _ = quick_run
    root = _read_only_copy(tmp_path / "checkout", ["Snakefile", "workflow", "config", "profiles", "envs"])
    work, home = tmp_path / "work", tmp_path / "home"
    work.mkdir()
    home.mkdir()  # writable: numba's cache goes to ~/.cache/numba
    try:
        before = _snapshot(root)
        env = job_env(_env(home, root, tmp_path))
        cmd = _unprivileged(snakemake_command(*RUN, snakefile=root / "Snakefile"))
        proc = subprocess.run(cmd, cwd=work, env=env, capture_output=True, text=True, timeout=1800)
        assert proc.returncode == 0, proc.stderr[-3000:]
        assert _snapshot(root) == before
        assert {p.name for p in work.iterdir()} <= {"results", "logs", ".snakemake"}
        ours = {f: p for f, p in _files(work / "results").items() if Path(f).name not in TIMING_FILES}
        theirs = {f: p for f, p in _files(reference / "results").items() if Path(f).name not in TIMING_FILES}
        assert sorted(ours) == sorted(theirs)
        for f in sorted(ours):
            assert ours[f].read_bytes() == theirs[f].read_bytes(), f
    finally:
        _chmod_tree(root, writable=True)


# ------------------------------------------------------------------ synth: all or nothing
def test_side_by_side_synth_with_a_failing_plot_leaves_no_forest(tmp_path, capsys):
    """Two plots recorded side by side (``--workers 2``); one of them cannot write its TLS folder
    (a file stands in its place). The command ends in one line and exit 2, and the other plot,
    recorded in full, leaves nothing behind either: only the blocking file remains."""
    from vlsforest.synth.forest import QUICK_FOREST

    forest = copy.deepcopy(QUICK_FOREST)
    forest["plots"]["Q2"] = {"targets": {"picea_abies": 1}, "area_ha": 0.16, "ground_elevation_m": 250.0}
    cfg = {**copy.deepcopy(TINY_SYNTH), "forest": forest}
    (tmp_path / "two.yaml").write_text(yaml.safe_dump(cfg))
    (tmp_path / "physics.yaml").write_text(yaml.safe_dump(CHEAP_PHYSICS))
    out = tmp_path / "forest"
    blocker = out / "plots" / "Q2" / "tls"
    blocker.parent.mkdir(parents=True)
    blocker.write_text("not a folder")
    rc = main(["synth", str(tmp_path / "two.yaml"), "--recording-physics", str(tmp_path / "physics.yaml"),
               "-o", str(out), "--seed", "1", "--workers", "2", "--quiet"])
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert rc == 2, err
    assert len(lines) == 1 and lines[0].startswith("vlsforest synth: error:") and str(blocker) in lines[0], err
    assert sorted(_files(out)) == ["plots/Q2/tls"]
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*")) == ["plots", "plots/Q2", "plots/Q2/tls"]


def _write_in_worker(folder: str, name: str):
    """A worker's part of the outputs: ``folder/name/a.txt``, collected, not installed."""
    from vlsforest.io.atomic import collect_outputs, write_text

    with collect_outputs() as pending:
        write_text(Path(folder) / name / "a.txt", name)
    return pending, os.getpid()


def _in_worker(*args):
    """:func:`_write_in_worker` in a spawned process (as synth's plots are)."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
        return pool.submit(_write_in_worker, *args).result()


def test_outputs_collected_in_a_worker_join_the_parent_transaction(tmp_path):
    """The parts of :mod:`vlsforest.io.atomic` that synth's worker processes use: a worker's
    finished files stay under temporary names until the parent's transaction ends; they are
    installed with it, or removed with it (with the folders made for them, one worker's folder
    inside another's). Adopted files carry the parent's process id, so that no writer takes them
    for the leftovers of the ended worker."""
    from vlsforest.io.atomic import adopt_outputs, collect_outputs, output_transaction, write_text

    (first, _), (second, _) = _in_worker(str(tmp_path / "shared"), "B"), _in_worker(str(tmp_path / "shared"), "A")
    names = [Path(f).name for f in _files(tmp_path)]
    assert len(names) == 2 and all(n.startswith(".tmp-") for n in names)
    with pytest.raises(RuntimeError):
        with output_transaction():
            write_text(tmp_path / "top.txt", "top")
            adopt_outputs(second)  # its folder shared/A lies in shared/, made by the other worker
            adopt_outputs(first)
            raise RuntimeError("a third plot failed")
    assert not any(tmp_path.iterdir())

    first, pid = _in_worker(str(tmp_path / "shared"), "B")
    assert pid != os.getpid()
    assert all(Path(f).name.startswith(f".tmp-{pid}-") for f in _files(tmp_path))
    with output_transaction():
        adopt_outputs(first)
        assert all(Path(f).name.startswith(f".tmp-{os.getpid()}-") for f in _files(tmp_path))
    assert {f: p.read_text() for f, p in _files(tmp_path).items()} == {"shared/B/a.txt": "B"}
    with pytest.raises(KeyboardInterrupt):
        with collect_outputs():
            write_text(tmp_path / "other" / "a.txt", "x")
            raise KeyboardInterrupt
    assert sorted(_files(tmp_path)) == ["shared/B/a.txt"] and not (tmp_path / "other").exists()


def test_stale_lock_is_found_only_when_no_snakemake_works_in_the_folder(tmp_path):
    """scripts/stale-lock.sh (run-study.sh removes such a lock, so that its command resumes a run
    killed with kill -9): no lock → 1; a lock and no Snakemake process in the folder → 0; a lock
    and a process named snakemake working in the folder → 1."""
    script = REPO / "scripts" / "stale-lock.sh"

    def check():
        return subprocess.run(["bash", str(script), str(tmp_path)], capture_output=True, text=True).returncode

    assert check() == 1
    locks = tmp_path / ".snakemake" / "locks"
    locks.mkdir(parents=True)
    assert check() == 1  # an empty lock folder is no lock
    (locks / "0.input.lock").write_text(str(tmp_path / "results") + "\n")
    assert check() == 0
    alive = subprocess.Popen(["bash", "-c", "exec -a snakemake sleep 60"], cwd=tmp_path)
    try:
        t0 = time.monotonic()
        while time.monotonic() - t0 < 10 and b"snakemake" not in Path(f"/proc/{alive.pid}/cmdline").read_bytes():
            time.sleep(0.05)
        assert check() == 1
    finally:
        alive.kill()
        alive.wait()
    assert check() == 0
