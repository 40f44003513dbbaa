"""Tests of vlsforest.pad: G(θ), the voxel traversal, the PAD estimators, loading and validation."""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from vlsforest.errors import ConfigError, InputDataError
from vlsforest.pad import (
    FLAG_CLIPPED,
    FLAG_FEW_PULSES,
    FLAG_SATURATED,
    FLAG_UNSAMPLED,
    LAD_NAMES,
    TlsScan,
    accumulate,
    estimate_pad,
    g_function,
    grid_for_scans,
    leaf_inclination_pdf,
    load_tls_scans,
    pad_to_vox,
)
from vlsforest.pad_validation import TABLE_COLUMNS, median_abs_bias

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"


# ----------------------------------------------------------------------------- helpers


def _scan(origin, direction, echoes=None, hit=None, divergence=0.0):
    """A TlsScan from per-shot origins/directions and per-shot lists of echo ranges (equal weights)."""
    direction = np.asarray(direction, float)
    direction = direction / np.linalg.norm(direction, axis=1)[:, None]
    n = len(direction)
    origin = np.broadcast_to(np.asarray(origin, float), (n, 3)).copy()
    echoes = echoes if echoes is not None else [[] for _ in range(n)]
    counts = np.array([len(e) for e in echoes])
    ptr = np.zeros(n + 1, np.int64)
    ptr[1:] = np.cumsum(counts)
    rng = np.array([r for e in echoes for r in sorted(e)], float)
    w = np.repeat(1.0 / np.maximum(counts, 1), counts)
    h = np.ones(len(rng), bool) if hit is None else np.asarray(hit, bool)
    return TlsScan(1, "test", origin, direction, ptr, rng, w, h, beam_divergence_rad=divergence, empty_shots=True)


# ----------------------------------------------------------------------------- G(θ)

# fixtures of the reference notes (adaptive quadrature), θ in degrees
G_FIXTURES = {
    "planophile": [0.8488, 0.7381, 0.4988, 0.3409, 0.2702],
    "erectophile": [0.4244, 0.4514, 0.5037, 0.5316, 0.5404],
    "plagiophile": [0.6791, 0.5990, 0.4810, 0.4408, 0.4323],
    "extremophile": [0.5942, 0.5905, 0.5215, 0.4317, 0.3783],
    "uniform": [0.6366, 0.5947, 0.5013, 0.4363, 0.4053],
}


@pytest.mark.parametrize("lad", sorted(G_FIXTURES))
def test_g_function_fixtures(lad):
    got = g_function([0.0, 30.0, 57.3, 75.0, 90.0], lad)
    np.testing.assert_allclose(got, G_FIXTURES[lad], atol=1.2e-4)


def test_g_function_closed_forms():
    pi = math.pi
    closed = {  # G(0) = ∫cos θL f, G(90°) = (2/π)∫sin θL f
        "planophile": (8 / (3 * pi), 8 / (3 * pi ** 2)),
        "erectophile": (4 / (3 * pi), 16 / (3 * pi ** 2)),
        "plagiophile": (32 / (15 * pi), 64 / (15 * pi ** 2)),
        "extremophile": (28 / (15 * pi), 56 / (15 * pi ** 2)),
        "uniform": (2 / pi, 4 / pi ** 2),
        "spherical": (0.5, 0.5),
    }
    for lad, (g0, g90) in closed.items():
        assert g_function(0.0, lad) == pytest.approx(g0, abs=1e-6), lad
        assert g_function(90.0, lad) == pytest.approx(g90, abs=1e-6), lad
    # spherical is 0.5 at every angle; upward beams fold onto downward ones
    np.testing.assert_allclose(g_function(np.linspace(0, 180, 37), "spherical"), 0.5, atol=1e-12)
    th = np.array([5.0, 33.3, 61.0, 89.9])
    for lad in LAD_NAMES:
        np.testing.assert_allclose(g_function(180.0 - th, lad), g_function(th, lad), atol=1e-12)


def test_g_function_mean_over_sphere_is_half():
    # any leaf angle distribution: the hemispherical mean of G, ∫ G(θ) sin θ dθ over [0, π/2], is 1/2
    x, w = np.polynomial.legendre.leggauss(200)
    th = 0.25 * np.pi * (x + 1.0)
    for lad in LAD_NAMES:
        mean = 0.25 * np.pi * np.sum(w * g_function(np.degrees(th), lad) * np.sin(th))
        assert mean == pytest.approx(0.5, abs=2e-4), lad
        dens = 0.25 * np.pi * np.sum(w * leaf_inclination_pdf(lad, th))
        assert dens == pytest.approx(1.0, abs=1e-10), lad


def test_g_function_errors():
    with pytest.raises(ConfigError, match="lad"):
        g_function(10.0, "banana")
    with pytest.raises(ConfigError, match="theta_deg"):
        g_function(200.0, "planophile")
    assert math.isnan(g_function(float("nan"), "planophile"))


# ----------------------------------------------------------------------------- traversal


def _brute_force_lengths(scan, origin, s, shape, dt=2e-4):
    """Per-voxel path length and shot count by fine sampling along shots without echoes."""
    lg = np.zeros(shape)
    nb = np.zeros(shape, int)
    for i in range(scan.n_shots):
        t = np.arange(dt / 2, 12.0, dt)
        p = scan.origin[i] + t[:, None] * scan.direction[i]
        c = np.floor((p - origin) / s).astype(int)
        c = c[np.all((c >= 0) & (c < shape), axis=1)]
        np.add.at(lg, tuple(c.T), dt)
        u = np.unique(c, axis=0)
        nb[tuple(u.T)] += 1
    return lg, nb


def test_traversal_matches_brute_force_inside_and_outside_origins():
    rng = np.random.default_rng(7)
    n = 120
    o = rng.uniform(-1.5, 3.5, (n, 3))  # many origins outside the grid (AMAPVox issue #9)
    d = rng.normal(size=(n, 3))
    sc = _scan(o, d)
    origin, s, shape = np.array([0.0, 0.25, -0.5]), 0.25, (8, 6, 7)
    acc = accumulate([sc], origin, s, shape, mean_leaf_area=None)
    lg, nb = _brute_force_lengths(sc, origin, s, shape)
    assert lg.sum() > 10.0  # the rays do cross the grid
    np.testing.assert_allclose(acc.lg_total, lg, atol=2.5e-4 * 2)
    np.testing.assert_array_equal(acc.nb_sampling, nb)
    # no echoes: the whole beam enters every crossed voxel (S = 1 without divergence)
    np.testing.assert_array_equal(acc.bs_entering, nb.astype(float))
    assert acc.bs_intercepted.sum() == 0.0


def test_axis_aligned_ray_from_outside_and_face_echo():
    # a ray along +x entering at x = 0: every voxel of its row gets exactly l = s
    s = 0.25
    sc = _scan([[-2.0, 0.1, 0.1]], [[1.0, 0.0, 0.0]])
    acc = accumulate([sc], [0.0, 0.0, 0.0], s, (6, 2, 2), mean_leaf_area=None)
    np.testing.assert_allclose(acc.lg_total[:, 0, 0], s, rtol=1e-12)
    assert acc.lg_total.sum() == pytest.approx(6 * s)
    # an echo exactly on the face x = 0.5 belongs to the voxel the ray leaves (i = 1)
    sc = _scan([[-2.0, 0.1, 0.1]], [[1.0, 0.0, 0.0]], echoes=[[2.5]])
    acc = accumulate([sc], [0.0, 0.0, 0.0], s, (6, 2, 2), mean_leaf_area=None)
    assert acc.nb_echos[1, 0, 0] == 1 and acc.nb_echos.sum() == 1
    assert acc.nb_sampling[:, 0, 0].tolist() == [1, 1, 0, 0, 0, 0]  # the beam stops there
    assert acc.lg_total[1, 0, 0] == pytest.approx(s)  # potential length of the whole voxel


def test_echo_weights_beam_section_and_ground_echoes():
    s = 0.25
    div = 2e-3  # full divergence (rad): S = π (tan(δ/2)·d)² at the voxel centre range d
    # one 2-echo shot along +x from the origin of voxel (0,0,0): echoes in voxels 2 and 4
    sc = _scan([[0.125, 0.125, 0.125]], [[1.0, 0.0, 0.0]], echoes=[[0.6, 1.1]], divergence=div)
    acc = accumulate([sc], [0.0, 0.0, 0.0], s, (8, 1, 1), mean_leaf_area=None)
    dist = np.arange(8) * s  # range of each voxel centre from the origin
    S = math.pi * (math.tan(div / 2) * dist) ** 2
    ent = acc.bs_entering[:, 0, 0]
    np.testing.assert_allclose(ent[:3], S[:3], rtol=1e-12)          # full beam up to the first echo
    np.testing.assert_allclose(ent[3:5], 0.5 * S[3:5], rtol=1e-12)  # half the beam after it
    assert ent[5:].sum() == 0.0                                      # nothing after the last echo
    np.testing.assert_allclose(acc.bs_intercepted[[2, 4], 0, 0], 0.5 * S[[2, 4]], rtol=1e-12)
    assert acc.nb_echos[:, 0, 0].tolist() == [0, 0, 1, 0, 1, 0, 0, 0]
    # a ground echo stops the beam but is no hit: its free path counts as transmitted
    sc = _scan([[0.125, 0.125, 0.125]], [[1.0, 0.0, 0.0]], echoes=[[0.6]], hit=[False])
    acc = accumulate([sc], [0.0, 0.0, 0.0], s, (8, 1, 1), mean_leaf_area=None)
    assert acc.nb_echos.sum() == 0 and acc.bs_intercepted.sum() == 0
    assert acc.nb_sampling[:, 0, 0].tolist() == [1, 1, 1, 0, 0, 0, 0, 0]
    pad, _ = estimate_pad(acc, min_pulses=1)
    assert pad[2, 0, 0] == 0.0


# ----------------------------------------------------------------------------- estimators


def _single_voxel_case(n_shots, n_hits, hit_ranges):
    """Horizontal shots along +x through one 0.25 m voxel [0, 0.25)³, origin 1 m before it."""
    rng = np.random.default_rng(3)
    yz = rng.uniform(0.01, 0.24, (n_shots, 2))
    o = np.column_stack([np.full(n_shots, -1.0), yz])
    d = np.tile([1.0, 0.0, 0.0], (n_shots, 1))
    echoes = [[1.0 + hit_ranges[i]] if i < n_hits else [] for i in range(n_shots)]
    return accumulate([_scan(o, d, echoes)], [0.0, 0.0, 0.0], 0.25, (1, 1, 1), mean_leaf_area=None)


def test_estimators_closed_forms_single_voxel():
    s, N, M = 0.25, 40, 10
    z_hit = np.linspace(0.02, 0.23, M)  # free paths of the hits inside the voxel
    acc = _single_voxel_case(N, M, z_hit)
    g90 = 8 / (3 * math.pi ** 2)  # planophile G at θ = 90°
    # transmittance: every record has l = s, so N·T^s = N − M
    T = (1 - M / N) ** (1 / s)
    pad, flags = estimate_pad(acc, lad="planophile", pad_max=50.0, estimator="transmittance")
    assert pad[0, 0, 0] == pytest.approx(-math.log(T) / g90, rel=1e-9)
    assert flags[0, 0, 0] == 0
    # bias-corrected FPL MLE: k = M/Σz − Σ_hit z/(Σz)², z the travelled free paths
    sz = (N - M) * s + z_hit.sum()
    k = M / sz - z_hit.sum() / sz ** 2
    pad, _ = estimate_pad(acc, lad="planophile", pad_max=50.0, estimator="fpl_unbiased")
    assert pad[0, 0, 0] == pytest.approx(k / g90, rel=1e-9)
    # per-voxel LAD and cap arrays are honoured: spherical G = 0.5
    pad, _ = estimate_pad(acc, lad=np.array(["spherical"], dtype=object), pad_max=np.array([50.0]),
                          ijk=[[0, 0, 0]])
    assert pad[0] == pytest.approx(-math.log(T) / 0.5, rel=1e-9)


def test_flags_min_pulses_saturation_and_clipping():
    z = np.full(20, 0.1)
    few = _single_voxel_case(4, 1, z)
    pad, flags = estimate_pad(few, min_pulses=5)
    assert math.isnan(pad[0, 0, 0]) and flags[0, 0, 0] & FLAG_FEW_PULSES
    pad, flags = estimate_pad(few, min_pulses=4, pad_max=50.0)
    assert math.isfinite(pad[0, 0, 0]) and flags[0, 0, 0] == 0
    sat = _single_voxel_case(6, 6, z)  # every shot intercepted: T = 0
    for est in ("transmittance", "fpl_unbiased"):
        pad, flags = estimate_pad(sat, pad_max=8.0, estimator=est)
        assert pad[0, 0, 0] == 8.0 and flags[0, 0, 0] & FLAG_SATURATED
    dense = _single_voxel_case(20, 19, z)  # T = 0.05^(1/0.25) → PAD ≈ 44 > 5
    pad, flags = estimate_pad(dense, pad_max=5.0)
    assert pad[0, 0, 0] == 5.0 and flags[0, 0, 0] & FLAG_CLIPPED
    empty = accumulate([_scan([[5.0, 5.0, 5.0]], [[1.0, 0.0, 0.0]])], [0.0, 0.0, 0.0], 0.25, (2, 2, 2))
    pad, flags = estimate_pad(empty)
    assert np.all(np.isnan(pad)) and np.all(flags & FLAG_UNSAMPLED)
    with pytest.raises(ConfigError, match="estimator"):
        estimate_pad(few, estimator="magic")
    with pytest.raises(ConfigError, match="min_pulses"):
        estimate_pad(few, min_pulses=0)
    with pytest.raises(ConfigError, match="pad_max"):
        estimate_pad(few, pad_max=np.ones(3))


def _turbid_block(k, theta_deg, n_shots, seed=0):
    """Shots entering a 1 m turbid cube (4×4×4 voxels) from below at a fixed zenith angle."""
    rng = np.random.default_rng(seed)
    th, az = math.radians(theta_deg), rng.uniform(0, 2 * math.pi, n_shots)
    d = np.column_stack([math.sin(th) * np.cos(az), math.sin(th) * np.sin(az), np.full(n_shots, math.cos(th))])
    start = np.column_stack([rng.uniform(0, 1, (n_shots, 2)), np.zeros(n_shots)])  # entry on z = 0
    o = start - 2.0 * d
    # exit of the cube along each ray
    t_exit = np.full(n_shots, np.inf)
    for a in range(3):
        with np.errstate(divide="ignore"):
            t_a = np.where(d[:, a] > 0, (1.0 - start[:, a]) / d[:, a],
                           np.where(d[:, a] < 0, -start[:, a] / d[:, a], np.inf))
        t_exit = np.minimum(t_exit, t_a)
    free = rng.exponential(1.0 / k, n_shots)
    echoes = [[2.0 + free[i]] if free[i] < t_exit[i] else [] for i in range(n_shots)]
    return accumulate([_scan(o, d, echoes)], [0.0, 0.0, 0.0], 0.25, (4, 4, 4), mean_leaf_area=None)


def test_turbid_medium_recovers_pad():
    # Beer–Lambert truth: k = G(θ)·PAD; both estimators recover PAD in every voxel
    pad_true, theta = 2.0, 30.0
    k = g_function(theta, "planophile") * pad_true
    acc = _turbid_block(k, theta, 80000)
    for est in ("transmittance", "fpl_unbiased"):
        pad, flags = estimate_pad(acc, lad="planophile", pad_max=10.0, estimator=est)
        assert np.all(flags == 0)
        assert np.mean(pad) == pytest.approx(pad_true, rel=0.03), est
        # each layer (≥ 16 voxels, ~500–1000 shots per voxel) within 6 %, each voxel within 25 %
        np.testing.assert_allclose(pad.mean(axis=(0, 1)), pad_true, rtol=0.06, err_msg=est)
        np.testing.assert_allclose(pad, pad_true, rtol=0.25, err_msg=est)
    # the wrong LAD gives the G ratio as bias (erectophile G(30°) = 0.4514 vs planophile 0.7381)
    pad_e, _ = estimate_pad(acc, lad="erectophile", pad_max=10.0)
    pad_p, _ = estimate_pad(acc, lad="planophile", pad_max=10.0)
    np.testing.assert_allclose(pad_e / pad_p, 0.7381 / 0.4514, rtol=2e-3)


def test_pad_to_vox_roundtrip(tmp_path):
    from vlsforest.io.vox import read_vox, write_vox

    pad_true = 1.5
    acc = _turbid_block(g_function(30.0, "planophile") * pad_true, 30.0, 5000, seed=2)
    acc.origin = np.array([-2.5, 10.0, 240.25])  # a global-lattice origin (multiples of 0.25)
    pad, flags = estimate_pad(acc, pad_max=5.0)
    vox = pad_to_vox(acc, pad, flags, 5.0, keep="sampled")
    write_vox(tmp_path / "p.vox", vox)
    back = read_vox(tmp_path / "p.vox")
    assert back.max_pad == 5.0
    np.testing.assert_array_equal(back.min_corner, acc.origin)
    np.testing.assert_array_equal(back.split, acc.shape)
    ijk = back.ijk
    np.testing.assert_array_equal(back.column("PadBVTotal"), pad[tuple(ijk.T)])
    np.testing.assert_array_equal(back.column("nbSampling"), acc.nb_sampling[tuple(ijk.T)])
    np.testing.assert_array_equal(back.column("flag"), flags[tuple(ijk.T)])
    assert back.n_voxels == int((acc.nb_sampling > 0).sum())
    np.testing.assert_allclose(back.column("lMeanTotal") * back.column("nbSampling"), back.column("lgTotal"))


# ----------------------------------------------------------------------------- loading and CLI


def test_load_quick_forest_scans(quick_forest, tmp_path):
    tls = quick_forest / "plots" / "Q1" / "tls"
    table = pd.read_csv(tls / "scans.csv")
    scans = load_tls_scans(tls, scan_ids=[1, 2])
    for sc in scans:
        row = table[table["scan_id"] == sc.scan_id].iloc[0]
        assert sc.empty_shots and sc.n_shots == row["n_shots"] and sc.n_echoes == row["n_points"]
        assert sc.n_shots > sc.n_echoes  # empty shots are included
        # rebuilt shots run through their echoes: the point lies on its beam (range noise only)
        from vlsforest.io.las import read_las

        pts = read_las(sc.source).xyz
        xyz = sc.echo_xyz()
        d_pts = np.sort(np.linalg.norm(pts - row[["x", "y", "z"]].to_numpy(float), axis=1))
        np.testing.assert_allclose(np.sort(np.linalg.norm(xyz - sc.origin[0], axis=1)), d_pts, atol=1e-6)
        np.testing.assert_allclose(sc.origin[0], row[["x", "y", "z"]].to_numpy(float), atol=1e-9)
        assert np.all(sc.echo_weight == 1.0)  # single returns
    # without the survey files, shots are rebuilt from the points: no empty shots
    fb = tmp_path / "tls"
    fb.mkdir()
    shutil.copy(tls / "scan_1.laz", fb / "scan_1.laz")
    shutil.copy(tls / "scans.csv", fb / "scans.csv")
    (sc_fb,) = load_tls_scans(fb)
    assert not sc_fb.empty_shots and sc_fb.n_shots == sc_fb.n_echoes == scans[0].n_echoes
    # … and without a scanner position: one clear error naming the scan
    (fb / "scans.csv").unlink()
    with pytest.raises(InputDataError, match=r"scan_1\.laz.*position"):
        load_tls_scans(fb)


def test_missing_position_real_tls_and_cli_error(tmp_path, capsys):
    from vlsforest.cli import main

    src = REAL / "LPine1_demo.laz"
    if not src.is_file():
        pytest.skip("real data folder absent")
    tls = tmp_path / "tls"
    tls.mkdir()
    (tls / "scan_1.laz").symlink_to(src)  # a real TLS plot that comes without scanner positions
    with pytest.raises(InputDataError, match=r"scan_1\.laz.*position"):
        load_tls_scans(tls)
    rc = main(["pad", str(tls), "-o", str(tmp_path / "x.vox")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "scan_1.laz" in err[0] and "position" in err[0]
    with pytest.raises(InputDataError, match="no such TLS folder"):
        load_tls_scans(tmp_path / "nothing")


def test_empty_shots_blocked_inside_the_minimum_range_are_left_out(tmp_path):
    """Scanner A (1.5 m minimum range) has a leaf 0.9 m in front of it: its shots into the leaf
    come back empty, like its shots into the sky. Scanner B, 5 m away, sees the leaf; A's empty
    shots that pass within blind_radius of B's echoes there are left out, the sky shots stay."""
    from vlsforest.pad.traverse import _drop_blind_shots

    ang = np.radians(np.arange(-3.0, 3.01, 0.5))
    a, b = np.meshgrid(ang, ang, indexing="ij")
    leaf_dirs = np.column_stack([np.cos(a.ravel()) * np.cos(b.ravel()), np.sin(a.ravel()) * np.cos(b.ravel()),
                                 np.sin(b.ravel())])  # within ±3° of +x: through the leaf (±0.1 m at 0.9 m)
    sky_dirs = np.column_stack([np.zeros(20), np.cos(np.radians(np.linspace(30, 80, 20))),
                                np.sin(np.radians(np.linspace(30, 80, 20)))])
    far = np.array([[-1.0, 0.0, 0.0]] * 5)  # five shots with an echo at 10 m
    dirs = np.vstack([leaf_dirs, sky_dirs, far])
    echoes = [[] for _ in range(len(leaf_dirs) + len(sky_dirs))] + [[10.0]] * 5
    sa = _scan([0.0, 0.0, 0.0], dirs, echoes)
    sa.range_min_m = 1.5
    # scanner B samples the leaf square x = 0.9, |y|, |z| ≤ 0.1 every 2 cm
    g = np.arange(-0.1, 0.1001, 0.02)
    yy, zz = np.meshgrid(g, g, indexing="ij")
    leaf = np.column_stack([np.full(yy.size, 0.9), yy.ravel(), zz.ravel()])
    ob = np.array([0.9, 5.0, 0.0])
    rb = np.linalg.norm(leaf - ob, axis=1)
    sb = _scan(ob, leaf - ob, [[r] for r in rb])
    sb.range_min_m = 1.5
    n_before = sa.n_shots
    _drop_blind_shots([sa, sb], radius=0.04)
    assert sa.blind_shots == len(leaf_dirs) and sa.n_shots == n_before - len(leaf_dirs)
    # what is left: the sky shots (empty) and the shots with echoes, with their echoes intact
    np.testing.assert_allclose(sa.direction[: len(sky_dirs)], sky_dirs / np.linalg.norm(sky_dirs, axis=1)[:, None])
    assert np.diff(sa.shot_ptr).tolist() == [0] * len(sky_dirs) + [1] * 5
    np.testing.assert_allclose(sa.echo_xyz(), [[-10.0, 0.0, 0.0]] * 5)
    assert sb.blind_shots == 0 and sb.n_shots == len(leaf)  # B's shots all have echoes
    # radius 0 switches it off; without a minimum range nothing is dropped
    sc = _scan([0.0, 0.0, 0.0], dirs, echoes)
    sc.range_min_m = 1.5
    _drop_blind_shots([sc, sb], radius=0.0)
    assert sc.blind_shots == 0 and sc.n_shots == n_before
    sc.range_min_m = 0.0
    _drop_blind_shots([sc, sb], radius=0.04)
    assert sc.blind_shots == 0
    with pytest.raises(ConfigError, match="blind_radius"):
        load_tls_scans(tmp_path, blind_radius=-1)


def test_grid_for_scans_global_lattice():
    sc = _scan([[0.3, 0.3, 0.3]], [[1.0, 1.0, 1.0]], echoes=[[3.0]])
    origin, shape = grid_for_scans([sc], 0.25, extent=[-1.1, -0.6, 3.3, 2.9])
    np.testing.assert_allclose(origin / 0.25, np.round(origin / 0.25), atol=1e-12)
    assert origin[0] == -1.25 and origin[1] == -0.75 and shape[0] == 19 and shape[1] == 15
    p = sc.echo_xyz()[0]
    assert origin[2] <= p[2] < origin[2] + shape[2] * 0.25
    with pytest.raises(ConfigError, match="extent"):
        grid_for_scans([sc], 0.25, extent=[1, 1, 0, 0])
    with pytest.raises(ConfigError, match="voxel_size"):
        grid_for_scans([sc], -1.0)


# ----------------------------------------------------------------------------- validation


def test_quick_forest_pad_and_validation(quick_forest, tmp_path):
    from vlsforest.cli import main
    from vlsforest.io.vox import read_vox

    tls = quick_forest / "plots" / "Q1" / "tls"
    out = tmp_path / "Q1.vox"
    rc = main(["pad", str(tls), "-o", str(out), "--validate", str(quick_forest)])
    assert rc == 0
    vox = read_vox(out)
    assert vox.max_pad == 5.0 and vox.res == 0.25
    np.testing.assert_allclose(vox.min_corner / 0.25, np.round(vox.min_corner / 0.25), atol=1e-9)
    pad = vox.column("PadBVTotal")
    ok = np.isfinite(pad)
    assert ok.sum() > 1000 and np.all((pad[ok] >= 0) & (pad[ok] <= 5.0))
    assert np.all(np.isnan(pad[vox.column("nbSampling") < 5]))
    table = pd.read_csv(tmp_path / "Q1_validation.csv")
    assert list(table.columns[:7]) == ["plot", "species", "estimator", "height_band", "n_voxels", "bias_pct", "rmse"]
    # the cap removes the part of the bias due to voxels denser than PADmax
    assert np.all(table["bias_pct_capped"].dropna() >= table.loc[table["bias_pct_capped"].notna(), "bias_pct"] - 1e-9)
    assert list(table.columns) == TABLE_COLUMNS
    assert set(table["species"]) == {"fagus_sylvatica", "picea_abies"}
    assert set(table["estimator"]) == {"transmittance", "fpl_unbiased"}
    assert (tmp_path / "Q1_validation.png").stat().st_size > 10_000
    allb = table[table["height_band"] == "crown"]
    assert np.all(allb["n_voxels"] > 500)
    # target-crown voxels crossed by ≥ 20 shots: the goal, |bias| ≤ 10 %, for both
    # estimators, and the median |bias| over species × crown thirds ≤ 10 %
    assert np.all(np.abs(allb["bias_pct"]) <= 10.0), allb
    assert np.all(allb["rmse"] < allb["mean_true_pad"] * 1.5)
    thirds = table[table["height_band"].isin(["lower", "middle", "upper"])].dropna(subset=["bias_pct"])
    median_bias = {est: float(np.median(np.abs(g["bias_pct"]))) for est, g in thirds.groupby("estimator")}
    assert set(median_bias) == {"transmittance", "fpl_unbiased"}
    assert max(median_bias.values()) <= 10.0, median_bias
    assert median_abs_bias(table).to_dict() == pytest.approx(median_bias)
    capped = allb[allb["estimator"] == "transmittance"]["bias_pct_capped"]
    assert np.all(np.abs(capped) <= 10.0), capped
    # occlusion: the upper crown holds a larger share of unsampled plant area than the lower crown
    for sp, g in table[table["estimator"] == "transmittance"].groupby("species"):
        fr = g.set_index("height_band")["frac_undersampled"]
        assert fr["upper"] > fr["lower"], sp


def test_low_return_scan_warning():
    from vlsforest.commands.pad import low_return_scans

    d = np.tile([1.0, 0.0, 0.0], (10, 1))
    scans = []
    for k, n_ret in ((1, 9), (2, 2), (3, 8)):  # scan 2: 20 % returns vs a median of 80 %
        sc = _scan(np.zeros(3), d, [[1.0]] * n_ret + [[]] * (10 - n_ret))
        sc.scan_id = k
        scans.append(sc)
    msgs = low_return_scans(scans)
    assert len(msgs) == 1 and msgs[0].startswith("scan 2: only 20 %")
    assert low_return_scans(scans[::2]) == []
