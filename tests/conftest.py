"""Shared fixtures: a small virtual forest, recorded once per test run; test order.

The forest is the ``quick`` preset (plot ``Q1``, 4 targets, ~60 surrounding trees) recorded with
the quick workflow's TLS settings (5 positions, 0.25° steps, no tilted scans) and the default
"real" recording physics. Stages downstream of synth (segmentation, stems, PAD, voxels, scenes)
test against it; only validation code may read its ``truth/`` folder.

``scripts/run-tests.sh`` runs the suite on two pytest-xdist workers with ``--dist loadgroup``.
No test carries an ``xdist_group`` mark (with pytest 9, pytest-xdist 3.8's groups have no effect:
the group name it appends to ``item._nodeid`` is not read by pytest 9's nodes, so a group's tests
were spread over both workers; upstream: pytest-dev/pytest-xdist#1386, open), so every test is its own unit, handed out in collection order:
one to each worker, then one more to each, then one at a time to whichever worker is free.
:func:`pytest_collection_modifyitems` puts the three longest tests, marked ``early``, first: the
diagnosis' region test and the SLURM run go to one worker, the diagnosis' hidden-threshold case to
the other, and the short tests fill in behind them. Run-wide fixtures (``quick_run``) are built
once per worker that needs them.
"""

from __future__ import annotations

import pytest

#: the synth settings of ``config/quick.yaml`` (kept in step by tests/test_workflow.py)
QUICK_SYNTH = {
    "forest": {"preset": "quick"},
    "tls": {"n_positions": 5, "step_deg": 0.25, "n_tilted": 0},
    "recordings": {"uls": {"repeats": 1, "cross_margin_m": 30}},
}


def pytest_collection_modifyitems(config, items):
    """Tests marked ``early`` first, in their collection order; the rest after them."""
    items.sort(key=lambda item: item.get_closest_marker("early") is None)  # stable


@pytest.fixture(scope="session")
def quick_forest(tmp_path_factory):
    """Folder of the recorded quick forest (``plots/Q1/…``, ``truth/…``); built once (~40 s)."""
    from vlsforest.synth.record import synthesize

    out = tmp_path_factory.mktemp("quick_forest") / "forest"
    synthesize(QUICK_SYNTH, out, seed=0, quiet=True)
    return out


@pytest.fixture(scope="session")
def quick_run(tmp_path_factory):
    """One completed end-to-end run of ``config/quick.yaml`` with the local executor, shared by
    every test module that inspects its outputs (~2.5 min on 2 cores)."""
    from wfrun import run_quick

    workdir = tmp_path_factory.mktemp("quick")
    proc, seconds = run_quick(workdir)
    print(f"\nquick end-to-end run: {seconds:.1f} s")
    return workdir, proc, seconds
