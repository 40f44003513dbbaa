"""The workflow's scheduler workaround (workflow/rules/common.smk, `_one_pending_reevaluation`):
at most one pending re-evaluation timer, and no lost wake-up."""

import threading
import time

from wfrun import COMMON, scheduler_workaround_source


def _workaround():
    # the function as the Snakefile defines it, compiled with common.smk's line numbers
    source, line = scheduler_workaround_source()
    ns = {}
    exec(compile("\n" * line + source, str(COMMON), "exec"), ns)
    return ns["_one_pending_reevaluation"]


class _Scheduler:
    def __init__(self):
        self._open_jobs = threading.Semaphore(0)


def _passes(sem, timeout):
    n = 0
    while sem.acquire(timeout=timeout):
        n += 1
    return n


def test_snakemake_piles_up_timers_without_the_workaround_and_not_with_it(monkeypatch):
    from snakemake.scheduling.job_scheduler import JobScheduler

    monkeypatch.setattr(JobScheduler, "_schedule_reevalutation", JobScheduler._schedule_reevalutation)
    # Snakemake as installed: every request starts a timer, each one a scheduling pass
    s = _Scheduler()
    for _ in range(5):
        JobScheduler._schedule_reevalutation(s, 0.05)
    assert _passes(s._open_jobs, 0.5) == 5
    # with the workaround: the requests made while one is pending give one pass …
    _workaround()()
    assert JobScheduler._schedule_reevalutation.one_pending
    s = _Scheduler()
    for _ in range(5):
        JobScheduler._schedule_reevalutation(s, 0.05)
    assert _passes(s._open_jobs, 0.5) == 1
    # … and the pass it triggers may ask for the next one (no wake-up is lost)
    t0 = time.perf_counter()
    for _ in range(3):
        JobScheduler._schedule_reevalutation(s, 0.05)
        assert s._open_jobs.acquire(timeout=2.0)
    assert 0.15 <= time.perf_counter() - t0 < 1.5
    # applying it twice changes nothing; its timers do not keep the interpreter alive
    patched = JobScheduler._schedule_reevalutation
    _workaround()()
    assert JobScheduler._schedule_reevalutation is patched
    JobScheduler._schedule_reevalutation(s, 10.0)
    assert s._vlsforest_reevaluation.daemon


def test_the_workflow_applies_the_workaround():
    # called at the top level of common.smk, which the Snakefile includes before any rule
    text = COMMON.read_text()
    assert text.count("\n_one_pending_reevaluation()\n") == 1
    snakefile = (COMMON.parents[2] / "Snakefile").read_text()
    assert snakefile.index('include: "workflow/rules/common.smk"') < snakefile.index("\nrule ")
