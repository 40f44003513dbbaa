"""Reading CSV tables (voxel centres, trajectories, tree and target tables) with one-line errors.

:func:`read_csv_table` reads a CSV file that a command or a scene part names: a missing file, a
file pandas cannot parse and a table without the columns the caller needs each end in one
:class:`~vlsforest.errors.InputDataError` naming the file. pandas is imported at the first call.
"""

from __future__ import annotations

from pathlib import Path

from vlsforest.errors import InputDataError

__all__ = ["read_csv_table"]


def read_csv_table(path, what: str = "CSV file", columns=()):
    """Read a CSV file with a header row.

    Parameters
    ----------
    path : path
        The file.
    what : str
        What the file is, for the messages (``"trajectory file"``: ``…: no such trajectory file``).
    columns : iterable of str
        Columns the table must have (exact names).

    Returns
    -------
    pandas.DataFrame
        The table as ``pandas.read_csv`` reads it.

    Raises
    ------
    InputDataError
        The file does not exist (or is not a file), pandas cannot read it (its reason, on one
        line), or it lacks one of ``columns`` (naming those it lacks); the message starts with
        the path.
    """
    import pandas as pd

    path = Path(path)
    if not path.is_file():
        raise InputDataError(f"{path}: no such {what}")
    try:
        df = pd.read_csv(path)
    except Exception as exc:  # pandas raises parser, decoding and OS errors alike
        raise InputDataError(f"{path}: not a readable CSV ({' '.join(str(exc).split())})") from None
    missing = set(columns) - set(df.columns)
    if missing:
        raise InputDataError(f"{path}: {what} lacks column(s) {sorted(missing)}")
    return df
