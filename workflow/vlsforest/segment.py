"""Tree segmentation of co-registered TLS scans: ground, stem seeds, competitive shortest paths.

The pipeline (:func:`segment_cloud`) has four steps.

1. **Filtering.** When the points carry a RIEGL-style pulse-shape deviation (attribute
   ``Deviation`` or ``deviation``), points above ``max_deviation`` are noise (classification 7,
   tree id 0) and take no further part. Without such a field nothing is filtered (the summary
   says so).
2. **Ground** (:func:`classify_ground`). A progressive morphological filter (Zhang et al. 2003)
   on a grid of per-cell lowest points keeps the cells whose minimum is close to the opened
   surface at growing window sizes; a terrain model (:class:`Dtm`) is interpolated from those
   cells and refined twice with a low per-cell quantile of the points near it. Points less than
   ``ground_tol`` above the model are ground (classification 2, tree id 0); points more than
   ``below_ground_tol`` below it are noise (classification 7, tree id 0). A cloud whose lowest
   points do not form a continuous surface anywhere ("no ground") is an error.
3. **Stem seeds** (:func:`find_stems`). Non-ground points in a height slice above the terrain
   (default 1–2 m) are thinned to a 2 cm grid and clustered by connected components of their
   radius graph. A cluster becomes a stem when a robust circle fit (RANSAC, then geometric
   least squares) has a plausible radius, small residuals, enough arc coverage and points in
   both halves of the slice with consistent centres. Seeds closer than their radii merge. The
   diameter at breast height (1.3 m) comes from a circle fit to the stem's points between 1.2
   and 1.4 m above the terrain.
4. **Competitive growth.** The non-ground points are thinned to a ``voxel`` grid (centroids);
   a graph links every voxel to its ``graph_k`` nearest neighbours closer than
   ``graph_radius`` with weight ``distance ** edge_power``. One multi-source Dijkstra
   (:func:`scipy.sparse.csgraph.dijkstra`, ``min_only=True``) from the voxels of all stem
   slices at once gives every reachable voxel the tree of the nearest seed along the graph.
   **Unreached voxels** form connected pieces of the graph (crown parts sampled too sparsely
   to link to a stem); a piece takes, as a whole, the tree of the labelled voxel nearest to any
   of its voxels when that lies within ``attach_dist`` (repeated, so pieces chain onto pieces
   attached before), otherwise tree id 0 (no tree). Every point then takes its voxel's tree.

Tree ids are 1..N in the order of stem x, then y (rounded to 1 mm), so that the same input gives
the same ids. Tree height is the highest point of the tree minus the terrain height at the stem.

Outputs of :func:`segment_files` (the ``vlsforest segment`` command):

* ``segmented.laz``: every input point with its attributes, classification (2 ground, 7 noise,
  1 otherwise) and the extra dimension ``tree_id`` (uint32; 0 = ground / no tree);
* ``trees.csv``: ``tree_id, x, y, z, dbh, height, n_points`` (stem centre at breast height, z of
  the terrain there, DBH in metres, height in metres);
* ``trees/{id}.laz``: the points of one tree with all original attributes;
* ``dtm.npz``: the terrain model, see :meth:`Dtm.save`.
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, dijkstra
from scipy.spatial import cKDTree

from vlsforest.errors import ConfigError, InputDataError
from vlsforest.io.atomic import atomic_path, make_folder, write_csv
from vlsforest.io.npz import ArraySpec, load_npz

#: the arrays of a terrain model file (:meth:`Dtm.save`)
DTM_SPEC = {"z": ArraySpec("f", ("ny", "nx"), finite=False), "measured": ArraySpec("b", ("ny", "nx")),
            "x0": ArraySpec("f", ()), "y0": ArraySpec("f", ()), "cell": ArraySpec("f", ())}

#: columns of the tree table
TREE_COLUMNS = ("tree_id", "x", "y", "z", "dbh", "height", "n_points")
#: LAS classification codes written to ``segmented.laz``
CLASS_UNCLASSIFIED, CLASS_GROUND, CLASS_NOISE = 1, 2, 7
#: attribute names recognised as a RIEGL pulse-shape deviation
DEVIATION_FIELDS = ("Deviation", "deviation")
#: fewest points a cloud must have to be segmented
MIN_POINTS = 100
#: factor on z when clustering the seed slice (vertical gaps count this much)
_SLICE_Z_SCALE = 0.25
#: quantile of the points near the terrain model that refines it (low: stem bases and low
#: vegetation lift the median)
_GROUND_QUANTILE = 0.25
#: breast height above the terrain [m]
BREAST_HEIGHT = 1.3


@dataclass(frozen=True)
class SegmentConfig:
    """Settings of the segmentation (lengths in metres).

    Parameters
    ----------
    ground_cell : float
        Cell size of the terrain model.
    ground_max_window : float
        Largest window of the morphological filter; should exceed the widest area without
        ground returns (occlusion shadows).
    ground_slope : float
        Terrain slope (rise over run) the morphological filter tolerates.
    ground_tol : float
        Points at most this far above the terrain model are ground.
    below_ground_tol : float
        Points more than this far below the terrain model are noise.
    min_ground_fraction : float
        Fraction of the occupied terrain cells that must hold a continuous ground surface;
        fewer is the error "no ground".
    slice_min, slice_max : float
        Height range above the terrain of the stem-seed slice.
    low_slice_min, low_slice_max : float
        A second, lower slice searched for stems the first one missed (trees whose crown or
        branches reach into the first slice); ``low_slice_max <= low_slice_min`` switches it off.
    seed_cluster_dist : float
        Linking distance of the slice points (after thinning to 2 cm) when clustering.
    seed_min_points : int
        Fewest thinned slice points a stem cluster must have.
    min_dbh, max_dbh : float
        Plausible stem diameters.
    voxel : float
        Voxel size of the graph.
    graph_radius : float
        Longest graph edge.
    graph_k : int
        Neighbours per voxel in the graph.
    edge_power : float
        Graph edge weight is ``length ** edge_power`` (> 1 prefers paths through dense material).
    attach_dist : float
        Unreached voxels join the nearest reached voxel's tree within this distance, else 0.
    max_deviation : float
        Largest accepted pulse-shape deviation (only when the points carry one).
    stem_bridge : float
        Longest vertical gap in a stem that the growth bridges; 0 switches bridging off. Stems
        hidden behind understorey or low crowns leave their tree's crown without a path to its
        seed; without a bridge the crown goes to a neighbour whose crown touches it. Above each
        stem's seed, the voxels within ``dbh / 2 + bridge_radius`` of the vertical through the
        stem centre are chained in height order, and a gap longer than ``graph_radius`` but at
        most ``stem_bridge`` becomes a graph edge as long as the straight line between the two
        voxels (the hidden stem). It never shortens a path that already exists.
    bridge_radius : float
        Half-width beyond the stem radius of the vertical column searched for bridges.
    seed : int
        Random seed of the RANSAC circle fits.
    no_ground : bool
        The cloud holds no ground points (removed beforehand): the terrain is taken as a
        plane through the local minima of the cloud (stem bases), no point is classified ground or noise, and the
        "no ground" check is skipped.
    """

    ground_cell: float = 0.5
    ground_max_window: float = 16.0
    ground_slope: float = 0.3
    ground_tol: float = 0.1
    below_ground_tol: float = 0.5
    min_ground_fraction: float = 0.1
    slice_min: float = 1.0
    slice_max: float = 2.0
    low_slice_min: float = 0.4
    low_slice_max: float = 1.0
    seed_cluster_dist: float = 0.1
    seed_min_points: int = 12
    min_dbh: float = 0.05
    max_dbh: float = 1.5
    voxel: float = 0.1
    graph_radius: float = 0.5
    graph_k: int = 16
    edge_power: float = 1.0
    attach_dist: float = 1.0
    max_deviation: float = 50.0
    stem_bridge: float = 20.0
    bridge_radius: float = 0.3
    seed: int = 0
    no_ground: bool = False

    def __post_init__(self):
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name == "no_ground":
                if not isinstance(v, (bool, np.bool_)):
                    raise ConfigError(f"segment.no_ground: must be true or false, got {v!r}")
                continue
            if f.name == "seed":
                if not isinstance(v, (int, np.integer)) or isinstance(v, bool):
                    raise ConfigError(f"segment.seed: must be an integer, got {v!r}")
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
                raise ConfigError(f"segment.{f.name}: must be a number, got {v!r}")
            if not math.isfinite(v):
                raise ConfigError(f"segment.{f.name}: must be finite, got {v!r}")
            if f.name == "min_ground_fraction":
                if not 0 <= v <= 1:
                    raise ConfigError(f"segment.{f.name}: must lie in [0, 1], got {v!r}")
            elif f.name == "stem_bridge":
                if v < 0:
                    raise ConfigError(f"segment.{f.name}: must be >= 0 (0 switches it off), got {v!r}")
            elif v <= 0:
                raise ConfigError(f"segment.{f.name}: must be > 0, got {v!r}")
        if self.slice_max <= self.slice_min:
            raise ConfigError(
                f"segment.slice_max: must exceed slice_min ({self.slice_min}), got {self.slice_max}"
            )
        if self.low_slice_max > self.low_slice_min and self.low_slice_min <= self.ground_tol:
            raise ConfigError(
                f"segment.low_slice_min: must exceed ground_tol ({self.ground_tol}), got {self.low_slice_min}"
            )
        if self.slice_min <= self.ground_tol:
            raise ConfigError(f"segment.slice_min: must exceed ground_tol ({self.ground_tol}), got {self.slice_min}")
        if self.max_dbh <= self.min_dbh:
            raise ConfigError(f"segment.max_dbh: must exceed min_dbh ({self.min_dbh}), got {self.max_dbh}")
        for key in ("graph_k", "seed_min_points"):
            if int(getattr(self, key)) != getattr(self, key):
                raise ConfigError(f"segment.{key}: must be an integer, got {getattr(self, key)!r}")

    @classmethod
    def from_dict(cls, d: dict | None) -> "SegmentConfig":
        """Build from a mapping; unknown keys are a :class:`ConfigError`."""
        d = dict(d or {})
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ConfigError(f"segment.{unknown[0]}: unknown key (known: {', '.join(sorted(names))})")
        return cls(**d)


# --------------------------------------------------------------------------------------------
# terrain model


@dataclass
class Dtm:
    """A gridded terrain model.

    ``z[j, i]`` is the ground elevation at ``x = x0 + (i + 0.5) * cell``,
    ``y = y0 + (j + 0.5) * cell``; ``measured[j, i]`` tells whether ground points lay in that
    cell (the others are interpolated or extrapolated).
    """

    x0: float
    y0: float
    cell: float
    z: np.ndarray
    measured: np.ndarray = None

    def __post_init__(self):
        self.z = np.asarray(self.z, dtype=np.float64)
        if self.measured is None:
            self.measured = np.ones(self.z.shape, bool)
        self.measured = np.asarray(self.measured, bool)

    def height_at(self, x, y) -> np.ndarray:
        """Terrain elevation at points ``x, y`` (bilinear between cell centres, clamped at edges)."""
        x = np.asarray(x, float)
        y = np.asarray(y, float)
        ny, nx = self.z.shape
        fx = np.clip((x - self.x0) / self.cell - 0.5, 0, nx - 1)
        fy = np.clip((y - self.y0) / self.cell - 0.5, 0, ny - 1)
        i0 = np.minimum(np.floor(fx).astype(np.int64), max(nx - 2, 0))
        j0 = np.minimum(np.floor(fy).astype(np.int64), max(ny - 2, 0))
        i1 = np.minimum(i0 + 1, nx - 1)
        j1 = np.minimum(j0 + 1, ny - 1)
        tx = fx - i0
        ty = fy - j0
        z = self.z
        return (
            z[j0, i0] * (1 - tx) * (1 - ty)
            + z[j0, i1] * tx * (1 - ty)
            + z[j1, i0] * (1 - tx) * ty
            + z[j1, i1] * tx * ty
        )

    def save(self, path) -> Path:
        """Write ``path`` (``.npz``) with arrays ``z`` (ny, nx), ``measured`` (ny, nx) and scalars
        ``x0``, ``y0``, ``cell``; ``z[j, i]`` is the elevation at the centre
        ``(x0 + (i + 0.5) cell, y0 + (j + 0.5) cell)``."""
        path = Path(path)
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            np.savez_compressed(
                fh, z=self.z, measured=self.measured, x0=np.float64(self.x0), y0=np.float64(self.y0),
                cell=np.float64(self.cell),
            )
        return path

    @classmethod
    def load(cls, path) -> "Dtm":
        """Read a file written by :meth:`save`."""
        d = load_npz(path, DTM_SPEC, "terrain model")
        if not float(d["cell"]) > 0:
            raise InputDataError(f"{path}: array 'cell' must be > 0, got {float(d['cell'])!r}")
        return cls(float(d["x0"]), float(d["y0"]), float(d["cell"]), d["z"], d["measured"])


def _grid_index(xy: np.ndarray, x0: float, y0: float, cell: float, nx: int) -> np.ndarray:
    i = np.floor((xy[:, 0] - x0) / cell).astype(np.int64)
    j = np.floor((xy[:, 1] - y0) / cell).astype(np.int64)
    return j * nx + i


def _cell_min(flat: np.ndarray, z: np.ndarray, n: int) -> np.ndarray:
    out = np.full(n, np.inf)
    np.minimum.at(out, flat, z) if len(flat) < 2_000_000 else _reduce_sorted(out, flat, z, np.minimum)
    return out


def _reduce_sorted(out, flat, z, ufunc):
    order = np.argsort(flat, kind="stable")
    f = flat[order]
    starts = np.flatnonzero(np.r_[True, f[1:] != f[:-1]])
    out[f[starts]] = ufunc.reduceat(z[order], starts)
    return out


def _cell_quantile(flat: np.ndarray, z: np.ndarray, n: int, q: float) -> np.ndarray:
    """Per-cell ``q`` quantile (lower order statistic) of ``z``; NaN in empty cells."""
    out = np.full(n, np.nan)
    if len(flat) == 0:
        return out
    order = np.lexsort((z, flat))
    f = flat[order]
    zs = z[order]
    starts = np.flatnonzero(np.r_[True, f[1:] != f[:-1]])
    ends = np.r_[starts[1:], len(f)]
    k = starts + np.floor(q * (ends - starts - 1)).astype(np.int64)
    out[f[starts]] = zs[k]
    return out


def _fill(z: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Fill cells outside ``valid`` from the outside in: each pass gives the unknown cells
    that touch known ones the mean of their known 3 × 3 neighbours (onion-peel inpainting)."""
    out = np.where(valid, z, 0.0).astype(np.float64)
    known = valid.copy()
    if known.all() or not known.any():
        return out
    kernel = np.ones((3, 3))
    while not known.all():
        s = ndimage.convolve(np.where(known, out, 0.0), kernel, mode="constant")
        c = ndimage.convolve(known.astype(np.float64), kernel, mode="constant")
        new = ~known & (c > 0)
        out[new] = s[new] / c[new]
        known |= new
    return out


def classify_ground(xyz: np.ndarray, config: SegmentConfig | None = None, source: str = "cloud"):
    """Find the ground points and the terrain model.

    Parameters
    ----------
    xyz : ndarray, shape (n, 3)
        Points.
    config : SegmentConfig, optional
        Settings (``ground_*``, ``below_ground_tol``, ``min_ground_fraction``).
    source : str
        Name used in error messages.

    Returns
    -------
    is_ground : ndarray of bool, shape (n,)
    is_noise : ndarray of bool, shape (n,)
        Points far below the terrain.
    dtm : Dtm

    Raises
    ------
    InputDataError
        When the lowest points form no continuous ground surface.
    """
    cfg = config or SegmentConfig()
    xyz = np.asarray(xyz, float)
    c = cfg.ground_cell
    x0 = math.floor(xyz[:, 0].min() / c) * c
    y0 = math.floor(xyz[:, 1].min() / c) * c
    nx = int(math.floor((xyz[:, 0].max() - x0) / c)) + 1
    ny = int(math.floor((xyz[:, 1].max() - y0) / c)) + 1
    flat = _grid_index(xyz, x0, y0, c, nx)
    z = xyz[:, 2]
    zmin = _cell_min(flat, z, nx * ny).reshape(ny, nx)
    occupied = np.isfinite(zmin)
    surface = _fill(np.where(occupied, zmin, 0.0), occupied)
    # progressive morphological filter
    nonground = ~occupied
    dh0 = max(2 * cfg.ground_tol, 0.2)
    w = 1
    wmax = max(3, int(round(cfg.ground_max_window / c)) | 1)
    while True:
        w = min(2 * w + 1, wmax)
        fp = _disk(w)
        opened = ndimage.grey_opening(surface, footprint=fp, mode="nearest")
        dh = min(dh0 + cfg.ground_slope * w * c, 3.0)
        nonground |= (zmin - opened) > dh
        surface = opened
        if w >= wmax:
            break
    if cfg.no_ground:
        # the cloud holds no ground (removed beforehand): the terrain is a plane through the
        # cells whose minimum is the lowest within 2.5 m (stem bases), refitted twice to the
        # lower half of them by residual; nothing is ground
        filled = _fill(np.where(occupied, zmin, 0.0), occupied)
        w = max(3, int(round(5.0 / c)) | 1)
        local = occupied & (zmin <= ndimage.grey_erosion(filled, footprint=_disk(w), mode="nearest"))
        jj, ii = np.nonzero(local)
        A = np.column_stack([x0 + (ii + 0.5) * c, y0 + (jj + 0.5) * c, np.ones(len(ii))])
        cz = zmin[local]
        use = np.ones(len(cz), bool)
        for _ in range(3):
            coef, *_ = np.linalg.lstsq(A[use], cz[use], rcond=None)
            res = cz - A @ coef
            use = res <= np.median(res)
            if use.sum() < 3:
                break
        gy, gx = np.mgrid[:ny, :nx]
        plane = coef[0] * (x0 + (gx + 0.5) * c) + coef[1] * (y0 + (gy + 0.5) * c) + coef[2]
        dtm = Dtm(x0, y0, c, plane, np.zeros(plane.shape, bool))
        return np.zeros(len(z), bool), np.zeros(len(z), bool), dtm
    good = occupied & ~nonground
    if good.sum() < 1:
        raise InputDataError(f"{source}: no ground found (no terrain cell passes the morphological filter)")
    dtm_z = _fill(np.where(good, zmin, 0.0), good)
    # refine with a low quantile of the points near the model
    for tol in (max(3 * cfg.ground_tol, 0.3), cfg.ground_tol):
        dtm = Dtm(x0, y0, c, dtm_z, good)
        dz = z - dtm.height_at(xyz[:, 0], xyz[:, 1])
        near = np.abs(dz) <= tol
        med = _cell_quantile(flat[near], z[near], nx * ny, _GROUND_QUANTILE).reshape(ny, nx)
        good = np.isfinite(med)
        if good.sum() < 1:
            raise InputDataError(f"{source}: no ground found")
        dtm_z = _fill(np.where(good, med, 0.0), good)
    dtm = Dtm(x0, y0, c, dtm_z, good)
    dz = z - dtm.height_at(xyz[:, 0], xyz[:, 1])
    is_noise = dz < -cfg.below_ground_tol
    is_ground = (dz <= cfg.ground_tol) & ~is_noise
    # continuity check: ground points must cover most sub-cells of a terrain cell
    sub = 4
    sflat = _grid_index(xyz[is_ground], x0, y0, c / sub, nx * sub)
    scount = np.zeros(nx * ny, np.int64)
    u = np.unique(sflat)
    si = u % (nx * sub)
    sj = u // (nx * sub)
    np.add.at(scount, (sj // sub) * nx + si // sub, 1)
    continuous = (scount >= sub * sub // 2).reshape(ny, nx)
    dtm.measured = continuous
    need = max(4, cfg.min_ground_fraction * occupied.sum())
    if continuous.sum() < need:
        raise InputDataError(
            f"{source}: no ground found ({int(continuous.sum())} of {int(occupied.sum())} occupied "
            f"{c:g} m cells hold a continuous ground surface, need {int(math.ceil(need))}; "
            "for a cloud whose ground was removed, set no_ground (CLI: --no-ground))"
        )
    return is_ground, is_noise, dtm


def _disk(w: int) -> np.ndarray:
    r = (w - 1) / 2
    yy, xx = np.mgrid[:w, :w] - r
    return (xx**2 + yy**2) <= r * r + 0.5


# --------------------------------------------------------------------------------------------
# circle fits and stem seeds


def fit_circle(xy: np.ndarray, iterations: int = 20):
    """Geometric least-squares circle fit.

    Parameters
    ----------
    xy : ndarray, shape (n, 2)
        Points (n ≥ 3).
    iterations : int
        Gauss-Newton steps after the algebraic (Kåsa) start.

    Returns
    -------
    cx, cy, r, rms : float
        Centre, radius and root-mean-square radial residual (NaN when degenerate).
    """
    xy = np.asarray(xy, float)
    if len(xy) < 3:
        return (math.nan,) * 4
    m = xy.mean(axis=0)
    p = xy - m
    A = np.column_stack([p, np.ones(len(p))])
    b = (p**2).sum(axis=1)
    try:
        sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    except np.linalg.LinAlgError:
        return (math.nan,) * 4
    cx, cy = sol[0] / 2, sol[1] / 2
    r2 = sol[2] + cx * cx + cy * cy
    if not np.isfinite(r2) or r2 <= 0:
        return (math.nan,) * 4
    r = math.sqrt(r2)
    for _ in range(iterations):
        dx = p[:, 0] - cx
        dy = p[:, 1] - cy
        d = np.hypot(dx, dy)
        d = np.where(d > 1e-12, d, 1e-12)
        res = d - r
        J = np.column_stack([-dx / d, -dy / d, -np.ones(len(d))])
        try:
            step, *_ = np.linalg.lstsq(J, -res, rcond=None)
        except np.linalg.LinAlgError:
            break
        cx, cy, r = cx + step[0], cy + step[1], r + step[2]
        if np.abs(step).max() < 1e-7:
            break
    d = np.hypot(p[:, 0] - cx, p[:, 1] - cy)
    rms = float(np.sqrt(np.mean((d - r) ** 2)))
    if not np.isfinite(r) or r <= 0:
        return (math.nan,) * 4
    return float(cx + m[0]), float(cy + m[1]), float(abs(r)), rms


def _ransac_circle(xy: np.ndarray, tol: float, rng: np.random.Generator, n_iter: int = 200,
                   r_max: float = 1.0):
    """Circle with most points within ``tol``, refined on its inliers; None when none."""
    n = len(xy)
    if n < 3:
        return None
    idx = rng.integers(0, n, size=(n_iter, 3))
    a, b, c = xy[idx[:, 0]], xy[idx[:, 1]], xy[idx[:, 2]]
    d = 2 * (a[:, 0] * (b[:, 1] - c[:, 1]) + b[:, 0] * (c[:, 1] - a[:, 1]) + c[:, 0] * (a[:, 1] - b[:, 1]))
    ok = np.abs(d) > 1e-12
    if not ok.any():
        return None
    a, b, c, d = a[ok], b[ok], c[ok], d[ok]
    a2, b2, c2 = (a**2).sum(1), (b**2).sum(1), (c**2).sum(1)
    ux = (a2 * (b[:, 1] - c[:, 1]) + b2 * (c[:, 1] - a[:, 1]) + c2 * (a[:, 1] - b[:, 1])) / d
    uy = (a2 * (c[:, 0] - b[:, 0]) + b2 * (a[:, 0] - c[:, 0]) + c2 * (b[:, 0] - a[:, 0])) / d
    r = np.hypot(a[:, 0] - ux, a[:, 1] - uy)
    keep = r < r_max
    if not keep.any():
        return None
    ux, uy, r = ux[keep], uy[keep], r[keep]
    res = np.abs(np.hypot(xy[None, :, 0] - ux[:, None], xy[None, :, 1] - uy[:, None]) - r[:, None])
    score = (res < tol).sum(axis=1)
    best = int(np.argmax(score))
    inl = res[best] < tol
    if inl.sum() < 3:
        return None
    cx, cy, rr, _ = fit_circle(xy[inl])
    if not np.isfinite(rr):
        return None
    res2 = np.abs(np.hypot(xy[:, 0] - cx, xy[:, 1] - cy) - rr)
    inl = res2 < tol
    if inl.sum() >= 3:
        cx, cy, rr, _ = fit_circle(xy[inl])
        if not np.isfinite(rr):
            return None
        inl = np.abs(np.hypot(xy[:, 0] - cx, xy[:, 1] - cy) - rr) < tol
    return cx, cy, rr, inl


def _arc_coverage(xy: np.ndarray, cx: float, cy: float) -> float:
    """Fraction of 10° sectors around the centre that hold points."""
    if len(xy) == 0:
        return 0.0
    ang = np.arctan2(xy[:, 1] - cy, xy[:, 0] - cx)
    bins = np.floor((ang + np.pi) / (2 * np.pi) * 36).astype(int) % 36
    return len(np.unique(bins)) / 36.0


def _stem_circle(xy: np.ndarray, cfg: SegmentConfig, rng: np.random.Generator, max_pts: int = 1500):
    """Robust circle of stem points; (cx, cy, r, inlier mask) or None."""
    if len(xy) > max_pts:
        sel = np.sort(rng.choice(len(xy), max_pts, replace=False))
    else:
        sel = np.arange(len(xy))
    sub = xy[sel]
    ext = float(np.max(np.ptp(sub, axis=0))) if len(sub) else 0.0
    tol = float(np.clip(0.05 * ext, 0.008, 0.03))
    fit = _ransac_circle(sub, tol, rng, r_max=cfg.max_dbh / 2 * 1.2)
    if fit is None:
        return None
    cx, cy, r, _ = fit
    inl = np.abs(np.hypot(xy[:, 0] - cx, xy[:, 1] - cy) - r) < tol
    return cx, cy, r, inl


def _voxel_keys(xyz: np.ndarray, size: float, origin: np.ndarray):
    """Integer voxel indices, unique voxel keys and the inverse map."""
    ijk = np.floor((xyz - origin) / size).astype(np.int64)
    ijk -= ijk.min(axis=0) if len(ijk) else 0
    dims = ijk.max(axis=0) + 1 if len(ijk) else np.ones(3, np.int64)
    key = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
    uniq, inv = np.unique(key, return_inverse=True)
    return uniq, inv.reshape(-1)


def _centroids(xyz: np.ndarray, inv: np.ndarray, n: int) -> np.ndarray:
    cnt = np.bincount(inv, minlength=n).astype(float)
    return np.column_stack([np.bincount(inv, weights=xyz[:, k], minlength=n) / cnt for k in range(3)])


def _cluster_stems(pts, ph, cfg: SegmentConfig, rng, lo: float, hi: float, max_stems: int = 3):
    """Circles of vertical stems in one slice cluster (sequential RANSAC).

    Yields ``(cx, cy, r, near)`` with ``near`` the mask of the cluster points that belong to
    the stem (within ``max(0.05, 0.25 r)`` of its circle).
    """
    mid = 0.5 * (lo + hi)
    thick = hi - lo
    left = np.ones(len(pts), bool)
    for _ in range(max_stems):
        idx = np.flatnonzero(left)
        if len(idx) < cfg.seed_min_points:
            return
        sub, sh = pts[idx], ph[idx]
        fit = _stem_circle(sub[:, :2], cfg, rng)
        if fit is None:
            return
        cx, cy, r, inl = fit
        n_in = int(inl.sum())
        if not (cfg.min_dbh / 2 <= r <= cfg.max_dbh / 2):
            return
        cov = _arc_coverage(sub[inl, :2], cx, cy)
        if n_in < cfg.seed_min_points or cov < 0.1:
            return
        # the same circle must explain both halves of the slice (a vertical stem, not a clump)
        ok = np.ptp(sh[inl]) >= 0.6 * thick
        lower = ph < mid
        centre = np.tile([cx, cy], (len(pts), 1))  # per point: its half's circle centre
        for half, phalf in ((sh < mid, lower), (sh >= mid, ~lower)):
            if not ok:
                break
            hin = half & inl
            if hin.sum() < max(3, 0.2 * n_in):
                ok = False
            elif hin.sum() >= 20:
                hx, hy, hr, _ = fit_circle(sub[hin, :2])
                ok = bool(np.isfinite(hr) and math.hypot(hx - cx, hy - cy) <= 0.5 * r + 0.05)
                if ok:
                    centre[phalf] = (hx, hy)
        if not ok:
            return
        # a stem section is hollow: few points inside the circle (measured from each half's own
        # centre, so that a leaning stem scanned all round is not taken for a solid clump)
        tol = max(0.02, 0.15 * r)
        inside = int((np.hypot(pts[:, 0] - centre[:, 0], pts[:, 1] - centre[:, 1]) < r - tol).sum())
        if inside > max(4, 0.15 * n_in):
            return
        dist = np.abs(np.hypot(pts[:, 0] - cx, pts[:, 1] - cy) - r)
        near = dist < max(0.05, 0.25 * r)
        yield cx, cy, r, near
        left &= ~near


def _slice_candidates(xyz, hag, lo: float, hi: float, cfg: SegmentConfig, rng) -> list:
    """Stem circles in the height slice ``[lo, hi]``: ``(cx, cy, r, indices, points, heights)``."""
    in_slice = np.flatnonzero((hag >= lo) & (hag <= hi))
    if len(in_slice) < cfg.seed_min_points:
        return []
    sxyz = xyz[in_slice]
    uniq, inv = _voxel_keys(sxyz, 0.02, np.zeros(3))
    cen = _centroids(sxyz, inv, len(uniq))
    cen[:, 2] *= _SLICE_Z_SCALE  # stems are vertical: link far along z, near across it
    tree = cKDTree(cen)
    pairs = tree.query_pairs(cfg.seed_cluster_dist, output_type="ndarray")
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(cen), len(cen)))
    ncomp, comp = connected_components(g, directed=False)
    sizes = np.bincount(comp, minlength=ncomp)
    point_comp = comp[inv]
    order = np.argsort(point_comp, kind="stable")
    starts = np.searchsorted(point_comp[order], np.arange(ncomp + 1))
    shag = hag[in_slice]
    thick = hi - lo
    cands = []
    for cid in np.flatnonzero(sizes >= cfg.seed_min_points):
        members = order[starts[cid]:starts[cid + 1]]
        pts = sxyz[members]
        ph = shag[members]
        if np.ptp(ph) < 0.6 * thick:
            continue
        for cx, cy, r, near in _cluster_stems(pts, ph, cfg, rng, lo, hi):
            cands.append((cx, cy, r, in_slice[members[near]], pts[near], ph[near]))
    return cands


def find_stems(xyz: np.ndarray, hag: np.ndarray, dtm: Dtm, config: SegmentConfig | None = None):
    """Stem seeds from a height slice of non-ground points.

    Parameters
    ----------
    xyz : ndarray, shape (n, 3)
        Non-ground points.
    hag : ndarray, shape (n,)
        Their heights above the terrain.
    dtm : Dtm
        Terrain model (for the stem base elevation).
    config : SegmentConfig, optional

    Returns
    -------
    stems : pandas.DataFrame
        One row per stem, ordered by x then y: ``x, y`` (centre at breast height), ``z``
        (terrain there), ``dbh``, ``radius_fit_rms``.
    seed_points : list of ndarray
        Per stem, the indices (into ``xyz``) of its slice points.
    """
    cfg = config or SegmentConfig()
    rng = np.random.default_rng(cfg.seed)
    empty = pd.DataFrame(columns=["x", "y", "z", "dbh", "radius_fit_rms"])
    cands = _slice_candidates(xyz, hag, cfg.slice_min, cfg.slice_max, cfg, rng)
    if cfg.low_slice_max > cfg.low_slice_min:
        # stems the first slice missed (branches or foliage of low crowns clutter it): the
        # lower slice adds those farther than their radii + 0.3 m from every stem found
        known = np.array([(c[0], c[1], c[2]) for c in cands]).reshape(-1, 3)
        for c in _slice_candidates(xyz, hag, cfg.low_slice_min, cfg.low_slice_max, cfg, rng):
            if len(known) == 0 or np.all(np.hypot(known[:, 0] - c[0], known[:, 1] - c[1]) > known[:, 2] + c[2] + 0.3):
                cands.append(c)
    if not cands:
        return empty, []
    # merge seeds of the same stem (split clusters)
    cands.sort(key=lambda c: -len(c[3]))
    merged: list[list] = []
    for c in cands:
        for m in merged:
            if math.hypot(c[0] - m[0], c[1] - m[1]) < max(c[2], m[2]) + 0.05:
                m[3] = np.concatenate([m[3], c[3]])
                m[4] = np.vstack([m[4], c[4]])
                m[5] = np.concatenate([m[5], c[5]])
                break
        else:
            merged.append(list(c))
    rows, seeds = [], []
    for cx, cy, r, idx, pts, ph in merged:
        # DBH: circle of the points between 1.2 and 1.4 m near the slice circle
        bh = (np.abs(ph - BREAST_HEIGHT) <= 0.1) & (np.abs(np.hypot(pts[:, 0] - cx, pts[:, 1] - cy) - r) < max(0.05, 0.3 * r))
        dbh = 2 * r
        rms = math.nan
        if bh.sum() >= 10:
            fit = _stem_circle(pts[bh, :2], cfg, rng)
            if fit is not None and cfg.min_dbh / 2 <= fit[2] <= cfg.max_dbh / 2 and fit[3].sum() >= 8:
                bx, by, br, binl = fit
                bx, by, br, rms = fit_circle(pts[bh][binl, :2])
                if np.isfinite(br) and math.hypot(bx - cx, by - cy) < 0.5 * r + 0.05:
                    cx, cy, dbh = bx, by, 2 * br
        rows.append((cx, cy, float(dtm.height_at(cx, cy)), dbh, rms))
        seeds.append(idx)
    seeds = [np.unique(sd) for sd in seeds]
    if not rows:
        return empty, []
    stems = pd.DataFrame(rows, columns=["x", "y", "z", "dbh", "radius_fit_rms"])
    order = np.lexsort((np.round(stems["y"].to_numpy(), 3), np.round(stems["x"].to_numpy(), 3)))
    stems = stems.iloc[order].reset_index(drop=True)
    seeds = [seeds[i] for i in order]
    return stems, seeds


# --------------------------------------------------------------------------------------------
# competitive growth


def _stem_bridges(cen: np.ndarray, seed_vox: list[np.ndarray], stems: pd.DataFrame, cfg: SegmentConfig):
    """Graph edges across the hidden parts of stems (see ``SegmentConfig.stem_bridge``).

    Returns ``(rows, cols, lengths)``: voxel index pairs and their straight-line distances.
    """
    empty = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
    if cfg.stem_bridge <= 0 or stems is None or len(stems) == 0 or len(cen) < 2:
        return empty
    plan = cKDTree(cen[:, :2])
    rows, cols = [], []
    for (sx, sy, dbh), vox in zip(stems[["x", "y", "dbh"]].to_numpy(float), seed_vox):
        if len(vox) == 0:
            continue
        col = np.asarray(plan.query_ball_point([sx, sy], dbh / 2 + cfg.bridge_radius), np.int64)
        # the column above the seed's top voxel, in height order
        col = col[cen[col, 2] >= cen[vox, 2].max() - cfg.voxel]
        col = col[np.argsort(cen[col, 2], kind="stable")]
        dz = np.diff(cen[col, 2])
        gap = (dz > cfg.graph_radius) & (dz <= cfg.stem_bridge)
        rows.append(col[:-1][gap])
        cols.append(col[1:][gap])
    if not rows:
        return empty
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    return rows, cols, np.linalg.norm(cen[rows] - cen[cols], axis=1)


def _grow(xyz: np.ndarray, seeds: list[np.ndarray], cfg: SegmentConfig, stems: pd.DataFrame | None = None):
    """Tree label (1..len(seeds), 0 = none) per point of ``xyz`` by competitive Dijkstra.

    ``stems`` (rows matching ``seeds``; columns ``x, y, dbh``) enables the stem bridges.
    """
    n = len(xyz)
    labels = np.zeros(n, np.int64)
    if n == 0 or not seeds:
        return labels, {"n_voxels": 0, "n_edges": 0, "n_bridges": 0, "unreached": 0, "attached": 0}
    uniq, inv = _voxel_keys(xyz, cfg.voxel, np.zeros(3))
    nv = len(uniq)
    cen = _centroids(xyz, inv, nv)
    tree = cKDTree(cen)
    k = min(int(cfg.graph_k) + 1, nv)
    dist, nb = tree.query(cen, k=k, distance_upper_bound=cfg.graph_radius, workers=-1)
    dist = dist.reshape(nv, -1)[:, 1:]
    nb = nb.reshape(nv, -1)[:, 1:]
    ok = np.isfinite(dist) & (nb < nv)
    rows = np.repeat(np.arange(nv), ok.sum(axis=1))
    cols = nb[ok]
    w = np.maximum(dist[ok], 1e-6) ** cfg.edge_power
    seed_vox = [np.unique(inv[idx]) for idx in seeds]
    b_rows, b_cols, b_len = _stem_bridges(cen, seed_vox, stems, cfg)
    if len(b_rows):
        rows = np.concatenate([rows, b_rows])
        cols = np.concatenate([cols, b_cols])
        w = np.concatenate([w, b_len ** cfg.edge_power])
    graph = coo_matrix((w, (rows, cols)), shape=(nv, nv)).tocsr()
    # seed voxels: label of the seed (a voxel claimed by two seeds keeps the first)
    seed_label = np.zeros(nv, np.int64)
    for t, vox in enumerate(seed_vox, start=1):
        free = seed_label[vox] == 0
        seed_label[vox[free]] = t
    src = np.flatnonzero(seed_label)
    _, _, sources = dijkstra(graph, directed=False, indices=src, min_only=True, return_predecessors=True)
    vlab = np.where(sources >= 0, seed_label[np.maximum(sources, 0)], 0)
    vlab[src] = seed_label[src]
    reached = vlab > 0
    n_unreached = int((~reached).sum())
    attached = 0
    if n_unreached and reached.any():
        # unreached parts (crown pieces the scans sampled too sparsely to link) join whole: a
        # connected piece takes the tree of the reached voxel nearest to any of its voxels when
        # that lies within attach_dist; repeated, so that pieces can chain onto attached ones
        un = np.flatnonzero(~reached)
        sub = graph[un][:, un]
        ncomp, comp = connected_components(sub, directed=False)
        todo = np.ones(ncomp, bool)
        for _ in range(8):
            have = vlab > 0
            if not todo.any() or not have.any():
                break
            rt = cKDTree(cen[have])
            open_ = todo[comp]
            d, j = rt.query(cen[un[open_]], k=1, distance_upper_bound=cfg.attach_dist, workers=-1)
            hit = np.isfinite(d)
            if not hit.any():
                break
            qc = comp[open_]
            best = np.full(ncomp, np.inf)
            np.minimum.at(best, qc[hit], d[hit])
            win = hit & (d <= best[qc])
            lab_c = np.zeros(ncomp, np.int64)
            lab_c[qc[win]] = vlab[np.flatnonzero(have)[j[win]]]
            new = todo & (lab_c > 0)
            sel = new[comp]
            vlab[un[sel]] = lab_c[comp[sel]]
            todo &= ~new
        attached = int((vlab[un] > 0).sum())
    labels = vlab[inv]
    info = {"n_voxels": nv, "n_edges": int(len(w)), "n_bridges": int(len(b_rows)), "unreached": n_unreached,
            "attached": attached}
    return labels, info


# --------------------------------------------------------------------------------------------
# whole cloud


@dataclass
class SegmentResult:
    """Outcome of :func:`segment_cloud`.

    Attributes
    ----------
    tree_id : ndarray of uint32, shape (n,)
        1..N per tree point, 0 for ground, noise and points of no tree.
    classification : ndarray of uint8, shape (n,)
        2 ground, 7 noise, 1 otherwise.
    trees : pandas.DataFrame
        Columns :data:`TREE_COLUMNS`.
    dtm : Dtm
    info : dict
        Counts and timings.
    """

    tree_id: np.ndarray
    classification: np.ndarray
    trees: pd.DataFrame
    dtm: Dtm
    info: dict = field(default_factory=dict)


def segment_cloud(cloud, config: SegmentConfig | None = None, source: str = "cloud") -> SegmentResult:
    """Segment a co-registered TLS cloud into trees.

    Parameters
    ----------
    cloud : vlsforest.io.las.PointCloud
        All scans of a plot.
    config : SegmentConfig, optional
    source : str
        Name used in error messages (the input file or files).

    Returns
    -------
    SegmentResult

    Raises
    ------
    InputDataError
        For fewer than :data:`MIN_POINTS` points, NaN/infinite coordinates or no ground.
    """
    cfg = config or SegmentConfig()
    t0 = time.perf_counter()
    xyz = np.asarray(cloud.xyz, float)
    n = len(xyz)
    if n < MIN_POINTS:
        raise InputDataError(f"{source}: only {n} points, need at least {MIN_POINTS} to segment")
    bad = ~np.isfinite(xyz).all(axis=1)
    if bad.any():
        raise InputDataError(f"{source}: {int(bad.sum())} points have NaN or infinite coordinates")
    info: dict = {"n_points": n}
    noise = np.zeros(n, bool)
    dev_field = next((f for f in DEVIATION_FIELDS if f in cloud.attrs), None)
    if dev_field is not None:
        dev = np.asarray(cloud.attrs[dev_field], float)
        noise |= ~(dev <= cfg.max_deviation)
        info["deviation_filter"] = f"{dev_field} > {cfg.max_deviation:g}: {int(noise.sum())} points dropped"
    else:
        info["deviation_filter"] = "no pulse-shape deviation field; nothing filtered"
    keep = np.flatnonzero(~noise)
    if len(keep) < MIN_POINTS:
        raise InputDataError(f"{source}: only {len(keep)} points pass the deviation filter, need {MIN_POINTS}")
    kxyz = xyz[keep]
    is_ground_k, is_noise_k, dtm = classify_ground(kxyz, cfg, source)
    t1 = time.perf_counter()
    noise[keep[is_noise_k]] = True
    ground = np.zeros(n, bool)
    ground[keep[is_ground_k]] = True
    veg = np.flatnonzero(~ground & ~noise)
    vxyz = xyz[veg]
    hag = vxyz[:, 2] - dtm.height_at(vxyz[:, 0], vxyz[:, 1])
    stems, seeds = find_stems(vxyz, hag, dtm, cfg)
    t2 = time.perf_counter()
    labels, ginfo = _grow(vxyz, seeds, cfg, stems)
    t3 = time.perf_counter()
    tree_id = np.zeros(n, np.uint32)
    tree_id[veg] = labels
    classification = np.full(n, CLASS_UNCLASSIFIED, np.uint8)
    classification[ground] = CLASS_GROUND
    classification[noise] = CLASS_NOISE
    nt = len(stems)
    counts = np.bincount(tree_id, minlength=nt + 1)[1:]
    zmax = np.full(nt + 1, -np.inf)
    lab = tree_id[veg]
    np.maximum.at(zmax, lab, vxyz[:, 2]) if len(lab) < 2_000_000 else _reduce_sorted(zmax, lab, vxyz[:, 2], np.maximum)
    trees = pd.DataFrame(
        {
            "tree_id": np.arange(1, nt + 1, dtype=np.int64),
            "x": stems["x"].to_numpy(float),
            "y": stems["y"].to_numpy(float),
            "z": stems["z"].to_numpy(float),
            "dbh": stems["dbh"].to_numpy(float),
            "height": np.where(counts > 0, zmax[1:] - stems["z"].to_numpy(float), np.nan),
            "n_points": counts.astype(np.int64),
        },
        columns=list(TREE_COLUMNS),
    )
    info.update(ginfo)
    info.update(
        {
            "n_ground": int(ground.sum()),
            "n_noise": int(noise.sum()),
            "n_trees": nt,
            "n_tree_points": int((tree_id > 0).sum()),
            "t_ground_s": t1 - t0,
            "t_seeds_s": t2 - t1,
            "t_growth_s": t3 - t2,
        }
    )
    return SegmentResult(tree_id, classification, trees, dtm, info)


# --------------------------------------------------------------------------------------------
# files


def _writable(cloud):
    """The cloud without attributes that ``write_las`` cannot place (LAS flag bits)."""
    from vlsforest.io.las import PointCloud

    flags = {"synthetic", "key_point", "withheld", "overlap", "scanner_channel", "scan_direction_flag",
             "edge_of_flight_line", "scan_angle_rank", "classification_flags"}
    attrs = {k: v for k, v in cloud.attrs.items() if k not in flags}
    return PointCloud(cloud.xyz, attrs)


def read_scans(paths) -> "PointCloud":
    """Read and concatenate LAS/LAZ scans (attributes missing in any file are dropped).

    Raises
    ------
    InputDataError
        When a file is missing, unreadable, empty or has NaN coordinates (names the file).
    """
    from vlsforest.io.las import PointCloud, read_las

    paths = [Path(p) for p in paths]
    if not paths:
        raise InputDataError("no input files given")
    clouds = [read_las(p) for p in paths]
    return PointCloud.concat(clouds)


def segment_files(paths, outdir, config: SegmentConfig | None = None, write_trees: bool = True,
                  quiet: bool = True) -> SegmentResult:
    """Segment LAS/LAZ scans of a plot and write the outputs into ``outdir``.

    Parameters
    ----------
    paths : list of str or Path
        Co-registered scans.
    outdir : str or Path
        Output folder: ``segmented.laz``, ``trees.csv``, ``trees/{id}.laz``, ``dtm.npz``.
    config : SegmentConfig, optional
    write_trees : bool
        Whether to write the per-tree files.
    quiet : bool
        Whether to keep progress lines off stderr.

    Returns
    -------
    SegmentResult
    """
    from vlsforest.io.las import write_las

    paths = [Path(p) for p in paths]
    t0 = time.perf_counter()
    cloud = read_scans(paths)
    source = str(paths[0]) if len(paths) == 1 else f"{paths[0]} (+{len(paths) - 1} more files)"
    t1 = time.perf_counter()
    if not quiet:
        print(f"segment: read {len(cloud)} points from {len(paths)} file(s) in {t1 - t0:.1f} s", file=sys.stderr)
    res = segment_cloud(cloud, config, source)
    t2 = time.perf_counter()
    out = make_folder(outdir)
    wc = _writable(cloud)
    wc.attrs["classification"] = res.classification
    write_las(out / "segmented.laz", wc, extra={"tree_id": res.tree_id})
    write_csv(out / "trees.csv", res.trees, index=False, float_format="%.4f", lineterminator="\n")
    res.dtm.save(out / "dtm.npz")
    if write_trees:
        tdir = make_folder(out / "trees")
        for old in tdir.glob("*.laz"):
            old.unlink()
        order = np.argsort(res.tree_id, kind="stable")
        sid = res.tree_id[order]
        bounds = np.searchsorted(sid, np.arange(1, len(res.trees) + 2))
        for t in range(1, len(res.trees) + 1):
            idx = order[bounds[t - 1]:bounds[t]]
            if len(idx):
                write_las(tdir / f"{t}.laz", wc.subset(idx), extra={"tree_id": res.tree_id[idx]})
    t3 = time.perf_counter()
    res.info.update({"t_read_s": t1 - t0, "t_segment_s": t2 - t1, "t_write_s": t3 - t2})
    return res


def match_stems(found_xy: np.ndarray, true_xy: np.ndarray, max_dist: float = 0.5):
    """One-to-one matching of found and true stem positions, closest pairs first.

    Parameters
    ----------
    found_xy, true_xy : ndarray, shape (n, 2) and (m, 2)
    max_dist : float
        Largest distance of a match.

    Returns
    -------
    list of (int, int)
        Pairs ``(found index, true index)``.
    """
    found_xy = np.asarray(found_xy, float).reshape(-1, 2)
    true_xy = np.asarray(true_xy, float).reshape(-1, 2)
    if len(found_xy) == 0 or len(true_xy) == 0:
        return []
    d = np.hypot(found_xy[:, None, 0] - true_xy[None, :, 0], found_xy[:, None, 1] - true_xy[None, :, 1])
    fi, ti = np.nonzero(d <= max_dist)
    order = np.lexsort((ti, fi, d[fi, ti]))
    used_f, used_t, pairs = set(), set(), []
    for k in order:
        f, t = int(fi[k]), int(ti[k])
        if f in used_f or t in used_t:
            continue
        used_f.add(f)
        used_t.add(t)
        pairs.append((f, t))
    return sorted(pairs)
