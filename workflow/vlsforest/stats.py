"""Comparison of simulated and reference tree metrics (Weiser et al. 2021, Sections 3–4).

Inputs are the workflow's tables:

``tree_metrics.csv``
    one row per tree × source: ``plot, tree_id, species, scenario, method`` and the metric
    columns of :data:`vlsforest.metrics.METRIC_COLUMNS`. ``method == "reference"`` rows are the
    real (reference) recordings, every other method is a simulation.
``voxel_counts.csv``
    ``plot, method, n_voxels``.
``sim_times.csv``
    ``plot, method, scenario, seconds``.

The public functions turn them into

* :func:`compute_errors` — per tree × method × scenario × metric: ``sim``, ``ref``,
  ``error = sim - ref`` and ``rel_error = 100 · (sim - ref) / |ref|`` (percent; the study's
  relative error of Hsd);
* :func:`summarize_errors` — mean, median, SD, MAE, RMSE and a percentile-bootstrap CI of the
  mean error by species, by species group and over all trees;
* :func:`paired_tests` — paired t-test and Wilcoxon signed-rank test of simulated vs reference
  values per group × scenario × method × metric;
* :func:`multireturn_ttest` — two-sample Student t-test of the multiple-return share, conifer
  vs broadleaf, per method (``reference`` included) and scenario (the study's t(28));
* :func:`table5` — voxel counts, simulation times and accuracy per method (Table 5 as numbers);
* :func:`evaluate_findings` / :func:`findings_markdown` — each qualitative finding of the study
  and each Table 5 row with our numbers and a verdict computed from them.

:func:`write_stats` runs everything and writes the files of ``vlsforest stats``.

Ordering: methods are ordered :data:`KNOWN_METHODS` first (in that order), then any other method
alphabetically; scenarios ``als, uls`` first, then others alphabetically; species by group
(broadleaf, conifer, other) and then name. Species map to groups through
:func:`vlsforest.domain.species.species_group`; a species it does not know belongs to the group
``"other"`` (:data:`OTHER_GROUP`), which is summarised but left out of the conifer-vs-broadleaf
tests.

Documented values for degenerate inputs (never an exception):

* a simulated tree without a reference row (or a NaN value on either side): ``error`` and
  ``rel_error`` NaN; ``rel_error`` is also NaN where ``ref == 0``;
* summaries over ``n`` finite errors: ``n == 0`` → every statistic NaN; ``n == 1`` → ``mean``,
  ``median``, ``mae``, ``rmse`` equal the one value, ``sd`` and the CI NaN;
* paired tests with fewer than 2 finite pairs: statistics and p-values NaN; differences that
  are all exactly zero: t and Wilcoxon NaN; constant non-zero differences: ``t = ±inf``,
  ``t_p = 0``, Wilcoxon as SciPy computes it;
* the two-sample test with fewer than 2 trees in either group: ``t``, ``p`` NaN;
* a finding or Table 5 row whose methods or scenarios are absent: verdict ``"not testable"``.
"""

from __future__ import annotations

import math
import warnings
import zlib
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import stats as _st

from vlsforest.domain.species import GROUPS, species_group
from vlsforest.errors import ConfigError, InputDataError
from vlsforest.io.atomic import write_csv, write_text
from vlsforest.metrics import METRIC_COLUMNS

__all__ = [
    "REFERENCE",
    "KNOWN_METHODS",
    "OTHER_GROUP",
    "GROUP_ORDER",
    "ID_COLUMNS",
    "FLOAT_FORMAT",
    "method_order",
    "scenario_order",
    "species_order",
    "read_table",
    "check_columns",
    "prepare_metrics",
    "check_errors",
    "block_rng",
    "bootstrap_mean_ci",
    "load_metrics",
    "load_voxel_counts",
    "load_sim_times",
    "compute_errors",
    "summarize_errors",
    "paired_tests",
    "multireturn_ttest",
    "table5",
    "evaluate_findings",
    "findings_markdown",
    "write_stats",
]

#: method name of the real (reference) recordings
REFERENCE = "reference"
#: simulation methods of the study, in display order
KNOWN_METHODS = (
    "fixed_0.25", "fixed_0.10", "fixed_0.05", "fixed_0.02",
    "scaled", "scaled_random_shift", "scaled_cog_shift",
)
#: scenarios in display order (others follow alphabetically)
KNOWN_SCENARIOS = ("als", "uls")
#: group of the species that :func:`vlsforest.domain.species.species_group` does not know
OTHER_GROUP = "other"
#: species groups in display order
GROUP_ORDER = (*GROUPS, OTHER_GROUP)
#: identifying columns of ``tree_metrics.csv``
ID_COLUMNS = ("plot", "tree_id", "species", "scenario", "method")
#: float format of every CSV written here
FLOAT_FORMAT = "%.10g"

#: significance level of the findings
ALPHA = 0.05
#: |mean multiple-return error| (percentage points) below which penetration counts as realistic
PENETRATION_TOLERANCE_PP = 5.0
#: the study's voxel-count ratio fixed_0.02 / scaled
VOXEL_RATIO_CLAIM = 50.0

# the study's Table 5 (qualitative); None = not stated
_TABLE5_CLAIMS = {
    "fixed_0.25": ("simple", "few", "strongly underestimated", "low"),
    "fixed_0.10": ("simple", None, "underestimated", "rather low"),
    "fixed_0.05": ("simple", "many", "realistic", "medium"),
    "fixed_0.02": ("simple", "very many", "overestimated", "high"),
    "scaled": ("complex", "few", "realistic", "high"),
    "scaled_random_shift": ("complex", "few", "realistic", "high"),
    "scaled_cog_shift": ("very complex", "few", "realistic", "high"),
}
_VOXEL_LEVEL = {"few": 0, "many": 1, "very many": 2}
_ACCURACY_LEVEL = {"low": 0, "rather low": 1, "medium": 2, "high": 3}
_PENETRATION_DIR = {
    "strongly underestimated": "underestimated", "underestimated": "underestimated",
    "realistic": "realistic", "overestimated": "overestimated",
}


# --------------------------------------------------------------------------- helpers / IO


def _group(species) -> str:
    """Group of a species, :data:`OTHER_GROUP` for a species of no known group."""
    return species_group(species, default=OTHER_GROUP)


def method_order(methods) -> list[str]:
    """Distinct simulated methods in display order (``reference`` left out).

    Known methods come first in :data:`KNOWN_METHODS` order, then the others alphabetically.
    """
    present = {str(m) for m in methods} - {REFERENCE}
    return [m for m in KNOWN_METHODS if m in present] + sorted(present - set(KNOWN_METHODS))


def scenario_order(scenarios) -> list[str]:
    """Distinct scenarios in display order.

    Parameters
    ----------
    scenarios : iterable
        Scenario names (repeats allowed).

    Returns
    -------
    list of str
        ``als``, ``uls`` first when present, then the others alphabetically.
    """
    present = {str(s) for s in scenarios}
    return [s for s in KNOWN_SCENARIOS if s in present] + sorted(present - set(KNOWN_SCENARIOS))


def species_order(species) -> list[str]:
    """Distinct species in display order.

    Parameters
    ----------
    species : iterable
        Species names (repeats allowed).

    Returns
    -------
    list of str
        Sorted by group (:data:`GROUP_ORDER`), then by name.
    """
    present = {str(s) for s in species}
    return sorted(present, key=lambda s: (GROUP_ORDER.index(_group(s)), s))


def _tree_sort_key(values: pd.Series) -> pd.Series:
    num = pd.to_numeric(values, errors="coerce")
    if num.notna().all():
        return num
    return values.astype(str)


def read_table(path, required, *, numeric=(), str_columns=()) -> pd.DataFrame:
    """Read a CSV and check its columns.

    Parameters
    ----------
    path : str or Path
        The CSV file.
    required : sequence of str
        Columns that must be present.
    numeric : sequence of str
        Columns converted to float (a non-numeric entry is an error).
    str_columns : sequence of str
        Columns read as text.

    Raises
    ------
    InputDataError
        Missing, unreadable or empty file, a missing column or a non-numeric value; the message
        names the file.
    """
    path = Path(path)
    if not path.is_file():
        raise InputDataError(f"{path}: no such file")
    try:
        df = pd.read_csv(path, dtype={c: str for c in str_columns}, keep_default_na=True)
    except pd.errors.EmptyDataError:
        raise InputDataError(f"{path}: the file is empty") from None
    except (pd.errors.ParserError, UnicodeDecodeError) as exc:
        raise InputDataError(f"{path}: not a readable CSV file ({exc})") from None
    return check_columns(df, required, numeric=numeric, source=str(path))


def check_columns(df: pd.DataFrame, required, *, numeric=(), source: str) -> pd.DataFrame:
    """A table with its required columns checked and its numeric columns converted.

    Parameters
    ----------
    df : pandas.DataFrame
        The table.
    required : sequence of str
        Columns that must be present.
    numeric : sequence of str
        Columns converted to float64; empty cells become NaN, other non-numbers are errors.
    source : str
        Name of the table for messages.

    Returns
    -------
    pandas.DataFrame
        A copy with the numeric columns as float64.

    Raises
    ------
    InputDataError
        For a missing column, an empty table or a non-numeric value in a numeric column.
    """
    missing = [c for c in required if c not in df.columns]
    if missing:
        raise InputDataError(f"{source}: missing column(s) {', '.join(missing)}")
    if len(df) == 0:
        raise InputDataError(f"{source}: the table holds no rows")
    df = df.copy()
    for c in numeric:
        conv = pd.to_numeric(df[c], errors="coerce")
        bad = conv.isna() & df[c].notna()
        if bad.any():
            raise InputDataError(
                f"{source}: column {c!r} has non-numeric value {df[c][bad].iloc[0]!r}"
            )
        df[c] = conv.astype(np.float64)
    return df


def load_metrics(path) -> pd.DataFrame:
    """Read ``tree_metrics.csv`` (see the module docstring); errors name the file."""
    return read_table(path, ID_COLUMNS + METRIC_COLUMNS, numeric=METRIC_COLUMNS, str_columns=ID_COLUMNS)


def load_voxel_counts(path) -> pd.DataFrame:
    """Read ``voxel_counts.csv`` (``plot, method, n_voxels``); errors name the file."""
    return read_table(path, ("plot", "method", "n_voxels"), numeric=("n_voxels",), str_columns=("plot", "method"))


def load_sim_times(path) -> pd.DataFrame:
    """Read ``sim_times.csv`` (``plot, method, scenario, seconds``); errors name the file."""
    return read_table(
        path, ("plot", "method", "scenario", "seconds"), numeric=("seconds",),
        str_columns=("plot", "method", "scenario"),
    )


def prepare_metrics(metrics: pd.DataFrame, source: str) -> pd.DataFrame:
    """A tree-metrics table (``tree_metrics.csv``) checked for the analysis.

    Parameters
    ----------
    metrics : pandas.DataFrame
        Columns :data:`ID_COLUMNS` and the metric columns.
    source : str
        Name of the table for messages.

    Returns
    -------
    pandas.DataFrame
        A copy with identifying columns as str and metrics as float64.

    Raises
    ------
    InputDataError
        For missing columns or values, duplicate tree × scenario × method rows, a tree with two
        species, or no ``reference`` rows.
    """
    df = check_columns(metrics, ID_COLUMNS + METRIC_COLUMNS, numeric=METRIC_COLUMNS, source=source)
    for c in ID_COLUMNS:
        if df[c].isna().any():
            raise InputDataError(f"{source}: column {c!r} has empty values")
        df[c] = df[c].astype(str)
    dup = df.duplicated(["plot", "tree_id", "scenario", "method"])
    if dup.any():
        r = df[dup].iloc[0]
        raise InputDataError(
            f"{source}: duplicate row for plot {r['plot']}, tree {r['tree_id']}, "
            f"scenario {r['scenario']}, method {r['method']}"
        )
    nsp = df.groupby(["plot", "tree_id"])["species"].nunique()
    if (nsp > 1).any():
        plot, tree = nsp[nsp > 1].index[0]
        raise InputDataError(f"{source}: tree {tree} of plot {plot} has more than one species")
    if not (df["method"] == REFERENCE).any():
        raise InputDataError(f"{source}: no {REFERENCE!r} rows (the real recordings) to compare with")
    return df


# --------------------------------------------------------------------------- errors


def compute_errors(metrics: pd.DataFrame, *, source: str = "tree metrics") -> pd.DataFrame:
    """Simulated minus reference value of every metric, per tree × method × scenario.

    Parameters
    ----------
    metrics : DataFrame
        The ``tree_metrics.csv`` table.
    source : str
        Name used in error messages (the file).

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
    out["group"] = out["species"].map(_group)
    with np.errstate(divide="ignore", invalid="ignore"):
        out["error"] = out["sim"] - out["ref"]
        rel = 100.0 * out["error"] / out["ref"].abs()
    out["rel_error"] = rel.where(out["ref"] != 0)
    out["_m"] = out["method"].map({m: i for i, m in enumerate(method_order(out["method"]))})
    out["_s"] = out["scenario"].map({s: i for i, s in enumerate(scenario_order(out["scenario"]))})
    out["_k"] = out["metric"].map({c: i for i, c in enumerate(cols)})
    out["_t"] = _tree_sort_key(out["tree_id"])
    out = out.sort_values(["_m", "_s", "plot", "_t", "tree_id", "_k"], kind="stable")
    out = out[["plot", "tree_id", "species", "group", "scenario", "method", "metric", "sim", "ref",
               "error", "rel_error"]]
    return out.reset_index(drop=True)


def check_errors(errors: pd.DataFrame, source: str = "errors") -> pd.DataFrame:
    """An errors table (as :func:`compute_errors` returns it) checked for the analysis.

    Parameters
    ----------
    errors : pandas.DataFrame
        Columns ``plot, tree_id, species, scenario, method, metric, sim, ref, error,
        rel_error`` (``group`` optional).
    source : str
        Name of the table for messages.

    Returns
    -------
    pandas.DataFrame
        A copy with identifying columns as str, values as float64 and a ``group`` column.
    """
    need = ("plot", "tree_id", "species", "scenario", "method", "metric", "sim", "ref", "error", "rel_error")
    df = check_columns(errors, need, numeric=("sim", "ref", "error", "rel_error"), source=source)
    for c in ("plot", "tree_id", "species", "scenario", "method", "metric"):
        df[c] = df[c].astype(str)
    if "group" not in df.columns:
        df["group"] = df["species"].map(_group)
    return df


def _wide(df: pd.DataFrame, values=("error", "rel_error", "sim", "ref")):
    """Per-tree rows (scenario, method, plot, tree) × metric matrices of ``values``.

    Returns the row table (``scenario, method, plot, tree_id, species, group``), the metric
    names and a dict of float arrays (rows × metrics).
    """
    keys = ["scenario", "method", "plot", "tree_id"]
    metrics = list(dict.fromkeys(df["metric"]))
    try:
        w = df.set_index(keys + ["metric"])[list(values)].unstack("metric")
    except ValueError:
        raise InputDataError("errors: duplicate rows for one tree × method × scenario × metric") from None
    info = df.drop_duplicates(keys).set_index(keys)[["species", "group"]].reindex(w.index)
    rows = info.reset_index()
    arrays = {v: w[v].reindex(columns=metrics).to_numpy(np.float64) for v in values}
    return rows, metrics, arrays


def _levels(df: pd.DataFrame):
    """(species label, group label, row mask) for every species, every group and all trees."""
    out = []
    for sp in species_order(df["species"]):
        out.append((sp, _group(sp), (df["species"] == sp).to_numpy()))
    groups = [g for g in GROUP_ORDER if (df["group"] == g).any()]
    for g in groups:
        out.append(("all", g, (df["group"] == g).to_numpy()))
    out.append(("all", "all", np.ones(len(df), bool)))
    return out


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
    info, metrics, arr = _wide(df)
    scen_col = info["scenario"].to_numpy()
    meth_col = info["method"].to_numpy()
    rows = []
    for sp, grp, mask in _levels(info):
        for sc in scenario_order(df["scenario"]):
            for me in method_order(df["method"]):
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


# --------------------------------------------------------------------------- tests


def _paired(sim: np.ndarray, ref: np.ndarray) -> tuple:
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
            res = _st.ttest_rel(s, r)
            t, tp = float(res.statistic), float(res.pvalue)
        try:
            w = _st.wilcoxon(s, r)
            ws, wp = float(w.statistic), float(w.pvalue)
        except ValueError:
            ws, wp = nan, nan
    return n, mean_d, t, tp, ws, wp


def _paired_block(sim: np.ndarray, ref: np.ndarray) -> list[tuple]:
    """:func:`_paired` for every column; clean columns go through SciPy in one call."""
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
            t = _st.ttest_rel(sim[:, idx], ref[:, idx], axis=0)
            w = _st.wilcoxon(sim[:, idx], ref[:, idx], axis=0)
        md = d[:, idx].mean(axis=0)
        for k, j in enumerate(idx):
            out[j] = (n, float(md[k]), float(t.statistic[k]), float(t.pvalue[k]),
                      float(w.statistic[k]), float(w.pvalue[k]))
    for j in np.flatnonzero(~clean):
        out[j] = _paired(sim[:, j], ref[:, j])
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
    info, metrics, arr = _wide(df, ("sim", "ref"))
    scen_col = info["scenario"].to_numpy()
    meth_col = info["method"].to_numpy()
    grp_col = info["group"].to_numpy()
    groups = ["all"] + [g for g in GROUP_ORDER if (grp_col == g).any()]
    rows = []
    for g in groups:
        gmask = np.ones(len(info), bool) if g == "all" else grp_col == g
        for sc in scenario_order(df["scenario"]):
            for me in method_order(df["method"]):
                sel = gmask & (scen_col == sc) & (meth_col == me)
                if not sel.any():
                    continue
                res = _paired_block(arr["sim"][sel], arr["ref"][sel])
                for k, r in zip(metrics, res):
                    rows.append((g, sc, me, k) + r)
    return pd.DataFrame(rows, columns=["group", "scenario", "method", "metric", "n", "mean_diff", "t_statistic",
                                       "t_p", "wilcoxon_statistic", "wilcoxon_p"])


def multireturn_ttest(metrics: pd.DataFrame, *, metric: str = "multi_return_pct",
                      source: str = "tree metrics") -> pd.DataFrame:
    """Two-sample Student t-test (equal variances) of a metric, conifer vs broadleaf.

    Parameters
    ----------
    metrics : DataFrame
        The ``tree_metrics.csv`` table.
    metric : str
        Metric column to compare (default the multiple-return share).
    source : str
        Name used in error messages.

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
    df["group"] = df["species"].map(_group)
    rows = []
    for me in [REFERENCE] + method_order(df["method"]):
        for sc in scenario_order(df["scenario"]):
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
                    res = _st.ttest_ind(c, b, equal_var=True)
                t, p = float(res.statistic), float(res.pvalue)
            rows.append((me, sc, len(c), len(b), mc, mb, mc - mb, t, len(c) + len(b) - 2, p))
    return pd.DataFrame(rows, columns=["method", "scenario", "n_conifer", "n_broadleaf", "mean_conifer",
                                       "mean_broadleaf", "diff", "t", "df", "p"])


# --------------------------------------------------------------------------- Table 5


def _penetration_class(mr_bias: float) -> str:
    if not np.isfinite(mr_bias):
        return "unknown"
    if mr_bias < -PENETRATION_TOLERANCE_PP:
        return "underestimated"
    if mr_bias > PENETRATION_TOLERANCE_PP:
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
        ``penetration`` (from ``mr_bias_pp``: below −5 pp "underestimated", above +5 pp
        "overestimated", else "realistic").
    """
    err = check_errors(errors, sources[0])
    vc = check_columns(voxel_counts, ("plot", "method", "n_voxels"), numeric=("n_voxels",), source=sources[1])
    st = check_columns(sim_times, ("plot", "method", "scenario", "seconds"), numeric=("seconds",),
                        source=sources[2])
    for t in (vc, st):
        for c in ("plot", "method") + (("scenario",) if "scenario" in t else ()):
            t[c] = t[c].astype(str)
    methods = method_order(pd.concat([err["method"], vc["method"], st["method"]]))
    vc_sim = vc[vc["method"] != REFERENCE]
    common = None
    for me in methods:
        plots = set(vc_sim.loc[vc_sim["method"] == me, "plot"])
        if plots:
            common = plots if common is None else common & plots
    common = common or set()
    scen = scenario_order(st["scenario"])
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
        row["penetration"] = _penetration_class(row["mr_bias_pp"])
        rows.append(row)
    out = pd.DataFrame(rows)
    fewest = out["n_voxels_common"].min(skipna=True) if len(out) else math.nan
    out.insert(4, "voxel_ratio", out["n_voxels_common"] / fewest if fewest and np.isfinite(fewest) else math.nan)
    return out.drop(columns="n_voxels_common")


# --------------------------------------------------------------------------- findings


def _fmt(x, nd=2) -> str:
    if x is None or not np.isfinite(x):
        return "n/a"
    return f"{x:.{nd}f}"


def _fmt_p(p) -> str:
    if p is None or not np.isfinite(p):
        return "n/a"
    return f"{p:.2g}" if p < 0.001 else f"{p:.3f}"


def _mean_err(err, method, scenario, metric):
    v = err.loc[(err["method"] == method) & (err["scenario"] == scenario) & (err["metric"] == metric), "error"]
    v = v.to_numpy(float)
    v = v[np.isfinite(v)]
    return float(v.mean()) if len(v) else math.nan


def _test_row(tests, method, scenario, metric):
    r = tests[(tests["group"] == "all") & (tests["method"] == method) & (tests["scenario"] == scenario)
              & (tests["metric"] == metric)]
    return r.iloc[0] if len(r) else None


def _verdict(ok_list) -> str:
    if not ok_list:
        return "not testable"
    return "agrees" if all(ok_list) else "disagrees"


def _paired_tree_diff(err, m_a, m_b, scenario, metric, col="sim", absolute=False):
    """Per-tree values of method a and b (sim or |error|) on their common trees."""
    def get(m):
        s = err[(err["method"] == m) & (err["scenario"] == scenario) & (err["metric"] == metric)]
        v = s.set_index(["plot", "tree_id"])[col].astype(float)
        return v.abs() if absolute else v
    a, b = get(m_a), get(m_b)
    j = pd.concat([a.rename("a"), b.rename("b")], axis=1, join="inner").dropna()
    return j["a"].to_numpy(), j["b"].to_numpy()


def evaluate_findings(errors: pd.DataFrame, tests: pd.DataFrame, mr_tests: pd.DataFrame,
                      t5: pd.DataFrame, voxel_counts: pd.DataFrame, *, alpha: float = ALPHA) -> list[dict]:
    """Check the study's qualitative findings against our numbers.

    Parameters
    ----------
    errors, tests, mr_tests, t5 : DataFrame
        Outputs of :func:`compute_errors`, :func:`paired_tests`, :func:`multireturn_ttest` and
        :func:`table5`.
    voxel_counts : DataFrame
        ``plot, method, n_voxels``.
    alpha : float
        Significance level.

    Returns
    -------
    list of dict
        One dict per finding with ``id``, ``claim`` (the study's statement), ``verdict``
        (``"agrees"``, ``"disagrees"`` or ``"not testable"``, decided from the numbers) and
        ``evidence`` (our numbers, one line per scenario/part).
    """
    err = check_errors(errors)
    scen = scenario_order(err["scenario"])
    methods = set(err["method"])
    out = []

    # F1: 0.25 m fixed voxels overestimate CBH and underestimate CPA
    ok, ev = [], []
    if "fixed_0.25" in methods:
        for sc in scen:
            cb, cp = _mean_err(err, "fixed_0.25", sc, "cbh"), _mean_err(err, "fixed_0.25", sc, "cpa")
            if not (np.isfinite(cb) and np.isfinite(cp)):
                continue
            tb, tc = _test_row(tests, "fixed_0.25", sc, "cbh"), _test_row(tests, "fixed_0.25", sc, "cpa")
            ok.append(cb > 0 and cp < 0)
            ev.append(f"{sc.upper()}: mean CBH error {_fmt(cb)} m (paired t p = {_fmt_p(tb['t_p'] if tb is not None else None)}), "
                      f"mean CPA error {_fmt(cp)} m² (p = {_fmt_p(tc['t_p'] if tc is not None else None)})")
    out.append(dict(id="F1", claim="0.25 m fixed voxels overestimate CBH and underestimate CPA.",
                    verdict=_verdict(ok), evidence=ev))

    # F2: scaled voxels match the accuracy of 0.02 m voxels with >= 50x fewer voxels
    ok, ev = [], []
    if {"scaled", "fixed_0.02"} <= methods:
        for sc in scen:
            for k, unit in (("cbh", "m"), ("cpa", "m²")):
                a, b = _paired_tree_diff(err, "scaled", "fixed_0.02", sc, k, col="error", absolute=True)
                if len(a) == 0:
                    continue
                mae_s, mae_f = float(a.mean()), float(b.mean())
                p = math.nan
                if len(a) >= 2 and np.any(a != b):
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")
                        try:
                            p = float(_st.wilcoxon(a, b, alternative="greater").pvalue)
                        except ValueError:
                            p = math.nan
                match = mae_s <= mae_f or not (np.isfinite(p) and p < alpha)
                ok.append(bool(match))
                ev.append(f"{sc.upper()} {k.upper()}: MAE scaled {_fmt(mae_s)} {unit} vs 0.02 m {_fmt(mae_f)} {unit} "
                          f"(one-sided Wilcoxon 'scaled worse' p = {_fmt_p(p)}): "
                          f"{'matches' if match else 'scaled significantly worse'}")
        vc = voxel_counts.copy()
        vc["plot"], vc["method"] = vc["plot"].astype(str), vc["method"].astype(str)
        ps = set(vc.loc[vc["method"] == "scaled", "plot"]) & set(vc.loc[vc["method"] == "fixed_0.02", "plot"])
        if ps:
            ns = float(vc.loc[(vc["method"] == "scaled") & vc["plot"].isin(ps), "n_voxels"].sum())
            nf = float(vc.loc[(vc["method"] == "fixed_0.02") & vc["plot"].isin(ps), "n_voxels"].sum())
            ratio = nf / ns if ns > 0 else math.inf
            ok.append(ratio >= VOXEL_RATIO_CLAIM)
            ev.append(f"voxels on {len(ps)} plot(s): 0.02 m {nf:.0f}, scaled {ns:.0f}, ratio {_fmt(ratio, 1)}× "
                      f"({'≥' if ratio >= VOXEL_RATIO_CLAIM else '<'} {VOXEL_RATIO_CLAIM:.0f}×)")
    out.append(dict(id="F2", claim="Scaled voxels match the accuracy (CBH, CPA) of 0.02 m fixed voxels with "
                                   "at least 50× fewer voxels.", verdict=_verdict(ok), evidence=ev))

    # F3: conifers significantly more multiple returns, in reference and scaled simulations
    def mr_parts(ms, want_sig):
        ok, ev = [], []
        for me in ms:
            for sc in scen:
                r = mr_tests[(mr_tests["method"] == me) & (mr_tests["scenario"] == sc)]
                if r.empty or not np.isfinite(r.iloc[0]["p"]):
                    continue
                r = r.iloc[0]
                sig = bool(r["diff"] > 0 and r["p"] < alpha)
                ok.append(sig == want_sig)
                ev.append(f"{me} {sc.upper()}: conifer {_fmt(r['mean_conifer'], 1)} % vs broadleaf "
                          f"{_fmt(r['mean_broadleaf'], 1)} %, t({int(r['df'])}) = {_fmt(r['t'])}, p = {_fmt_p(r['p'])}")
        return ok, ev

    ok, ev = mr_parts([m for m in (REFERENCE, "scaled") if m == REFERENCE or m in methods], True)
    if not any(e.startswith("scaled ") for e in ev):
        ok = []  # the claim needs the scaled simulations as well
    out.append(dict(id="F3", claim="Conifers have significantly more multiple returns than broadleaf trees, in "
                                   "the reference data and in the scaled-voxel simulations.",
                    verdict=_verdict(ok), evidence=ev))
    fixed = [m for m in method_order(methods) if m.startswith("fixed_")]
    ok, ev = mr_parts(fixed, False)
    out.append(dict(id="F3b", claim="Fixed voxels do not reproduce this conifer–broadleaf difference.",
                    verdict=_verdict(ok), evidence=ev))

    # F4: CoG shift lowers multiple returns and CPA
    ok, ev = [], []
    if {"scaled", "scaled_cog_shift"} <= methods:
        for sc in scen:
            for k, unit in (("multi_return_pct", "pp"), ("cpa", "m²")):
                a, b = _paired_tree_diff(err, "scaled_cog_shift", "scaled", sc, k)
                if len(a) == 0:
                    continue
                d = float(np.mean(a - b))
                ok.append(d < 0)
                ev.append(f"{sc.upper()} {k}: mean change CoG − scaled {_fmt(d)} {unit} over {len(a)} trees")
    out.append(dict(id="F4", claim="Shifting the scaled cubes to the centre of gravity lowers the multiple-return "
                                   "share and the CPA.", verdict=_verdict(ok), evidence=ev))

    # F5: large fixed voxels: Hmean and Hmin too high, Hsd too low
    ok, ev = [], []
    for me in ("fixed_0.25", "fixed_0.10"):
        if me not in methods:
            continue
        for sc in scen:
            hm, hn, hs = (_mean_err(err, me, sc, k) for k in ("hmean", "hmin", "hsd"))
            if not all(np.isfinite([hm, hn, hs])):
                continue
            ok.append(hm > 0 and hn > 0 and hs < 0)
            ev.append(f"{me} {sc.upper()}: mean error Hmean {_fmt(hm)} m, Hmin {_fmt(hn)} m, Hsd {_fmt(hs)} m")
    out.append(dict(id="F5", claim="Large fixed voxels (0.25, 0.10 m) give too high Hmean and Hmin and too low Hsd.",
                    verdict=_verdict(ok), evidence=ev))

    # F6: random shift changes nothing
    ok, ev = [], []
    if {"scaled", "scaled_random_shift"} <= methods:
        for sc in scen:
            for k in ("hmean", "multi_return_pct", "cbh", "cpa"):
                a, b = _paired_tree_diff(err, "scaled_random_shift", "scaled", sc, k)
                if len(a) < 2:
                    continue
                n, md, t, tp, _, _ = _paired(a, b)
                if not np.isfinite(tp):
                    tp = 1.0 if md == 0 else 0.0
                ok.append(tp >= alpha)
                ev.append(f"{sc.upper()} {k}: mean change random − scaled {_fmt(md)}, paired t p = {_fmt_p(tp)}")
    out.append(dict(id="F6", claim="The random shift of the scaled cubes changes nothing significantly "
                                   "(Hmean, multiple returns, CBH, CPA).", verdict=_verdict(ok), evidence=ev))

    # F7: 0.02 m voxels overestimate ULS multiple returns
    ok, ev = [], []
    if "fixed_0.02" in methods and "uls" in scen:
        for g in ("conifer", "broadleaf"):
            e = err[(err["method"] == "fixed_0.02") & (err["scenario"] == "uls") & (err["metric"] == "multi_return_pct")
                    & (err["group"] == g)]["error"].to_numpy(float)
            e = e[np.isfinite(e)]
            if len(e):
                ok.append(e.mean() > 0)
                ev.append(f"{g}: mean ULS multiple-return error {_fmt(float(e.mean()), 1)} pp "
                          f"(study: ≈ {'+8' if g == 'conifer' else '+20'} pp)")
    out.append(dict(id="F7", claim="0.02 m fixed voxels overestimate the ULS multiple-return share.",
                    verdict=_verdict(ok), evidence=ev))

    # Table 5 rows
    t5 = t5.set_index("method") if "method" in t5.columns else t5
    present = [m for m in KNOWN_METHODS if m in t5.index]
    for me, (complexity, voxels, penetration, accuracy) in _TABLE5_CLAIMS.items():
        claim = (f"Table 5, {me}: model generation {complexity}; voxels: {voxels or 'not stated'}; "
                 f"penetration {penetration}; CBH/CPA accuracy {accuracy}.")
        ok, ev = [], []
        if me in t5.index:
            r = t5.loc[me]
            if voxels is not None and np.isfinite(r["voxel_ratio"]):
                lv = _VOXEL_LEVEL[voxels]
                bad = [o for o in present if o != me and _TABLE5_CLAIMS[o][1] is not None
                       and _VOXEL_LEVEL[_TABLE5_CLAIMS[o][1]] != lv and np.isfinite(t5.loc[o, "voxel_ratio"])
                       and np.sign(r["voxel_ratio"] - t5.loc[o, "voxel_ratio"]) != np.sign(lv - _VOXEL_LEVEL[_TABLE5_CLAIMS[o][1]])]
                ok.append(not bad)
                ev.append(f"voxels {r['n_voxels']:.0f} ({_fmt(r['voxel_ratio'], 1)}× the fewest)"
                          + (f"; out of the study's order against {', '.join(bad)}" if bad else ""))
            if np.isfinite(r["mr_bias_pp"]):
                ours = r["penetration"]
                want = _PENETRATION_DIR[penetration]
                good = ours == want
                extra = ""
                if penetration == "strongly underestimated" and "fixed_0.10" in t5.index \
                        and np.isfinite(t5.loc["fixed_0.10", "mr_bias_pp"]):
                    stronger = r["mr_bias_pp"] < t5.loc["fixed_0.10", "mr_bias_pp"]
                    good = good and stronger
                    extra = f"; {'more' if stronger else 'not more'} negative than fixed_0.10"
                ok.append(bool(good))
                ev.append(f"penetration {ours} (mean multiple-return error {_fmt(r['mr_bias_pp'], 1)} pp, "
                          f"tolerance ±{PENETRATION_TOLERANCE_PP:g} pp{extra})")
            if np.isfinite(r["accuracy_error_pct"]):
                la = _ACCURACY_LEVEL[accuracy]
                bad = [o for o in present if o != me and _ACCURACY_LEVEL[_TABLE5_CLAIMS[o][3]] != la
                       and np.isfinite(t5.loc[o, "accuracy_error_pct"])
                       and (r["accuracy_error_pct"] < t5.loc[o, "accuracy_error_pct"])
                       != (la > _ACCURACY_LEVEL[_TABLE5_CLAIMS[o][3]])]
                ok.append(not bad)
                ev.append(f"CBH/CPA error {_fmt(r['accuracy_error_pct'], 1)} % (CBH MAE {_fmt(r['cbh_mae_m'])} m, "
                          f"CPA MAE {_fmt(r['cpa_mae_m2'], 1)} m²)"
                          + (f"; out of the study's order against {', '.join(bad)}" if bad else ""))
            ev.append("model generation complexity: not measured")
        out.append(dict(id=f"T5:{me}", claim=claim, verdict=_verdict(ok), evidence=ev))
    return out


def findings_markdown(findings: list[dict]) -> str:
    """Render :func:`evaluate_findings` as Markdown (``findings.md``)."""
    n_ok = sum(f["verdict"] == "agrees" for f in findings)
    n_bad = sum(f["verdict"] == "disagrees" for f in findings)
    n_na = sum(f["verdict"] == "not testable" for f in findings)
    lines = [
        "# Findings of Weiser et al. (2021) checked against our numbers",
        "",
        f"{n_ok} agree, {n_bad} disagree, {n_na} not testable. Verdicts are computed from the tables in this "
        f"folder (errors.csv, tests.csv, multireturn_ttest.csv, table5.csv); significance level {ALPHA:g}.",
        "",
    ]
    sections = [("Qualitative findings", [f for f in findings if not f["id"].startswith("T5:")]),
                ("Table 5", [f for f in findings if f["id"].startswith("T5:")])]
    for title, items in sections:
        lines += [f"## {title}", ""]
        for f in items:
            lines.append(f"- **{f['id']}** {f['claim']} — **{f['verdict']}**")
            for e in f["evidence"]:
                lines.append(f"  - {e}")
        lines.append("")
    return "\n".join(lines)


# --------------------------------------------------------------------------- driver


def _write_csv(df: pd.DataFrame, path: Path) -> Path:
    return write_csv(path, df, index=False, float_format=FLOAT_FORMAT, na_rep="NaN", lineterminator="\n")


#: the files of ``vlsforest stats``: key → file name inside an output folder
STATS_FILES = {
    "errors": "errors.csv",
    "summary_by_species": "summary_by_species.csv",
    "tests": "tests.csv",
    "multireturn_ttest": "multireturn_ttest.csv",
    "table5": "table5.csv",
    "findings": "findings.md",
}


def stats_outputs(outputs) -> dict:
    """The output file of each key of :data:`STATS_FILES`.

    Parameters
    ----------
    outputs : str, Path or mapping
        A folder (the files get the names of :data:`STATS_FILES` inside it) or a mapping of
        every key of :data:`STATS_FILES` to its file.

    Returns
    -------
    dict of str to Path

    Raises
    ------
    ConfigError
        A mapping that misses a key or has an unknown one.
    """
    if isinstance(outputs, Mapping):
        missing = [k for k in STATS_FILES if k not in outputs]
        unknown = [k for k in outputs if k not in STATS_FILES]
        if missing or unknown:
            raise ConfigError(f"stats outputs: missing {missing}, unknown {unknown} (keys: {', '.join(STATS_FILES)})")
        return {k: Path(outputs[k]) for k in STATS_FILES}
    return {k: Path(outputs) / name for k, name in STATS_FILES.items()}


def write_stats(metrics_path, voxel_counts_path, sim_times_path, outputs, *, seed: int = 0,
                n_boot: int = 2000) -> dict:
    """Run every comparison and write the files of ``vlsforest stats``.

    Parameters
    ----------
    metrics_path, voxel_counts_path, sim_times_path : str or Path
        The input tables (see the module docstring).
    outputs : str, Path or mapping
        Where the files go: a folder, or a mapping of every key of :data:`STATS_FILES` to its
        file (:func:`stats_outputs`); parent folders are created.
    seed : int
        Bootstrap seed.
    n_boot : int
        Bootstrap resamples.

    Returns
    -------
    dict of str to Path
        ``errors, summary_by_species, tests, multireturn_ttest, table5, findings`` → the files
        written.
    """
    files = stats_outputs(outputs)
    metrics = load_metrics(metrics_path)
    vc = load_voxel_counts(voxel_counts_path)
    st = load_sim_times(sim_times_path)
    errors = compute_errors(metrics, source=str(metrics_path))
    summary = summarize_errors(errors, n_boot=n_boot, seed=seed)
    tests = paired_tests(errors)
    mr = multireturn_ttest(metrics, source=str(metrics_path))
    t5 = table5(errors, vc, st, sources=(str(metrics_path), str(voxel_counts_path), str(sim_times_path)))
    findings = evaluate_findings(errors, tests, mr, t5, vc)
    paths = {
        "errors": _write_csv(errors, files["errors"]),
        "summary_by_species": _write_csv(summary, files["summary_by_species"]),
        "tests": _write_csv(tests, files["tests"]),
        "multireturn_ttest": _write_csv(mr, files["multireturn_ttest"]),
        "table5": _write_csv(t5, files["table5"]),
    }
    fp = files["findings"]
    write_text(fp, findings_markdown(findings))
    paths["findings"] = fp
    return paths
