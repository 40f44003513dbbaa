"""Significance tests: paired simulated-vs-reference tests and the conifer-vs-broadleaf t-test.

* :func:`paired_tests` — paired t-test and Wilcoxon signed-rank test of simulated vs reference
  values per group × scenario × method × metric;
* :func:`multireturn_ttest` — two-sample Student t-test of the multiple-return share, conifer
  vs broadleaf, per method (``reference`` included) and scenario (the study's t(28));
* :func:`paired_difference` — the paired statistics of one pair of samples.

Degenerate inputs: fewer than 2 finite pairs give NaN statistics and p-values; differences
that are all exactly zero give NaN t and Wilcoxon; constant non-zero differences give
``t = ±inf``, ``t_p = 0`` and Wilcoxon as SciPy computes it; the two-sample test with fewer than
2 trees in either group gives NaN ``t``, ``p``.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence

import numpy as np
import pandas as pd
from scipy import stats as sps

from vlsforest.errors import ConfigError
from vlsforest.stats.tables import (
    GROUP_ORDER,
    REFERENCE,
    check_errors,
    group_of,
    method_order,
    prepare_metrics,
    scenario_order,
    wide_errors,
)

__all__ = ["paired_difference", "paired_tests", "multireturn_ttest"]

def paired_difference(sim: np.ndarray, ref: np.ndarray) -> tuple:
    """Paired statistics of ``sim`` against ``ref`` over their finite pairs.

    Parameters
    ----------
    sim, ref : ndarray
        Paired samples (NaN is missing).

    Returns
    -------
    tuple
        ``(n, mean_diff, t, t_p, wilcoxon_statistic, wilcoxon_p)``; degenerate cases as in the
        module docstring.
    """
    ok = np.isfinite(sim) & np.isfinite(ref)
    s, r = sim[ok], ref[ok]
    n = int(ok.sum())
    nan = float("nan")
    if n < 2:
        return n, (float(np.mean(s - r)) if n else nan), nan, nan, nan, nan
    d = s - r
    mean_d = float(d.mean())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if np.all(d == 0):
            return n, mean_d, nan, nan, nan, nan
        if np.all(d == d[0]):
            t, tp = math.copysign(math.inf, d[0]), 0.0
        else:
            res = sps.ttest_rel(s, r)
            t, tp = float(res.statistic), float(res.pvalue)
        try:
            w = sps.wilcoxon(s, r)
            ws, wp = float(w.statistic), float(w.pvalue)
        except ValueError:
            ws, wp = nan, nan
    return n, mean_d, t, tp, ws, wp


def _paired_block(sim: np.ndarray, ref: np.ndarray) -> list[tuple]:
    """:func:`paired_difference` for every column; clean columns go through SciPy in one call."""
    m = sim.shape[1]
    out = [None] * m
    d = sim - ref
    fin = np.isfinite(d).all(axis=0)
    n = d.shape[0]
    clean = np.zeros(m, bool)
    if n >= 2:
        for j in np.flatnonzero(fin):
            ad = np.abs(d[:, j])
            # no zero differences, no ties in |d|, not constant: SciPy's column-wise result
            clean[j] = ad.min() > 0 and len(np.unique(ad)) == n and np.ptp(d[:, j]) > 0
    idx = np.flatnonzero(clean)
    if len(idx):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            t = sps.ttest_rel(sim[:, idx], ref[:, idx], axis=0)
            w = sps.wilcoxon(sim[:, idx], ref[:, idx], axis=0)
        md = d[:, idx].mean(axis=0)
        for k, j in enumerate(idx):
            out[j] = (n, float(md[k]), float(t.statistic[k]), float(t.pvalue[k]),
                      float(w.statistic[k]), float(w.pvalue[k]))
    for j in np.flatnonzero(~clean):
        out[j] = paired_difference(sim[:, j], ref[:, j])
    return out


def paired_tests(errors: pd.DataFrame) -> pd.DataFrame:
    """Paired t-test and Wilcoxon signed-rank test of simulated vs reference values.

    Parameters
    ----------
    errors : DataFrame
        Output of :func:`compute_errors`.

    Returns
    -------
    DataFrame
        One row per group (``all`` then broadleaf, conifer, other) × scenario × method × metric
        with ``n`` (finite pairs), ``mean_diff`` (mean of sim − ref), ``t_statistic, t_p``
        (:func:`scipy.stats.ttest_rel`, two-sided) and ``wilcoxon_statistic, wilcoxon_p``
        (:func:`scipy.stats.wilcoxon`, two-sided, zero differences dropped). Degenerate cases
        as in the module docstring.
    """
    df = check_errors(errors)
    info, metrics, arr = wide_errors(df, ("sim", "ref"))
    scen_col = info["scenario"].to_numpy()
    meth_col = info["method"].to_numpy()
    grp_col = info["group"].to_numpy()
    groups = ["all"] + [g for g in GROUP_ORDER if (grp_col == g).any()]
    rows = []
    for g in groups:
        gmask = np.ones(len(info), bool) if g == "all" else grp_col == g
        for sc in scenario_order(df["scenario"], pd.unique(df["scenario"])):
            for me in method_order(df["method"], pd.unique(df["method"])):
                sel = gmask & (scen_col == sc) & (meth_col == me)
                if not sel.any():
                    continue
                res = _paired_block(arr["sim"][sel], arr["ref"][sel])
                for k, r in zip(metrics, res):
                    rows.append((g, sc, me, k) + r)
    return pd.DataFrame(rows, columns=["group", "scenario", "method", "metric", "n", "mean_diff", "t_statistic",
                                       "t_p", "wilcoxon_statistic", "wilcoxon_p"])


def multireturn_ttest(metrics: pd.DataFrame, *, metric: str = "multi_return_pct",
                      source: str = "tree metrics", methods: Sequence[str] = (),
                      scenarios: Sequence[str] = ()) -> pd.DataFrame:
    """Two-sample Student t-test (equal variances) of a metric, conifer vs broadleaf.

    Parameters
    ----------
    metrics : DataFrame
        The ``tree_metrics.csv`` table.
    metric : str
        Metric column to compare (default the multiple-return share).
    source : str
        Name used in error messages.
    methods, scenarios : sequence of str
        Display order (e.g. the configuration's); others follow alphabetically.

    Returns
    -------
    DataFrame
        One row per method (``reference`` first) × scenario: ``n_conifer, n_broadleaf,
        mean_conifer, mean_broadleaf, diff`` (conifer − broadleaf), ``t, df`` (``n_c + n_b − 2``)
        and two-sided ``p``. Trees of group ``other`` and NaN values are left out.
    """
    df = prepare_metrics(metrics, source)
    if metric not in df.columns:
        raise ConfigError(f"metric: {metric!r} is not a column of {source}")
    df["group"] = df["species"].map(group_of)
    rows = []
    for me in [REFERENCE] + method_order(df["method"], methods):
        for sc in scenario_order(df["scenario"], scenarios):
            blk = df[(df["method"] == me) & (df["scenario"] == sc)]
            if blk.empty:
                continue
            c = blk.loc[blk["group"] == "conifer", metric].to_numpy(float)
            b = blk.loc[blk["group"] == "broadleaf", metric].to_numpy(float)
            c, b = c[np.isfinite(c)], b[np.isfinite(b)]
            mc = float(c.mean()) if len(c) else math.nan
            mb = float(b.mean()) if len(b) else math.nan
            t = p = math.nan
            if len(c) >= 2 and len(b) >= 2:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    res = sps.ttest_ind(c, b, equal_var=True)
                t, p = float(res.statistic), float(res.pvalue)
            rows.append((me, sc, len(c), len(b), mc, mb, mc - mb, t, len(c) + len(b) - 2, p))
    return pd.DataFrame(rows, columns=["method", "scenario", "n_conifer", "n_broadleaf", "mean_conifer",
                                       "mean_broadleaf", "diff", "t", "df", "p"])
