"""Tests of vlsforest.metrics and the ``vlsforest metrics`` command.

Analytic clouds (cylinder, cone with a stem, hand-made pulses) have known answers; the CBH
optimisations (directional bounds, hull vertices) are checked against brute-force
re-implementations of both CBH definitions on random and voxel-quantised trees.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.distance import pdist

from vlsforest.cli import main as cli_main
from vlsforest.errors import ConfigError, InputDataError
from vlsforest.io.las import PointCloud, read_las, write_las
from vlsforest.metrics import (
    CBH_SLICE,
    CBH_THRESHOLD,
    METRIC_COLUMNS,
    PERCENTILES,
    _diameter,
    cloud_metrics,
    tree_metrics,
    zpcum_lidr,
)

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"
UTM = np.array([481_234.0, 3_812_987.0, 0.0])


# ----------------------------------------------------------------------------- builders


def _ring(radius, z, n_theta, phase=0.0):
    t = phase + np.arange(n_theta) * (2 * np.pi / n_theta)
    return np.column_stack([radius * np.cos(t), radius * np.sin(t), np.full(n_theta, z)])


def _cylinder(r, h, n_theta=64, n_z=1001):
    zs = np.linspace(0.0, h, n_z)
    return np.concatenate([_ring(r, z, n_theta) for z in zs])


def _polygon_area(r, n):
    """Area of the regular n-gon inscribed in a circle of radius r."""
    return 0.5 * n * r * r * math.sin(2 * math.pi / n)


def _cone_tree(hc=4.0, hm=7.0, h=12.0, r_stem=0.2, r_max=2.0, dz=0.01, n_theta=64):
    """Stem of radius r_stem up to hc; crown radius linear r_stem→r_max (hc..hm), r_max→0 (hm..h)."""
    zs = np.round(np.arange(0.0, h + dz / 2, dz), 10)
    radius = np.where(
        zs < hc,
        r_stem,
        np.where(zs <= hm, r_stem + (r_max - r_stem) * (zs - hc) / (hm - hc), r_max * (h - zs) / (h - hm)),
    )
    pts = np.concatenate([_ring(r, z, n_theta) for r, z in zip(radius, zs)])
    return pts, zs, radius


def _random_tree(rng, n=3000, height=18.0, quantise=None):
    """A stem, an ellipsoidal crown and a few ground points (seeded)."""
    n_stem, n_ground = n // 6, n // 20
    n_crown = n - n_stem - n_ground
    zc0 = rng.uniform(3.0, 8.0)
    t = rng.uniform(0, 2 * np.pi, n_stem)
    stem = np.column_stack([0.15 * np.cos(t), 0.15 * np.sin(t), rng.uniform(0, zc0, n_stem)])
    u = rng.normal(size=(n_crown, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    a, c = rng.uniform(1.0, 3.0), (height - zc0) / 2
    crown = u * np.array([a, a * rng.uniform(0.7, 1.0), c]) + np.array([0, 0, zc0 + c])
    ground = np.column_stack([rng.uniform(-3, 3, (n_ground, 2)), rng.uniform(-0.05, 0.05, n_ground)])
    pts = np.concatenate([stem, crown, ground])
    if quantise:
        pts = np.round(pts / quantise) * quantise
    return pts


def _ref_cbh_paper(xy, z):
    """Brute force: first 0.1 m slice whose max pairwise xy distance exceeds 1.5 m."""
    k = np.maximum(np.floor(np.round(z / CBH_SLICE, 9)), 0).astype(int)
    for kk in np.unique(k):
        m = k == kk
        if m.sum() >= 2 and pdist(xy[m]).max() > CBH_THRESHOLD:
            return (kk + 0.5) * CBH_SLICE
    return 0.0


def _ref_cbh_authors(xy, z):
    """Literal reading of metrics.md §4 (authors' compute_cbh), with pdist over all points."""
    dz = 0.1
    num = math.ceil(np.max(z) / dz)
    lim = np.arange(0, dz * num, dz)
    centres = np.arange(dz / 2, dz * num + dz / 2, dz)
    w = np.zeros(len(centres))
    for i in range(min(len(lim), len(centres))):
        if i == 0:
            if len(lim) < 2:
                break
            m = z <= lim[1]
        else:
            m = (z > lim[i - 1]) & (z <= lim[i])
        if m.sum() > 2:
            w[i] = pdist(xy[m]).max()
    start = 0
    for i, d in enumerate(w):
        if d <= 1.3 and i > 10:
            start = i
            break
    thr = 1.0 + (0.5 if np.max(z) > 15 else 0.0)
    for i, d in enumerate(w):
        if i > start and d >= thr and d > w[i - 1]:
            return float(centres[i])
    return 0.0


# ----------------------------------------------------------------------------- analytic clouds


def test_columns_and_order():
    m = tree_metrics(_cylinder(1.0, 5.0, n_theta=16, n_z=51))
    assert tuple(m) == METRIC_COLUMNS
    assert METRIC_COLUMNS[0] == "n_points"
    assert [c for c in METRIC_COLUMNS if c.startswith("p")] == [f"p{p:02d}" for p in PERCENTILES]
    assert [c for c in METRIC_COLUMNS if c.startswith("dens")] == [f"dens_{k:02d}" for k in range(1, 11)]
    assert METRIC_COLUMNS[-4:] == ("multi_return_pct", "height", "cbh", "cpa")


@pytest.mark.parametrize("r", [1.0, 2.5])
def test_cylinder(r):
    h, n_theta, n_z = 10.0, 64, 1001
    pts = _cylinder(r, h, n_theta, n_z) + UTM  # real-world coordinates: checks the centring
    m = tree_metrics(pts, ground_z=0.0)
    n = n_theta * n_z
    assert m["n_points"] == n
    assert m["hmin"] == 0.0 and m["height"] == pytest.approx(h, abs=1e-12)
    assert m["hmean"] == pytest.approx(h / 2, abs=1e-9)
    # discrete uniform heights on a regular grid: var = h² (n_z+1) / (12 (n_z-1)) (ddof=0)
    var0 = h * h * (n_z + 1) / (12 * (n_z - 1))
    assert m["hsd"] == pytest.approx(math.sqrt(var0 * n / (n - 1)), rel=1e-9)
    assert m["hsd"] == pytest.approx(h / math.sqrt(12), rel=2e-3)
    for p in PERCENTILES:  # uniform: p-th percentile = p·h/100 within one grid step
        assert abs(m[f"p{p:02d}"] - p * h / 100) <= h / (n_z - 1)
    # 2r > 1.5: the very first slice is wider than the threshold
    assert m["cbh"] == pytest.approx(0.05)
    poly = _polygon_area(r, n_theta)
    assert m["cpa"] == pytest.approx(poly, rel=1e-9)
    assert poly < m["cpa"] * (1 + 1e-9) <= math.pi * r * r
    # inscribed-polygon bound: πr² − area ≤ πr² (1 − sin(2π/n) / (2π/n))
    step = 2 * math.pi / n_theta
    assert math.pi * r * r - m["cpa"] <= math.pi * r * r * (1 - math.sin(step) / step) + 1e-9
    # densities: ten equal shares, the top ring counted in bin 10
    assert sum(m[f"dens_{k:02d}"] for k in range(1, 11)) == pytest.approx(100.0)
    assert m["dens_01"] == pytest.approx(100 * 100 * n_theta / n)
    assert m["dens_10"] == pytest.approx(100 * 101 * n_theta / n)


def test_cylinder_random_angles_area_bound():
    rng = np.random.default_rng(3)
    r, h = 1.2, 6.0
    t = rng.uniform(0, 2 * np.pi, 20000)
    pts = np.column_stack([r * np.cos(t), r * np.sin(t), rng.uniform(0, h, t.size)])
    m = tree_metrics(pts)
    assert 0.999 * math.pi * r * r < m["cpa"] <= math.pi * r * r
    assert m["hsd"] == pytest.approx(h / math.sqrt(12), rel=0.02)
    assert m["cbh"] == pytest.approx(0.05)


def test_thin_cylinder_has_no_crown():
    r, h = 0.5, 8.0  # 2r = 1.0 < 1.5: no slice qualifies
    pts = _cylinder(r, h, 32, 401)
    m = tree_metrics(pts, ground_z=-1.0)  # heights shift by +1
    assert m["cbh"] == 0.0
    assert m["cpa"] == pytest.approx(_polygon_area(r, 32), rel=1e-9)  # hull of all points
    assert m["hmin"] == pytest.approx(1.0) and m["height"] == pytest.approx(h + 1.0)


def test_cone_crown_base():
    hc, hm, h, r0, rmax = 4.0, 7.0, 12.0, 0.2, 2.0
    pts, zs, radius = _cone_tree(hc, hm, h, r0, rmax)
    m = tree_metrics(pts)
    # crown width 2·radius exceeds 1.5 m above z* (analytic); the first ring level above z*
    # is in the slice whose centre is the CBH
    z_star = hc + (0.75 - r0) / (rmax - r0) * (hm - hc)
    first_level = zs[zs > z_star + 1e-12][0]
    expected = (math.floor(round(first_level / 0.1, 9)) + 0.5) * 0.1
    assert hc < expected < hm
    assert m["cbh"] == pytest.approx(expected, abs=1e-12)
    assert m["height"] == pytest.approx(h)
    # crown points z >= CBH include the widest ring (radius rmax at hm)
    assert m["cpa"] == pytest.approx(_polygon_area(rmax, 64), rel=1e-9)
    # authors' convention on the same tree: brute reference, threshold 1.0 m (tree <= 15 m)
    ma = tree_metrics(pts, cbh_convention="authors")
    assert ma["cbh"] == pytest.approx(_ref_cbh_authors(pts[:, :2], pts[:, 2]), abs=1e-12)
    z_star_a = hc + (0.5 - r0) / (rmax - r0) * (hm - hc)
    assert z_star_a < ma["cbh"] < z_star_a + 0.2
    # everything but cbh/cpa is convention independent
    for c in METRIC_COLUMNS:
        if c not in ("cbh", "cpa"):
            assert ma[c] == m[c] or (np.isnan(ma[c]) and np.isnan(m[c]))


def test_tall_cone_authors_threshold():
    # taller than 15 m: the authors' threshold becomes 1.5 m
    pts, _, _ = _cone_tree(hc=6.0, hm=10.0, h=18.0, dz=0.02, n_theta=32)
    ma = tree_metrics(pts, cbh_convention="authors")
    ref = _ref_cbh_authors(pts[:, :2], pts[:, 2])
    assert ma["cbh"] == pytest.approx(ref, abs=1e-12)
    assert ma["cbh"] > 6.0


def test_cpa_uses_points_at_or_above_cbh():
    # upright cone crown, widest at its base: the rings below the CBH slice centre are not crown
    zs = np.round(np.arange(0.0, 10.0 + 0.005, 0.01), 10)
    radius = np.where(zs < 3.0, 0.1, 2.0 * (10.0 - zs) / 7.0)
    pts = np.concatenate([_ring(r, z, 64) for r, z in zip(radius, zs)])
    m = tree_metrics(pts)
    first = zs[radius * 2 > 1.5][0]  # first ring wider than 1.5 m (the crown base ring)
    assert m["cbh"] == pytest.approx((math.floor(round(first / 0.1, 9)) + 0.5) * 0.1, abs=1e-12)
    widest_crown_ring = radius[zs >= m["cbh"]].max()
    assert widest_crown_ring < radius[zs == first][0]
    assert m["cpa"] == pytest.approx(_polygon_area(widest_crown_ring, 64), rel=1e-9)


def test_cpa_falls_back_to_all_points():
    # a thin pole with three far-apart points in the top slice: CBH = top slice centre, only
    # those 3 points at or above it (≤ 3) → CPA = hull of all points
    pole = _cylinder(0.5, 5.0, 16, 51)
    top = np.array([[-1.0, 0.0, 6.06], [1.0, 0.0, 6.07], [0.0, 0.2, 6.08]])
    pts = np.concatenate([pole, top])
    m = tree_metrics(pts)
    assert m["cbh"] == pytest.approx(6.05)
    from scipy.spatial import ConvexHull

    assert m["cpa"] == pytest.approx(ConvexHull(pts[:, :2]).volume, rel=1e-12)
    assert m["cpa"] > _polygon_area(0.5, 16)


def test_authors_rules_ground_skip_and_widening():
    def rings(spec, n_theta=32, dz=0.02):
        out = []
        for z0, z1, r in spec:
            for z in np.round(np.arange(z0, z1 - 1e-9, dz), 10):
                out.append(_ring(r, z + dz / 2, n_theta))
        return np.concatenate(out)

    # ground skip: a narrow base (slices < 10), a wide understorey layer, a narrow stem, a crown
    pts = rings([(0.0, 0.5, 0.15), (0.5, 1.5, 1.5), (1.5, 5.0, 0.15), (5.0, 9.0, 2.0)])
    ma = tree_metrics(pts, cbh_convention="authors")
    assert ma["cbh"] == pytest.approx(_ref_cbh_authors(pts[:, :2], pts[:, 2]), abs=1e-12)
    assert 5.0 < ma["cbh"] < 5.3  # the understorey below slice 11 is skipped
    assert tree_metrics(pts)["cbh"] < 0.7  # the paper's rule has no skip: understorey counts
    # widening rule (tree <= 15 m, threshold 1.0): a 1.2 m wide stem (<= 1.3 → ground skip
    # at slice 11) then 1.1 m: both >= 1.0 but never wider than the slice below
    pts = rings([(0.0, 3.0, 0.6), (3.0, 5.0, 0.55), (5.0, 8.0, 1.5)])
    ma = tree_metrics(pts, cbh_convention="authors")
    assert ma["cbh"] == pytest.approx(_ref_cbh_authors(pts[:, :2], pts[:, 2]), abs=1e-12)
    assert 5.0 < ma["cbh"] < 5.3


def test_densities_hand_count():
    rng = np.random.default_rng(11)
    z = np.concatenate([rng.uniform(-0.3, 9.0, 200), [9.0, 10.0]])  # top point 10.0
    xyz = np.column_stack([rng.normal(size=z.size), rng.normal(size=z.size), z])
    m = tree_metrics(xyz)
    hmax = 10.0
    counts = [0] * 10
    for v in z:
        for k in range(10):
            lo, hi = k * hmax / 10, (k + 1) * hmax / 10
            if (lo <= v < hi) or (k == 0 and v < lo) or (k == 9 and v == hmax):
                counts[k] += 1
                break
    dens = [m[f"dens_{k:02d}"] for k in range(1, 11)]
    assert dens == pytest.approx([100 * c / z.size for c in counts])
    assert sum(dens) == pytest.approx(100.0)
    # the same hand count on exact bin edges: 0, 1, …, 10 → one per bin, two in bin 10
    z = np.arange(11.0)
    m = tree_metrics(np.column_stack([z, z * 0, z]))
    edge = [1] * 9 + [2]
    assert [m[f"dens_{k:02d}"] for k in range(1, 11)] == pytest.approx([100 * c / 11 for c in edge])


def test_zpcum_lidr():
    z = np.arange(11.0)  # z=0 dropped (z > 0), z=10 = zmax dropped (interval 11)
    counts = np.array([0] + [1] * 9, float)  # z=k lands in bin k+1
    assert zpcum_lidr(z) == pytest.approx(np.cumsum(counts / counts.sum() * 100)[:9])
    assert np.all(zpcum_lidr([-1.0, -0.5, 0.0]) == 0)  # zmax <= zmin
    # against a naive "share <= k·zmax/10" it is close but not equal on random data
    rng = np.random.default_rng(5)
    z = rng.uniform(0, 20, 5000)
    naive = np.array([np.mean(z <= k * z.max() / 10) * 100 for k in range(1, 10)])
    assert np.max(np.abs(zpcum_lidr(z) - naive)) < 0.5


# ----------------------------------------------------------------------------- multi-return


def _pulses():
    # (gps_time, point_source_id, return_number, number_of_returns)
    rows = [
        (1.0, 1, 1, 3), (1.0, 1, 2, 3), (1.0, 1, 3, 3),  # A: complete 3-return pulse
        (1.0, 2, 1, 1),                                   # B: same time, other source
        (2.0, 1, 2, 2),                                   # C: partial, only its 2nd return
        (3.0, 1, 1, 1),                                   # D: single
        (4.0, 1, 1, 2),                                   # E: partial, only its 1st return
    ]  # fmt: skip
    a = np.array(rows)
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(len(a), 3)) + [0, 0, 5]
    return xyz, dict(gps_time=a[:, 0], point_source_id=a[:, 1].astype(int),
                     return_number=a[:, 2].astype(int), number_of_returns=a[:, 3].astype(int))


def test_multi_return_definitions():
    xyz, kw = _pulses()
    pulse = tree_metrics(xyz, **kw)["multi_return_pct"]
    assert pulse == pytest.approx(100 * 3 / 5)  # A, C, E of A..E
    first = tree_metrics(xyz, multi_return="first_return", **kw)["multi_return_pct"]
    assert first == pytest.approx(100 * 2 / 4)  # first returns A1, B, D, E; multi: A1, E
    per = tree_metrics(xyz, multi_return="per_return", **kw)["multi_return_pct"]
    assert per == pytest.approx(100 * 5 / 7)  # A×3, C, E of 7 points
    # without a point source id, A and B share a GPS time and are one pulse
    kw2 = dict(kw, point_source_id=None)
    assert tree_metrics(xyz, **kw2)["multi_return_pct"] == pytest.approx(100 * 3 / 4)
    # permuting the points changes nothing
    perm = np.random.default_rng(1).permutation(len(xyz))
    kw3 = {k: v[perm] for k, v in kw.items()}
    assert tree_metrics(xyz[perm], **kw3)["multi_return_pct"] == pytest.approx(pulse)
    # missing information → NaN
    assert np.isnan(tree_metrics(xyz, number_of_returns=kw["number_of_returns"])["multi_return_pct"])
    assert np.isnan(tree_metrics(xyz, gps_time=kw["gps_time"])["multi_return_pct"])
    # no first return in the subset → NaN for first_return
    sel = kw["return_number"] > 1
    kw4 = {k: v[sel] for k, v in kw.items()}
    assert np.isnan(tree_metrics(xyz[sel], multi_return="first_return", **kw4)["multi_return_pct"])


def test_per_return_at_least_pulse():
    rng = np.random.default_rng(21)
    gps, nor, rn = [], [], []
    for p in range(400):
        k = int(rng.integers(1, 5))
        present = [r for r in range(1, k + 1) if rng.random() < 0.6] or [1]
        for r in present:
            gps.append(float(p))
            nor.append(k)
            rn.append(r)
    gps, nor, rn = map(np.array, (gps, nor, rn))
    xyz = np.column_stack([rng.normal(size=(gps.size, 2)), rng.uniform(0, 20, gps.size)])
    kw = dict(gps_time=gps, number_of_returns=nor, return_number=rn)
    pulse = tree_metrics(xyz, **kw)["multi_return_pct"]
    per = tree_metrics(xyz, multi_return="per_return", **kw)["multi_return_pct"]
    # brute force over pulses
    multi = {g for g, k in zip(gps, nor) if k > 1}
    assert pulse == pytest.approx(100 * len(multi) / len(set(gps)))
    assert per == pytest.approx(100 * np.mean(nor > 1))
    assert per > pulse  # some multi-return pulses contribute several points


# ----------------------------------------------------------------------------- CBH vs brute force


@pytest.mark.parametrize("seed", range(6))
def test_cbh_matches_brute_force(seed):
    rng = np.random.default_rng(seed)
    quant = (None, 0.25, 0.1)[seed % 3]  # voxel-like clouds have collinear/duplicate slices
    pts = _random_tree(rng, n=2500, height=rng.uniform(8, 25), quantise=quant)
    m = tree_metrics(pts)
    ma = tree_metrics(pts, cbh_convention="authors")
    assert m["cbh"] == pytest.approx(_ref_cbh_paper(pts[:, :2], pts[:, 2]), abs=1e-12)
    assert ma["cbh"] == pytest.approx(_ref_cbh_authors(pts[:, :2], pts[:, 2]), abs=1e-12)
    # CPA: hull of the points at or above CBH (brute: sample-based upper/lower checks)
    crown = pts[pts[:, 2] >= m["cbh"], :2]
    from scipy.spatial import ConvexHull

    assert m["cpa"] == pytest.approx(ConvexHull(crown - crown.mean(0)).volume, rel=1e-12)


def test_collinear_slice_fallback():
    # points on a line at 11.25° (between the bound directions), length 1.51 > 1.5:
    # the bounds cannot decide, Qhull fails (collinear), brute force must find 1.51
    t = np.linspace(0.0, 1.51, 40)
    d = np.array([math.cos(math.pi / 16), math.sin(math.pi / 16)])
    xy = t[:, None] * d
    assert _diameter(xy) == pytest.approx(1.51, rel=1e-12)
    xyz = np.column_stack([xy, np.full(40, 0.02)])
    top = np.array([[0.0, 0.0, 3.0]])
    m = tree_metrics(np.concatenate([xyz, top]))
    assert m["cbh"] == pytest.approx(0.05)
    assert m["cpa"] == 0.0  # crown (z >= 0.05) is one point → all points, collinear
    # shorter than the threshold: no crown
    m2 = tree_metrics(np.concatenate([xyz * [0.99, 0.99, 1], top]))
    assert m2["cbh"] == 0.0
    # duplicate-only slice: width 0
    assert _diameter(np.zeros((30, 2))) == 0.0


# ----------------------------------------------------------------------------- edge cases


def test_single_point():
    m = tree_metrics(np.array([[5.0, 6.0, 7.5]]), ground_z=0.5)
    assert m["n_points"] == 1
    assert np.isnan(m["hsd"])
    assert all(m[f"p{p:02d}"] == pytest.approx(7.0) for p in PERCENTILES)
    assert m["hmin"] == m["hmean"] == m["height"] == pytest.approx(7.0)
    assert m["cbh"] == 0.0 and m["cpa"] == 0.0
    assert m["dens_10"] == pytest.approx(100.0)


def test_two_points():
    xyz = np.array([[0.0, 0.0, 0.02], [2.0, 0.0, 0.04]])  # same slice, 2 m apart
    m = tree_metrics(xyz)
    assert m["hsd"] == pytest.approx(np.std([0.02, 0.04], ddof=1))
    assert m["p50"] == pytest.approx(0.03)
    assert m["cbh"] == pytest.approx(0.05)
    assert m["cpa"] == 0.0
    # the authors' code needs > 2 points per slice and a tree taller than 0.1 m
    assert tree_metrics(xyz, cbh_convention="authors")["cbh"] == 0.0


def test_collinear_tree_and_flat_crown():
    # a vertical line of points: no width anywhere, no area
    z = np.linspace(0, 10, 200)
    m = tree_metrics(np.column_stack([np.zeros_like(z), np.zeros_like(z), z]))
    assert m["cbh"] == 0.0 and m["cpa"] == 0.0
    assert m["hsd"] == pytest.approx(np.std(z, ddof=1))
    # all points at one height: flat crown
    rng = np.random.default_rng(2)
    xy = rng.uniform(-2, 2, (500, 2))
    m = tree_metrics(np.column_stack([xy, np.full(500, 8.0)]))
    assert m["hsd"] == 0.0
    assert m["dens_10"] == pytest.approx(100.0)
    assert m["cbh"] == pytest.approx((math.floor(8.0 / 0.1 + 1e-9) + 0.5) * 0.1)
    assert m["cpa"] > 0
    # everything at the ground: bin 1 holds all
    m = tree_metrics(np.column_stack([xy, np.zeros(500)]))
    assert m["dens_01"] == pytest.approx(100.0) and m["height"] == 0.0
    assert m["cbh"] == pytest.approx(0.05)
    assert tree_metrics(np.column_stack([xy, np.zeros(500)]), cbh_convention="authors")["cbh"] == 0.0


def test_nan_and_bad_options():
    xyz = np.array([[0.0, 0.0, 1.0], [np.nan, 0.0, 2.0]])
    with pytest.raises(InputDataError, match="my-tree"):
        tree_metrics(xyz, source="my-tree")
    with pytest.raises(ConfigError, match="multi_return"):
        tree_metrics(xyz[:1], multi_return="bogus")
    with pytest.raises(ConfigError, match="cbh_convention"):
        tree_metrics(xyz[:1], cbh_convention="bogus")
    with pytest.raises(InputDataError, match="gps_time"):
        tree_metrics(xyz[:1], gps_time=[1.0, 2.0])
    cloud = PointCloud(xyz, {"tid": np.array([1.0, 1.0])})
    with pytest.raises(InputDataError, match="plot.laz"):
        cloud_metrics(cloud, "tid", source="plot.laz")
    with pytest.raises(InputDataError, match="'treeID'"):
        cloud_metrics(PointCloud(xyz[:1], {"tid": np.ones(1)}), "treeID", source="plot.laz")


# ----------------------------------------------------------------------------- cloud_metrics


def _labelled_cloud(seed=0):
    rng = np.random.default_rng(seed)
    parts, ids, gz = [], [], {}
    for tid, dx in ((7, 0.0), (3, 10.0), (12, 20.0)):
        p = _random_tree(rng, n=800, height=12.0 + tid) + [dx, 0, 100.0 + tid]
        parts.append(p)
        ids.append(np.full(len(p), float(tid)))
        gz[tid] = 100.0 + tid
    noise = rng.uniform(0, 20, (50, 3))
    parts.append(noise)
    ids.append(np.where(np.arange(50) % 2 == 0, np.nan, 1.7976931348623157e308))
    xyz = np.concatenate(parts)
    n = len(xyz)
    attrs = {
        "tid": np.concatenate(ids),
        "gps_time": np.arange(n, dtype=float) // 2,
        "number_of_returns": (np.arange(n) % 3 + 1).astype(np.uint8),
        "return_number": np.ones(n, np.uint8),
        "point_source_id": np.ones(n, np.uint16),
    }
    return PointCloud(xyz, attrs), gz


def test_cloud_metrics_groups_and_ground():
    cloud, gz = _labelled_cloud()
    df = cloud_metrics(cloud, "tid", ground_z=gz)
    assert list(df.columns) == ["tree_id", *METRIC_COLUMNS]
    assert df["tree_id"].tolist() == [3, 7, 12]
    assert df["tree_id"].dtype == np.int64 and df["n_points"].dtype == np.int64
    for _, row in df.iterrows():
        sel = cloud.attrs["tid"] == row["tree_id"]
        ref = tree_metrics(
            cloud.xyz[sel],
            ground_z=gz[int(row["tree_id"])],
            **{k: cloud.attrs[k][sel] for k in ("gps_time", "number_of_returns", "return_number", "point_source_id")},
        )
        for c in METRIC_COLUMNS:
            assert row[c] == pytest.approx(ref[c], nan_ok=True)
        assert -0.05 <= row["hmin"] < 0.1  # ground_z mapping normalised each tree (ground ±0.05)
    assert df["n_points"].sum() == np.sum(np.isfinite(cloud.attrs["tid"]) & (cloud.attrs["tid"] < 1e300))
    # a scalar ground shifts every height
    df0 = cloud_metrics(cloud, "tid", ground_z=0.0)
    assert (df0["height"] - df["height"]).tolist() == pytest.approx([103.0, 107.0, 112.0])
    with pytest.raises(ConfigError, match="tree 12"):
        cloud_metrics(cloud, "tid", ground_z={3: 0.0, 7: 0.0})


def test_cloud_metrics_empty_requested_tree_and_float_ids():
    cloud, gz = _labelled_cloud()
    df = cloud_metrics(cloud, "tid", tree_ids=[12, 99, 3], ground_z=0.0)
    assert df["tree_id"].tolist() == [3, 12, 99]
    empty = df[df["tree_id"] == 99].iloc[0]
    assert empty["n_points"] == 0
    assert all(np.isnan(empty[c]) for c in METRIC_COLUMNS if c != "n_points")
    cloud.attrs["tid"] = np.where(cloud.attrs["tid"] == 3, 3.5, cloud.attrs["tid"])
    df = cloud_metrics(cloud, "tid")
    assert df["tree_id"].dtype == np.float64 and df["tree_id"].tolist() == [3.5, 7.0, 12.0]


def test_cloud_metrics_warns_once_without_gps():
    cloud, _ = _labelled_cloud()
    cloud.attrs["gps_time"] = np.zeros(len(cloud))  # not recorded
    with pytest.warns(UserWarning, match="gps_time") as rec:
        df = cloud_metrics(cloud, "tid", source="x.laz")
    assert len([w for w in rec if issubclass(w.category, UserWarning)]) == 1
    assert df["multi_return_pct"].isna().all()
    # per_return needs number_of_returns only
    df = cloud_metrics(cloud, "tid", multi_return="per_return")
    assert df["multi_return_pct"].notna().all()


# ----------------------------------------------------------------------------- CLI


def test_cli_end_to_end(tmp_path, capsys):
    cloud, _ = _labelled_cloud(seed=4)
    las = write_las(tmp_path / "plot.laz", cloud)
    out = tmp_path / "m.csv"
    rc = cli_main(["metrics", str(las), "--tree-id", "tid", "-o", str(out)])
    assert rc == 0
    df = pd.read_csv(out)
    assert list(df.columns) == ["tree_id", *METRIC_COLUMNS]
    ref = cloud_metrics(read_las(las), "tid")
    assert df["tree_id"].tolist() == ref["tree_id"].tolist() == [3, 7, 12]
    for c in METRIC_COLUMNS:
        assert np.allclose(df[c], ref[c], atol=1e-6, rtol=0, equal_nan=True)
    first = out.read_bytes()
    assert cli_main(["metrics", str(las), "--tree-id", "tid", "-o", str(out)]) == 0
    assert out.read_bytes() == first  # deterministic
    # options reach the computation
    out2 = tmp_path / "m2.csv"
    rc = cli_main(["metrics", str(las), "--tree-id", "tid", "--ground-z", "100", "-o", str(out2),
                   "--multi-return", "per_return", "--cbh-convention", "authors"])  # fmt: skip
    assert rc == 0
    df2 = pd.read_csv(out2)
    assert np.allclose(df2["height"], df["height"] - 100, atol=2e-6)
    ref2 = cloud_metrics(read_las(las), "tid", ground_z=100.0, multi_return="per_return", cbh_convention="authors")
    assert np.allclose(df2["cbh"], ref2["cbh"], atol=1e-6)
    assert np.allclose(df2["multi_return_pct"], ref2["multi_return_pct"], atol=1e-6)


def test_cli_errors_and_warning(tmp_path, capsys):
    cloud, _ = _labelled_cloud(seed=1)
    del cloud.attrs["gps_time"]  # written as zeros → not recorded
    las = write_las(tmp_path / "nogps.las", cloud)
    out = tmp_path / "m.csv"
    capsys.readouterr()
    rc = cli_main(["metrics", str(las), "--tree-id", "treeID", "-o", str(out)])
    err = capsys.readouterr().err
    assert rc == 2
    assert "nogps.las" in err and "treeID" in err and "Traceback" not in err
    assert not out.exists()
    rc = cli_main(["metrics", str(las), "--tree-id", "tid", "-o", str(out)])
    err = capsys.readouterr().err
    assert rc == 0
    assert err.count("vlsforest metrics: warning:") == 1 and "gps_time" in err
    assert pd.read_csv(out)["multi_return_pct"].isna().all()
    rc = cli_main(["metrics", str(tmp_path / "absent.laz"), "--tree-id", "tid", "-o", str(out)])
    assert rc == 2 and "absent.laz" in capsys.readouterr().err


# ----------------------------------------------------------------------------- real data


@pytest.mark.realdata
def test_real_mixedconifer(tmp_path):
    path = REAL / "MixedConifer.laz"
    if not path.is_file():
        pytest.skip(f"real data absent: {path}")
    cloud = read_las(path)
    tid = cloud.attrs["treeID"]
    valid = np.isfinite(tid) & (tid < 1e300)
    labels = np.unique(tid[valid])
    df = cloud_metrics(cloud, "treeID", source=str(path))
    assert len(df) == len(labels)
    assert df["tree_id"].tolist() == labels.astype(int).tolist()
    assert df["n_points"].sum() == valid.sum()
    assert np.isfinite(df["height"]).all()
    dens = df[[f"dens_{k:02d}" for k in range(1, 11)]].sum(axis=1)
    assert np.allclose(dens, 100.0)
    assert (df["height"] == [tid_max for tid_max in (cloud.xyz[tid == t, 2].max() for t in labels)]).all()
    assert ((df["cbh"] >= 0) & (df["cbh"] <= df["height"] + 0.1)).all()
    assert (df["cpa"] >= 0).all() and np.isfinite(df["cpa"]).all()
    # first returns only: each pulse has exactly one point here, so the three definitions agree
    assert (cloud.attrs["return_number"] == 1).all()
    for mode in ("first_return", "per_return"):
        other = cloud_metrics(cloud, "treeID", multi_return=mode)
        assert np.allclose(other["multi_return_pct"], df["multi_return_pct"])
    authors = cloud_metrics(cloud, "treeID", cbh_convention="authors")
    assert np.isfinite(authors["cbh"]).all()
    # CLI on the real file
    out = tmp_path / "mc.csv"
    assert cli_main(["metrics", str(path), "--tree-id", "treeID", "-o", str(out)]) == 0
    assert len(pd.read_csv(out)) == len(labels)
