"""Cube geometry on the voxel lattice.

A voxel model's cubes are axis-aligned. A full cube fills its lattice cell; a PAD-scaled cube
(HELIOS++ and Weiser et al. 2021) has the side ``a = a0 · (PAD / PADmax)^alpha``
(:func:`scaled_cubes`). The simulator traces cubes directly or as triangles
(:func:`cube_triangles`), and the HELIOS++ export writes the same triangles as OBJ.
"""

from __future__ import annotations

import numpy as np

from vlsforest.errors import ConfigError

__all__ = ["CUBE_CORNERS", "CUBE_FACES", "cube_triangles", "scaled_cubes"]

#: the 8 corners of the cube [-1, 1]³; corner index = 4·x + 2·y + z (0 for −1, 1 for +1)
CUBE_CORNERS = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
CUBE_CORNERS.flags.writeable = False
#: the 12 outward-facing triangles of that cube, as corner indices
CUBE_FACES = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                       [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]], dtype=np.int64)
CUBE_FACES.flags.writeable = False


def cube_triangles(centre, half, first: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Triangles of axis-aligned cubes: 8 vertices and 12 faces per cube.

    Parameters
    ----------
    centre : ndarray (n, 3)
        Cube centres.
    half : ndarray (n,)
        Half sides.
    first : int
        Index of the first cube among all cubes of a mesh: faces index its vertices from
        ``8·first`` on, so that pieces of one mesh can be built one after the other.

    Returns
    -------
    vertices : ndarray float64 (8n, 3)
        Cube ``c``'s corners are rows ``8c … 8c + 7`` (order of :data:`CUBE_CORNERS`).
    faces : ndarray int64 (12n, 3)
        Vertex indices, counter-clockwise seen from outside.
    """
    centre = np.asarray(centre, dtype=np.float64).reshape(-1, 3)
    half = np.asarray(half, dtype=np.float64).reshape(-1)
    verts = (centre[:, None, :] + half[:, None, None] * CUBE_CORNERS[None]).reshape(-1, 3)
    faces = (CUBE_FACES[None] + 8 * np.arange(first, first + len(centre))[:, None, None]).reshape(-1, 3)
    return verts, faces


def scaled_cubes(ijk, pad, pad_max, a0: float = 0.25, alpha: float = 0.5) -> np.ndarray:
    """Half sides of PAD-scaled cubes: ``a/2 = a0/2 · (clip(PAD, 0, PADmax) / PADmax)^alpha``.

    Parameters
    ----------
    ijk : ndarray (n, 3)
        Lattice cells of the cubes (not used by the formula; kept for the callers' symmetry).
    pad : array_like (n,)
        Plant area density (m²/m³) per cell; NaN counts as 0.
    pad_max : float or array_like (n,)
        PADmax (m²/m³), > 0; one value or one per cell.
    a0 : float
        Cell size (m), > 0: the side of a cube with PAD ≥ PADmax.
    alpha : float
        Exponent, > 0 (the study: 0.5).

    Returns
    -------
    ndarray (n,)
        Half sides; 0 where PAD is 0 or NaN (no cube).

    Raises
    ------
    ConfigError
        For ``a0``, ``alpha`` or a ``pad_max`` that is not finite and > 0.
    """
    if not (np.isfinite(a0) and a0 > 0):
        raise ConfigError(f"a0 must be > 0, got {a0!r}")
    if not (np.isfinite(alpha) and alpha > 0):
        raise ConfigError(f"alpha must be > 0, got {alpha!r}")
    pad = np.asarray(pad, dtype=np.float64)
    pad_max = np.broadcast_to(np.asarray(pad_max, dtype=np.float64), pad.shape)
    if (~np.isfinite(pad_max) | (pad_max <= 0)).any():
        raise ConfigError("pad_max must be > 0")
    p = np.where(np.isfinite(pad), np.clip(pad, 0.0, pad_max), 0.0)
    return 0.5 * a0 * (p / pad_max) ** alpha
