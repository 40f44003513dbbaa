"""The study's Table 5 as numbers: voxels, simulation time, penetration and accuracy per method."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from vlsforest.stats.claims import REALISTIC_PENETRATION
from vlsforest.stats.tables import REFERENCE, check_columns, check_errors, method_order, scenario_order

__all__ = ["penetration_class", "table5"]


def penetration_class(mr_bias: float) -> str:
    """The Table 5 penetration class of a mean multiple-return error (percentage points).

    Parameters
    ----------
    mr_bias : float
        Mean simulated − reference multiple-return share (pp).

    Returns
    -------
    str
        ``"underestimated"`` below −:data:`~vlsforest.stats.claims.REALISTIC_PENETRATION`,
        ``"overestimated"`` above +it, else ``"realistic"``; ``"unknown"`` for NaN.
    """
    tol = REALISTIC_PENETRATION.value
    if not np.isfinite(mr_bias):
        return "unknown"
    if mr_bias < -tol:
        return "underestimated"
    if mr_bias > tol:
        return "overestimated"
    return "realistic"


def table5(errors: pd.DataFrame, voxel_counts: pd.DataFrame, sim_times: pd.DataFrame, *,
           sources=("errors", "voxel counts", "sim times")) -> pd.DataFrame:
    """Voxel counts, simulation time and accuracy per method (the study's Table 5 as numbers).

    Parameters
    ----------
    errors : DataFrame
        Output of :func:`compute_errors`.
    voxel_counts : DataFrame
        ``plot, method, n_voxels``.
    sim_times : DataFrame
        ``plot, method, scenario, seconds``.
    sources : tuple of str
        Names of the three inputs for error messages.

    Returns
    -------
    DataFrame
        One row per simulated method with ``n_plots_voxels, n_voxels`` (sum over plots),
        ``voxel_ratio`` (voxels over the plots every method has, relative to the method with
        the fewest), ``seconds_<scenario>`` (sum over plots) and ``seconds_total``, mean errors
        over all trees and scenarios: ``mr_bias_pp`` (multiple-return share, percentage
        points), ``hmean_bias_m``, ``cbh_bias_m``, ``cbh_mae_m``, ``cpa_bias_m2``,
        ``cpa_mae_m2``; ``cbh_rel_mae_pct`` and ``cpa_rel_mae_pct`` (MAE in % of the mean
        reference value), ``accuracy_error_pct`` (their mean; lower is better) and
        ``penetration`` (from ``mr_bias_pp`` by :func:`penetration_class`).
    """
    err = check_errors(errors, sources[0])
    vc = check_columns(voxel_counts, ("plot", "method", "n_voxels"), numeric=("n_voxels",), source=sources[1])
    st = check_columns(sim_times, ("plot", "method", "scenario", "seconds"), numeric=("seconds",),
                        source=sources[2])
    for t in (vc, st):
        for c in ("plot", "method") + (("scenario",) if "scenario" in t else ()):
            t[c] = t[c].astype(str)
    methods = method_order(pd.concat([err["method"], vc["method"], st["method"]]), pd.unique(err["method"]))
    vc_sim = vc[vc["method"] != REFERENCE]
    common = None
    for me in methods:
        plots = set(vc_sim.loc[vc_sim["method"] == me, "plot"])
        if plots:
            common = plots if common is None else common & plots
    common = common or set()
    scen = scenario_order(st["scenario"], pd.unique(err["scenario"]))
    rows = []
    for me in methods:
        e = err[err["method"] == me]

        def mean_of(metric, col="error", absolute=False):
            v = e.loc[e["metric"] == metric, col].to_numpy(float)
            v = v[np.isfinite(v)]
            if absolute:
                v = np.abs(v)
            return float(v.mean()) if len(v) else math.nan

        v = vc_sim[vc_sim["method"] == me]
        row = {
            "method": me,
            "n_plots_voxels": int(v["plot"].nunique()),
            "n_voxels": float(v["n_voxels"].sum()) if len(v) else math.nan,
            "n_voxels_common": float(v.loc[v["plot"].isin(common), "n_voxels"].sum()) if len(v) and common else math.nan,
        }
        for sc in scen:
            s = st[(st["method"] == me) & (st["scenario"] == sc)]["seconds"]
            row[f"seconds_{sc}"] = float(s.sum()) if len(s) else math.nan
        secs = [row[f"seconds_{sc}"] for sc in scen]
        row["seconds_total"] = float(np.nansum(secs)) if any(np.isfinite(secs)) else math.nan
        row["mr_bias_pp"] = mean_of("multi_return_pct")
        row["hmean_bias_m"] = mean_of("hmean")
        row["cbh_bias_m"] = mean_of("cbh")
        row["cbh_mae_m"] = mean_of("cbh", absolute=True)
        row["cpa_bias_m2"] = mean_of("cpa")
        row["cpa_mae_m2"] = mean_of("cpa", absolute=True)
        cref = mean_of("cbh", "ref")
        aref = mean_of("cpa", "ref")
        row["cbh_rel_mae_pct"] = 100 * row["cbh_mae_m"] / cref if cref and np.isfinite(cref) else math.nan
        row["cpa_rel_mae_pct"] = 100 * row["cpa_mae_m2"] / aref if aref and np.isfinite(aref) else math.nan
        parts = [row["cbh_rel_mae_pct"], row["cpa_rel_mae_pct"]]
        row["accuracy_error_pct"] = float(np.mean(parts)) if all(np.isfinite(parts)) else math.nan
        row["penetration"] = penetration_class(row["mr_bias_pp"])
        rows.append(row)
    out = pd.DataFrame(rows)
    fewest = out["n_voxels_common"].min(skipna=True) if len(out) else math.nan
    out.insert(4, "voxel_ratio", out["n_voxels_common"] / fewest if fewest and np.isfinite(fewest) else math.nan)
    return out.drop(columns="n_voxels_common")
