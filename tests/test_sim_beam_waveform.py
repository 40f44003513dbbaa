"""Unit tests of the sub-ray pattern, energy model and peak detection against closed forms."""

import numpy as np
import pytest

from vlsforest.errors import ConfigError
from vlsforest.sim.beam import gaussian_weight, ring_counts, subray_directions, subray_pattern
from vlsforest.sim.waveform import C_M_PER_NS, detect_returns, pulse_shape, subray_energy


@pytest.mark.parametrize("q,n", [(1, 1), (2, 7), (3, 19), (4, 37), (5, 61)])
def test_subray_counts(q, n):
    assert ring_counts(q).sum() == n
    assert subray_pattern(q, 0.5).n == n


def test_ring_angles_and_unit_directions():
    pat = subray_pattern(3, 0.3)
    ang = np.hypot(pat.offsets[:, 0], pat.offsets[:, 1])
    # HELIOS placement: rings at 0, div/3, 2div/3 off axis
    assert np.allclose(np.unique(np.round(ang, 12)), [0, 0.1e-3, 0.2e-3])
    d = np.array([[0.0, 0.0, -1.0]])
    e = np.array([[1.0, 0.0, 0.0]])
    dirs = subray_directions(d, e, pat)[0]
    assert np.allclose(np.linalg.norm(dirs, axis=1), 1.0)
    off_axis = np.arccos(np.clip(dirs @ d[0], -1, 1))
    assert np.allclose(np.sort(off_axis), np.sort(ang), atol=1e-9)


def test_gaussian_weights_follow_profile():
    pat = subray_pattern(3, 0.25)
    w = pat.weights(np.full(pat.n, 1e6), range0=0.0)
    assert np.allclose(np.unique(np.round(w, 6)), np.round([np.exp(-8 / 9), np.exp(-2 / 9), 1.0], 6))
    # weight = exp(-2 r²/w²) of the sub-ray's lateral offset at range R, with w = div·R (HELIOS)
    R = 700.0
    r = np.hypot(*pat.offsets.T) * R
    assert np.allclose(pat.weights(np.full(pat.n, R)), np.exp(-2 * r ** 2 / (0.25e-3 * R) ** 2))
    # the R0 term of the beam-waist model reduces the exponent
    assert gaussian_weight(1.0, 100.0, range0=100.0) == pytest.approx(np.exp(-1.0))


def test_elliptical_pattern_scales_axes():
    pat = subray_pattern(3, [1.6, 0.5], orientation_deg=0)
    assert np.abs(pat.offsets[:, 0]).max() == pytest.approx(2 / 3 * 1.6e-3)
    assert np.abs(pat.offsets[:, 1]).max() == pytest.approx(2 / 3 * 0.5e-3, rel=1e-9)
    rot = subray_pattern(3, [1.6, 0.5], orientation_deg=90)
    assert np.abs(rot.offsets[:, 1]).max() == pytest.approx(2 / 3 * 1.6e-3)
    with pytest.raises(ConfigError):
        subray_pattern(3, [0.5, 1.6])


def test_pulse_shape_reference_values():
    p = pulse_shape(4.0, 0.25)
    assert len(p) == 16 and p[0] == 0 and np.argmax(p) == 5
    assert p[5] == pytest.approx(0.5369, abs=1e-4)
    assert p[4] == pytest.approx(0.5322, abs=1e-4)


def test_energy_magnitude_and_cos_squared():
    e0 = subray_energy(500.0, 1.0, 1.0, 50.0, 19, average_power_w=4, receiver_diameter_m=0.15,
                       optical_efficiency=0.99)
    assert 700 < e0 < 780  # reference: ~740 units for the central sub-ray at 500 m
    e60 = subray_energy(500.0, 1.0, 0.5, 50.0, 19, average_power_w=4, receiver_diameter_m=0.15,
                        optical_efficiency=0.99)
    assert e60 / e0 == pytest.approx(0.25)  # Lambertian: σ ∝ cos² a
    e1000 = subray_energy(1000.0, 1.0, 1.0, 50.0, 19, average_power_w=4, receiver_diameter_m=0.15,
                          optical_efficiency=0.99)
    assert e0 / e1000 == pytest.approx(4.0)  # extended target: 1/R²


def _two(d1, d2, **kw):
    return detect_returns(np.array([0, 2]), np.array([d1, d2]), np.array([100.0, 100.0]), **kw)


def test_single_target_exact_range():
    r = detect_returns(np.array([0, 1]), np.array([523.4567]), np.array([5.0]), window_size_ns=1.5)
    assert r["n_returns"][0] == 1 and abs(r["range"][0] - 523.4567) < 1e-9


def test_close_targets_merge_to_midpoint():
    r = _two(500.0, 500.3, window_size_ns=1.75, peak_rule="helios")
    assert r["n_returns"][0] == 1
    assert r["range"][0] == pytest.approx(500.15, abs=0.0375)


def test_helios_rule_reference_vectors():
    # replica vectors of the reference notes: 500 m and 503 m → 1 return at win 7, 2 at win 4
    assert _two(500.0, 503.0, window_size_ns=1.75, peak_rule="helios")["n_returns"][0] == 1
    assert _two(500.0, 503.0, window_size_ns=1.0, peak_rule="helios")["n_returns"][0] == 2
    # two equal targets resolve at win 6/7 only between 0.68 and 1.19 m
    for sep, n in [(0.6, 1), (0.8, 2), (1.0, 2), (1.3, 1)]:
        assert _two(500.0, 500.0 + sep, window_size_ns=1.5, peak_rule="helios")["n_returns"][0] == n


def test_threshold_scope_under_the_helios_rule():
    """A lone echo whose peak is twice the threshold: a receiver's threshold on the peak
    (``threshold_scope="peak"``, and the physical rule) reports it; a threshold that every
    bin of the helios rule's window must reach drops it, because the echo's first bin after
    the pulse's start holds only 23 % of its peak (4 ns pulse, 0.25 ns bins)."""
    shape = pulse_shape(4.0, 0.25)
    assert shape[1] / shape.max() == pytest.approx(0.23, abs=0.01)
    energy = 1000.0
    peak = energy * shape.max()
    ptr, ranges, e = np.array([0, 1]), np.array([100.0]), np.array([energy])

    def amps(**kw):
        return detect_returns(ptr, ranges, e, window_size_ns=1.5, **kw)["amplitude"]

    assert amps(peak_rule="helios", min_energy=0.5 * peak).size == 0
    assert amps(peak_rule="helios", min_energy=0.5 * peak, threshold_scope="window").size == 0
    for kw in ({"peak_rule": "helios", "threshold_scope": "peak"}, {"peak_rule": "physical"},
               {"peak_rule": "physical", "threshold_scope": "peak"}):
        assert amps(min_energy=0.5 * peak, **kw) == pytest.approx([peak])
        assert amps(min_energy=1.01 * peak, **kw).size == 0
    # the peak scope keeps HELIOS++ 1.0.8's neighbour floor: without a threshold both scopes agree
    assert amps(peak_rule="helios", threshold_scope="peak") == pytest.approx(amps(peak_rule="helios"))
    with pytest.raises(ConfigError):
        amps(threshold_scope="bins")


def test_physical_rule_resolves_isolated_echoes():
    dead = C_M_PER_NS * 1.5  # 0.45 m
    assert _two(500.0, 503.0, window_size_ns=1.5)["n_returns"][0] == 2
    assert _two(500.0, 500.0 + 0.9 * dead, window_size_ns=1.5)["n_returns"][0] == 1
    r = _two(500.0, 510.0, window_size_ns=1.5)
    assert np.allclose(r["range"], [500.0, 510.0], atol=C_M_PER_NS * 0.25)


def test_max_returns_and_threshold():
    ptr = np.array([0, 3])
    rng = np.array([500.0, 505.0, 510.0])
    en = np.array([10.0, 3.0, 6.0])
    assert detect_returns(ptr, rng, en, max_returns=1)["range"].tolist() == [500.0]
    r = detect_returns(ptr, rng, en, min_energy=0.537 * 5.0)
    # the 3-unit echo (peak 0.537·3 = 1.6) is removed, the 6- and 10-unit ones stay
    assert np.allclose(r["range"], [500.0, 510.0], atol=0.08)
    assert (r["amplitude"] >= 0.537 * 5.0).all()


def test_waveform_matches_a_hit_by_hit_reference():
    """Energies summed per bin before the pulse shape is added give the waveform of adding one
    shape per hit: same returns, amplitudes to rounding, on pulses whose hits share bins."""
    from vlsforest.sim.waveform import pulse_shape

    rng = np.random.default_rng(11)
    bin_m = C_M_PER_NS * 0.25
    shape = pulse_shape(4.0, 0.25)
    ptr, ranges, energy = [0], [], []
    for k in range(600):
        n = int(rng.integers(1, 25))
        base = 500.0 + rng.uniform(0, 1)
        # every third pulse has all its hits inside one bin (open ground; the kernel's shortcut),
        # the others mix a ground-like cluster with crown hits spread over a few metres
        r = base + np.where((k % 3 == 0) | (rng.random(n) < 0.5), rng.uniform(0, 0.9 * bin_m, n),
                            rng.uniform(0, 4.0, n))
        ranges.extend(r)
        energy.extend(rng.uniform(0.5, 20.0, n))
        ptr.append(len(ranges))
    ptr, ranges, energy = np.array(ptr), np.array(ranges), np.array(energy)
    got = detect_returns(ptr, ranges, energy, window_size_ns=1.0)
    want_amp, want_range = [], []
    for p in range(len(ptr) - 1):
        r, e = ranges[ptr[p]:ptr[p + 1]], energy[ptr[p]:ptr[p + 1]]
        lo = r.min()
        nb = int((r.max() - lo) / bin_m) + len(shape)
        wave = np.zeros(nb)
        for d, en in zip(r, e):  # one pulse shape per hit
            b = int((d - lo) / bin_m)
            k = min(len(shape), nb - b)
            wave[b:b + k] += shape[:k] * en
        win = 4  # 1.0 ns / 0.25 ns
        for i in range(nb):
            v = wave[i]
            if v > 0 and (wave[max(0, i - win):i] < v).all() and (wave[i + 1:i + win + 1] <= v).all():
                want_amp.append(v)
                want_range.append(lo + (i - int(np.argmax(shape))) * bin_m)
    assert len(got["amplitude"]) == len(want_amp) > 600
    assert np.allclose(got["amplitude"], want_amp, rtol=1e-12)
    assert np.allclose(got["range"], want_range, rtol=0, atol=1e-9)


def test_one_bin_pulse_is_the_pulse_shape_times_its_energy():
    from vlsforest.sim.waveform import _is_unimodal, pulse_shape

    shape = pulse_shape(4.0, 0.25)
    k = int(np.argmax(shape))
    assert _is_unimodal(shape, k) and not _is_unimodal(np.array([0.0, 1.0, 1.0, 0.5]), 1)
    ranges = np.array([60.031, 60.0, 60.05, 60.02])  # all within one 0.075 m bin
    energy = np.array([3.0, 1.5, 2.0, 0.25])
    r = detect_returns(np.array([0, 4]), ranges, energy, window_size_ns=1.0)
    assert r["n_returns"].tolist() == [1] and r["range"][0] == 60.0 and r["hit"][0] == 1
    assert r["amplitude"][0] == pytest.approx(shape[k] * energy.sum(), rel=1e-15)
    # the threshold applies to that peak; a zero window makes every bin of the waveform a peak
    assert detect_returns(np.array([0, 4]), ranges, energy, min_energy=shape[k] * 6.8)["n_returns"][0] == 0
    assert detect_returns(np.array([0, 4]), ranges, energy, window_size_ns=0.0)["n_returns"][0] == len(shape) - 1


def test_nearest_hit_gives_object():
    r = detect_returns(np.array([0, 3]), np.array([500.0, 500.02, 507.0]), np.ones(3) * 10)
    assert r["n_returns"][0] == 2
    assert r["hit"].tolist() == [0, 2]


def test_hit_energy_matches_subray_energy():
    from vlsforest.sim.waveform import hit_energy

    rng = np.random.default_rng(0)
    pat = subray_pattern(3, 0.5)
    n = 500
    sub = rng.integers(0, pat.n, n)
    part = rng.integers(0, 3, n)
    r = rng.uniform(50, 800, n)
    cos = rng.uniform(0, 1, n)
    refl, spec, shin = np.array([20.0, 45.0, 60.0]), np.array([0.0, 0.3, 0.0]), np.array([10.0, 5.0, 10.0])
    kw = dict(average_power_w=4, receiver_diameter_m=0.15, optical_efficiency=0.99)
    a = hit_energy(r, sub, cos, part, pat.frac, refl, spec, shin, pat.n, range0=100.0, m2=1.2, atm_alpha=1e-4, **kw)
    w = gaussian_weight(pat.frac[sub], r, 100.0, 1.2)
    b = subray_energy(r, w, cos, refl[part], pat.n, specularity=spec[part], shininess=shin[part], atm_alpha=1e-4, **kw)
    assert np.allclose(a, b, rtol=1e-12)


def test_beam_weight_without_exp_agrees_with_exp():
    """The per-hit Gaussian weight exp(-a) · Taylor(exp(y)) (y = a R0²/(R² + R0²) ≤ 0.03) agrees
    with exp(-a R²/(R² + R0²)) to a few ulp, on both sides of the switch to exp and at R0 = 0."""
    from vlsforest.sim.waveform import _beam_weight, _weight_consts

    frac = np.unique(np.concatenate([subray_pattern(q, 0.5).frac for q in (2, 3, 4, 5)]))
    r = np.geomspace(0.05, 5000.0, 4001)
    n_poly = 0
    for m2 in (1.0, 1.2, 1.5):
        a, ea = _weight_consts(frac, m2)
        assert np.allclose(a, 2 * (frac * m2) ** 2, rtol=1e-15) and np.allclose(ea, np.exp(-a), rtol=1e-15)
        for r0 in (0.0, 1.5, 3.0, 100.0):
            for k in range(len(frac)):
                got = np.array([_beam_weight(x, a[k], ea[k], r0) for x in r])
                want = np.exp(-2 * (frac[k] * m2) ** 2 * r ** 2 / (r ** 2 + r0 ** 2))
                assert np.abs(got / want - 1).max() < 1e-15, (m2, r0, k)
                n_poly += int(np.sum(a[k] * r0 ** 2 / (r ** 2 + r0 ** 2) <= 0.03))
    assert n_poly > 10000  # the polynomial branch was exercised
    assert _beam_weight(70.0, 0.0, 1.0, 3.0) == 1.0  # the central sub-ray


def _reference_physical(ranges, energy, win, bin_m=C_M_PER_NS * 0.25):
    """Plain-Python statement of the physical peak rule (for comparison)."""
    shape = pulse_shape(4.0, 0.25)
    d0 = min(ranges)
    nb = int((max(ranges) - d0) / bin_m) + len(shape)
    wave = [0.0] * nb
    for d, e in sorted(zip(ranges, energy), key=lambda x: x[0]):
        b = int((d - d0) / bin_m)
        for i, p in enumerate(shape):
            if b + i < nb:
                wave[b + i] += p * e
    out = []
    for i, v in enumerate(wave):
        if v <= 0:
            continue
        left = wave[max(0, i - win):i]
        right = wave[i + 1:min(nb, i + win + 1)]
        if all(x < v for x in left) and all(x <= v for x in right):
            out.append(d0 + (i - 5) * bin_m)
    return out


def test_peak_rule_matches_plain_statement():
    rng = np.random.default_rng(7)
    for _ in range(300):
        n = int(rng.integers(1, 12))
        r = 300 + np.cumsum(rng.exponential(0.4, n))
        e = rng.uniform(1, 100, n)
        win_ns = float(rng.choice([0.5, 1.0, 1.5, 1.75]))
        got = detect_returns(np.array([0, n]), r, e, window_size_ns=win_ns)["range"]
        want = _reference_physical(list(r), list(e), int(win_ns / 0.25))
        assert np.allclose(got, want), (r, e, win_ns)


@pytest.mark.parametrize("rule,dedupe,max_returns", [("physical", False, 0), ("helios", True, 2)])
def test_detect_traced_equals_collected_hits_then_detection(rule, dedupe, max_returns):
    """The fused pass over the cast gives exactly hit_energy + detect_returns on the collected hits."""
    from vlsforest.sim.waveform import (detect_returns, detect_traced, detection_constants, energy_constants,
                                        hit_energy)

    rng = np.random.default_rng(4)
    ns, nl, m = 7, 300, 450
    live = np.sort(rng.choice(m, nl, replace=False)).astype(np.int64)
    base = rng.uniform(5.0, 60.0, nl)
    t = np.repeat(base, ns) + rng.choice([0.0, 0.02, 0.6, 3.0], nl * ns) + rng.uniform(0, 0.01, nl * ns)
    t[rng.random(nl * ns) < 0.3] = np.inf
    t[rng.random(nl * ns) < 0.05] = 2.0  # nearer than range_min
    t[::11] = t[1::11][: len(t[::11])]  # duplicate ranges
    part = rng.integers(0, 3, nl * ns).astype(np.int32)
    part[~np.isfinite(t)] = -1
    cos_inc = rng.uniform(0.1, 1.0, nl * ns)
    frac = np.r_[0.0, np.full(6, 0.5)]
    refl, spec, shin = np.array([30.0, 50.0, 10.0, 0.0]), np.array([0.0, 0.3, 0.0, 0.0]), np.array([10.0, 5.0, 1.0, 1])
    energy_kw = dict(average_power_w=4.0, receiver_diameter_m=0.15, optical_efficiency=0.9, range0=3.0, m2=1.0)
    det_kw = dict(pulse_length_ns=4.0, bin_size_ns=0.25, window_size_ns=1.5, min_energy=0.0, max_returns=max_returns,
                  peak_rule=rule, two_way_time=False, dedupe_ranges=dedupe)
    got = detect_traced(t, part, cos_inc, live, ns, m, 3.0, frac, refl, spec, shin,
                        energy_constants(n_subrays=ns, **energy_kw), detection_constants(**det_kw))
    # reference: collect the hits, then the two-step detection
    ok = np.isfinite(t) & (t >= 3.0)
    idx = np.flatnonzero(ok)
    pulse = live[idx // ns]
    ptr = np.zeros(m + 1, np.int64)
    np.cumsum(np.bincount(pulse, minlength=m), out=ptr[1:])
    energy = hit_energy(t[idx], idx % ns, cos_inc[idx].astype(np.float32), part[idx], frac, refl, spec, shin, ns,
                        **energy_kw)
    ref = detect_returns(ptr, t[idx], energy, **det_kw)
    assert len(ref["range"]) > nl // 2
    for k, name in enumerate(("pulse", "range", "amplitude")):
        np.testing.assert_array_equal(got[k], ref[name], err_msg=name)
    np.testing.assert_array_equal(got[3], idx[ref["hit"]])
    np.testing.assert_array_equal(got[4], ref["return_number"])
    np.testing.assert_array_equal(got[5], ref["number_of_returns"])
    np.testing.assert_array_equal(got[6], ref["n_returns"])
