"""Deterministic ``.npz`` files (the same arrays give the same bytes)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["save_npz"]


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
    path.parent.mkdir(parents=True, exist_ok=True)
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name in arrays:
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.asanyarray(arrays[name]), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            zf.writestr(info, buf.getvalue())
    return path
