"""Stem points and stem meshes of target trees (screened Poisson reconstruction).

The study meshed each target stem from its TLS points with CloudCompare's Poisson
reconstruction (octree depth 8); the crown and everything else was voxelised. This module does
the same from one tree's TLS cloud:

1. **Stem points** (:func:`trace_stem`, :func:`select_stem_points`): the stem is followed in
   horizontal slices (default 0.25 m) by robust circle fits. The first circle is found by RANSAC
   at breast height (1.0–1.6 m above the base) near the given base position (and with a radius
   near DBH/2 when the DBH is known); from there the tracker walks down to the ground and up
   into the crown (when the stem is hidden at breast height, the first circle is sought in
   slabs from 0.4 to 3.4 m). Each slice predicts the axis position (straight extrapolation of the last
   1.5 m of centres, so lean and sweep are followed) and the radius (median of the last fits,
   never growing upwards), refits the circle on the points near the predicted surface (the
   centre only, with the predicted radius, when the visible arc is narrower than 120°), and is
   accepted when enough points lie within ``tolerance`` of the circle, the arc they cover is
   wide enough and the circle stays close to the prediction. Gaps (occlusion) of up to
   ``max_gap`` are bridged; the tracker stops above that, or where the predicted radius falls
   below ``min_radius``. The stem points are the points within ``tolerance`` of the circle of
   an accepted slice: a subset of the input, nothing is added or moved, so the tree's other
   points (the crown) are the complement.
2. **Crown base**: the lowest height where at least ``crown_min_points`` tree points lie more
   than ``crown_margin`` outside the stem surface in a 0.5 m window (reported; the stem is
   tracked through it).
3. **Mesh** (:func:`stem_mesh`): stem points thinned to one per ``voxel`` cube, PCA normals
   (``k`` neighbours) turned towards the scanner that measured each point (the stem is convex,
   so this is outwards), screened Poisson reconstruction by pymeshlab (depth 8, full depth 5,
   scale 1.1, 1.5 samples per node, point weight 4: CloudCompare's defaults as in the study,
   one thread so that the output is reproducible).
4. **Trimming**: the Poisson surface is closed and balloons where there are no points (the cut
   at the ground, the top, hidden back sides). Vertices whose Poisson sampling density (the
   vertex quality) is below the ``density_quantile`` quantile are removed with their faces;
   so are faces with any point farther than ``max_extent`` from the nearest stem point
   (checked on a barycentric grid of 15 probes per face, with the grid spacing added as a
   bound) and connected pieces of fewer than ``min_component_faces`` faces. The result is an
   open surface that nowhere extends more than ``max_extent`` (default 9 cm, less than the
   10 cm asked for) beyond the stem points; the simulator uses it as an opaque stem.

All computations are deterministic (fixed RANSAC seed, stable sorts, a single Poisson thread):
the same input gives the same mesh bytes.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from vlsforest.errors import ConfigError, InputDataError
from vlsforest.io.las import PointCloud
from vlsforest.io.mesh import TriangleMesh

#: breast height (m above the stem base)
BREAST_HEIGHT = 1.3
#: fewest stem points a mesh is built from
MIN_STEM_POINTS = 50
#: fewest points a tree cloud must hold
MIN_TREE_POINTS = 20

#: lower ends of the slabs where the first circle is sought, in order (m above the base)
_INIT_SLABS = (1.0, 0.4, 1.6, 2.2, 2.8)
_INIT_THICKNESS = 0.6
_RANSAC_ITER = 300
#: barycentric probe grid of the trimming (n subdivisions of each edge)
_BARY_N = 4
_BARY = np.array(
    [(i, j, _BARY_N - i - j) for i in range(_BARY_N + 1) for j in range(_BARY_N + 1 - i)], dtype=np.float64
) / _BARY_N
_SEED = 20210101


# ============================================================================ results
@dataclass
class StemAxis:
    """The tracked stem: one entry per slice.

    Attributes
    ----------
    z : ndarray (n,)
        Slice centre heights (absolute z), ascending.
    center : ndarray (n, 2)
        Circle centres (x, y) (the prediction where the slice was not accepted).
    radius : ndarray (n,)
        Circle radii (m).
    n_points : ndarray (n,)
        Stem points (circle inliers) of each slice.
    accepted : ndarray (n,) of bool
        Whether the slice holds a stem circle supported by the points.
    mask : ndarray (m,) of bool
        Stem points among the input points.
    crown_base : float
        Crown base estimate (absolute z); ``nan`` when no crown was found.
    slice_height, tolerance : float
        The settings used.
    """

    z: np.ndarray
    center: np.ndarray
    radius: np.ndarray
    n_points: np.ndarray
    accepted: np.ndarray
    mask: np.ndarray
    crown_base: float
    slice_height: float
    tolerance: float

    @property
    def z_range(self) -> tuple[float, float]:
        """Bottom and top (absolute z) of the accepted slices; ``(nan, nan)`` when none."""
        if not self.accepted.any():
            return (math.nan, math.nan)
        zs = self.z[self.accepted]
        return (float(zs.min() - self.slice_height / 2), float(zs.max() + self.slice_height / 2))


@dataclass
class StemResult:
    """Stem of one tree: points, axis, trimmed Poisson mesh and a summary.

    Attributes
    ----------
    mesh : TriangleMesh
        The trimmed Poisson mesh (absolute coordinates).
    mask : ndarray of bool
        Stem points among the tree's points.
    axis : StemAxis
        The tracked stem.
    summary : dict
        JSON-ready figures (what ``stem.json`` holds).
    """

    mesh: TriangleMesh
    mask: np.ndarray
    axis: StemAxis
    summary: dict = field(default_factory=dict)


# ============================================================================ checks
def _check_xyz(xyz, source: str, min_points: int = MIN_TREE_POINTS) -> np.ndarray:
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputDataError(f"{source}: points must have shape (n, 3), got {xyz.shape}")
    if len(xyz) == 0:
        raise InputDataError(f"{source}: no points")
    bad = ~np.isfinite(xyz).all(axis=1)
    if bad.any():
        raise InputDataError(f"{source}: {int(bad.sum())} points have NaN or infinite coordinates")
    if len(xyz) < min_points:
        raise InputDataError(f"{source}: only {len(xyz)} points, too few for a stem (need ≥ {min_points})")
    return xyz


def _check_base(base) -> np.ndarray:
    try:
        b = np.asarray(base, dtype=np.float64).reshape(3)
    except (ValueError, TypeError):
        raise ConfigError(f"base: must be three numbers x y z, got {base!r}") from None
    if not np.isfinite(b).all():
        raise ConfigError(f"base: must be finite, got {b.tolist()}")
    return b


def _check_positive(name: str, value, allow_none: bool = False):
    if value is None and allow_none:
        return None
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{name}: must be a number, got {value!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise ConfigError(f"{name}: must be a positive number, got {value!r}")
    return v


# ============================================================================ circle fits
def _circle_lsq(xy: np.ndarray, c0: np.ndarray, r0: float, fix_radius: bool, n_iter: int = 8):
    """Geometric least-squares circle (Gauss–Newton) from a start; the radius fixed or free."""
    c = np.array(c0, dtype=np.float64)
    r = float(r0)
    for _ in range(n_iter):
        d = xy - c
        dist = np.hypot(d[:, 0], d[:, 1])
        dist = np.maximum(dist, 1e-9)
        res = dist - r
        u = d / dist[:, None]
        if fix_radius:
            jac = -u
        else:
            jac = np.column_stack([-u, -np.ones(len(xy))])
        step, *_ = np.linalg.lstsq(jac, -res, rcond=None)
        if not np.all(np.isfinite(step)):
            break
        c = c + step[:2]
        if not fix_radius:
            r = r + step[2]
        if np.abs(step).max() < 1e-6:
            break
    return c, r


def _arc_coverage(xy: np.ndarray, c: np.ndarray) -> float:
    """Angle (degrees) covered by the directions of ``xy`` seen from ``c`` (360 minus the largest gap)."""
    if len(xy) < 2:
        return 0.0
    a = np.sort(np.arctan2(xy[:, 1] - c[1], xy[:, 0] - c[0]))
    gaps = np.diff(np.concatenate([a, a[:1] + 2 * np.pi]))
    return float(360.0 - np.degrees(gaps.max()))


def _fit_slice(xy, c_pred, r_pred, tol, band, fix_ratio_cov=120.0):
    """Refit a circle near a prediction. Returns (center, radius, inlier mask, coverage)."""
    d = np.hypot(xy[:, 0] - c_pred[0], xy[:, 1] - c_pred[1])
    inl = np.abs(d - r_pred) < band
    c, r = np.array(c_pred, dtype=np.float64), float(r_pred)
    cov = 0.0
    for width in (band, max(band * 0.5, tol), tol, tol):
        if inl.sum() < 3:
            break
        cov = _arc_coverage(xy[inl], c)
        fix = cov < fix_ratio_cov
        c_new, r_new = _circle_lsq(xy[inl], c, r_pred if fix else r, fix)
        if not (np.all(np.isfinite(c_new)) and math.isfinite(r_new) and r_new > 0):
            break
        c, r = c_new, (r_pred if fix else r_new)
        d = np.hypot(xy[:, 0] - c[0], xy[:, 1] - c[1])
        inl = np.abs(d - r) < width
    cov = _arc_coverage(xy[inl], c) if inl.sum() >= 2 else 0.0
    return c, r, inl, cov


def _ransac_init(xy, base_xy, r_hint, tol, rng):
    """RANSAC circle near the base in the breast-height slab. Returns (center, radius) or None."""
    n = len(xy)
    if n < 3:
        return None
    r_lo, r_hi = (0.02, 1.2) if r_hint is None else (0.6 * r_hint - 0.01, 1.5 * r_hint + 0.02)
    best, best_score = None, 0
    idx = rng.integers(0, n, size=(_RANSAC_ITER, 3))
    p1, p2, p3 = xy[idx[:, 0]], xy[idx[:, 1]], xy[idx[:, 2]]
    # circumcircles of the triples
    ax, ay = p1[:, 0], p1[:, 1]
    bx, by = p2[:, 0], p2[:, 1]
    cx, cy = p3[:, 0], p3[:, 1]
    den = 2 * (ax * (by - cy) + bx * (cy - ay) + cx * (ay - by))
    ok = np.abs(den) > 1e-12
    den = np.where(ok, den, 1.0)
    a2, b2, c2 = ax**2 + ay**2, bx**2 + by**2, cx**2 + cy**2
    ux = (a2 * (by - cy) + b2 * (cy - ay) + c2 * (ay - by)) / den
    uy = (a2 * (cx - bx) + b2 * (ax - cx) + c2 * (bx - ax)) / den
    rr = np.hypot(ax - ux, ay - uy)
    off = np.hypot(ux - base_xy[0], uy - base_xy[1])
    ok &= (rr > r_lo) & (rr < r_hi) & (off < rr + 0.3)
    for k in np.flatnonzero(ok):
        d = np.hypot(xy[:, 0] - ux[k], xy[:, 1] - uy[k])
        score = int(np.count_nonzero(np.abs(d - rr[k]) < tol))
        if score > best_score:
            best, best_score = (np.array([ux[k], uy[k]]), float(rr[k])), score
    if best is None:
        return None
    c, r = best
    c, r, inl, cov = _fit_slice(xy, c, r, tol, 2 * tol, fix_ratio_cov=90.0 if r_hint is None else 120.0)
    if r_hint is not None and cov < 120.0:
        c, r, inl, cov = _fit_slice(xy, c, r_hint, tol, 2 * tol)
    if inl.sum() < 10:
        return None
    return c, r


# ============================================================================ tracking
def trace_stem(
    xyz,
    base,
    dbh: float | None = None,
    *,
    slice_height: float = 0.25,
    tolerance: float = 0.03,
    max_gap: float = 3.0,
    min_radius: float = 0.02,
    min_slice_points: int = 8,
    min_coverage: float = 45.0,
    crown_margin: float = 0.3,
    crown_min_points: int = 10,
    source: str = "points",
) -> StemAxis:
    """Follow the stem of one tree through horizontal slices and select its surface points.

    Parameters
    ----------
    xyz : array_like (n, 3)
        The tree's points (all returns of all scans).
    base : array_like (3,)
        Stem base: centre x, y at the ground and the ground height z.
    dbh : float, optional
        Diameter at breast height (m); guides the first circle fit.
    slice_height : float
        Slice thickness (m).
    tolerance : float
        Largest distance of a stem point from the fitted circle (m).
    max_gap : float
        Longest run of unsupported slices (occlusion) bridged above/below (m).
    min_radius : float
        The tracker stops where the predicted radius falls below this (m).
    min_slice_points : int
        Fewest circle inliers of an accepted slice.
    min_coverage : float
        Narrowest arc (degrees, seen from the centre) the inliers of an accepted slice cover.
    crown_margin, crown_min_points : float, int
        Crown base: lowest 0.5 m window with ≥ ``crown_min_points`` points farther than
        ``crown_margin`` outside the stem surface.
    source : str
        Name of the input for error messages (e.g. the file).

    Returns
    -------
    StemAxis

    Raises
    ------
    InputDataError
        Empty, tiny or non-finite clouds, or no stem found near the base (names ``source``).
    ConfigError
        Bad settings (names the setting).
    """
    xyz = _check_xyz(xyz, source)
    base = _check_base(base)
    dbh = _check_positive("dbh", dbh, allow_none=True)
    slice_height = _check_positive("slice_height", slice_height)
    tolerance = _check_positive("tolerance", tolerance)
    max_gap = _check_positive("max_gap", max_gap)
    min_radius = _check_positive("min_radius", min_radius)
    crown_margin = _check_positive("crown_margin", crown_margin)
    if int(min_slice_points) < 3:
        raise ConfigError(f"min_slice_points: must be ≥ 3, got {min_slice_points}")
    if not 0 <= float(min_coverage) < 360:
        raise ConfigError(f"min_coverage: must be in [0, 360), got {min_coverage}")

    p = xyz - base
    z = p[:, 2]
    rng = np.random.default_rng(_SEED)
    r_hint = None if dbh is None else dbh / 2

    # --- first circle: the breast-height slab, else slabs just below/above it
    init = None
    reach = 1.0 if r_hint is None else 2 * r_hint + 0.3
    near = np.hypot(p[:, 0], p[:, 1]) < reach
    for z_start in _INIT_SLABS:
        slab = near & (z >= z_start) & (z < z_start + _INIT_THICKNESS)
        init = _ransac_init(p[slab, :2], np.zeros(2), r_hint, tolerance, rng)
        if init is not None:
            break
    if init is None:
        raise InputDataError(
            f"{source}: no stem found near the base {base.tolist()} (circle fits at "
            f"{min(_INIT_SLABS)}–{max(_INIT_SLABS) + _INIT_THICKNESS} m above it; "
            f"{int((near & (z > 0) & (z < 4)).sum())} points within {reach:.2f} m horizontally, 0–4 m up)"
        )
    c0, r0 = init
    z_init = z_start + _INIT_THICKNESS / 2

    # --- slices
    h = slice_height
    zmin = float(z.min())
    zmax = float(z.max())
    k_lo = int(math.floor(max(zmin, -2.0) / h))
    k_hi = int(math.floor(zmax / h))
    k0 = int(math.floor(z_init / h))
    order = np.argsort(z, kind="stable")
    zs = z[order]
    n_sl = k_hi - k_lo + 1
    bounds = np.searchsorted(zs, (np.arange(k_lo, k_hi + 2)) * h)
    centers = np.zeros((n_sl, 2))
    radii = np.zeros(n_sl)
    npts = np.zeros(n_sl, dtype=np.int64)
    acc = np.zeros(n_sl, dtype=bool)
    visited = np.zeros(n_sl, dtype=bool)
    mask_sorted = np.zeros(len(z), dtype=bool)
    max_miss = max(1, int(round(max_gap / h)))

    def run(direction: int):
        hist_z, hist_c, hist_r = [z_init], [c0], [r0]
        miss = 0
        k = k0 if direction > 0 else k0 - 1
        while k_lo <= k <= k_hi:
            zc = (k + 0.5) * h
            # prediction: straight line through the last 1.5 m of centres
            hz = np.array(hist_z[-max(2, int(1.5 / h)):])
            hc = np.array(hist_c[-len(hz):])
            if len(hz) >= 3 and np.ptp(hz) > 0.3:
                A = np.column_stack([np.ones(len(hz)), hz - hz.mean()])
                coef, *_ = np.linalg.lstsq(A, hc, rcond=None)
                c_pred = coef[0] + coef[1] * (zc - hz.mean())
            else:
                c_pred = hc[-1]
            r_pred = float(np.median(hist_r[-4:]))
            if direction > 0 and r_pred < min_radius:
                break
            i = k - k_lo
            lo, hi = bounds[i], bounds[i + 1]
            xy = p[order[lo:hi], :2]
            band = max(2 * tolerance, 0.25 * r_pred)
            ok = False
            if len(xy) >= min_slice_points:
                c, r, inl, cov = _fit_slice(xy, c_pred, r_pred, tolerance, band)
                grow = 1.1 if direction > 0 else 1.3
                ok = (
                    inl.sum() >= min_slice_points
                    and cov >= min_coverage
                    and np.hypot(*(c - c_pred)) <= max(0.03, 0.25 * r_pred)
                    and 0.7 * r_pred <= r <= grow * r_pred
                )
            if ok:
                centers[i], radii[i], npts[i], acc[i] = c, r, int(inl.sum()), True
                mask_sorted[lo:hi] = inl
                hist_z.append(zc)
                hist_c.append(c)
                hist_r.append(r)
                miss = 0
            else:
                centers[i], radii[i] = c_pred, r_pred
                miss += 1
                if miss > max_miss:
                    break
            visited[i] = True
            k += direction

    run(+1)
    run(-1)

    mask = np.zeros(len(z), dtype=bool)
    mask[order] = mask_sorted
    zc_all = (np.arange(k_lo, k_hi + 1) + 0.5) * h
    keep = visited
    axis_z = zc_all[keep]
    centers_k, radii_k, acc_k = centers[keep], radii[keep], acc[keep]
    crown_base = _crown_base(p, z, axis_z, centers_k, radii_k, acc_k, crown_margin, crown_min_points)
    return StemAxis(
        z=axis_z + base[2],
        center=centers_k + base[:2],
        radius=radii_k,
        n_points=npts[keep],
        accepted=acc_k,
        mask=mask,
        crown_base=crown_base + base[2] if math.isfinite(crown_base) else math.nan,
        slice_height=h,
        tolerance=tolerance,
    )


def _crown_base(p, z, axis_z, centers, radii, acc, margin, min_points, window=0.5) -> float:
    """Lowest window (relative height) with ≥ ``min_points`` points well outside the stem."""
    if not acc.any():
        return math.nan
    az, ac, ar = axis_z[acc], centers[acc], radii[acc]
    cx = np.interp(z, az, ac[:, 0])
    cy = np.interp(z, az, ac[:, 1])
    r = np.interp(z, az, ar)
    outside = np.hypot(p[:, 0] - cx, p[:, 1] - cy) > r + margin
    zo = np.sort(z[outside & (z > 0.5)])
    if len(zo) < min_points:
        return math.nan
    # windows starting at each outside point: the first holding min_points of them
    ends = np.searchsorted(zo, zo + window, side="left")
    hit = np.flatnonzero(ends - np.arange(len(zo)) >= min_points)
    if len(hit) == 0:
        return math.nan
    return float(zo[hit[0]])


def select_stem_points(xyz, base, dbh: float | None = None, **kwargs) -> np.ndarray:
    """Boolean mask of the stem surface points of one tree (see :func:`trace_stem`)."""
    return trace_stem(xyz, base, dbh, **kwargs).mask


# ============================================================================ meshing
def _thin(xyz: np.ndarray, voxel: float) -> np.ndarray:
    """Indices of one point per ``voxel`` cube (the first in input order), sorted."""
    key = np.floor((xyz - xyz.min(axis=0)) / voxel).astype(np.int64)
    _, first = np.unique(key, axis=0, return_index=True)
    return np.sort(first)


def _normals(xyz: np.ndarray, k: int) -> np.ndarray:
    """PCA normals: direction of least variance of the ``k`` nearest neighbours."""
    k = min(k, len(xyz))
    _, nb = cKDTree(xyz).query(xyz, k=k)
    nbp = xyz[nb]
    nbp = nbp - nbp.mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", nbp, nbp)
    _, vec = np.linalg.eigh(cov)
    return vec[:, :, 0]


def _poisson(points: np.ndarray, normals: np.ndarray, depth: int):
    """Screened Poisson via pymeshlab; returns (vertices, faces, density)."""
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=points, v_normals_matrix=normals))
    ms.generate_surface_reconstruction_screened_poisson(
        depth=int(depth), fulldepth=5, cgdepth=0, scale=1.1, samplespernode=1.5,
        pointweight=4.0, iters=8, confidence=False, preclean=False, threads=1,
    )
    m = ms.current_mesh()
    return (
        np.asarray(m.vertex_matrix(), dtype=np.float64),
        np.asarray(m.face_matrix(), dtype=np.int64),
        np.asarray(m.vertex_scalar_array(), dtype=np.float64),
    )


def _components(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """Connected component label of each face (faces sharing a vertex are connected)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    nf = len(faces)
    rows = np.repeat(np.arange(nf), 3)
    cols = faces.ravel()
    g = coo_matrix((np.ones(len(rows), dtype=np.int8), (rows, nf + cols)), shape=(nf + n_vertices,) * 2)
    _, lab = connected_components(g, directed=False)
    return lab[:nf]


def _compact(vertices: np.ndarray, faces: np.ndarray):
    used = np.zeros(len(vertices), dtype=bool)
    used[faces.ravel()] = True
    new = np.cumsum(used) - 1
    return vertices[used], new[faces] if len(faces) else faces.reshape(0, 3)


def stem_mesh(
    xyz,
    scan_ids,
    scanner_positions: dict,
    *,
    depth: int = 8,
    voxel: float = 0.01,
    k: int = 16,
    density_quantile: float = 0.02,
    max_extent: float = 0.09,
    min_component_faces: int = 50,
    source: str = "points",
) -> TriangleMesh:
    """Trimmed screened-Poisson mesh of stem points.

    Parameters
    ----------
    xyz : array_like (n, 3)
        Stem points.
    scan_ids : array_like (n,)
        Scan that measured each point (keys of ``scanner_positions``).
    scanner_positions : dict of int to array_like (3,)
        Scanner position of each scan; normals are turned towards it.
    depth : int
        Poisson octree depth (study: 8).
    voxel : float
        Thinning cube (m): one point per cube is meshed.
    k : int
        Neighbours of the PCA normals.
    density_quantile : float
        Vertices with a Poisson density below this quantile are trimmed (0 keeps all).
    max_extent : float
        Faces with any point farther than this from every stem point are trimmed (m): the mesh
        never extends more than ``max_extent`` beyond the stem points.
    min_component_faces : int
        Connected pieces with fewer faces are dropped.
    source : str
        Name of the input for error messages.

    Returns
    -------
    TriangleMesh

    Raises
    ------
    InputDataError
        Too few, non-finite points, or scan ids without a scanner position.
    ConfigError
        Bad settings.
    """
    xyz = _check_xyz(xyz, source, MIN_STEM_POINTS)
    scan_ids = np.asarray(scan_ids)
    if scan_ids.shape != (len(xyz),):
        raise InputDataError(f"{source}: {scan_ids.shape} scan ids for {len(xyz)} points")
    if not isinstance(depth, (int, np.integer)) or not 4 <= int(depth) <= 12:
        raise ConfigError(f"depth: must be an integer in 4..12, got {depth!r}")
    voxel = _check_positive("voxel", voxel)
    max_extent = _check_positive("max_extent", max_extent)
    if not 0 <= float(density_quantile) < 1:
        raise ConfigError(f"density_quantile: must be in [0, 1), got {density_quantile!r}")
    if int(k) < 3:
        raise ConfigError(f"k: must be ≥ 3, got {k!r}")
    ids = np.unique(scan_ids)
    missing = [int(i) for i in ids if int(i) not in scanner_positions]
    if missing:
        raise InputDataError(f"{source}: no scanner position for scan id(s) {missing[:10]}")
    spos = np.array([np.asarray(scanner_positions[int(i)], dtype=np.float64).reshape(3) for i in ids])
    if not np.isfinite(spos).all():
        raise InputDataError(f"{source}: scanner positions must be finite")

    origin = np.floor(xyz.min(axis=0))
    local = xyz - origin
    sel = _thin(local, voxel)
    pts = local[sel]
    if len(pts) < MIN_STEM_POINTS:
        raise InputDataError(f"{source}: only {len(pts)} stem points after thinning to {voxel} m (need ≥ {MIN_STEM_POINTS})")
    nrm = _normals(pts, int(k))
    view = spos[np.searchsorted(ids, scan_ids[sel])] - origin - pts
    flip = np.einsum("ij,ij->i", nrm, view) < 0
    nrm[flip] *= -1

    verts, faces, dens = _poisson(pts, nrm, int(depth))
    if len(faces) == 0:
        raise InputDataError(f"{source}: the Poisson reconstruction gave an empty surface")
    drop = np.zeros(len(verts), dtype=bool)
    if density_quantile > 0:
        drop |= dens < np.quantile(dens, density_quantile)
    tree = cKDTree(local)
    drop |= tree.query(verts, k=1)[0] > max_extent
    faces = faces[~drop[faces].any(axis=1)]
    # probe each face on a barycentric grid: every point of a kept face is then within
    # max_extent of a stem point (a point is at most one sub-triangle edge from a probe)
    corners = verts[faces]
    probes = np.einsum("pk,fkd->fpd", _BARY, corners)
    edge = np.linalg.norm(corners - np.roll(corners, -1, axis=1), axis=2).max(axis=1)
    far = tree.query(probes.reshape(-1, 3), k=1)[0].reshape(len(faces), len(_BARY)).max(axis=1)
    faces = faces[far + edge / _BARY_N <= max_extent]
    if len(faces):
        lab = _components(faces, len(verts))
        sizes = np.bincount(lab)
        faces = faces[sizes[lab] >= int(min_component_faces)]
    if len(faces) == 0:
        raise InputDataError(f"{source}: nothing of the Poisson surface is left after trimming")
    v, f = _compact(verts, faces)
    return TriangleMesh(v + origin, f)


# ============================================================================ one tree
def build_stem(
    tree_cloud: PointCloud,
    scanner_positions: dict,
    base,
    dbh: float | None = None,
    depth: int = 8,
    *,
    source: str = "tree cloud",
    trace_options: dict | None = None,
    mesh_options: dict | None = None,
) -> StemResult:
    """Select the stem points of one tree and mesh them.

    Parameters
    ----------
    tree_cloud : PointCloud
        All TLS points of the tree; ``point_source_id`` holds the scan id.
    scanner_positions : dict of int to array_like (3,)
        Scanner position per scan id.
    base : array_like (3,)
        Stem base (x, y, ground z).
    dbh : float, optional
        Diameter at breast height (m).
    depth : int
        Poisson octree depth.
    source : str
        Name of the input for error messages (the file).
    trace_options, mesh_options : dict, optional
        Further keyword arguments of :func:`trace_stem` and :func:`stem_mesh`.

    Returns
    -------
    StemResult
        ``summary`` holds: ``n_tree_points``, ``n_stem_points``, ``stem_fraction``, ``base``,
        ``dbh_given``, ``dbh_fitted`` (2 × circle radius at 1.3 m, ``None`` if not tracked
        there), ``stem_z_range`` / ``stem_height_range`` (stem points, absolute / above the
        base), ``mesh_z_range`` / ``mesh_height_range`` (the height range meshed),
        ``crown_base_z`` / ``crown_base_height`` (``None`` when no crown was found),
        ``n_slices_accepted``, ``mean_radius`` (accepted slices) and ``mean_radius_below_crown``,
        ``depth``, ``mesh_vertices``, ``mesh_faces``, ``mesh_area_m2``, ``time_select_s``,
        ``time_mesh_s``.

    Raises
    ------
    InputDataError
        No ``point_source_id``, too few/non-finite points, no stem near the base, scan ids
        without a scanner position (names ``source``).
    ConfigError
        Bad base, DBH or settings.
    """
    if "point_source_id" not in tree_cloud.attrs:
        raise InputDataError(f"{source}: no point_source_id (scan id) field")
    t0 = time.perf_counter()
    axis = trace_stem(tree_cloud.xyz, base, dbh, source=source, **(trace_options or {}))
    t1 = time.perf_counter()
    n_stem = int(axis.mask.sum())
    if n_stem < MIN_STEM_POINTS:
        raise InputDataError(f"{source}: only {n_stem} stem points found (need ≥ {MIN_STEM_POINTS})")
    stem_xyz = tree_cloud.xyz[axis.mask]
    mesh = stem_mesh(
        stem_xyz,
        tree_cloud.attrs["point_source_id"][axis.mask],
        scanner_positions,
        depth=depth,
        source=source,
        **(mesh_options or {}),
    )
    t2 = time.perf_counter()
    zlo, zhi = float(stem_xyz[:, 2].min()), float(stem_xyz[:, 2].max())
    b = _check_base(base)
    acc = axis.accepted
    below = acc & (axis.z < axis.crown_base) if math.isfinite(axis.crown_base) else acc
    summary = {
        "n_tree_points": int(len(tree_cloud)),
        "n_stem_points": n_stem,
        "stem_fraction": n_stem / len(tree_cloud),
        "base": [float(x) for x in b],
        "dbh_given": dbh,
        "dbh_fitted": _dbh_fit(axis, b[2]),
        "stem_z_range": [zlo, zhi],
        "stem_height_range": [zlo - b[2], zhi - b[2]],
        "mesh_z_range": [float(mesh.vertices[:, 2].min()), float(mesh.vertices[:, 2].max())],
        "mesh_height_range": [float(mesh.vertices[:, 2].min() - b[2]), float(mesh.vertices[:, 2].max() - b[2])],
        "crown_base_z": axis.crown_base,
        "crown_base_height": axis.crown_base - b[2] if math.isfinite(axis.crown_base) else None,
        "n_slices_accepted": int(acc.sum()),
        "mean_radius": float(axis.radius[acc].mean()) if acc.any() else None,
        "mean_radius_below_crown": float(axis.radius[below].mean()) if below.any() else None,
        "depth": int(depth),
        "mesh_vertices": mesh.n_vertices,
        "mesh_faces": mesh.n_faces,
        "mesh_area_m2": mesh.area(),
        "time_select_s": t1 - t0,
        "time_mesh_s": t2 - t1,
    }
    if summary["crown_base_z"] is not None and not math.isfinite(summary["crown_base_z"]):
        summary["crown_base_z"] = None
    return StemResult(mesh=mesh, mask=axis.mask, axis=axis, summary=summary)


def _dbh_fit(axis: StemAxis, ground: float):
    """Twice the fitted radius at breast height (interpolated); ``None`` when not covered."""
    acc = axis.accepted
    if acc.sum() < 2:
        return None
    hz = axis.z[acc] - ground
    if not hz.min() <= BREAST_HEIGHT <= hz.max():
        return None
    return float(2 * np.interp(BREAST_HEIGHT, hz, axis.radius[acc]))


def read_scanner_positions(path) -> dict:
    """Scanner positions from a ``scans.csv`` (columns ``scan_id, x, y, z``): dict id → (3,)."""
    from vlsforest.io.csvfile import read_csv_table

    path = Path(path)
    df = read_csv_table(path, "scan table", ids=("scan_id",), numbers=("x", "y", "z"))
    if df.empty:
        raise InputDataError(f"{path}: no scans listed")
    ids = df["scan_id"].to_numpy()
    pos = df[["x", "y", "z"]].to_numpy()
    if len(np.unique(ids)) != len(ids):
        raise InputDataError(f"{path}: duplicate scan_id values")
    return {int(i): pos[n] for n, i in enumerate(ids)}


__all__ = [
    "StemAxis",
    "StemResult",
    "trace_stem",
    "select_stem_points",
    "stem_mesh",
    "build_stem",
    "read_scanner_positions",
]
