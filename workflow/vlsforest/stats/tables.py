"""The tables of the comparison: names, display order, reading and checking.

Inputs are the workflow's tables:

``tree_metrics.csv``
    one row per tree × source: ``plot, tree_id, species, scenario, method`` and the metric
    columns of :data:`vlsforest.metrics.METRIC_COLUMNS`. ``method == "reference"`` rows are the
    real (reference) recordings, every other method is a simulation.
``voxel_counts.csv``
    ``plot, method, n_voxels``.
``sim_times.csv``
    ``plot, method, scenario, seconds``.

Display order: methods and scenarios in the order the caller gives (the study configuration's
order), then any other alphabetically; species by group (broadleaf, conifer, other) and then
name. Species map to groups through :func:`vlsforest.domain.species.species_group`; a species it
does not know belongs to the group ``"other"`` (:data:`OTHER_GROUP`), which is summarised but
left out of the conifer-vs-broadleaf tests.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from vlsforest.domain.species import GROUPS, species_group
from vlsforest.errors import InputDataError
from vlsforest.io.atomic import write_csv
from vlsforest.metrics import METRIC_COLUMNS

__all__ = [
    "REFERENCE",
    "OTHER_GROUP",
    "GROUP_ORDER",
    "ID_COLUMNS",
    "FLOAT_FORMAT",
    "group_of",
    "method_order",
    "scenario_order",
    "species_order",
    "tree_sort_key",
    "read_table",
    "check_columns",
    "load_metrics",
    "load_voxel_counts",
    "load_sim_times",
    "prepare_metrics",
    "check_errors",
    "wide_errors",
    "error_levels",
    "write_table",
]

#: method name of the real (reference) recordings
REFERENCE = "reference"
#: group of the species that :func:`vlsforest.domain.species.species_group` does not know
OTHER_GROUP = "other"
#: species groups in display order
GROUP_ORDER = (*GROUPS, OTHER_GROUP)
#: identifying columns of ``tree_metrics.csv``
ID_COLUMNS = ("plot", "tree_id", "species", "scenario", "method")
#: float format of every CSV written here
FLOAT_FORMAT = "%.10g"


def group_of(species) -> str:
    """Group of a species, :data:`OTHER_GROUP` for a species of no known group."""
    return species_group(species, default=OTHER_GROUP)


def _ordered(names, order: Sequence[str]) -> list[str]:
    present = {str(n) for n in names}
    first = [n for n in dict.fromkeys(str(o) for o in order) if n in present]
    return first + sorted(present - set(first))


def method_order(methods, order: Sequence[str] = ()) -> list[str]:
    """Distinct simulated methods in display order (``reference`` left out).

    Parameters
    ----------
    methods : iterable
        Method names (repeats allowed).
    order : sequence of str
        The preferred order (e.g. the configuration's ``methods``); names not in it follow
        alphabetically.

    Returns
    -------
    list of str
    """
    return _ordered({str(m) for m in methods} - {REFERENCE}, order)


def scenario_order(scenarios, order: Sequence[str] = ()) -> list[str]:
    """Distinct scenarios in display order: those of ``order`` first, the others alphabetically.

    Parameters
    ----------
    scenarios : iterable
        Scenario names (repeats allowed).
    order : sequence of str
        The preferred order (e.g. the configuration's ``scenarios``).

    Returns
    -------
    list of str
    """
    return _ordered(scenarios, order)


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
    return sorted(present, key=lambda s: (GROUP_ORDER.index(group_of(s)), s))


def tree_sort_key(values: pd.Series) -> pd.Series:
    """Sort key of tree ids: numeric where every id is a number, else the text."""
    num = pd.to_numeric(values, errors="coerce")
    if num.notna().all():
        return num
    return values.astype(str)


def write_table(df: pd.DataFrame, path) -> Path:
    """Write a table as the stats files are written (:data:`FLOAT_FORMAT`, ``NaN``, LF), atomically."""
    return write_csv(path, df, index=False, float_format=FLOAT_FORMAT, na_rep="NaN", lineterminator="\n")


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
        df["group"] = df["species"].map(group_of)
    return df


def wide_errors(df: pd.DataFrame, values=("error", "rel_error", "sim", "ref")):
    """Per-tree rows (scenario, method, plot, tree) × metric matrices of ``values``.

    Parameters
    ----------
    df : pandas.DataFrame
        A checked errors table (:func:`check_errors`).
    values : sequence of str
        Value columns to spread.

    Returns
    -------
    rows : pandas.DataFrame
        ``scenario, method, plot, tree_id, species, group`` per row.
    metrics : list of str
        The metric of each column.
    arrays : dict of str to ndarray
        Per value column, a float array (rows × metrics).
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


def error_levels(df: pd.DataFrame):
    """(species label, group label, row mask) for every species, every group and all trees.

    Parameters
    ----------
    df : pandas.DataFrame
        Rows with ``species`` and ``group`` columns.

    Returns
    -------
    list of tuple
        ``(species, group, mask)``: one per species, then ``("all", group, mask)`` per group
        present and ``("all", "all", mask)``.
    """
    out = []
    for sp in species_order(df["species"]):
        out.append((sp, group_of(sp), (df["species"] == sp).to_numpy()))
    groups = [g for g in GROUP_ORDER if (df["group"] == g).any()]
    for g in groups:
        out.append(("all", g, (df["group"] == g).to_numpy()))
    out.append(("all", "all", np.ones(len(df), bool)))
    return out
