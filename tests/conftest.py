"""Shared fixtures, the two test tiers and the test order.

Tiers
-----
Every test is in the **unit** tier unless it is marked ``e2e`` (end to end). The e2e tier holds
the workflow runs (dry and real), the CLI walked through as the documentation shows it, and
every test that reads the quick study (fixtures ``quick_run`` and ``quick_forest``). Here the
``e2e`` mark is set on the modules of :data:`E2E_MODULES`, on every test that uses a fixture of
:data:`E2E_FIXTURES` and on every test whose own code runs Snakemake (:data:`E2E_CALLS`); other
tests of the tier (a Snakemake run in a helper or fixture, a forest recorded several times)
carry ``@pytest.mark.e2e`` themselves. ``slow``
tests (the default forest, the documentation's workflow runs) are a third set that neither tier
runs (``scripts/run-slow-tests.sh``).

Shared quick study
------------------
``quick_run`` is one completed run of ``config/quick.yaml`` (the quick virtual forest: plot
``Q1``, 4 targets, ~60 surrounding trees; the quick workflow's TLS settings; the default "real"
recording physics), built **once per test run**: the first process that needs it builds it in
the run's shared temporary folder under a file lock, every other pytest-xdist worker waits for
it and reads the same folder (``tests/runwide.py``). ``quick_forest`` is that run's recorded
forest (``results/forest``: ``plots/Q1/…``, ``truth/…``); only validation code may read its
``truth/`` folder. Tests read the shared study and never change it (Snakemake dry runs, reports
written elsewhere and a no-op rerun leave it as it is); a test that needs a changed study copies
it first (``shutil.copytree`` keeps the file times Snakemake compares) or runs the workflow in
its own folder.

Order
-----
``scripts/run-tests.sh`` runs the suite on two pytest-xdist workers with ``--dist loadgroup``.
No test carries an ``xdist_group`` mark (with pytest 9, pytest-xdist 3.8's groups have no effect:
the group name it appends to ``item._nodeid`` is not read by pytest 9's nodes, so a group's tests
were spread over both workers; upstream: pytest-dev/pytest-xdist#1386, open), so every test is its
own unit, handed out in collection order: one to each worker, then one more to each, then one at
a time to whichever worker is free. :func:`pytest_collection_modifyitems` puts the three longest
tests, marked ``early``, first: the diagnosis' region test and the SLURM run go to one worker, the
diagnosis' hidden-threshold case to the other, and the short tests fill in behind them.
"""

from __future__ import annotations

import inspect
import subprocess

import pytest
from runwide import SharedBuildError, built_once, run_dir

#: the synth settings of ``config/quick.yaml`` (tests/test_study_config.py keeps them in step)
QUICK_SYNTH = {
    "forest": {"preset": "quick"},
    "tls": {"n_positions": 5, "step_deg": 0.25, "n_tilted": 0},
    "recordings": {"uls": {"repeats": 1, "cross_margin_m": 30}},
}

#: test modules that are end to end as a whole
E2E_MODULES = frozenset({
    "test_workflow.py",          # Snakemake dry runs, the quick run, reruns, lint, profiles
    "test_slurm_cluster.py",     # the quick run through a local SLURM cluster
    "test_report_browser.py",    # the quick run's report in headless Chromium
    "test_default_forest.py",    # the default forest (also slow)
    "test_realdata_bretten.py",  # the study's ALS and ULS surveys over a real tree
})

#: fixtures that make a test end to end wherever it stands
E2E_FIXTURES = frozenset({"quick_run", "quick_forest"})

#: calls of tests/wfrun.py that run Snakemake: a test whose own code makes one is end to end
E2E_CALLS = ("snakemake_cli(", "snakemake_command(", "run_quick(")


def _runs_snakemake(item) -> bool:
    try:
        source = inspect.getsource(item.function)
    except (AttributeError, TypeError, OSError):
        return False
    return any(call in source for call in E2E_CALLS)


def is_e2e(item) -> bool:
    """Whether ``item`` belongs to the end-to-end tier (see the module's docstring)."""
    return (item.path.name in E2E_MODULES or bool(E2E_FIXTURES.intersection(item.fixturenames))
            or item.get_closest_marker("e2e") is not None or _runs_snakemake(item))


@pytest.hookimpl(tryfirst=True)  # before pytest's own hook deselects by mark (-m)
def pytest_collection_modifyitems(config, items):
    """Mark the e2e tier; tests marked ``early`` first, in their collection order."""
    for item in items:
        if is_e2e(item) and item.get_closest_marker("e2e") is None:
            item.add_marker(pytest.mark.e2e)
    items.sort(key=lambda item: item.get_closest_marker("early") is None)  # stable


def _completed(record):
    return subprocess.CompletedProcess(record["args"], record["returncode"], record["stdout"], record["stderr"])


@pytest.fixture(scope="session")
def quick_run(tmp_path_factory):
    """One completed end-to-end run of ``config/quick.yaml`` with the local executor, built once
    per test run and shared by every test (and worker) that inspects its outputs (~2.5 min on 2
    cores). Returns (working directory, the run's ``CompletedProcess``, its seconds)."""
    from wfrun import run_quick

    def build(workdir):
        proc, seconds = run_quick(workdir)
        return {"args": [str(a) for a in proc.args], "returncode": proc.returncode,
                "stdout": proc.stdout, "stderr": proc.stderr, "seconds": seconds}

    try:
        workdir, record = built_once(run_dir(tmp_path_factory), "quick_study", build)
    except SharedBuildError as exc:
        pytest.fail(str(exc), pytrace=False)
    print(f"\nquick end-to-end run: {record['seconds']:.1f} s")
    return workdir, _completed(record), record["seconds"]


@pytest.fixture(scope="session")
def quick_forest(quick_run):
    """Folder of the quick study's recorded forest (``plots/Q1/…``, ``truth/…``), as
    ``vlsforest synth`` writes it for :data:`QUICK_SYNTH` with seed 0."""
    return quick_run[0] / "results" / "forest"
