"""A benchmark's reference for the diagnosis: how a simulation told the hidden truth does.

When the "real" recording was made with known hidden physics (``validation/diagnose_campaign.py``),
the error of a simulation told those values is the error the diagnosis can at best recover
(what is left is the voxel reconstruction's own). :func:`told_truth` measures it beside the error
as given and with the fitted values; :func:`vlsforest.diagnose.diagnose` takes the values as its
``truth`` argument and reports this under ``oracle``.
"""

from __future__ import annotations

import time

import numpy as np

from vlsforest.diagnose import stats as st
from vlsforest.diagnose.features import FEATURES


def told_truth(study, truth: dict, found: dict, cost: dict, t0: float) -> dict:
    """The errors (mean per-tree loss) as given, told ``truth`` and with the fitted model.

    Parameters
    ----------
    study : simulation.Study
        The diagnosis' study (its caches: simulations it already made are not made again).
    truth : dict
        Candidate id → the hidden values.
    found : dict
        The search's result (:func:`.search.search`): its ``D0``, ``w`` and ``model``.
    cost : dict
        The diagnosis' own cost; these simulations are counted apart from it.
    t0 : float
        ``time.perf_counter()`` at the diagnosis' start.

    Returns
    -------
    dict
        ``values``, ``error_given``, ``error_told_truth``, ``error_fitted``; the observables
        significantly worse when told the truth than as given (``worse_told_truth``: the voxel
        model's own error compensated there) and with the fitted values than with the truth
        (``worse_fitted_than_truth``); ``residual_told_truth`` per observable (the
        reconstruction's own error) and ``cost`` (these simulations' traces and seconds).
    """
    D0, w = found["D0"], found["w"]
    D_or = study.residual({k: dict(v) for k, v in truth.items()})
    D_fit = study.residual(found["model"])
    return {"values": truth, "error_given": float(np.nanmean(st.tree_loss(D0, w))),
            "error_told_truth": float(np.nanmean(st.tree_loss(D_or, w))),
            "error_fitted": float(np.nanmean(st.tree_loss(D_fit, w))),
            "worse_told_truth": st.worse_metrics(D0, D_or, FEATURES),
            "worse_fitted_than_truth": st.worse_metrics(D_or, D_fit, FEATURES),
            "residual_told_truth": {f: (float(np.nanmean(D_or[:, j])) if np.isfinite(D_or[:, j]).any()
                                        else None) for j, f in enumerate(FEATURES)},
            "cost": {"traced_simulations": study.n_traced - cost["traced_simulations"],
                     "seconds": round(time.perf_counter() - t0 - cost["seconds"], 1)}}
