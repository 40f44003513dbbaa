"""Per-tree point-cloud metrics (Weiser et al. 2021, Table 4).

For every tree cloud (all returns, heights above ground ``z - ground_z``) :func:`tree_metrics`
returns, in this order (:data:`METRIC_COLUMNS`):

``n_points``
    number of points.
``hmin``, ``hmean``, ``hsd``
    minimum, mean and sample standard deviation (``ddof=1``) of the heights.
``p01 p05 p10 p20 p30 p40 p50 p60 p70 p80 p90 p95 p99``
    height percentiles, linear interpolation (``np.percentile`` default = R ``type=7``).
``dens_01 … dens_10``
    % of the points in 10 equal height bins ``[(k-1)·H/10, k·H/10)`` between 0 and the maximum
    height ``H``; the top point (``z == H``) goes to bin 10 and points below the ground
    (``z < 0``) go to bin 1. The values sum to 100.
``multi_return_pct``
    % of pulses with more than one return; three definitions (``multi_return=``):

    * ``"pulse"`` (default): over the distinct pulses of the tree cloud, a pulse being one
      ``(point_source_id, gps_time)`` pair, the share whose ``number_of_returns > 1`` (the
      largest ``number_of_returns`` among the pulse's points present counts). Returns are never
      recounted from the subset, so partial pulses count by their ``number_of_returns``.
    * ``"first_return"``: ``count(RN == 1 & NoR > 1) / count(RN == 1)``.
    * ``"per_return"``: ``count(NoR > 1) / n``; never smaller than ``"pulse"``.
``height``
    the maximum height ``H``.
``cbh``
    crown base height. ``cbh_convention="paper"`` (default): 0.1 m slices
    ``[k·0.1, (k+1)·0.1)`` from the ground upwards (points below the ground join slice 0); the
    first slice whose largest horizontal (xy) distance between two of its points *exceeds*
    1.5 m; CBH = that slice's centre ``(k + 0.5)·0.1`` (rounded to 10 decimals, so that a
    point at the centre height, e.g. 3.05, counts as "at or above CBH"). ``cbh_convention="authors"``
    reproduces the authors' script (``syssifoss`` ``compute_cbh``, see
    ``shared/reference/metrics.md`` §4): overlapping slices from ``np.arange`` limits, widths
    only for slices with more than 2 points, threshold 1.5 m if ``max(z) > 15`` else 1.0 m,
    the ground skip (first slice index > 10 with width ≤ 1.3 m), the "wider than the slice
    below" rule and the reported centre one slice too high.
``cpa``
    crown projection area: area of the 2-D convex hull of the xy of the points with
    ``z >= cbh`` (all points when 3 or fewer remain), computed after subtracting the mean xy.

Slice and bin membership is decided on ``z / width`` rounded to 9 decimals, so that a height
such as 0.3 m lies in the slice starting at 0.3 m despite binary rounding.

Documented values for degenerate trees (never an exception):

* **n = 0** (a requested tree without points): ``n_points = 0`` and every other metric NaN.
* **n = 1**: ``hsd`` NaN (ddof = 1); percentiles, ``hmin``, ``hmean`` and ``height`` equal the
  point's height; ``cbh`` 0.0; ``cpa`` 0.0.
* **n = 2** or otherwise fewer than 3 distinct xy positions: ``cpa`` 0.0 (no area).
* **no slice wide enough** (no crown found, short or thin trees): ``cbh`` 0.0 and ``cpa`` the
  hull area of all points.
* **collinear or duplicate-only slices**: Qhull cannot build a 2-D hull
  (``QhullError``); the slice width is then the exact maximum pairwise distance of the slice's
  distinct points (the same quantity). A slice with a single distinct xy has width 0.
* **collinear crown** (all crown xy on a line, or one xy): ``cpa`` 0.0.
* **flat crown** (all points at the same height ``H > 0``): every point is in bin 10
  (``dens_10 = 100``), ``hsd`` 0.0, ``cbh`` = centre of that slice if it is wide enough, else
  0.0.
* **maximum height ≤ 0** (all points at or below the ground): the bins have no extent and every
  point counts in bin 1 (``dens_01 = 100``, the others 0).
* **multi-return information missing** (``gps_time`` or ``number_of_returns`` for
  ``"pulse"``, ``return_number`` or ``number_of_returns`` for ``"first_return"``,
  ``number_of_returns`` for ``"per_return"``): ``multi_return_pct`` NaN. ``point_source_id``
  missing means one source. ``"first_return"`` with no first return in the tree: NaN.
  :func:`cloud_metrics` treats an attribute that is 0 for every point of the cloud (a LAS
  writer's default for "not recorded") as missing and warns once.
* ``cbh_convention="authors"``: where the authors' script would fail (maximum height ≤ 0.1 m,
  giving fewer than two slice limits, or a slice-limit array longer than the centre array) the
  slices it cannot index are skipped; CBH is 0.0 when nothing qualifies.

NaN or infinite coordinates raise :class:`~vlsforest.errors.InputDataError` naming the input.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping

import numpy as np
import pandas as pd
from scipy.spatial import ConvexHull, QhullError

from vlsforest.errors import ConfigError, InputDataError
from vlsforest.io.las import PointCloud

#: the number format of the per-tree metrics tables (``vlsforest metrics``, ``vlsforest extract --metrics``)
FLOAT_FORMAT = "%.6f"

__all__ = [
    "METRIC_COLUMNS",
    "PERCENTILES",
    "MULTI_RETURN_MODES",
    "CBH_CONVENTIONS",
    "tree_metrics",
    "cloud_metrics",
    "crown_projection_area",
    "zpcum_lidr",
]

#: percentile ranks reported as ``pXX``
PERCENTILES = (1, 5, 10, 20, 30, 40, 50, 60, 70, 80, 90, 95, 99)
#: number of height bins for ``dens_XX``
N_DENSITY_BINS = 10
#: CBH slice thickness (m) and width threshold (m) of the paper's definition
CBH_SLICE = 0.1
CBH_THRESHOLD = 1.5
#: accepted values of ``multi_return`` and ``cbh_convention``
MULTI_RETURN_MODES = ("pulse", "first_return", "per_return")
CBH_CONVENTIONS = ("paper", "authors")

#: column names of a metrics row after ``tree_id``
METRIC_COLUMNS = (
    ("n_points", "hmin", "hmean", "hsd")
    + tuple(f"p{p:02d}" for p in PERCENTILES)
    + tuple(f"dens_{k:02d}" for k in range(1, N_DENSITY_BINS + 1))
    + ("multi_return_pct", "height", "cbh", "cpa")
)

# directions used for the cheap lower/upper bounds of a slice's diameter
_N_DIRS = 8
_ANGLES = np.arange(_N_DIRS) * (np.pi / _N_DIRS)
_DIRS = np.stack([np.cos(_ANGLES), np.sin(_ANGLES)])  # (2, 8)
_DIRS[:, 0] = (1.0, 0.0)  # exact axis projections
_DIRS[:, _N_DIRS // 2] = (0.0, 1.0)
# the true diameter is at most the widest directional extent / cos(pi / (2 * _N_DIRS))
_UPPER_FACTOR = 1.0 / math.cos(math.pi / (2 * _N_DIRS)) * (1 + 1e-12)
_LOWER_SAFETY = 1 + 1e-12
_BIN_DECIMALS = 9
_NO_TREE = 1e300


# --------------------------------------------------------------------------- public API


def tree_metrics(
    xyz,
    *,
    ground_z: float = 0.0,
    return_number=None,
    number_of_returns=None,
    gps_time=None,
    point_source_id=None,
    multi_return: str = "pulse",
    cbh_convention: str = "paper",
    source: str = "tree cloud",
) -> dict:
    """Compute the Table 4 metrics of one tree cloud.

    Parameters
    ----------
    xyz : array_like, shape (n, 3)
        The tree's points (all returns).
    ground_z : float
        Terrain height at the stem; heights are ``z - ground_z``.
    return_number, number_of_returns, gps_time, point_source_id : array_like, optional
        Per-point LAS attributes for ``multi_return_pct`` (see the module docstring).
    multi_return : {"pulse", "first_return", "per_return"}
        Definition of the share of pulses with multiple returns.
    cbh_convention : {"paper", "authors"}
        Crown base height definition.
    source : str
        Name of the input used in error messages.

    Returns
    -------
    dict
        Keys :data:`METRIC_COLUMNS` in order; ``n_points`` is an int, the rest floats.

    Raises
    ------
    InputDataError
        When ``xyz`` is not (n, 3), holds NaN/inf, or an attribute has the wrong length.
    ConfigError
        For an unknown ``multi_return`` / ``cbh_convention`` or a non-finite ``ground_z``.
    """
    _check_options(multi_return, cbh_convention)
    try:
        ground_z = float(ground_z)
    except (TypeError, ValueError):
        raise ConfigError(f"ground_z: not a number ({ground_z!r})") from None
    if not math.isfinite(ground_z):
        raise ConfigError(f"ground_z: must be finite, got {ground_z}")
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        if xyz.size == 0:
            xyz = xyz.reshape(0, 3)
        else:
            raise InputDataError(f"{source}: coordinates must have shape (n, 3), got {xyz.shape}")
    n = len(xyz)
    bad = ~np.isfinite(xyz).all(axis=1)
    if bad.any():
        raise InputDataError(f"{source}: {int(bad.sum())} points have NaN or infinite coordinates")
    attrs = {}
    for name, arr in (
        ("return_number", return_number),
        ("number_of_returns", number_of_returns),
        ("gps_time", gps_time),
        ("point_source_id", point_source_id),
    ):
        if arr is not None:
            arr = np.asarray(arr).reshape(-1)
            if len(arr) != n:
                raise InputDataError(f"{source}: attribute {name!r} has {len(arr)} values for {n} points")
        attrs[name] = arr

    out = dict.fromkeys(METRIC_COLUMNS, np.nan)
    out["n_points"] = n
    if n == 0:
        return out

    z = xyz[:, 2] - ground_z
    xy = xyz[:, :2] - xyz[0, :2]  # shift first, then centre: keeps precision in UTM
    xy = xy - xy.mean(axis=0)

    out["hmin"] = float(z.min())
    out["hmean"] = float(z.mean())
    out["hsd"] = float(np.std(z, ddof=1)) if n > 1 else np.nan
    for p, v in zip(PERCENTILES, np.percentile(z, PERCENTILES)):
        out[f"p{p:02d}"] = float(v)
    hmax = float(z.max())
    for k, v in enumerate(_densities(z, hmax), start=1):
        out[f"dens_{k:02d}"] = float(v)
    out["multi_return_pct"] = _multi_return_pct(multi_return, **attrs)
    out["height"] = hmax
    if cbh_convention == "paper":
        cbh = _cbh_paper(xy, z)
    else:
        cbh = _cbh_authors(xy, z)
    out["cbh"] = float(cbh)
    out["cpa"] = _cpa(xy, z, cbh)
    return out


def crown_projection_area(xyz, cbh: float, *, ground_z: float = 0.0) -> float:
    """The ``cpa`` of :func:`tree_metrics` with a given crown base height.

    Parameters
    ----------
    xyz : array_like, shape (n, 3)
        The tree's points.
    cbh : float
        Crown base height above ``ground_z`` (m): the points at or above it are the crown.
    ground_z : float
        Terrain height at the stem.

    Returns
    -------
    float
        The area (m²) of the 2-D convex hull of the crown points' xy (of all points when 3 or
        fewer are in the crown; 0.0 when they have no area), as :func:`tree_metrics` computes
        ``cpa`` from its own CBH.

    Raises
    ------
    InputDataError
        When ``xyz`` is not (n, 3) or holds NaN/inf.
    """
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3) if np.size(xyz) == 0 else np.asarray(xyz, np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputDataError(f"coordinates must have shape (n, 3), got {xyz.shape}")
    if not np.isfinite(xyz).all():
        raise InputDataError("coordinates hold NaN or infinite values")
    if len(xyz) == 0:
        return 0.0
    xy = xyz[:, :2] - xyz[0, :2]
    return _cpa(xy - xy.mean(axis=0), xyz[:, 2] - float(ground_z), float(cbh))


def cloud_metrics(
    cloud: PointCloud,
    tree_id_field: str,
    ground_z=0.0,
    *,
    tree_ids=None,
    source: str | None = None,
    **kw,
) -> pd.DataFrame:
    """Compute :func:`tree_metrics` for every tree of a labelled cloud.

    Parameters
    ----------
    cloud : PointCloud
        Points with a per-point tree label in ``cloud.attrs[tree_id_field]`` and, optionally,
        ``return_number``, ``number_of_returns``, ``gps_time`` and ``point_source_id``.
    tree_id_field : str
        Name of the label attribute. Labels that are NaN, infinite or of magnitude ≥ 1e300 mean
        "no tree"; those points are dropped.
    ground_z : float or mapping
        Terrain height, one value for all trees or a mapping tree id → z.
    tree_ids : iterable, optional
        Trees to report. Default: every label present. A requested tree without points gets a
        row with ``n_points = 0`` and NaN metrics; labels not requested are ignored.
    source : str, optional
        Name of the input (e.g. the file) for error messages.
    **kw
        ``multi_return`` and ``cbh_convention``, passed on to :func:`tree_metrics`.

    Returns
    -------
    pandas.DataFrame
        One row per tree sorted by tree id; columns ``tree_id`` then :data:`METRIC_COLUMNS`.
        ``tree_id`` is int64 when every id is integral, float64 otherwise.

    Raises
    ------
    InputDataError
        Missing label field, NaN coordinates (names ``source``).
    ConfigError
        Unknown options, or a tree missing from a ``ground_z`` mapping.

    Warns
    -----
    UserWarning
        Once, when the cloud lacks the attributes needed for ``multi_return_pct``.
    """
    unknown = set(kw) - {"multi_return", "cbh_convention"}
    if unknown:
        raise TypeError(f"cloud_metrics() got unexpected keyword argument(s) {sorted(unknown)}")
    multi_return = kw.get("multi_return", "pulse")
    cbh_convention = kw.get("cbh_convention", "paper")
    _check_options(multi_return, cbh_convention)
    source = source or "point cloud"
    if tree_id_field not in cloud.attrs:
        raise InputDataError(
            f"{source}: no tree-id field {tree_id_field!r} (fields: {', '.join(sorted(cloud.attrs)) or 'none'})"
        )
    bad = ~np.isfinite(cloud.xyz).all(axis=1)
    if bad.any():
        raise InputDataError(f"{source}: {int(bad.sum())} points have NaN or infinite coordinates")

    labels = np.asarray(cloud.attrs[tree_id_field]).astype(np.float64)
    valid = np.isfinite(labels) & (np.abs(labels) < _NO_TREE)
    mr_attrs, missing = _multi_return_attrs(cloud, multi_return)
    if missing and valid.any():
        warnings.warn(
            f"{source}: no usable {', '.join(missing)}; multi_return_pct ({multi_return}) is NaN",
            UserWarning,
            stacklevel=2,
        )

    idx = np.flatnonzero(valid)
    lab = labels[idx]
    order = np.argsort(lab, kind="stable")
    idx = idx[order]
    lab = lab[order]
    present, starts = np.unique(lab, return_index=True)
    bounds = dict(zip(present.tolist(), zip(starts.tolist(), np.append(starts[1:], len(lab)).tolist())))

    if tree_ids is None:
        wanted = present
    else:
        wanted = np.unique(np.asarray(list(tree_ids), dtype=np.float64))
        if not np.all(np.isfinite(wanted)):
            raise ConfigError("tree_ids: must be finite numbers")

    rows = []
    for tid in wanted.tolist():
        gz = _ground_for(ground_z, tid)
        if tid in bounds:
            a, b = bounds[tid]
            sel = idx[a:b]
        else:
            sel = idx[:0]
        kwargs = {k: (v[sel] if v is not None else None) for k, v in mr_attrs.items()}
        row = tree_metrics(
            cloud.xyz[sel],
            ground_z=gz,
            multi_return=multi_return,
            cbh_convention=cbh_convention,
            source=f"{source} tree {_fmt_id(tid)}",
            **kwargs,
        )
        rows.append(row)

    ids = np.asarray(wanted, dtype=np.float64)
    if ids.size == 0 or np.all(ids == np.round(ids)):
        ids = ids.astype(np.int64)
    df = pd.DataFrame({"tree_id": ids})
    for col in METRIC_COLUMNS:
        vals = [r[col] for r in rows]
        df[col] = np.asarray(vals, dtype=np.int64 if col == "n_points" else np.float64)
    return df


def zpcum_lidr(z, zmin: float = 0.0) -> np.ndarray:
    """lidR's cumulative height-bin percentages ``zpcum1..zpcum9`` (for cross-checks).

    Follows lidR ``stdmetrics_z``: breaks ``seq(zmin, zmax, (zmax - zmin)/10)``, only points
    with ``z > zmin`` counted, bins closed on the left, points at ``zmax`` dropped, the counts
    normalised by the points kept in the 10 bins and accumulated.

    Parameters
    ----------
    z : array_like
        Heights.
    zmin : float
        Lower break (lidR's default 0).

    Returns
    -------
    ndarray, shape (9,)
        Cumulative % for bins 1..9; all 0 when ``max(z) <= zmin``; NaN when no point falls in
        the 10 bins (every point above ``zmin`` is at ``zmax``) or ``z`` is empty.
    """
    z = np.asarray(z, dtype=np.float64).reshape(-1)
    if z.size == 0:
        return np.full(9, np.nan)
    zmax = float(z.max())
    if zmax <= zmin:
        return np.zeros(9)
    breaks = _r_seq(zmin, zmax, (zmax - zmin) / 10.0)
    kept = z[z > zmin]
    d = np.searchsorted(breaks, kept, side="right")  # R findInterval
    counts = np.bincount(d, minlength=12)[1:11].astype(np.float64)
    total = counts.sum()
    if total == 0:
        return np.full(9, np.nan)
    return np.cumsum(counts / total * 100.0)[:9]


# --------------------------------------------------------------------------- helpers


def _check_options(multi_return, cbh_convention):
    if multi_return not in MULTI_RETURN_MODES:
        raise ConfigError(f"multi_return: {multi_return!r} is not one of {', '.join(MULTI_RETURN_MODES)}")
    if cbh_convention not in CBH_CONVENTIONS:
        raise ConfigError(f"cbh_convention: {cbh_convention!r} is not one of {', '.join(CBH_CONVENTIONS)}")


def _fmt_id(tid: float) -> str:
    return str(int(tid)) if float(tid).is_integer() else repr(tid)


def _ground_for(ground_z, tid: float) -> float:
    if isinstance(ground_z, Mapping):
        for key in ((int(tid),) if float(tid).is_integer() else ()) + (tid, str(_fmt_id(tid))):
            if key in ground_z:
                return ground_z[key]
        raise ConfigError(f"ground_z: no value for tree {_fmt_id(tid)}")
    return ground_z


def _multi_return_attrs(cloud: PointCloud, mode: str):
    """Per-point attribute arrays for ``tree_metrics`` and the names missing for ``mode``."""
    need = {
        "pulse": ("gps_time", "number_of_returns"),
        "first_return": ("return_number", "number_of_returns"),
        "per_return": ("number_of_returns",),
    }[mode]
    out = {}
    for name in ("return_number", "number_of_returns", "gps_time", "point_source_id"):
        arr = cloud.attrs.get(name)
        if arr is not None and name != "point_source_id" and len(arr) and not np.any(np.asarray(arr) != 0):
            arr = None  # all zero: the field was not recorded
        out[name] = arr
    missing = [name for name in need if out[name] is None]
    if missing:
        out = dict.fromkeys(out)
    return out, missing


def _bin_index(values: np.ndarray, width: float) -> np.ndarray:
    """floor(values / width) with a 1e-9 tolerance against binary rounding."""
    return np.floor(np.round(values / width, _BIN_DECIMALS)).astype(np.int64)


def _densities(z: np.ndarray, hmax: float) -> np.ndarray:
    n = len(z)
    if hmax <= 0:
        out = np.zeros(N_DENSITY_BINS)
        out[0] = 100.0
        return out
    k = np.clip(_bin_index(z, hmax / N_DENSITY_BINS), 0, N_DENSITY_BINS - 1)
    return np.bincount(k, minlength=N_DENSITY_BINS) * (100.0 / n)


def _multi_return_pct(mode, *, return_number, number_of_returns, gps_time, point_source_id) -> float:
    if number_of_returns is None:
        return np.nan
    nor = np.asarray(number_of_returns, dtype=np.int64)
    if mode == "per_return":
        return float(np.count_nonzero(nor > 1) * 100.0 / len(nor))
    if mode == "first_return":
        if return_number is None:
            return np.nan
        first = np.asarray(return_number) == 1
        nfirst = np.count_nonzero(first)
        if nfirst == 0:
            return np.nan
        return float(np.count_nonzero(first & (nor > 1)) * 100.0 / nfirst)
    # pulse
    if gps_time is None:
        return np.nan
    gps = np.asarray(gps_time, dtype=np.float64)
    psid = np.zeros(len(gps), np.int64) if point_source_id is None else np.asarray(point_source_id, np.int64)
    order = np.lexsort((gps, psid))
    g, s, r = gps[order], psid[order], nor[order]
    new = np.ones(len(g), bool)
    new[1:] = (g[1:] != g[:-1]) | (s[1:] != s[:-1])
    starts = np.flatnonzero(new)
    pulse_nor = np.maximum.reduceat(r, starts)
    return float(np.count_nonzero(pulse_nor > 1) * 100.0 / len(starts))


def _brute_diameter(pts: np.ndarray) -> float:
    """Exact maximum pairwise distance, in blocks (used for degenerate slices)."""
    pts = np.unique(pts, axis=0)
    m = len(pts)
    if m < 2:
        return 0.0
    best = 0.0
    block = max(1, 4_000_000 // m)
    for a in range(0, m, block):
        d = pts[a : a + block, None, :] - pts[None, :, :]
        best = max(best, float(np.sqrt(np.max(np.einsum("ijk,ijk->ij", d, d)))))
    return best


def _diameter(pts: np.ndarray) -> float:
    """Largest pairwise xy distance of a set of 2-D points (hull vertices + brute force)."""
    if len(pts) < 2:
        return 0.0
    if len(pts) <= 16:
        return _brute_diameter(pts)
    try:
        hull = ConvexHull(pts)
    except QhullError:  # collinear or duplicate-only: same quantity by brute force
        return _brute_diameter(pts)
    return _brute_diameter(pts[hull.vertices])


def _slice_bounds(xy: np.ndarray, k: np.ndarray):
    """Group points by slice index; per group the lower/upper diameter bounds.

    Returns the sorted xy, the group slice indices, starts, counts, lower, upper.
    """
    order = np.argsort(k, kind="stable")
    ks = k[order]
    xs = xy[order]
    keys, starts, counts = np.unique(ks, return_index=True, return_counts=True)
    proj = xs @ _DIRS  # (n, 8)
    ext = np.maximum.reduceat(proj, starts, axis=0) - np.minimum.reduceat(proj, starts, axis=0)
    lower = ext.max(axis=1)
    upper = lower * _UPPER_FACTOR
    return xs, keys, starts, counts, lower, upper


def _cbh_paper(xy: np.ndarray, z: np.ndarray) -> float:
    """Paper definition: centre of the first 0.1 m slice wider than 1.5 m, else 0."""
    k = np.maximum(_bin_index(z, CBH_SLICE), 0)
    xs, keys, starts, counts, lower, upper = _slice_bounds(xy, k)
    thr = CBH_THRESHOLD
    for j in np.flatnonzero((counts >= 2) & (upper > thr)):
        if lower[j] > thr * _LOWER_SAFETY or _diameter(xs[starts[j] : starts[j] + counts[j]]) > thr:
            return round((keys[j] + 0.5) * CBH_SLICE, 10)  # 3.05, not 3.0500000000000003
    return 0.0


def _cbh_authors(xy: np.ndarray, z: np.ndarray) -> float:
    """The authors' ``compute_cbh`` (metrics.md §4) without its crashes."""
    dz = CBH_SLICE
    zmax = float(np.max(z))
    num = math.ceil(zmax / dz)
    upper_lim = dz * num
    lim = np.arange(0, upper_lim, dz)
    centres = np.arange(0 + dz / 2, upper_lim + dz / 2, dz)
    nslice = min(len(lim), len(centres))
    if nslice < 2:
        return 0.0
    thr = 1.0 + (0.5 if zmax > 15 else 0.0)
    # slice i > 0: lim[i-1] < z <= lim[i]  <=>  searchsorted(lim, z, 'left') == i
    # slice 0: z <= lim[1]  <=>  index 0 or 1 (overlaps slice 1)
    idx = np.searchsorted(lim, z, side="left")
    keep = idx < nslice
    xs, keys, starts, counts, lower, upper = _slice_bounds(xy[keep], idx[keep])
    groups = {
        int(kk): (int(s), int(c), float(lo), float(hi))
        for kk, s, c, lo, hi in zip(keys, starts, counts, lower, upper)
    }
    # slice 0 = groups 0 and 1 together
    pts0 = [xs[s : s + c] for kk, (s, c, _, _) in groups.items() if kk in (0, 1)]
    pts0 = np.concatenate(pts0) if pts0 else np.zeros((0, 2))

    cache: dict[int, float] = {}

    def count(i: int) -> int:
        if i == 0:
            return len(pts0)
        return groups[i][1] if i in groups else 0

    def bounds(i: int) -> tuple[float, float]:
        if count(i) <= 2:
            return 0.0, 0.0
        if i == 0:
            w = width(0)
            return w, w
        _, _, lo, hi = groups[i]
        return lo, hi

    def width(i: int) -> float:
        if i not in cache:
            if count(i) <= 2:
                cache[i] = 0.0
            elif i == 0:
                cache[i] = _diameter(pts0)
            else:
                s, c, _, _ = groups[i]
                cache[i] = _diameter(xs[s : s + c])
        return cache[i]

    start = 0
    for i in range(11, nslice):  # ground skip: first i > 10 with width <= 1.3
        lo, hi = bounds(i)
        if hi <= 1.3 or (lo <= 1.3 * _LOWER_SAFETY and width(i) <= 1.3):
            start = i
            break
    for i in range(start + 1, nslice):
        lo, hi = bounds(i)
        if hi < thr:
            continue
        w = width(i)
        if w >= thr:
            lo_prev, hi_prev = bounds(i - 1)
            if hi_prev < w or w > width(i - 1):
                return float(centres[i])
    return 0.0


def _cpa(xy: np.ndarray, z: np.ndarray, cbh: float) -> float:
    """Convex-hull area of the crown points' xy (all points if ≤ 3 remain), centred."""
    crown = xy[z >= cbh]
    if len(crown) <= 3:
        crown = xy
    if len(crown) < 3:
        return 0.0
    crown = crown - crown.mean(axis=0)
    try:
        return float(ConvexHull(crown).volume)
    except QhullError:  # collinear or fewer than 3 distinct points
        return 0.0


def _r_seq(start: float, stop: float, by: float) -> np.ndarray:
    """R's ``seq(start, stop, by)`` for by > 0."""
    n = int((stop - start) / by + 1e-10)
    x = start + np.arange(n + 1) * by
    return np.minimum(x, stop)
