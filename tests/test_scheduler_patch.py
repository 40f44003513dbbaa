"""The scheduler patch (workflow/rules/scheduler_patch.py): on unless VLSFOREST_SCHEDULER_PATCH=0,
applied only to the Snakemake method it was written against (a warning only where it was asked for
with VLSFOREST_SCHEDULER_PATCH=1), at most one pending re-evaluation timer, no lost wake-up.

``test_installed_snakemake_is_the_one_the_patch_was_written_for`` fails when Snakemake's private
``JobScheduler._schedule_reevalutation`` changes: then the patch must be re-checked (or dropped).
"""

import importlib.util
import threading
import time

import pytest
from wfrun import REPO, snakemake_cli

PATCH_FILE = REPO / "workflow" / "rules" / "scheduler_patch.py"


def _load():
    spec = importlib.util.spec_from_file_location("scheduler_patch_under_test", PATCH_FILE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


class _Scheduler:
    def __init__(self):
        self._open_jobs = threading.Semaphore(0)


def _passes(sem, timeout):
    n = 0
    while sem.acquire(timeout=timeout):
        n += 1
    return n


def test_installed_snakemake_is_the_one_the_patch_was_written_for():
    from snakemake.scheduling.job_scheduler import JobScheduler

    patch = _load()
    assert not getattr(JobScheduler._schedule_reevalutation, "one_pending", False)
    assert patch.compatible(JobScheduler)
    # the scheduler still wakes its loop through the semaphore the patch releases
    import inspect

    assert "self._open_jobs" in inspect.getsource(JobScheduler)


def test_a_different_method_is_not_patched():
    patch = _load()

    class Other:
        def _schedule_reevalutation(self, delay):
            pass

    with pytest.warns(UserWarning, match="not patched"):
        assert not patch.apply(Other)
    assert not getattr(Other._schedule_reevalutation, "one_pending", False)
    with pytest.warns(UserWarning, match="not patched"):
        assert not patch.apply(type("NoMethod", (), {}))


def test_on_unless_the_variable_is_zero():
    patch = _load()
    assert patch.enabled({}) and not patch.demanded({})
    assert not patch.enabled({patch.ENV_VAR: "0"})
    assert not patch.apply_if_enabled({patch.ENV_VAR: "0"})
    assert patch.enabled({patch.ENV_VAR: "1"}) and patch.demanded({patch.ENV_VAR: "1"})
    for off in ("false", "Off", " no "):
        assert not patch.enabled({patch.ENV_VAR: off}), off


def test_another_snakemake_is_left_alone_with_a_warning_only_when_asked(monkeypatch):
    import warnings

    from snakemake.scheduling import job_scheduler

    patch = _load()

    class Other:
        def _schedule_reevalutation(self, delay):
            pass

    monkeypatch.setattr(job_scheduler, "JobScheduler", Other)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert not patch.apply_if_enabled({})  # the default: no patch, no warning
    with pytest.warns(UserWarning, match="not patched"):
        assert not patch.apply_if_enabled({patch.ENV_VAR: "1"})
    assert not getattr(Other._schedule_reevalutation, "one_pending", False)


def test_one_pending_timer_and_no_lost_wakeup(monkeypatch):
    from snakemake.scheduling.job_scheduler import JobScheduler

    monkeypatch.setattr(JobScheduler, "_schedule_reevalutation", JobScheduler._schedule_reevalutation)
    # Snakemake as installed: every request starts a timer, each one a scheduling pass
    s = _Scheduler()
    for _ in range(5):
        JobScheduler._schedule_reevalutation(s, 0.05)
    assert _passes(s._open_jobs, 0.5) == 5
    # patched: the requests made while one is pending give one pass …
    patch = _load()
    assert patch.apply_if_enabled({patch.ENV_VAR: "1"})
    assert JobScheduler._schedule_reevalutation.one_pending
    s = _Scheduler()
    # a delay far longer than the five requests take, also on a loaded machine: they all fall
    # into the first one's pending time
    for _ in range(5):
        JobScheduler._schedule_reevalutation(s, 1.0)
    assert _passes(s._open_jobs, 2.0) == 1
    # … and the pass it triggers may ask for the next one (no wake-up is lost)
    t0 = time.perf_counter()
    for _ in range(3):
        JobScheduler._schedule_reevalutation(s, 0.05)
        assert s._open_jobs.acquire(timeout=2.0)
    assert 0.15 <= time.perf_counter() - t0 < 1.5
    # applying it twice changes nothing; its timers do not keep the interpreter alive
    patched = JobScheduler._schedule_reevalutation
    assert patch.apply()
    assert JobScheduler._schedule_reevalutation is patched
    JobScheduler._schedule_reevalutation(s, 10.0)
    assert s._vlsforest_reevaluation.daemon


@pytest.mark.e2e  # Snakemake dry runs
@pytest.mark.parametrize("value, applied", [(None, True), ("0", False), ("1", True)])
def test_the_workflow_applies_it_unless_switched_off(tmp_path, value, applied):
    """A copy of the repository whose Snakefile reports, after the workflow is parsed, whether
    Snakemake's method is the patched one."""
    import os
    import shutil

    repo = tmp_path / "repo"
    repo.mkdir()
    for folder in ("workflow", "config", "envs"):
        shutil.copytree(REPO / folder, repo / folder, ignore=shutil.ignore_patterns("__pycache__"))
    probe = repo / "Snakefile"
    probe.write_text(
        (REPO / "Snakefile").read_text()
        + "\nfrom snakemake.scheduling.job_scheduler import JobScheduler as _JS\n"
        "print('PATCHED', getattr(_JS._schedule_reevalutation, 'one_pending', False))\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "VLSFOREST_SCHEDULER_PATCH"}
    if value is not None:
        env["VLSFOREST_SCHEDULER_PATCH"] = value
    proc = snakemake_cli("-n", "--cores", 1, "--configfile", REPO / "config" / "quick.yaml",
                         "--workflow-profile", "none", cwd=tmp_path, env=env, snakefile=probe)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert f"PATCHED {applied}" in proc.stdout
