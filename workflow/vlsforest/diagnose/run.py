"""The diagnosis from a set-up to its report: a spill folder for traces, the plots' simulations,
the search, the report.

The steps are those of :mod:`.search` (locate, attribute, model) and :mod:`.report`; the
simulations and their trace cache are :mod:`.simulation` and :mod:`.traces`.
"""

from __future__ import annotations

import shutil
import sys
import tempfile
import time
from pathlib import Path

from vlsforest.diagnose import library as lib
from vlsforest.diagnose.report import assemble
from vlsforest.diagnose.search import search
from vlsforest.diagnose.setup import Setup
from vlsforest.diagnose.simulation import Study
from vlsforest.diagnose.truth import told_truth
from vlsforest.errors import ConfigError


def diagnose(setup: Setup, log=None, work_dir=None, truth: dict | None = None) -> dict:
    """Run the diagnosis (:mod:`.search`); return the report mapping (:mod:`.report`).

    Parameters
    ----------
    setup : Setup
    log : callable, optional
        Takes each progress line (default: print to stderr).
    work_dir : path, optional
        Where a temporary folder may hold ray traces that a later stage reads back instead of
        tracing again (up to one per trace-side candidate, ≈ 3.5 GB each on the default forest);
        it is deleted before returning. Without it every trace is made anew when needed.
    truth : dict, optional
        For benchmarks on recordings with hidden physics: candidate id → the hidden values. The
        report's ``oracle`` then compares the errors as given, told the truth and with the fitted
        values (:func:`.truth.told_truth`; its simulations are not counted in ``cost``); without
        it ``oracle`` is None. The search never sees these values.
    """
    spill = None
    if work_dir is not None:
        try:
            Path(work_dir).mkdir(parents=True, exist_ok=True)
            spill = Path(tempfile.mkdtemp(prefix=".diagnose-traces-", dir=work_dir))
        except OSError as exc:
            raise ConfigError(f"{work_dir}: cannot hold the diagnosis' temporary traces there "
                              f"({exc.strerror or exc})") from None
    try:
        return _diagnose(setup, log or (lambda m: print(f"diagnose: {m}", file=sys.stderr, flush=True)), spill,
                         truth)
    finally:
        if spill is not None:
            shutil.rmtree(spill, ignore_errors=True)


def _candidates(study, setup: Setup, log) -> list:
    """The set-up's candidates, less ``tls_occlusion`` when a scene has no PAD-scaled crowns
    (an error when it was named)."""
    cands = lib.select(setup.candidates)
    if not study.has_scaled and any(c.name == "tls_occlusion" for c in cands):
        if setup.candidates_given:
            raise ConfigError("candidate tls_occlusion corrects PAD-scaled voxel crowns, but a plot's scene has "
                              "none (a fixed-size method?); leave it out of 'candidates'")
        cands = [c for c in cands if c.name != "tls_occlusion"]
        log("tls_occlusion left out: the scenes have no PAD-scaled voxel crowns")
    return cands


def _diagnose(setup: Setup, log, spill_dir, truth) -> dict:
    t0 = time.perf_counter()
    study = Study(setup, log, spill_dir)
    found = search(study, _candidates(study, setup, log), setup, log)
    cost = {"traced_simulations": study.n_traced, "traces_read_back": study.n_loaded,
            "seconds": round(time.perf_counter() - t0, 1)}
    oracle = None if truth is None else told_truth(study, truth, found, cost, t0)
    rep = assemble(setup, found, cost, oracle)
    log(f"verdict: {rep['verdict']} ({cost['traced_simulations']} traced simulations, {cost['traces_read_back']} "
        f"read back from disk, {cost['seconds']:.0f} s)")
    return rep
