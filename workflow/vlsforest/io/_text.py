"""Vectorised text columns shared by the readers and writers of the text formats (.vox, OBJ).

A private module of :mod:`vlsforest.io`: its functions serve :mod:`vlsforest.io.vox` and
:mod:`vlsforest.io.mesh` only.
"""

from __future__ import annotations

import numpy as np

__all__ = ["column_text", "join_rows", "token_counts"]


def token_counts(buf: bytes) -> np.ndarray:
    """Number of whitespace-separated tokens on each ``\\n``-separated line of ``buf``.

    Vectorised: token starts and newlines are located once, and the starts between two
    consecutive newlines are counted by a binary search over the (few) newline positions.
    """
    b = np.frombuffer(buf, dtype=np.uint8)
    if b.size == 0:
        return np.zeros(0, dtype=np.int64)
    nl = b == 10
    ws = b <= 32  # space, tab, CR, LF, VT, FF and other control bytes
    start = ~ws
    start[1:] &= ws[:-1]
    starts = np.flatnonzero(start)
    newlines = np.flatnonzero(nl)
    before = np.searchsorted(starts, newlines)
    return np.diff(np.concatenate([[0], before, [len(starts)]]))


def _int_text(a: np.ndarray) -> np.ndarray:
    """Integers as a bytes array, through a lookup table when the values are small."""
    a = a.astype(np.int64)
    if len(a) and a.min() >= 0 and a.max() < len(a):
        return np.arange(int(a.max()) + 1).astype("S")[a]
    return a.astype("S")


def column_text(a: np.ndarray) -> np.ndarray:
    """Format one column as a bytes array ('S' dtype), exactly round-trippable."""
    n = len(a)
    if a.dtype.kind in "iu":
        return _int_text(a)
    finite = np.isfinite(a)
    if (
        n
        and finite.all()
        and np.all(a == np.round(a))
        and np.all(np.abs(a) < 2.0**53)
        and not np.any(np.signbit(a) & (a == 0))
    ):
        if np.all(a == a[0]):
            text = str(int(a[0])).encode()
            return np.full(n, text, dtype=f"S{len(text)}")
        return _int_text(a)
    out = a.astype("S32")  # numpy's shortest round-trip repr (Dragon4)
    if not finite.all():
        out[np.isnan(a)] = b"NaN"
        out[np.isposinf(a)] = b"Infinity"
        out[np.isneginf(a)] = b"-Infinity"
    if n:
        out = out.astype(f"S{int(np.strings.str_len(out).max())}")
    return out


def join_rows(cols: list[np.ndarray]) -> bytes:
    """Join byte-string columns with single spaces, one row per line (vectorised)."""
    n = len(cols[0])
    if n == 0:
        return b""
    parts = []
    for c_i, c in enumerate(cols):
        w = c.dtype.itemsize
        parts.append(np.ascontiguousarray(c).view(np.uint8).reshape(n, w))
        sep = np.full((n, 1), 10 if c_i == len(cols) - 1 else 32, dtype=np.uint8)
        parts.append(sep)
    m = np.concatenate(parts, axis=1)
    return m[m != 0].tobytes()
