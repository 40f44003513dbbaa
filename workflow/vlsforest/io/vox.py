"""AMAPVox ``.vox`` voxel files (the text layout HELIOS++ reads for voxel scene parts).

Layout (AMAPVox ≤ 1.6)::

    VOXEL SPACE
    #min_corner: x y z
    #max_corner: x y z
    #split: nx ny nz
    #res: 0.25 #max_pad: 5.0 #build-version: 1.4.3
    i j k PadBVTotal angleMean bsEntering ... attenuationBiasCorrection
    0 15 45 0.7 ...

A cube's centre is ``min_corner + (ijk + 0.5) * res`` and ``max_pad`` is read from the header
(HELIOS looks for it on the ``#res:`` line only, so :func:`write_vox` puts every further header
item there). ``#max_corner`` is kept as read; it is not used for placement and files written by
other tools are often inconsistent in it.

:func:`write_vox` writes numbers so that reading gives back exactly the same float64 values and a
second write gives identical bytes: floats as the shortest string that round-trips, columns whose
values are all whole numbers as integers, NaN as ``NaN`` and infinities as ``Infinity``.
"""

from __future__ import annotations

import io
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vlsforest.errors import InputDataError
from vlsforest.io.atomic import atomic_path
from vlsforest.io._text import column_text, join_rows, token_counts

#: attribute columns of the AMAPVox 1.4–1.6 layout, in file order (after ``i j k``)
STANDARD_COLUMNS = (
    "PadBVTotal",
    "angleMean",
    "bsEntering",
    "bsIntercepted",
    "bsPotential",
    "ground_distance",
    "lMeanTotal",
    "lgTotal",
    "nbEchos",
    "nbSampling",
    "transmittance",
    "attenuation",
    "attenuationBiasCorrection",
)
_IJK = ("i", "j", "k")
_RESERVED = ("min_corner", "max_corner", "split", "res")
_ITEM = re.compile(r"#\s*([^#:\s][^#:]*?)\s*:\s*([^#]*?)\s*(?=#|$)")
_KEY_OK = re.compile(r"^[^#:\s]+$")
_NA = ["NaN", "nan", "NAN", "-NaN", "-nan", "+NaN", "+nan"]


@dataclass(eq=False)
class VoxFile:
    """The content of one ``.vox`` file.

    Parameters
    ----------
    min_corner, max_corner : array_like, shape (3,)
        Grid corners (float64). Only ``min_corner`` places the voxels.
    split : array_like, shape (3,)
        Number of cells along x, y, z (int).
    res : float
        Cell edge length.
    header : dict of str to str
        Further header items in file order (``max_pad``, ``build-version``, ``lad_type`` ...).
    columns : list of str
        Column names, the first three ``i j k``.
    data : dict of str to ndarray
        One array per column: ``i j k`` int32, the others float64 (NaN allowed).
    source : str or None
        The file it was read from (used in error messages; not compared).
    """

    min_corner: np.ndarray
    max_corner: np.ndarray
    split: np.ndarray
    res: float
    header: dict = field(default_factory=dict)
    columns: list = field(default_factory=lambda: list(_IJK))
    data: dict = field(default_factory=dict)
    source: str | None = None

    def __post_init__(self):
        where = f"{self.source}: " if self.source else ""
        self.min_corner = np.asarray(self.min_corner, dtype=np.float64).reshape(3)
        self.max_corner = np.asarray(self.max_corner, dtype=np.float64).reshape(3)
        split = np.asarray(self.split)
        if split.shape != (3,) or not np.all(np.isfinite(split)) or np.any(split != np.round(split)):
            raise InputDataError(f"{where}#split must be three whole numbers, got {self.split!r}")
        self.split = split.astype(np.int64)
        if np.any(self.split < 1):
            raise InputDataError(f"{where}#split must be positive, got {self.split.tolist()}")
        self.res = float(self.res)
        if not (np.isfinite(self.res) and self.res > 0):
            raise InputDataError(f"{where}#res must be a positive number, got {self.res!r}")
        if not np.all(np.isfinite(self.min_corner)):
            raise InputDataError(f"{where}#min_corner must be finite, got {self.min_corner.tolist()}")
        self.header = {str(k): str(v) for k, v in dict(self.header).items()}
        for k, v in self.header.items():
            if k in _RESERVED or not _KEY_OK.match(k) or "#" in v or "\n" in v or "\r" in v:
                raise InputDataError(f"{where}invalid header item {k!r}: {v!r}")
        self.columns = [str(c) for c in self.columns]
        if tuple(self.columns[:3]) != _IJK:
            raise InputDataError(f"{where}the first three columns must be 'i j k', got {self.columns[:3]}")
        if len(set(self.columns)) != len(self.columns):
            raise InputDataError(f"{where}duplicate column names in {self.columns}")
        for c in self.columns:
            if not _KEY_OK.match(c):
                raise InputDataError(f"{where}invalid column name {c!r}")
        if set(self.data) != set(self.columns):
            raise InputDataError(
                f"{where}data columns {sorted(self.data)} do not match the column list {self.columns}"
            )
        data = {}
        n = None
        for c in self.columns:
            a = np.asarray(self.data[c])
            if a.ndim != 1:
                raise InputDataError(f"{where}column {c!r} must be one-dimensional")
            if n is None:
                n = len(a)
            elif len(a) != n:
                raise InputDataError(f"{where}column {c!r} has {len(a)} values, 'i' has {n}")
            if c in _IJK:
                if a.dtype.kind == "f" and (not np.all(np.isfinite(a)) or np.any(a != np.round(a))):
                    raise InputDataError(f"{where}column {c!r} holds values that are not whole numbers")
                a = a.astype(np.int64)
                if len(a) and (a.min() < 0 or a.max() > np.iinfo(np.int32).max):
                    raise InputDataError(f"{where}column {c!r} holds values outside 0..2^31-1")
                a = a.astype(np.int32)
            else:
                a = a.astype(np.float64)
            data[c] = a
        self.data = data

    # ------------------------------------------------------------------ accessors
    @property
    def n_voxels(self) -> int:
        """Number of voxels (rows)."""
        return len(self.data["i"])

    @property
    def ijk(self) -> np.ndarray:
        """Cell indices, shape (n, 3), int32."""
        return np.stack([self.data["i"], self.data["j"], self.data["k"]], axis=1)

    def centres(self) -> np.ndarray:
        """Cell centres ``min_corner + (ijk + 0.5) * res``, shape (n, 3), float64 (HELIOS placement)."""
        return self.min_corner + (self.ijk.astype(np.float64) + 0.5) * self.res

    def column(self, name: str) -> np.ndarray:
        """Return the array of column ``name``.

        Raises
        ------
        InputDataError
            If the column does not exist (names the file when known).
        """
        if name not in self.data:
            where = f"{self.source}: " if self.source else ""
            raise InputDataError(f"{where}no column {name!r} in the .vox data; columns are {self.columns}")
        return self.data[name]

    @property
    def max_pad(self) -> float | None:
        """``max_pad`` from the header as a float, or None when the header has none."""
        v = self.header.get("max_pad")
        if v is None:
            return None
        try:
            return float(v)
        except ValueError:
            where = f"{self.source}: " if self.source else ""
            raise InputDataError(f"{where}header item max_pad is not a number: {v!r}") from None

    def __eq__(self, other) -> bool:
        if not isinstance(other, VoxFile):
            return NotImplemented
        if not (
            np.array_equal(self.min_corner, other.min_corner)
            and np.array_equal(self.max_corner, other.max_corner, equal_nan=True)
            and np.array_equal(self.split, other.split)
            and self.res == other.res
            and list(self.header.items()) == list(other.header.items())
            and self.columns == other.columns
        ):
            return False
        for c in self.columns:
            a, b = self.data[c], other.data[c]
            if a.dtype != b.dtype:
                return False
            if not np.array_equal(a, b, equal_nan=a.dtype.kind == "f"):
                return False
        return True

    __hash__ = None  # mutable


# ---------------------------------------------------------------------- helpers
def _fmt_float(x: float) -> str:
    """Shortest round-trip text of one float (``NaN``/``Infinity`` spelled as AMAPVox does)."""
    x = float(x)
    if np.isnan(x):
        return "NaN"
    if np.isinf(x):
        return "Infinity" if x > 0 else "-Infinity"
    return repr(x)


def _parse_header_items(line: str) -> list[tuple[str, str]]:
    return [(m.group(1), m.group(2)) for m in _ITEM.finditer(line)]


def _floats(path, lineno, key, value, n) -> np.ndarray:
    parts = value.split()
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        vals = []
    if len(vals) != n:
        raise InputDataError(f"{path}: line {lineno}: #{key} needs {n} number(s), got {value!r}")
    return np.array(vals, dtype=np.float64)


# ---------------------------------------------------------------------- reading
def read_vox(path) -> VoxFile:
    """Read an AMAPVox ``.vox`` file.

    Parameters
    ----------
    path : str or Path
        The file.

    Returns
    -------
    VoxFile

    Raises
    ------
    InputDataError
        Missing or empty file, first line not ``VOXEL SPACE``, missing ``#min_corner``, ``#split``
        or ``#res``, missing column line, rows with the wrong number of cells, non-numeric cells,
        i/j/k that are not whole numbers or lie outside ``#split``, or a voxel listed twice.
        The message names the file and, where it applies, the line.
    """
    import pandas as pd

    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise InputDataError(f"{path}: .vox file not found") from None
    except OSError as e:
        raise InputDataError(f"{path}: cannot read .vox file ({e})") from None
    if not raw.strip():
        raise InputDataError(f"{path}: .vox file is empty")

    # ---- header: read line by line until the column-name line
    pos = 0
    lineno = 0
    first = None
    items: list[tuple[str, str, int]] = []
    col_line = None
    while pos < len(raw):
        end = raw.find(b"\n", pos)
        end = len(raw) if end < 0 else end
        line = raw[pos:end].decode("utf-8", errors="replace").strip().lstrip("\ufeff")
        pos = end + 1
        lineno += 1
        if first is None:
            if not line:
                continue
            first = line
            if line.upper() != "VOXEL SPACE":
                raise InputDataError(
                    f"{path}: not an AMAPVox .vox file (line {lineno} is {line[:60]!r}, expected 'VOXEL SPACE')"
                )
            continue
        if not line:
            continue
        if line.startswith("#"):
            items.extend((k, v, lineno) for k, v in _parse_header_items(line))
            continue
        col_line = line
        break
    if col_line is None:
        raise InputDataError(f"{path}: no column-name line ('i j k ...') after the header")
    columns = col_line.split()
    if tuple(columns[:3]) != _IJK:
        raise InputDataError(
            f"{path}: line {lineno}: expected the column-name line starting with 'i j k', got {col_line[:80]!r}"
        )
    if len(set(columns)) != len(columns):
        raise InputDataError(f"{path}: line {lineno}: duplicate column names")
    col_lineno = lineno

    spec: dict[str, tuple[str, int]] = {}
    header: dict[str, str] = {}
    for k, v, ln in items:
        if k in _RESERVED:
            spec[k] = (v, ln)
        else:
            header[k] = v
    for k in ("min_corner", "split", "res"):
        if k not in spec:
            raise InputDataError(f"{path}: header has no #{k}: item")
    min_corner = _floats(path, spec["min_corner"][1], "min_corner", spec["min_corner"][0], 3)
    split_f = _floats(path, spec["split"][1], "split", spec["split"][0], 3)
    res = float(_floats(path, spec["res"][1], "res", spec["res"][0], 1)[0])
    if np.any(split_f != np.round(split_f)) or np.any(split_f < 1):
        raise InputDataError(f"{path}: line {spec['split'][1]}: #split must be three positive integers")
    if not (np.isfinite(res) and res > 0):
        raise InputDataError(f"{path}: line {spec['res'][1]}: #res must be positive, got {res}")
    split = split_f.astype(np.int64)
    if "max_corner" in spec:
        max_corner = _floats(path, spec["max_corner"][1], "max_corner", spec["max_corner"][0], 3)
    else:
        max_corner = min_corner + split * res

    # ---- body
    body = raw[pos:]
    ncol = len(columns)
    counts = token_counts(body)
    bad = np.flatnonzero((counts != 0) & (counts != ncol))
    if bad.size:
        ln = col_lineno + 1 + int(bad[0])
        raise InputDataError(
            f"{path}: line {ln}: {int(counts[bad[0]])} values, expected {ncol} (one per column)"
        )
    nrows = int(np.count_nonzero(counts))
    if nrows == 0:
        arr = np.zeros((0, ncol))
    else:
        try:
            df = pd.read_csv(
                io.BytesIO(body),
                sep=" " if _single_spaced(body, counts) else r"\s+",
                header=None,
                names=list(range(ncol)),
                dtype=np.float64,
                engine="c",
                keep_default_na=False,
                na_values=_NA,
                skip_blank_lines=True,
                comment=None,
                quoting=3,  # csv.QUOTE_NONE: a quote is a bad cell, not a quoted number
            )
            arr = df.to_numpy(dtype=np.float64)
        except (ValueError, pd.errors.ParserError) as e:
            _raise_bad_cell(path, body, col_lineno, columns, e)
        if arr.shape != (nrows, ncol):  # pragma: no cover - guarded by the token count
            raise InputDataError(f"{path}: could not parse the voxel rows ({arr.shape} vs {nrows} rows)")

    ijk = arr[:, :3]
    if not np.all(np.isfinite(ijk)) or np.any(ijk != np.round(ijk)):
        bad_row = int(np.flatnonzero(~np.all(np.isfinite(ijk) & (ijk == np.round(ijk)), axis=1))[0])
        raise InputDataError(
            f"{path}: line {_row_line(counts, col_lineno, bad_row)}: i j k must be whole numbers, "
            f"got {ijk[bad_row].tolist()}"
        )
    outside = np.any((ijk < 0) | (ijk >= split), axis=1)
    if outside.any():
        bad_row = int(np.flatnonzero(outside)[0])
        raise InputDataError(
            f"{path}: line {_row_line(counts, col_lineno, bad_row)}: voxel {ijk[bad_row].astype(int).tolist()} "
            f"lies outside #split {split.tolist()}"
        )
    ijk_i = ijk.astype(np.int64)
    if nrows > 1:
        lin = (ijk_i[:, 0] * split[1] + ijk_i[:, 1]) * split[2] + ijk_i[:, 2]
        order = np.argsort(lin, kind="stable")
        dup = np.flatnonzero(lin[order][1:] == lin[order][:-1])
        if dup.size:
            bad_row = int(max(order[dup[0]], order[dup[0] + 1]))
            raise InputDataError(
                f"{path}: line {_row_line(counts, col_lineno, bad_row)}: voxel {ijk_i[bad_row].tolist()} "
                "is listed twice"
            )
    data = {c: arr[:, n] for n, c in enumerate(columns)}
    return VoxFile(
        min_corner=min_corner,
        max_corner=max_corner,
        split=split,
        res=res,
        header=header,
        columns=columns,
        data=data,
        source=str(path),
    )


def _single_spaced(body: bytes, counts: np.ndarray) -> bool:
    """True when cells are separated by exactly one space (the fast pandas path applies).

    A line with t tokens needs at least t - 1 separators; if the whole body holds exactly
    sum(t - 1) spaces and no other whitespace besides newlines, every line is single-spaced with
    no leading or trailing blanks (empty lines are fine, whitespace-only lines are not).
    """
    if b"\t" in body or b"\r" in body or b"\x0b" in body or b"\x0c" in body:
        return False
    nonblank = int(np.count_nonzero(counts))
    return body.count(b" ") == int(counts.sum()) - nonblank


def _row_line(counts: np.ndarray, col_lineno: int, row: int) -> int:
    """File line number (1-based) of data row ``row`` (blank lines skipped)."""
    nonblank = np.flatnonzero(counts != 0)
    return col_lineno + 1 + int(nonblank[row])


def _raise_bad_cell(path, body: bytes, col_lineno: int, columns: list[str], err: Exception):
    na = set(_NA)
    for n, line in enumerate(body.decode("utf-8", errors="replace").split("\n")):
        for c, tok in enumerate(line.split()):
            if tok in na:
                continue
            try:
                float(tok)
                ok = "_" not in tok
            except ValueError:
                ok = False
            if not ok:
                raise InputDataError(
                    f"{path}: line {col_lineno + 1 + n}: value {tok[:40]!r} in column {columns[c]!r} is not a number"
                ) from None
    raise InputDataError(f"{path}: could not parse the voxel rows ({err})") from None


# ---------------------------------------------------------------------- writing
def write_vox(path, vox: VoxFile) -> None:
    """Write a ``.vox`` file in the AMAPVox layout.

    Header lines come in the order ``VOXEL SPACE``, ``#min_corner:``, ``#max_corner:``,
    ``#split:``, ``#res:`` and the further header items on the ``#res:`` line as ``#key: value``;
    then the column-name line and one row per voxel. ``read_vox(path) == vox`` exactly, and
    writing what was read gives identical bytes.

    Parameters
    ----------
    path : str or Path
        Output file (parent directories are created).
    vox : VoxFile
        What to write.

    Raises
    ------
    InputDataError
        If a voxel lies outside ``vox.split`` or is listed twice (the file could not be read back).
    """
    path = Path(path)
    vox = VoxFile(  # re-validate (the object may have been edited since construction)
        vox.min_corner, vox.max_corner, vox.split, vox.res, vox.header, vox.columns, vox.data, vox.source
    )
    ijk = vox.ijk.astype(np.int64)
    if len(ijk):
        outside = np.any((ijk < 0) | (ijk >= vox.split), axis=1)
        if outside.any():
            raise InputDataError(
                f"{path}: cannot write voxel {ijk[np.argmax(outside)].tolist()}: outside split {vox.split.tolist()}"
            )
        lin = np.sort((ijk[:, 0] * vox.split[1] + ijk[:, 1]) * vox.split[2] + ijk[:, 2])
        if np.any(lin[1:] == lin[:-1]):
            raise InputDataError(f"{path}: cannot write: a voxel (i, j, k) is listed twice")

    res_line = "#res: " + _fmt_float(vox.res)
    for k, v in vox.header.items():
        res_line += f" #{k}: {v}" if v else f" #{k}:"
    head = "\n".join(
        [
            "VOXEL SPACE",
            "#min_corner: " + " ".join(_fmt_float(x) for x in vox.min_corner),
            "#max_corner: " + " ".join(_fmt_float(x) for x in vox.max_corner),
            "#split: " + " ".join(str(int(x)) for x in vox.split),
            res_line,
            " ".join(vox.columns),
        ]
    )
    body = join_rows([column_text(vox.data[c]) for c in vox.columns])
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(head.encode("utf-8") + b"\n")
        f.write(body)


# ---------------------------------------------------------------------- building
def make_vox(
    ijk,
    res: float,
    min_corner,
    columns: dict | None = None,
    max_pad: float | None = None,
    header: dict | None = None,
    split=None,
) -> VoxFile:
    """Build a :class:`VoxFile` with the AMAPVox column set.

    Parameters
    ----------
    ijk : array_like, shape (n, 3)
        Non-negative integer cell indices.
    res : float
        Cell edge length.
    min_corner : array_like, shape (3,)
        Grid origin (the lower corner of cell (0, 0, 0)).
    columns : dict of str to array_like, optional
        Values of standard columns (``PadBVTotal`` ...) and of any extra columns; standard
        columns not given are filled with 0, extra columns follow the standard ones in the
        order given.
    max_pad : float, optional
        Written to the header as ``max_pad`` (HELIOS ``scaled`` mode needs it).
    header : dict of str to str, optional
        Further header items, in order.
    split : array_like, shape (3,), optional
        Grid size; default ``ijk.max(axis=0) + 1``.

    Returns
    -------
    VoxFile
        With ``max_corner = min_corner + split * res``.
    """
    ijk = np.asarray(ijk)
    if ijk.size == 0:
        ijk = np.zeros((0, 3), dtype=np.int64)
    if ijk.ndim != 2 or ijk.shape[1] != 3:
        raise InputDataError(f"ijk must have shape (n, 3), got {ijk.shape}")
    if ijk.dtype.kind == "f" and (not np.all(np.isfinite(ijk)) or np.any(ijk != np.round(ijk))):
        raise InputDataError("ijk must hold whole numbers")
    ijk = ijk.astype(np.int64)
    if len(ijk) and ijk.min() < 0:
        raise InputDataError("ijk must be non-negative")
    if split is None:
        split = ijk.max(axis=0) + 1 if len(ijk) else np.ones(3, dtype=np.int64)
    split = np.asarray(split, dtype=np.int64).reshape(3)
    min_corner = np.asarray(min_corner, dtype=np.float64).reshape(3)
    n = len(ijk)
    columns = dict(columns or {})
    for c in _IJK:
        if c in columns:
            raise InputDataError(f"column {c!r} comes from ijk, do not pass it in columns")
    names = list(_IJK) + list(STANDARD_COLUMNS) + [c for c in columns if c not in STANDARD_COLUMNS]
    data = {"i": ijk[:, 0], "j": ijk[:, 1], "k": ijk[:, 2]}
    for c in names[3:]:
        v = columns.get(c)
        a = np.zeros(n) if v is None else np.broadcast_to(np.asarray(v, dtype=np.float64), (n,)).copy()
        data[c] = a
    hdr = {str(k): str(v) for k, v in (header or {}).items()}
    if max_pad is not None:
        hdr["max_pad"] = _fmt_float(max_pad)
    return VoxFile(
        min_corner=min_corner,
        max_corner=min_corner + split * float(res),
        split=split,
        res=float(res),
        header=hdr,
        columns=names,
        data=data,
    )


__all__ = ["STANDARD_COLUMNS", "VoxFile", "make_vox", "read_vox", "write_vox"]
