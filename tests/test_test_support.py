"""The test suite's own machinery: the run-wide shared build (tests/runwide.py), the tier marks
(tests/conftest.py) and the slow tests' outcome record (tests/outcome_record.py), each on a
small made-up case."""

from __future__ import annotations

import json
import multiprocessing
import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from types import SimpleNamespace

import pytest
from runwide import SharedBuildError, built_once, run_dir

TESTS = Path(__file__).resolve().parent


def _pytest(args, cwd, timeout=120):
    """``python -m pytest`` in ``cwd`` with tests/ importable (runwide, outcome_record)."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-p", "no:dash", *args],
                          cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)


# ----------------------------------------------------------------------------- shared build
def _build_in_a_child(root):
    """Build ``shared`` (0.3 s, logging each build) from a separate process."""
    def build(folder):
        with open(root / "builds.log", "a") as fh:
            fh.write(f"{os.getpid()}\n")
        time.sleep(0.3)
        (folder / "data.txt").write_text("built")
        return {"pid": os.getpid()}

    folder, record = built_once(root, "shared", build)
    return str(folder), record, (folder / "data.txt").read_text()


def test_processes_asking_at_once_share_one_build(tmp_path):
    with multiprocessing.get_context("fork").Pool(3) as pool:
        results = pool.map(_build_in_a_child, [tmp_path] * 3)
    builds = (tmp_path / "builds.log").read_text().split()
    assert len(builds) == 1
    assert results == [(str(tmp_path / "shared"), {"pid": int(builds[0])}, "built")] * 3


def test_a_failed_build_fails_every_later_request_without_a_second_try(tmp_path):
    calls = []

    def build(folder):
        calls.append(folder)
        raise ValueError("no disk")

    with pytest.raises(SharedBuildError, match="no disk"):
        built_once(tmp_path, "x", build)
    with pytest.raises(SharedBuildError, match="failed earlier in this run:(.|\n)*ValueError: no disk"):
        built_once(tmp_path, "x", build)
    assert len(calls) == 1


def test_run_dir_is_the_controllers_base_folder_on_a_worker(tmp_path, monkeypatch):
    factory = SimpleNamespace(getbasetemp=lambda: tmp_path / "gw1")
    monkeypatch.setenv("PYTEST_XDIST_WORKER", "gw1")
    assert run_dir(factory) == tmp_path
    monkeypatch.delenv("PYTEST_XDIST_WORKER")
    assert run_dir(factory) == tmp_path / "gw1"


def test_two_xdist_workers_build_a_run_wide_fixture_once(tmp_path):
    """A made-up suite whose four tests use one run-wide fixture, on two pytest-xdist workers:
    both workers run tests, the build happens once, every test sees the same folder."""
    (tmp_path / "conftest.py").write_text(textwrap.dedent("""
        import os, time
        import pytest
        from runwide import built_once, run_dir

        @pytest.fixture(scope="session")
        def shared(tmp_path_factory):
            root = run_dir(tmp_path_factory)
            def build(folder):
                with open(root / "builds.log", "a") as fh:
                    fh.write(os.environ["PYTEST_XDIST_WORKER"] + "\\n")
                time.sleep(1.0)
                return {}
            return built_once(root, "shared", build)[0], root
    """))
    (tmp_path / "test_dummy.py").write_text(textwrap.dedent("""
        import os
        import pytest

        @pytest.mark.parametrize("k", range(4))
        def test_uses_the_shared_folder(shared, k):
            folder, root = shared
            with open(root / "seen.log", "a") as fh:
                fh.write(f"{os.environ['PYTEST_XDIST_WORKER']} {folder}\\n")
    """))
    base = tmp_path / "base"
    proc = _pytest(["-q", "-n", "2", "--dist", "load", "--basetemp", str(base), "test_dummy.py"], cwd=tmp_path)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert len((base / "builds.log").read_text().split()) == 1
    seen = [line.split() for line in (base / "seen.log").read_text().splitlines()]
    assert len(seen) == 4
    assert {w for w, _ in seen} == {"gw0", "gw1"}
    assert {f for _, f in seen} == {str(base / "shared")}


# ----------------------------------------------------------------------------- tier marks
def test_the_tiers_split_by_module_by_fixture_and_by_mark(tmp_path):
    """conftest.py marks whole modules of its list and tests using the quick study e2e; a test
    can mark itself; everything else is in the unit tier."""
    collected = {}
    for tier in ("e2e and not slow", "not e2e and not slow"):
        proc = _pytest(["--collect-only", "-q", "-m", tier, "tests/test_workflow.py", "tests/test_segment.py",
                        "tests/test_bad_inputs.py"], cwd=TESTS.parent)
        assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
        collected[tier] = {line.split("[")[0] for line in proc.stdout.splitlines() if "::" in line}
    e2e, unit = collected["e2e and not slow"], collected["not e2e and not slow"]
    assert not e2e & unit
    assert "tests/test_workflow.py::test_lint_passes" in e2e  # module list
    assert "tests/test_segment.py::test_quick_forest_against_truth" in e2e  # quick_forest fixture
    assert "tests/test_bad_inputs.py::test_bad_workflow_config_stops_with_one_line" in e2e  # own mark
    assert not any(t.startswith("tests/test_workflow.py") for t in unit)
    assert "tests/test_segment.py::test_real_tls_plot_lpine" in unit
    assert "tests/test_bad_inputs.py::test_bad_yaml_is_one_line_naming_the_file" in unit


def _runs_the_workflow(tmp_path):
    from wfrun import snakemake_cli

    return snakemake_cli("-n", cwd=tmp_path)


def _reads_a_file(tmp_path):
    return (tmp_path / "a.csv").read_text()


def test_a_test_whose_code_runs_snakemake_is_e2e():
    from conftest import is_e2e

    def item(function, name="test_x.py", fixtures=(), marked=False):
        return SimpleNamespace(path=Path(name), fixturenames=list(fixtures), function=function,
                               get_closest_marker=lambda mark: object() if marked else None)

    assert is_e2e(item(_runs_the_workflow))
    assert not is_e2e(item(_reads_a_file))
    assert is_e2e(item(_reads_a_file, name="test_workflow.py"))
    assert is_e2e(item(_reads_a_file, fixtures=["tmp_path", "quick_forest"]))
    assert is_e2e(item(_reads_a_file, marked=True))


# ----------------------------------------------------------------------------- outcome record
DUMMY_SUITE = """
import time
import pytest

def test_passes():
    time.sleep(0.25)

def test_fails():
    assert 1 == 2, "one is not two"

@pytest.mark.skip(reason="not on this machine")
def test_skipped():
    pass

@pytest.mark.xfail(strict=True, reason="a known gap")
def test_known_gap():
    assert False

@pytest.mark.xfail(strict=True, reason="a gap that is closed")
def test_closed_gap():
    pass

@pytest.fixture
def broken():
    raise RuntimeError("the set-up broke")

def test_set_up_error(broken):
    pass
"""


def test_outcomes_are_written_as_one_row_per_test_and_replace_the_last_run(tmp_path):
    (tmp_path / "test_dummy.py").write_text(DUMMY_SUITE)
    out = tmp_path / "results" / "slow_tests.jsonl"
    proc = _pytest(["-q", "-p", "outcome_record", "--record-outcomes", str(out), "test_dummy.py"], cwd=tmp_path)
    assert proc.returncode == 1, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert f"6 test outcome(s) written to {out}" in proc.stdout
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    by_test = {r["test"].split("::")[1]: r for r in rows}
    assert [r["test"] for r in rows][0] == "test_dummy.py::test_passes"  # the order they ran
    assert {t: (r["outcome"], r["message"]) for t, r in by_test.items()} == {
        "test_passes": ("passed", ""),
        "test_fails": ("failed", "AssertionError: one is not two"),
        "test_skipped": ("skipped", "not on this machine"),
        "test_known_gap": ("xfailed", "a known gap"),
        "test_closed_gap": ("failed", "[XPASS(strict)] a gap that is closed"),
        "test_set_up_error": ("error", "RuntimeError: the set-up broke"),
    }
    assert by_test["test_passes"]["seconds"] >= 0.25  # it sleeps that long
    assert all(r["seconds"] < 60 for r in rows)
    for r in rows:
        assert r["exit_code"] == 1 and r["date"] == rows[0]["date"]
        assert r["command"].startswith("python -m pytest ") and "--record-outcomes" in r["command"]
        assert {"host", "os", "cpu", "cpus", "memory_gb", "python"} <= set(r["machine"])
        assert "commit" in r
    # a second run replaces the file; a run that selects nothing leaves it alone
    proc = _pytest(["-q", "-p", "outcome_record", "--record-outcomes", str(out), "test_dummy.py::test_passes"],
                   cwd=tmp_path)
    assert proc.returncode == 0, proc.stdout[-3000:]
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    assert [(r["test"], r["outcome"], r["exit_code"]) for r in rows] == [("test_dummy.py::test_passes", "passed", 0)]
    proc = _pytest(["-q", "-p", "outcome_record", "--record-outcomes", str(out), "-k", "no_such_test",
                    "test_dummy.py"], cwd=tmp_path)
    assert proc.returncode == 5
    assert [json.loads(line)["test"] for line in out.read_text().splitlines()] == ["test_dummy.py::test_passes"]
    assert list(out.parent.iterdir()) == [out]  # no temporary left


def test_the_slow_test_command_records_the_slow_tests():
    """scripts/run-slow-tests.sh runs the `slow` tests in one process with the recorder, into
    benchmarks/results/."""
    script = (TESTS.parent / "scripts" / "run-slow-tests.sh").read_text()
    assert "-p outcome_record --record-outcomes" in script and "-m slow" in script
    assert "benchmarks/results/slow_tests.jsonl" in script
    assert "-p no:xdist" in script
