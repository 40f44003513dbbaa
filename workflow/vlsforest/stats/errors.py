"""Simulated minus reference: per-tree errors and their summaries with bootstrap intervals.

* :func:`compute_errors` — per tree × method × scenario × metric: ``sim``, ``ref``,
  ``error = sim - ref`` and ``rel_error = 100 · (sim - ref) / |ref|`` (percent; the study's
  relative error of Hsd);
* :func:`summarize_errors` — mean, median, SD, MAE, RMSE and a percentile-bootstrap CI of the
  mean error by species, by species group and over all trees.

Documented values for degenerate inputs (never an exception): a simulated tree without a
reference row (or a NaN value on either side) has NaN ``error`` and ``rel_error``;
``rel_error`` is also NaN where ``ref == 0``. Summaries over ``n`` finite errors: ``n == 0`` →
every statistic NaN; ``n == 1`` → ``mean``, ``median``, ``mae``, ``rmse`` equal the one value,
``sd`` and the CI NaN.

Row order: the errors table is sorted by method and scenario in the display order given to
:func:`compute_errors`; every later table keeps the order in which methods and scenarios first
appear in it.
"""

from __future__ import annotations

import warnings
import zlib
from collections.abc import Sequence

import numpy as np
import pandas as pd

from vlsforest.errors import ConfigError
from vlsforest.metrics import METRIC_COLUMNS
from vlsforest.stats.tables import (
    ID_COLUMNS,
    REFERENCE,
    check_errors,
    error_levels,
    group_of,
    method_order,
    prepare_metrics,
    scenario_order,
    tree_sort_key,
    wide_errors,
)

__all__ = ["compute_errors", "bootstrap_mean_ci", "block_rng", "summarize_errors"]


def compute_errors(metrics: pd.DataFrame, *, source: str = "tree metrics", methods: Sequence[str] = (),
                   scenarios: Sequence[str] = ()) -> pd.DataFrame:
    """Simulated minus reference value of every metric, per tree × method × scenario.

    Parameters
    ----------
    metrics : DataFrame
        The ``tree_metrics.csv`` table.
    source : str
        Name used in error messages (the file).
    methods, scenarios : sequence of str
        Display order of the methods and scenarios (e.g. the configuration's); others follow
        alphabetically.

    Returns
    -------
    DataFrame
        Columns ``plot, tree_id, species, group, scenario, method, metric, sim, ref, error,
        rel_error`` (``rel_error`` in percent of ``|ref|``), ordered by method, scenario, plot,
        tree and metric (:data:`~vlsforest.metrics.METRIC_COLUMNS` order).
    """
    df = prepare_metrics(metrics, source)
    key = ["plot", "tree_id", "scenario"]
    ref = df[df["method"] == REFERENCE]
    sim = df[df["method"] != REFERENCE]
    cols = list(METRIC_COLUMNS)
    long_sim = sim.melt(id_vars=list(ID_COLUMNS), value_vars=cols, var_name="metric", value_name="sim")
    long_ref = ref.melt(id_vars=key, value_vars=cols, var_name="metric", value_name="ref")
    out = long_sim.merge(long_ref, on=key + ["metric"], how="left")
    out["group"] = out["species"].map(group_of)
    with np.errstate(divide="ignore", invalid="ignore"):
        out["error"] = out["sim"] - out["ref"]
        rel = 100.0 * out["error"] / out["ref"].abs()
    out["rel_error"] = rel.where(out["ref"] != 0)
    out["_m"] = out["method"].map({m: i for i, m in enumerate(method_order(out["method"], methods))})
    out["_s"] = out["scenario"].map({s: i for i, s in enumerate(scenario_order(out["scenario"], scenarios))})
    out["_k"] = out["metric"].map({c: i for i, c in enumerate(cols)})
    out["_t"] = tree_sort_key(out["tree_id"])
    out = out.sort_values(["_m", "_s", "plot", "_t", "tree_id", "_k"], kind="stable")
    out = out[["plot", "tree_id", "species", "group", "scenario", "method", "metric", "sim", "ref",
               "error", "rel_error"]]
    return out.reset_index(drop=True)

def bootstrap_mean_ci(x: np.ndarray, rng: np.random.Generator, n_boot: int, level: float):
    """Percentile-bootstrap confidence interval of the mean of each column.

    Parameters
    ----------
    x : ndarray (n, m)
        Values; NaN is missing. Columns without NaN share the resampled rows; each other column
        is resampled over its finite values.
    rng : numpy.random.Generator
        Source of the resamples (e.g. :func:`block_rng`).
    n_boot : int
        Number of resamples.
    level : float
        Confidence level, e.g. 0.95.

    Returns
    -------
    lo, hi : ndarray (m,)
        Interval bounds; NaN for a column with fewer than 2 values.
    """
    n, m = x.shape
    lo = np.full(m, np.nan)
    hi = np.full(m, np.nan)
    q = [(1 - level) / 2, 1 - (1 - level) / 2]
    finite = np.isfinite(x)
    full = finite.all(axis=0)
    if n >= 2 and full.any():
        idx = rng.integers(0, n, size=(n_boot, n))
        means = x[:, full][idx].mean(axis=1)  # (n_boot, k)
        lo[full], hi[full] = np.quantile(means, q, axis=0)
    for j in np.flatnonzero(~full):
        v = x[finite[:, j], j]
        if len(v) >= 2:
            idx = rng.integers(0, len(v), size=(n_boot, len(v)))
            lo[j], hi[j] = np.quantile(v[idx].mean(axis=1), q)
    return lo, hi


def block_rng(seed: int, *names) -> np.random.Generator:
    """A random generator of its own for one block of a table.

    Parameters
    ----------
    seed : int
        The analysis seed.
    *names : str
        Names of the block (e.g. species, scenario, method); seeded by their CRC-32, so a
        block's numbers do not depend on the other blocks.

    Returns
    -------
    numpy.random.Generator
    """
    return np.random.default_rng([int(seed), zlib.crc32("|".join(names).encode())])


def summarize_errors(errors: pd.DataFrame, *, n_boot: int = 2000, seed: int = 0, ci: float = 0.95) -> pd.DataFrame:
    """Summaries of the errors by species, by species group and over all trees.

    Parameters
    ----------
    errors : DataFrame
        Output of :func:`compute_errors`.
    n_boot : int
        Bootstrap resamples for the CI of the mean (≥ 100).
    seed : int
        Seed; each (species, group, scenario, method) block draws from its own generator
        derived from ``seed`` and its names, so that adding a method changes no other row.
    ci : float
        Confidence level of the interval, in (0, 1).

    Returns
    -------
    DataFrame
        One row per species/group level × scenario × method × metric with columns
        ``species, group, scenario, method, metric, n, mean, median, sd, mae, rmse, ci_low,
        ci_high, mean_rel_error, median_rel_error, mean_sim, mean_ref``. Group rows have
        ``species == "all"``, the overall row ``species == group == "all"``.
    """
    if not isinstance(n_boot, (int, np.integer)) or n_boot < 100:
        raise ConfigError(f"n_boot: must be an integer ≥ 100, got {n_boot!r}")
    if not (0 < ci < 1):
        raise ConfigError(f"ci: must lie in (0, 1), got {ci!r}")
    df = check_errors(errors)
    info, metrics, arr = wide_errors(df)
    scen_col = info["scenario"].to_numpy()
    meth_col = info["method"].to_numpy()
    rows = []
    for sp, grp, mask in error_levels(info):
        for sc in scenario_order(df["scenario"], pd.unique(df["scenario"])):
            for me in method_order(df["method"], pd.unique(df["method"])):
                sel = mask & (scen_col == sc) & (meth_col == me)
                if not sel.any():
                    continue
                e = arr["error"][sel]
                lo, hi = bootstrap_mean_ci(e, block_rng(seed, sp, grp, sc, me), n_boot, ci)
                n = np.isfinite(e).sum(axis=0)
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", RuntimeWarning)
                    stats = {
                        "n": n,
                        "mean": np.nanmean(e, axis=0),
                        "median": np.nanmedian(e, axis=0),
                        "sd": np.where(n >= 2, np.nanstd(e, axis=0, ddof=1), np.nan),
                        "mae": np.nanmean(np.abs(e), axis=0),
                        "rmse": np.sqrt(np.nanmean(e**2, axis=0)),
                        "ci_low": lo,
                        "ci_high": hi,
                        "mean_rel_error": np.nanmean(arr["rel_error"][sel], axis=0),
                        "median_rel_error": np.nanmedian(arr["rel_error"][sel], axis=0),
                        "mean_sim": np.nanmean(arr["sim"][sel], axis=0),
                        "mean_ref": np.nanmean(arr["ref"][sel], axis=0),
                    }
                part = pd.DataFrame(stats)
                part.insert(0, "metric", metrics)
                part.insert(0, "method", me)
                part.insert(0, "scenario", sc)
                part.insert(0, "group", grp)
                part.insert(0, "species", sp)
                rows.append(part)
    out = pd.concat(rows, ignore_index=True)
    out["n"] = out["n"].astype(np.int64)
    return out
