"""Deterministic ``.npz`` files (the same arrays give the same bytes) and one validating loader.

:func:`save_npz` writes; :func:`load_npz` reads a file kind described by :class:`ArraySpec`
records and turns every defect (missing, empty, truncated, not an npz, wrong dtype or shape,
mismatched lengths, NaN) into one :class:`~vlsforest.errors.InputDataError` naming the file.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vlsforest.errors import InputDataError
from vlsforest.io.atomic import atomic_path

__all__ = ["save_npz", "load_npz", "ArraySpec"]


def save_npz(path, arrays: dict) -> Path:
    """Write arrays as a compressed ``.npz`` with fixed zip timestamps.

    Parameters
    ----------
    path : path
        The file to write; its folder is created.
    arrays : dict str → array_like
        Arrays by name, written in the dict's order (no pickled objects).

    Returns
    -------
    Path
        ``path``.
    """
    import io
    import zipfile

    path = Path(path)
    with atomic_path(path) as tmp, zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name in arrays:
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.asanyarray(arrays[name]), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            zf.writestr(info, buf.getvalue())
    return path


@dataclass(frozen=True)
class ArraySpec:
    """What one array of an ``.npz`` file must be (see :func:`load_npz`).

    Parameters
    ----------
    kinds : str
        Accepted numpy dtype kinds (``"f"`` float, ``"i"``/``"u"`` integers, ``"b"`` bool);
        an integer array is accepted where ``"f"`` is.
    shape : tuple
        The array's shape: an ``int`` fixes an axis, ``None`` lets it vary, and a ``str``
        names a length that every array using the same name must share (e.g. ``"n"``).
    required : bool
        Whether the array must be present.
    finite : bool
        Whether every value must be finite (float arrays only).
    """

    kinds: str = "fiu"
    shape: tuple = ("n",)
    required: bool = True
    finite: bool = True


def _read_arrays(path: Path, what: str) -> dict:
    """All arrays of an ``.npz`` (no pickles); any reading failure is an :class:`InputDataError`."""
    import zipfile

    if not path.is_file():
        raise InputDataError(f"{path}: no such file (expected a {what} .npz)")
    if path.stat().st_size == 0:
        raise InputDataError(f"{path}: the {what} file is empty")
    if not zipfile.is_zipfile(path):
        raise InputDataError(f"{path}: not a {what} .npz file (not a zip archive)")
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except Exception as exc:  # truncated or corrupt members: zlib.error, EOFError, BadZipFile, ValueError …
        raise InputDataError(f"{path}: the {what} file cannot be read: truncated, corrupt or holding pickled "
                             f"objects ({type(exc).__name__}: {' '.join(str(exc).split())})") from None


def load_npz(path, spec: dict, what: str, prefixes: dict | None = None) -> dict:
    """Load an ``.npz`` file and validate every array against a specification.

    Parameters
    ----------
    path : str or Path
        The file.
    spec : dict str → ArraySpec
        The named arrays the file kind holds.
    what : str
        The file kind, for messages (``"hits"``, ``"crowns"`` …).
    prefixes : dict str → ArraySpec, optional
        A specification for every further array whose name starts with the key (e.g. the
        ``hit_`` arrays of a hits file); other unknown arrays are kept unchecked.

    Returns
    -------
    dict str → ndarray
        Every array of the file.

    Raises
    ------
    InputDataError
        For a missing, empty, truncated or non-npz file, or an array that is missing, of the
        wrong dtype or shape, of a length that differs from its fellows, or holds NaN or
        infinite values. The message names the file and the array.
    """
    path = Path(path)
    arrays = _read_arrays(path, what)
    checks = [(name, s) for name, s in spec.items()]
    for prefix, s in (prefixes or {}).items():
        checks += [(name, s) for name in arrays if name.startswith(prefix) and name not in spec]
    lengths: dict = {}
    for name, s in checks:
        if name not in arrays:
            if s.required:
                raise InputDataError(f"{path}: the {what} file lacks the array {name!r}")
            continue
        a = arrays[name]
        kinds = s.kinds + ("iu" if "f" in s.kinds else "")
        if a.dtype.kind not in kinds:
            raise InputDataError(f"{path}: array {name!r} has dtype {a.dtype}, expected "
                                 f"{'/'.join(_KIND_NAMES[k] for k in s.kinds)}")
        if a.ndim != len(s.shape):
            raise InputDataError(f"{path}: array {name!r} has shape {a.shape}, expected "
                                 f"{len(s.shape)} dimension(s)")
        for axis, (n, want) in enumerate(zip(a.shape, s.shape)):
            if isinstance(want, int) and n != want:
                raise InputDataError(f"{path}: array {name!r} has shape {a.shape}, expected {want} along axis {axis}")
            if isinstance(want, str):
                other = lengths.setdefault(want, (name, n))
                if other[1] != n:
                    raise InputDataError(f"{path}: array {name!r} has {n} rows but {other[0]!r} has {other[1]}")
        if s.finite and a.dtype.kind == "f" and not np.isfinite(a).all():
            bad = int(np.size(a) - np.count_nonzero(np.isfinite(a)))
            raise InputDataError(f"{path}: array {name!r} holds {bad} NaN or infinite value(s)")
    return arrays


_KIND_NAMES = {"f": "float", "i": "int", "u": "uint", "b": "bool"}
