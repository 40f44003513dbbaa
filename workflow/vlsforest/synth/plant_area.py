"""True plant area per voxel of generated trees, on any axis-aligned grid.

Convention (one-sided plant area, as PAD = plant area / voxel volume):

* foliage faces count their one-sided area (a leaf element is a flat, single-sided surface);
* woody faces (stem, branches) count **half** their surface area — the one-sided area of a
  cylinder in the sense of the plant area index (half the total surface, as in the
  "hemisurface" convention of Chen & Black 1992).

Triangles are clipped exactly against the voxel planes (Sutherland–Hodgman in a numba kernel,
slab by slab along x, then y, then z), so every triangle's area is distributed over the
voxels it crosses and the sum over voxels equals the tree's plant area to rounding error.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from vlsforest.errors import ConfigError
from vlsforest.synth.trees import PLANT_AREA_WEIGHT, TreeGeometry


@dataclass
class PlantAreaGrid:
    """Sparse per-voxel plant area.

    Attributes
    ----------
    ijk : ndarray int64 (n, 3)
        Voxel indices; voxel (i, j, k) spans ``origin + (i, j, k) * cell_size`` to
        ``origin + (i+1, j+1, k+1) * cell_size``.
    area : ndarray float64 (n,)
        One-sided plant area in the voxel (m²); PAD = area / cell volume.
    origin, cell_size : ndarray (3,)
    shape : tuple or None
        Grid shape; when given, only voxels inside it are listed.
    outside : float
        Plant area falling outside ``shape`` (0 when shape is None).
    """

    ijk: np.ndarray
    area: np.ndarray
    origin: np.ndarray
    cell_size: np.ndarray
    shape: tuple | None
    outside: float

    @property
    def total(self) -> float:
        """All plant area, inside and outside the grid."""
        return float(self.area.sum() + self.outside)

    def pad(self) -> np.ndarray:
        """Plant area density per listed voxel (m²/m³)."""
        return self.area / float(np.prod(self.cell_size))

    def dense(self) -> np.ndarray:
        """Dense (nx, ny, nz) array of plant area (needs ``shape``)."""
        if self.shape is None:
            raise ConfigError("shape: a dense array needs the grid shape")
        out = np.zeros(self.shape)
        np.add.at(out, tuple(self.ijk.T), self.area)
        return out


@njit(cache=True)
def _clip_plane(src, n, axis, plane, sign, dst):
    """Sutherland–Hodgman: keep sign*(x[axis] − plane) >= 0; returns the new vertex count."""
    m = 0
    for i in range(n):
        j = (i + 1) % n
        ds = sign * (src[i, axis] - plane)
        de = sign * (src[j, axis] - plane)
        ins = ds >= 0.0
        ine = de >= 0.0
        if ins != ine:
            t = ds / (ds - de)
            for c in range(3):
                dst[m, c] = src[i, c] + t * (src[j, c] - src[i, c])
            m += 1
        if ine:
            for c in range(3):
                dst[m, c] = src[j, c]
            m += 1
    return m


@njit(cache=True)
def _poly_area(P, n):
    sx = 0.0
    sy = 0.0
    sz = 0.0
    for i in range(1, n - 1):
        ax = P[i, 0] - P[0, 0]
        ay = P[i, 1] - P[0, 1]
        az = P[i, 2] - P[0, 2]
        bx = P[i + 1, 0] - P[0, 0]
        by = P[i + 1, 1] - P[0, 1]
        bz = P[i + 1, 2] - P[0, 2]
        sx += ay * bz - az * by
        sy += az * bx - ax * bz
        sz += ax * by - ay * bx
    return 0.5 * np.sqrt(sx * sx + sy * sy + sz * sz)


@njit(cache=True)
def _clip_kernel(tris, w, cs):
    """Exact clipping of triangles (relative to the grid origin) into voxels."""
    n = tris.shape[0]
    cap = max(16, 4 * n)
    cells = np.empty((cap, 3), np.int64)
    area = np.empty(cap)
    cnt = 0
    A = np.empty((16, 3))
    B = np.empty((16, 3))
    C = np.empty((16, 3))
    T = np.empty((16, 3))
    lo = np.empty(3, np.int64)
    hi = np.empty(3, np.int64)
    for t in range(n):
        if w[t] == 0.0:
            continue
        for ax in range(3):
            mn = min(tris[t, 0, ax], tris[t, 1, ax], tris[t, 2, ax]) / cs[ax]
            mx = max(tris[t, 0, ax], tris[t, 1, ax], tris[t, 2, ax]) / cs[ax]
            lo[ax] = np.int64(np.floor(mn))
            hi[ax] = max(np.int64(np.ceil(mx)) - 1, lo[ax])
        for i in range(lo[0], hi[0] + 1):
            for v in range(3):
                for c in range(3):
                    T[v, c] = tris[t, v, c]
            na = 3
            if hi[0] > lo[0]:
                m = _clip_plane(T, 3, 0, i * cs[0], 1.0, B)
                na = _clip_plane(B, m, 0, (i + 1) * cs[0], -1.0, A)
            else:
                for v in range(3):
                    for c in range(3):
                        A[v, c] = T[v, c]
            if na < 3:
                continue
            ylo = lo[1]
            yhi = hi[1]
            for j in range(ylo, yhi + 1):
                if yhi > ylo:
                    m = _clip_plane(A, na, 1, j * cs[1], 1.0, T)
                    nb = _clip_plane(T, m, 1, (j + 1) * cs[1], -1.0, B)
                else:
                    nb = na
                    for v in range(na):
                        for c in range(3):
                            B[v, c] = A[v, c]
                if nb < 3:
                    continue
                for k in range(lo[2], hi[2] + 1):
                    if hi[2] > lo[2]:
                        m = _clip_plane(B, nb, 2, k * cs[2], 1.0, T)
                        nc = _clip_plane(T, m, 2, (k + 1) * cs[2], -1.0, C)
                    else:
                        nc = nb
                        for v in range(nb):
                            for c in range(3):
                                C[v, c] = B[v, c]
                    if nc < 3:
                        continue
                    a = _poly_area(C, nc) * w[t]
                    if a <= 0.0:
                        continue
                    if cnt == cap:
                        cap *= 2
                        c2 = np.empty((cap, 3), np.int64)
                        a2 = np.empty(cap)
                        c2[:cnt] = cells[:cnt]
                        a2[:cnt] = area[:cnt]
                        cells = c2
                        area = a2
                    cells[cnt, 0] = i
                    cells[cnt, 1] = j
                    cells[cnt, 2] = k
                    area[cnt] = a
                    cnt += 1
    return cells[:cnt], area[:cnt]


def clip_triangles_to_grid(tris: np.ndarray, weights: np.ndarray, origin, cell_size,
                           chunk: int = 1_000_000):
    """Exact per-voxel area of triangles (n, 3, 3) times their weights.

    Parameters
    ----------
    tris : ndarray (n, 3, 3)
        Triangle vertices (world coordinates).
    weights : ndarray (n,)
        Factor applied to each triangle's area (plant-area convention).
    origin, cell_size :
        Grid corner and voxel edge length(s).
    chunk : int
        Triangles processed at once.

    Returns
    -------
    ijk : ndarray int64 (k, 3)
        Unique voxel indices touched.
    area : ndarray float64 (k,)
        Summed weighted area per voxel.
    """
    origin = np.asarray(origin, dtype=float).reshape(3)
    cs = np.broadcast_to(np.asarray(cell_size, dtype=float), (3,)).astype(float)
    all_cells, all_area = [], []
    for s in range(0, tris.shape[0], chunk):
        P = np.ascontiguousarray(tris[s:s + chunk] - origin, dtype=np.float64)
        c, a = _clip_kernel(P, np.ascontiguousarray(weights[s:s + chunk], dtype=np.float64), cs)
        all_cells.append(c)
        all_area.append(a)
    if not all_cells or sum(len(a) for a in all_area) == 0:
        return np.zeros((0, 3), np.int64), np.zeros(0)
    cells = np.concatenate(all_cells)
    area = np.concatenate(all_area)
    mn = cells.min(axis=0)
    ext = cells.max(axis=0) - mn + 1
    key = ((cells[:, 0] - mn[0]) * ext[1] + (cells[:, 1] - mn[1])) * ext[2] + (cells[:, 2] - mn[2])
    uk, inv = np.unique(key, return_inverse=True)
    summed = np.bincount(inv, weights=area, minlength=uk.size)
    ijk = np.stack([uk // (ext[1] * ext[2]), (uk // ext[2]) % ext[1], uk % ext[2]], axis=1) + mn
    return ijk.astype(np.int64), summed


def _as_list(geometries):
    if isinstance(geometries, TreeGeometry):
        return [geometries]
    if isinstance(geometries, tuple) and len(geometries) == 3 and \
            isinstance(geometries[0], np.ndarray):
        return [geometries]
    return list(geometries)


def true_plant_area(geometries, origin, cell_size, shape=None, organs=None,
                    chunk: int = 1_000_000) -> PlantAreaGrid:
    """True one-sided plant area per voxel of one or more trees.

    Parameters
    ----------
    geometries : TreeGeometry or iterable of TreeGeometry
        Trees (or ``(vertices, faces, organ)`` tuples).
    origin : (3,) array_like
        Corner of voxel (0, 0, 0).
    cell_size : float or (3,)
        Voxel edge length(s) (m).
    shape : (nx, ny, nz), optional
        Grid shape; voxels outside it are dropped from the listing and their area reported
        as ``outside``.  None lists every voxel touched (indices may be negative).
    organs : iterable of int, optional
        Only these organ codes (0 stem, 1 branch, 2 foliage).
    chunk : int
        Triangles clipped at once (memory bound).

    Returns
    -------
    PlantAreaGrid
    """
    cs = np.broadcast_to(np.asarray(cell_size, dtype=float), (3,)).astype(float)
    if not np.all(np.isfinite(cs)) or np.any(cs <= 0):
        raise ConfigError(f"cell_size: must be positive, got {cell_size!r}")
    origin = np.asarray(origin, dtype=float).reshape(-1)
    if origin.shape != (3,) or not np.isfinite(origin).all():
        raise ConfigError(f"origin: expected three finite numbers, got {origin!r}")
    if shape is not None:
        shape = tuple(int(s) for s in shape)
        if len(shape) != 3 or min(shape) <= 0:
            raise ConfigError(f"shape: expected three positive ints, got {shape!r}")
    tris_l, w_l = [], []
    for g in _as_list(geometries):
        if isinstance(g, TreeGeometry):
            v, f, o = g.vertices, g.faces, g.organ
        else:
            v, f, o = g
        sel = np.ones(f.shape[0], bool) if organs is None else \
            np.isin(o, np.asarray(list(organs)))
        tris_l.append(np.asarray(v, dtype=float)[f[sel]])
        w_l.append(PLANT_AREA_WEIGHT[o[sel]])
    tris = np.concatenate(tris_l) if tris_l else np.zeros((0, 3, 3))
    w = np.concatenate(w_l) if w_l else np.zeros(0)
    ijk, area = clip_triangles_to_grid(tris, w, origin, cs, chunk)
    outside = 0.0
    if shape is not None:
        inside = np.all((ijk >= 0) & (ijk < np.asarray(shape)), axis=1)
        outside = float(area[~inside].sum())
        ijk, area = ijk[inside], area[inside]
    return PlantAreaGrid(ijk=ijk, area=area, origin=origin, cell_size=cs, shape=shape,
                         outside=outside)


__all__ = ["PlantAreaGrid", "true_plant_area", "clip_triangles_to_grid"]
