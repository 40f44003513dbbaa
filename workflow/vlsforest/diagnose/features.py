"""Per-tree observables for the diagnosis: the study's metrics plus pulse-level, stratified ones.

Every observable is computed the same way for a real recording and for a simulation, from the
points that :func:`label_trees` gives each tree (the points within the extraction radius of the
tree's TLS points, as the study extracted its reference clouds) and from the ground returns in
the column under the tree's crown.

Observables (columns of :func:`tree_features`):

* the study's metrics ``height``, ``hmean``, ``p10``, ``p50``, ``p90``, ``p99``, ``cbh``,
  ``cpa``, ``multi_return_pct`` (:mod:`vlsforest.metrics`, heights above the stem base);
* ``returns_per_pulse`` — returns of the tree per pulse that hit it (pulses: GPS time + source id);
* ``rn1_share``, ``rn2_share``, ``rn3plus_share`` — return-number distribution (% of returns);
* ``first_p50``, ``first_p90``, ``first_max`` — heights of first returns;
* ``interecho_median``, ``interecho_p10``, ``interecho_short_pct`` — 3-D distance between
  consecutive echoes of one pulse within the tree, and the % of those below
  :data:`SHORT_ECHO_M`;
* ``interecho_floor`` — the 1st percentile of those distances: the closest echo pairs the
  sensor separates, i.e. its dead zone (pulse width and peak-detection window), whatever the
  voxel model. The other inter-echo observables also follow the spacing of the crown's
  elements, which a voxel reconstruction gets wrong; this one is where a dead-zone change shows
  and the reconstruction hardly does;
* ``multi_pct_nadir`` / ``multi_pct_offnadir`` and ``rpp_nadir`` / ``rpp_offnadir`` — multiple
  returns and returns per pulse in two scan-angle strata (|angle| < :data:`ANGLE_SPLIT_DEG` and
  above);
* ``crown_extent_ratio`` — crown extent along x over extent along y (5–95 % range of the points
  at or above CBH; directional footprints stretch crowns one way);
* ``ground_share_pct`` — % of returns in the crown column that are ground returns;
* ``ground_sd_nadir`` — SD of the ground returns at scan angles below :data:`ANGLE_SPLIT_DEG`
  about a local plane fitted per 1 m cell and flight line (range noise thickens it);
* ``ground_sd_growth`` — ln(SD off-nadir / SD nadir), the same roughness at scan angles of
  :data:`ANGLE_SPLIT_DEG` and above over that below. Off nadir a footprint spreads over a range
  interval that grows with its extent along the scan times tan(scan angle), so the growth
  follows that extent — at a given solid angle the beam's shape, an ellipse's major axis lying
  along the scan unless turned. Both strata's ground echoes are also pulled by the vegetation
  that shares their pulses (see below), which a voxel reconstruction gets wrong; that mixing
  scales the roughness of both strata alike to first order and cancels in the ratio, as it did
  does not in an all-angle roughness;
* ``ground_dz_lines`` — median absolute offset between the ground of two flight lines in the
  same 1 m cell (trajectory errors move whole strips);
* ``ground_sd_single``, ``ground_dz_single`` — the roughness (all scan angles) and the offset
  from the ground returns of pulses with a single return only. A ground echo that shares its
  pulse with vegetation is pulled by it (the waveform's peaks merge within the dead zone), so
  the three above also follow the beam's footprint and the low vegetation, which a voxel
  reconstruction gets wrong; these two keep what moves the ground itself (range noise, strip
  shifts) without that mixing;
* ``int_p01_rel``, ``int_p05_rel`` — the 1st and 5th percentile of the tree's echo intensities
  divided by the 10th: scale-free (real intensities are rarely calibrated, and a reflectance
  change scales them all), but a detection threshold cuts the weak end and raises them;
* ``int_floor`` — the 0.1 % percentile of the intensities: where a detection threshold cuts, it
  *is* the threshold (in the simulator's amplitude units), whatever the voxel model.

Missing values (too few points in a stratum) are NaN and are left out of every statistic.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from vlsforest.errors import InputDataError

#: scan-angle split between the nadir and the off-nadir stratum (degrees)
ANGLE_SPLIT_DEG = 15.0
#: inter-echo distances below this count as "short" (m)
SHORT_ECHO_M = 1.0
#: the ground observables read the ground returns this far beyond a tree's crown radius (m)
GROUND_PAD_M = 2.0
#: the study's metrics used as observables
STUDY_METRICS = ("height", "hmean", "p10", "p50", "p90", "p99", "cbh", "cpa", "multi_return_pct")
#: every observable, in column order
FEATURES = STUDY_METRICS + (
    "returns_per_pulse", "rn1_share", "rn2_share", "rn3plus_share",
    "first_p50", "first_p90", "first_max",
    "interecho_median", "interecho_p10", "interecho_short_pct", "interecho_floor",
    "multi_pct_nadir", "multi_pct_offnadir", "rpp_nadir", "rpp_offnadir",
    "crown_extent_ratio", "ground_share_pct", "ground_sd_nadir", "ground_sd_growth", "ground_dz_lines",
    "ground_sd_single", "ground_dz_single",
    "int_p01_rel", "int_p05_rel", "int_floor",
)
#: the stratum each observable describes (for the located mismatches, in words)
STRATUM = {
    **{m: "whole tree" for m in STUDY_METRICS},
    "returns_per_pulse": "pulses", "rn1_share": "return number 1", "rn2_share": "return number 2",
    "rn3plus_share": "return number ≥ 3", "first_p50": "first returns", "first_p90": "first returns",
    "first_max": "first returns (tree top)", "interecho_median": "echo pairs of a pulse",
    "interecho_p10": "echo pairs of a pulse", "interecho_floor": "closest echo pairs of a pulse (1 %)",
    "interecho_short_pct": f"echo pairs < {SHORT_ECHO_M:g} m",
    "multi_pct_nadir": f"scan angle < {ANGLE_SPLIT_DEG:g}°", "multi_pct_offnadir": f"scan angle ≥ {ANGLE_SPLIT_DEG:g}°",
    "rpp_nadir": f"scan angle < {ANGLE_SPLIT_DEG:g}°", "rpp_offnadir": f"scan angle ≥ {ANGLE_SPLIT_DEG:g}°",
    "crown_extent_ratio": "crown (along x / along y)", "ground_share_pct": "ground under the crown",
    "ground_sd_nadir": f"ground under the crown, scan angle < {ANGLE_SPLIT_DEG:g}°",
    "ground_sd_growth": f"ground under the crown, scan angle ≥ {ANGLE_SPLIT_DEG:g}° over < {ANGLE_SPLIT_DEG:g}°",
    "ground_dz_lines": "ground under the crown, between flight lines",
    "ground_sd_single": "single-return ground under the crown",
    "ground_dz_single": "single-return ground under the crown, between flight lines",
    "int_p01_rel": "weakest echoes (intensity / its 10th percentile)",
    "int_p05_rel": "weak echoes (intensity / its 10th percentile)",
    "int_floor": "weakest detected echoes (0.1 % intensity)",
}
_MIN_PULSES = 10


def cloud_arrays(cloud) -> dict:
    """The per-point arrays the observables need, from a PointCloud or a simulation result.

    Parameters
    ----------
    cloud : vlsforest.io.las.PointCloud or vlsforest.sim.SimulationResult

    Returns
    -------
    dict of ndarray
        ``xyz``, ``return_number``, ``number_of_returns``, ``gps_time``, ``point_source_id``,
        ``scan_angle``, ``classification``, ``intensity`` (NaN when absent).
    """
    if hasattr(cloud, "points") and isinstance(cloud.points, dict):  # SimulationResult
        p = cloud.points
        get = p.__getitem__
        xyz = np.asarray(p["xyz"], dtype=np.float64)
        has = p.__contains__
    else:
        xyz = np.asarray(cloud.xyz, dtype=np.float64)
        get = cloud.attrs.__getitem__
        has = cloud.attrs.__contains__
    need = ("return_number", "number_of_returns", "gps_time", "point_source_id", "scan_angle")
    missing = [k for k in need if not has(k)]
    if missing:
        raise InputDataError(f"the point cloud lacks {', '.join(missing)} (needed to identify pulses)")
    out = {"xyz": xyz}
    for k in need:
        out[k] = np.asarray(get(k))
    out["classification"] = (np.asarray(get("classification")) if has("classification")
                             else np.zeros(len(xyz), np.uint8))
    out["intensity"] = (np.asarray(get("intensity"), np.float64) if has("intensity")
                        else np.full(len(xyz), np.nan))
    if not np.isfinite(xyz).all():
        raise InputDataError("the point cloud holds NaN or infinite coordinates")
    return out


def label_trees(arrays: dict, tree_points: dict, radius: float) -> np.ndarray:
    """Tree id per point: the nearest tree whose TLS points lie within ``radius`` (0 = none).

    Ground and noise returns (LAS classes 2, 7, 18) are never a tree's, as in
    :func:`vlsforest.extract.extract_reference`.
    """
    return tree_labeller(tree_points, radius)(arrays)


def tree_labeller(tree_points: dict, radius: float, workers: int = 1):
    """:func:`label_trees` for many clouds of the same trees: the trees' search structures are
    built once; the returned callable takes the ``arrays`` of a cloud (and optionally a
    column index of its x, y, as :func:`tree_features` takes it) and gives its labels.
    ``workers``: threads of the nearest-point queries."""
    from vlsforest.extract import TreeLabeller
    from vlsforest.io.las import PointCloud

    lab = TreeLabeller(tree_points, radius, workers)

    def label(arrays: dict, columns=None) -> np.ndarray:
        return lab(PointCloud(arrays["xyz"], {"classification": arrays["classification"]}), columns=columns)
    return label


def _pulse_key(a: dict, idx: np.ndarray) -> np.ndarray:
    """Integer pulse key per point (GPS time and source id)."""
    t = np.round(np.asarray(a["gps_time"][idx], np.float64) * 1e7).astype(np.int64)
    s = np.asarray(a["point_source_id"][idx], np.int64)
    return t * 1024 + s


def _pct(x, q):
    return float(np.percentile(x, q)) if len(x) else np.nan


def _multi_and_rpp(key, nret):
    """% of pulses with > 1 return and returns per pulse, from per-point pulse keys."""
    if len(key) == 0:
        return np.nan, np.nan
    uk, first = np.unique(key, return_index=True)
    if len(uk) < _MIN_PULSES:
        return np.nan, np.nan
    return 100.0 * float(np.mean(nret[first] > 1)), len(key) / len(uk)


def _interecho(xyz, key, rn):
    order = np.lexsort((rn, key))
    k, p = key[order], xyz[order]
    same = k[1:] == k[:-1]
    if not same.any():
        return np.array([])
    return np.linalg.norm(p[1:][same] - p[:-1][same], axis=1)


def _ground_stats(xyz, line, cell=1.0):
    """(local SD about per-cell planes, median |offset| between flight lines) of ground returns.

    Per 1 m cell and flight line with ≥ 5 returns a plane z = a + b·dx + c·dy is fitted by least
    squares (from per-group sums, vectorised); the SD pools the residuals (corrected for the 3
    fitted parameters); the offset compares the planes' heights at the cell centre between lines.
    """
    if len(xyz) < 20:
        return np.nan, np.nan
    ij = np.floor(xyz[:, :2] / cell).astype(np.int64)
    centre = (ij + 0.5) * cell
    dx, dy = xyz[:, 0] - centre[:, 0], xyz[:, 1] - centre[:, 1]
    z = xyz[:, 2]
    key = np.stack([ij[:, 0], ij[:, 1], np.asarray(line, np.int64)], axis=1)
    # the groups in np.unique(key, axis=0)'s lexicographic order, from one integer per row
    k = key - key.min(axis=0)
    span = k.max(axis=0) + 1
    _, first, inv, cnt = np.unique((k[:, 0] * span[1] + k[:, 1]) * span[2] + k[:, 2], return_index=True,
                                   return_inverse=True, return_counts=True)
    groups = key[first]
    g = len(groups)

    def s(v):
        return np.bincount(inv, weights=v, minlength=g)

    n = cnt.astype(float)
    sx, sy, sz = s(dx), s(dy), s(z)
    sxx, sxy, syy, sxz, syz, szz = s(dx * dx), s(dx * dy), s(dy * dy), s(dx * z), s(dy * z), s(z * z)
    A = np.stack([np.stack([n, sx, sy], -1), np.stack([sx, sxx, sxy], -1), np.stack([sy, sxy, syy], -1)], 1)
    rhs = np.stack([sz, sxz, syz], -1)
    ok = cnt >= 5
    ok &= np.abs(np.linalg.det(np.where(ok[:, None, None], A, np.eye(3)))) > 1e-9
    if not ok.any():
        return np.nan, np.nan
    coef = np.linalg.solve(A[ok], rhs[ok][..., None])[..., 0]
    sse = szz[ok] - np.sum(coef * rhs[ok], axis=1)
    dof = n[ok] - 3
    sd = float(np.sqrt(max(np.sum(np.maximum(sse, 0.0)) / np.sum(dof), 0.0))) if np.sum(dof) > 0 else np.nan
    cells = groups[ok][:, :2]
    height = coef[:, 0]
    order = np.lexsort((cells[:, 1], cells[:, 0]))
    cells, height = cells[order], height[order]
    # |height difference| of every pair of lines in a cell, for the cells of each line count m
    same = np.r_[True, np.any(cells[1:] != cells[:-1], axis=1), True]
    bounds = np.flatnonzero(same)
    sizes = np.diff(bounds)
    diffs = []
    for m in np.unique(sizes[sizes > 1]):
        first, second = np.triu_indices(m, 1)
        h = height[bounds[:-1][sizes == m][:, None] + np.arange(m)]
        diffs.append(np.abs(h[:, first] - h[:, second]).ravel())
    dz = float(np.median(np.concatenate(diffs))) if diffs else np.nan
    return sd, dz


def _within(xy, columns, cx, cy, r):
    """Indices (ascending) of the points of ``xy`` within distance ``r`` of (cx, cy); only the
    columns of ``columns`` (a :class:`~vlsforest.extract.ColumnIndex` of ``xy``) around the
    disc are tested."""
    pad = r + 1e-6 + 1e-12 * max(abs(cx), abs(cy))  # the columns only pre-select: the disc test decides
    near = columns.box(cx - pad, cy - pad, cx + pad, cy + pad)
    dx, dy = xy[near, 0] - cx, xy[near, 1] - cy
    return np.sort(near[dx * dx + dy * dy <= r ** 2])


def tree_features(arrays: dict, labels: np.ndarray, trees: pd.DataFrame, columns=None) -> pd.DataFrame:
    """Observables of every tree (rows) — see the module docstring for the columns.

    Parameters
    ----------
    arrays : dict
        From :func:`cloud_arrays`.
    labels : ndarray of int
        Tree id per point (:func:`label_trees`).
    trees : pandas.DataFrame
        One row per tree with ``tree_id``, stem base ``x``, ``y``, ``z`` and ``crown_radius``
        (m; the column under the crown for the ground observables).
    columns : vlsforest.extract.ColumnIndex, optional
        A column index of the points' x, y (built here if not given; labelling can share it).

    Returns
    -------
    pandas.DataFrame
        Index ``tree_id``, columns :data:`FEATURES`; NaN where a tree has too few points.
    """
    from vlsforest.extract import ColumnIndex, stable_argsort
    from vlsforest.metrics import tree_metrics

    xyz = arrays["xyz"]
    n = len(xyz)
    if len(labels) != n:
        raise InputDataError(f"{len(labels)} labels for {n} points")
    rows = []
    order = stable_argsort(labels)
    bounds = np.searchsorted(labels[order], np.asarray(trees["tree_id"], np.int64), side="left")
    ends = np.searchsorted(labels[order], np.asarray(trees["tree_id"], np.int64), side="right")
    gsel = arrays["classification"] == 2
    gxyz = xyz[gsel]
    gline = np.asarray(arrays["point_source_id"])[gsel]
    gsingle = np.asarray(arrays["number_of_returns"])[gsel] == 1
    gnadir = np.abs(np.asarray(arrays["scan_angle"], np.float64)[gsel]) < ANGLE_SPLIT_DEG
    allxy = xyz[:, :2]
    columns = ColumnIndex(allxy) if columns is None else columns
    gcolumns = ColumnIndex(gxyz[:, :2])
    for (_, t), b, e in zip(trees.iterrows(), bounds, ends):
        idx = order[b:e]
        row = {"tree_id": int(t.tree_id)}
        if len(idx) < 20:
            rows.append(row)
            continue
        p = xyz[idx]
        rn = np.asarray(arrays["return_number"][idx], np.int64)
        nret = np.asarray(arrays["number_of_returns"][idx], np.int64)
        ang = np.abs(np.asarray(arrays["scan_angle"][idx], np.float64))
        key = _pulse_key(arrays, idx)
        m = tree_metrics(p, ground_z=float(t.z), return_number=rn, number_of_returns=nret,
                         gps_time=arrays["gps_time"][idx], point_source_id=arrays["point_source_id"][idx])
        row.update({k: float(m[k]) for k in STUDY_METRICS})
        _, row["returns_per_pulse"] = _multi_and_rpp(key, nret)
        for name, sel in (("rn1_share", rn == 1), ("rn2_share", rn == 2), ("rn3plus_share", rn >= 3)):
            row[name] = 100.0 * float(sel.mean())
        hf = p[rn == 1, 2] - float(t.z)
        row["first_p50"], row["first_p90"] = _pct(hf, 50), _pct(hf, 90)
        row["first_max"] = float(hf.max()) if len(hf) else np.nan
        inten = arrays["intensity"][idx]
        if np.isfinite(inten).all():
            row["int_floor"] = _pct(inten, 0.1)
            p10 = _pct(inten, 10)
            if p10 > 0:
                row["int_p01_rel"], row["int_p05_rel"] = _pct(inten, 1) / p10, _pct(inten, 5) / p10
        ie = _interecho(p, key, rn)
        if len(ie) >= 10:
            med, ie_p10, floor = np.percentile(ie, (50, 10, 1))  # one partition for the three
            row["interecho_median"], row["interecho_p10"], row["interecho_floor"] = float(med), float(ie_p10), float(floor)
            row["interecho_short_pct"] = 100.0 * float(np.mean(ie < SHORT_ECHO_M))
        for suffix, sel in (("nadir", ang < ANGLE_SPLIT_DEG), ("offnadir", ang >= ANGLE_SPLIT_DEG)):
            row[f"multi_pct_{suffix}"], row[f"rpp_{suffix}"] = _multi_and_rpp(key[sel], nret[sel])
        crown = p[p[:, 2] - float(t.z) >= row["cbh"]] if np.isfinite(row["cbh"]) else p
        if len(crown) >= 10:
            ex = np.percentile(crown[:, 0], 95) - np.percentile(crown[:, 0], 5)
            ey = np.percentile(crown[:, 1], 95) - np.percentile(crown[:, 1], 5)
            row["crown_extent_ratio"] = float(ex / ey) if ey > 0 else np.nan
        col = _within(allxy, columns, float(t.x), float(t.y), float(t.crown_radius))
        if len(col) >= 20:
            row["ground_share_pct"] = 100.0 * float(np.mean(arrays["classification"][col] == 2))
        gcol = _within(gxyz[:, :2], gcolumns, float(t.x), float(t.y), float(t.crown_radius) + GROUND_PAD_M)
        row["ground_dz_lines"] = _ground_stats(gxyz[gcol], gline[gcol])[1]
        gn, go = gcol[gnadir[gcol]], gcol[~gnadir[gcol]]
        row["ground_sd_nadir"] = sd_n = _ground_stats(gxyz[gn], gline[gn])[0]
        sd_o = _ground_stats(gxyz[go], gline[go])[0]
        if sd_n > 0 and sd_o > 0:  # NaN (too few echoes in a stratum) fails both
            row["ground_sd_growth"] = float(np.log(sd_o / sd_n))
        gs = gcol[gsingle[gcol]]
        row["ground_sd_single"], row["ground_dz_single"] = _ground_stats(gxyz[gs], gline[gs])
        rows.append(row)
    df = pd.DataFrame(rows).set_index("tree_id")
    return df.reindex(columns=list(FEATURES)).astype(float)


def tree_table(tree_points: dict, stems: pd.DataFrame) -> pd.DataFrame:
    """Trees for :func:`tree_features` from segmented TLS trees.

    Parameters
    ----------
    tree_points : dict int → ndarray (m, 3)
        TLS points of each tree.
    stems : pandas.DataFrame
        The segmentation's tree table (``tree_id``, ``x``, ``y``, ``z``).

    Returns
    -------
    pandas.DataFrame
        ``tree_id``, ``x``, ``y``, ``z``, ``crown_radius`` (half the mean horizontal 5–95 %
        extent of the tree's TLS points more than 2 m above its base, at least 1 m).
    """
    rows = []
    for _, s in stems.sort_values("tree_id").iterrows():
        tid = int(s.tree_id)
        if tid not in tree_points:
            continue
        p = np.asarray(tree_points[tid])
        up = p[p[:, 2] > float(s.z) + 2.0]
        if len(up) < 10:
            r = 1.0
        else:
            ext = np.percentile(up[:, :2], 95, axis=0) - np.percentile(up[:, :2], 5, axis=0)
            r = max(1.0, float(ext.mean()) / 2.0)
        rows.append({"tree_id": tid, "x": float(s.x), "y": float(s.y), "z": float(s.z), "crown_radius": r})
    return pd.DataFrame(rows, columns=["tree_id", "x", "y", "z", "crown_radius"])
