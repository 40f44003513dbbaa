"""Shared fixtures: a small virtual forest, recorded once per test session; test order.

The forest is the ``quick`` preset (plot ``Q1``, 4 targets, ~60 surrounding trees) recorded with
the quick workflow's TLS settings (5 positions, 0.25° steps, no tilted scans) and the default
"real" recording physics. Stages downstream of synth (segmentation, stems, PAD, voxels, scenes)
test against it; only validation code may read its ``truth/`` folder.

``scripts/run-tests.sh`` runs the suite on two pytest-xdist workers (``--dist loadgroup``). The
two longest parts, the SLURM end-to-end run and the diagnosis' end-to-end cases, carry an
``xdist_group`` mark: each group runs on one worker, and :func:`pytest_collection_modifyitems`
puts the grouped tests first so that the two groups start at once, on different workers, while
the short tests fill in behind them. Session fixtures (``quick_run``) are built once per worker
that needs them.
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
    """Grouped tests (``xdist_group``) first, in their collection order; the rest after them."""
    items.sort(key=lambda item: item.get_closest_marker("xdist_group") is None)  # stable


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
