"""Reading CSV tables (voxel centres, trajectories, tree and target tables) with one-line errors.

:func:`read_csv_table` reads a CSV file that a command or a scene part names: a missing file, a
file pandas cannot parse and a table without the columns the caller needs each end in one
:class:`~vlsforest.errors.InputDataError` naming the file. :func:`read_height_table` also
checks a table of trees and their ground heights (a ground table, a plot's targets). pandas is
imported at the first call.
"""

from __future__ import annotations

from pathlib import Path

from vlsforest.errors import InputDataError

__all__ = ["read_csv_table", "read_height_table"]


def read_csv_table(path, what: str = "CSV file", columns=(), ids=(), numbers=()):
    """Read a CSV file with a header row.

    Parameters
    ----------
    path : path
        The file.
    what : str
        What the file is, for the messages (``"trajectory file"``: ``…: no such trajectory file``).
    columns : iterable of str
        Columns the table must have (exact names).
    ids : iterable of str
        Further columns it must have that hold integer ids (tree or target ids); they are
        returned as int64.
    numbers : iterable of str
        Further columns it must have that hold finite numbers (coordinates, heights); they are
        returned as float64.

    Returns
    -------
    pandas.DataFrame
        The table as ``pandas.read_csv`` reads it, ``ids`` as int64, ``numbers`` as float64.

    Raises
    ------
    InputDataError
        The file does not exist (or is not a file), pandas cannot read it (its reason, on one
        line), it lacks one of ``columns`` or ``ids`` (naming those it lacks), or a value of
        ``ids`` is not an integer or a value of ``numbers`` not a finite number (naming the
        column); the message starts with the path.
    """
    import numpy as np
    import pandas as pd

    path = Path(path)
    ids, numbers = tuple(ids), tuple(numbers)
    if not path.is_file():
        raise InputDataError(f"{path}: no such {what}")
    try:
        df = pd.read_csv(path)
    except Exception as exc:  # pandas raises parser, decoding and OS errors alike
        raise InputDataError(f"{path}: not a readable CSV ({' '.join(str(exc).split())})") from None
    missing = (set(columns) | set(ids) | set(numbers)) - set(df.columns)
    if missing:
        raise InputDataError(f"{path}: {what} lacks column(s) {sorted(missing)}")
    for col in ids:
        v = pd.to_numeric(df[col], errors="coerce").to_numpy(np.float64)
        if not (np.isfinite(v).all() and (v == np.round(v)).all()):
            raise InputDataError(f"{path}: {what} has ids in column {col!r} that are not integers")
        df[col] = v.astype(np.int64)
    for col in numbers:
        v = pd.to_numeric(df[col], errors="coerce").to_numpy(np.float64)
        if not np.isfinite(v).all():
            raise InputDataError(f"{path}: {what} has values in column {col!r} that are not finite numbers")
        df[col] = v
    return df


def read_height_table(path, what: str, ids=(), columns=()):
    """Read a table of trees with their ground height ``z`` (a ground table, a plot's targets).

    Parameters
    ----------
    path : path
        The file.
    what : str
        What the file is, for the messages.
    ids : iterable of str
        Columns of integer ids the table must have.
    columns : iterable of str
        Further columns it must have.

    Returns
    -------
    pandas.DataFrame
        The table, with ``z`` as float64 and each of ``ids`` as int64.

    Raises
    ------
    InputDataError
        As :func:`read_csv_table`, and when a ``z`` is not a finite number or an id not an
        integer (naming the column).
    """
    return read_csv_table(path, what, columns, ids, numbers=("z",))
