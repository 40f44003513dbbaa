"""Tests of scanner presets, deflectors, platforms and SURVEY.yaml parsing (vlsforest.sim)."""

from __future__ import annotations

import copy
import dataclasses
import math
import pickle

import numpy as np
import pytest

from vlsforest.errors import ConfigError
from vlsforest.sim.deflector import deflect, deflector_pattern, sweep, tls_grid
from vlsforest.sim.pulses import PulseBatch
from vlsforest.sim.scanner import (
    FLAT_KEYS,
    INPUT_KEYS,
    PRESETS,
    REAL_BEAMS,
    ScannerSettings,
    datasheet_divergence,
    emission_half_angle_deg,
    fwhm_to_1e2,
    scanner_from_dict,
    scanner_from_preset,
    input_key,
    validate_scanner,
)
from vlsforest.sim.survey import load_survey, survey_from_dict

FIELDS = ("slot", "gps_time", "origin", "direction", "scan_dir", "scan_angle_deg", "source_id")


def custom(deflector, **kw):
    base = dict(deflector=deflector, prf_hz=1000.0, scan_freq_hz=10.0, scan_angle_deg=30.0,
                beam_divergence_mrad=0.5)
    base.update(kw)
    return base


def airborne(scanner, legs=None, speed=10.0, **extra):
    if legs is None:
        legs = [{"start": [0.0, 0.0, 100.0], "end": [0.0, 100.0, 100.0]}]
    d = {"scanner": scanner, "platform": {"type": "linear", "speed_mps": speed, "legs": legs}}
    d.update(extra)
    return d


def tls_survey(**over):
    o = {"tls_h_step_deg": 2.0, "tls_v_step_deg": 1.0}
    o.update(over)
    return {
        "scanner": "riegl_vz400",
        "overrides": o,
        "platform": {"type": "static", "positions": [
            {"position": [0.0, 0.0, 1.5]},
            {"position": [10.0, 0.0, 1.5], "heading_deg": 90.0, "tilt_deg": 30.0},
        ]},
    }


def all_pulses(s):
    return s.pulses(0, s.n_slots)


def ground_hits(b, ground_z=0.0):
    t = (ground_z - b.origin[:, 2]) / b.direction[:, 2]
    return b.origin + t[:, None] * b.direction


# --------------------------------------------------------------------------- presets


def test_presets_load_and_validate():
    assert {"riegl_vq780i", "riegl_minivux1uav", "riegl_vz400"} <= set(PRESETS)
    for name, preset in PRESETS.items():
        validate_scanner(preset)
        assert scanner_from_preset(name) == preset
        assert scanner_from_preset(name, {}) == preset
    vq = PRESETS["riegl_vq780i"]
    assert vq.emitter.prf_hz == 1e6
    assert (vq.deflector.kind, vq.deflector.scan_freq_hz, vq.deflector.scan_angle_deg) == ("polygon", 250.0, 30.0)
    # HELIOS++ 1.0.8's riegl_vq_780i: scanAngleMax 45°, scanAngleEffectiveMax 30°, accuracy 0.02 m
    assert (vq.deflector.max_scan_angle_deg, vq.deflector.effective_max_scan_angle_deg) == (45.0, 30.0)
    assert vq.detector.range_noise_m == 0.02
    assert vq.beam.divergence_mrad == (0.25, 0.25) and vq.detector.window_size_ns == 1.75
    uls = PRESETS["riegl_minivux1uav"]
    assert uls.emitter.prf_hz == 1e5
    d = uls.deflector
    assert (d.kind, d.scan_freq_hz, d.max_scan_angle_deg) == ("rotating", 50.0, 180.0)
    assert uls.beam.divergence_mrad == (0.5, 0.5)
    assert uls.detector.window_size_ns == 1.5 and uls.detector.range_noise_m == 0.015
    tls = PRESETS["riegl_vz400"]
    assert tls.deflector.kind == "tls" and tls.tls.v_fov_deg == (-40.0, 60.0) and tls.tls.h_fov_deg == (0.0, 360.0)
    # the VZ-400 datasheet: 0.35 mrad full angle at 1/e², 7 mm exit diameter, 5 mm accuracy
    assert 2 * tls.beam.divergence_mrad[0] == pytest.approx(0.35) and tls.beam.exit_diameter_m == 0.007
    assert tls.detector.range_noise_m == 0.005


def helios_mirror_angles(half_deg, freq, prf, n, window_deg=None):
    """HELIOS++ 1.0.8's PolygonMirrorBeamDeflector (doSimStep, lastPulseLeftDevice) run for ``n``
    pulses from a leg's start: the angle starts at 0; before each pulse it grows by
    (freq · 2M) / prf radians and is set to −M once it reaches +M; a pulse leaves the device when
    |angle| ≤ the window (radians, no tolerance). Returns the angles in degrees and, with
    ``window_deg``, whether each pulse is emitted."""
    m = half_deg * (math.pi / 180.0)
    step = (freq * (m - (-m))) / prf
    x, out = 0.0, []
    for _ in range(n):
        x += step
        if x >= m:
            x = -m
        out.append(x)
    rad = np.array(out)
    if window_deg is None:
        return np.degrees(rad)
    return np.degrees(rad), np.abs(rad) <= window_deg * (math.pi / 180.0)


def test_vq780i_emits_two_thirds_of_its_prf():
    """The mirror sweeps ±45° at 250 lines/s and 1 MHz, stepped as HELIOS++ steps it: 4,001 slots
    per line (its float sum of 4,000 steps of 0.0225° stays below 45°, so a line takes one slot
    more); the device emits within ±30°: 2,667 per line, 2/3 of the PRF."""
    vq = PRESETS["riegl_vq780i"]
    n = 1_000_000
    emitted, _, _, angle = deflect(vq, np.arange(n))
    ref, on = helios_mirror_angles(45.0, 250.0, 1e6, n, 30.0)
    starts = np.flatnonzero(ref == -45.0)
    assert np.all(np.diff(starts) == 4001) and starts[0] == 2000
    np.testing.assert_array_equal(emitted, on)
    np.testing.assert_allclose(angle, ref[emitted], atol=1e-9)
    # every full line: nodes -45 + 0.0225·j within [-30, 30], j = 667 … 3333
    per_line = np.add.reduceat(emitted, starts)[:-1]
    assert np.all(per_line == 2667)
    assert emitted.sum() / n == pytest.approx(2.0 / 3.0, abs=1e-3)
    assert np.abs(angle).max() <= 30.0 + 1e-9 and emission_half_angle_deg(vq) == 30.0
    # the same through a survey's compiled pulse path, over one second of flight
    s = survey_from_dict(airborne("riegl_vq780i", legs=[{"start": [0, 0, 700], "end": [0, 51, 700]}], speed=51.0))
    assert s.n_slots == n
    assert len(all_pulses(s)) == emitted.sum()
    assert len(s.pulses_toward(0, s.n_slots, [-1e4, -1e4, -1e4], [1e4, 1e4, 1e4], 0.0)[2]) == emitted.sum()


def test_minivux_steps_as_helios():
    """The rotating mirror at 100 kHz / 50 Hz: HELIOS++'s float sum takes 2,001 slots per turn,
    a leg starts at nadir (the first pulse one step right of it), and the pulses at exactly
    ±90° (slot 499 of the first turn, 500 of the later ones) leave the device or not as
    HELIOS++'s rounded sum decides; likewise with a ±45° survey angle."""
    ref, on = helios_mirror_angles(180.0, 50.0, 1e5, 12_000, 90.0)
    starts = np.flatnonzero(ref == -180.0)
    assert np.all(np.diff(starts) == 2001)
    emitted, _, _, angle = deflect(PRESETS["riegl_minivux1uav"], np.arange(12_000))
    np.testing.assert_array_equal(emitted, on)
    np.testing.assert_allclose(angle, ref[emitted], atol=1e-9)
    assert angle[0] == pytest.approx(0.18)
    _, on45 = helios_mirror_angles(180.0, 50.0, 1e5, 12_000, 45.0)
    sc = survey_from_dict(airborne("riegl_minivux1uav", overrides={"scan_angle_deg": 45.0})).scanner
    np.testing.assert_array_equal(deflect(sc, np.arange(12_000))[0], on45)


def test_datasheet_divergences_are_stored_as_the_half_angle():
    assert datasheet_divergence(full_1e2_mrad=0.25) == (0.125, 0.125)
    major, minor = datasheet_divergence(fwhm_mrad=(1.6, 0.5))
    # 1.6 × 0.5 mrad at 50 % peak intensity = 2.718 × 0.849 mrad at 1/e², halved
    assert (major, minor) == pytest.approx((2.718 / 2, 0.849 / 2), abs=1e-3)
    s = scanner_from_preset("riegl_minivux1uav", {"beam_divergence_fwhm_mrad": [1.6, 0.5]})
    assert s.beam.divergence_mrad == pytest.approx((major, minor))
    s = scanner_from_preset("riegl_vq780i", {"beam_divergence_full_1e2_mrad": 0.25})
    assert s.beam.divergence_mrad == (0.125, 0.125)
    assert datasheet_divergence(**REAL_BEAMS["riegl_vz400"]) == pytest.approx(PRESETS["riegl_vz400"].beam.divergence_mrad)
    spec = {k: v for k, v in custom("conic").items() if k != "beam_divergence_mrad"}
    assert scanner_from_dict(spec | {"beam_divergence_full_1e2_mrad": 1.0}).beam.divergence_mrad == (0.5, 0.5)
    with pytest.raises(ConfigError, match="once"):
        scanner_from_preset("riegl_vq780i", {"beam_divergence_mrad": 0.2, "beam_divergence_fwhm_mrad": 0.2})
    with pytest.raises(ConfigError, match=r"overrides\.beam_divergence_fwhm_mrad"):
        scanner_from_preset("riegl_vq780i", {"beam_divergence_fwhm_mrad": 0})


def test_fwhm_to_1e2_matches_a_numeric_gaussian():
    w = 1.0  # 1/e² radius of I(r) = exp(-2 r² / w²)
    r = np.linspace(0, 2, 2_000_001)
    intensity = np.exp(-2 * r**2 / w**2)
    fwhm = 2 * r[np.argmin(np.abs(intensity - 0.5))]
    assert fwhm_to_1e2(fwhm) == pytest.approx(2 * w, rel=1e-5)
    assert np.allclose(fwhm_to_1e2([1.6, 0.5]), [2.718, 0.849], atol=1e-3)


def test_overrides_are_coerced():
    s = scanner_from_preset("riegl_vq780i", {"beam_divergence_mrad": 0.4, "prf_hz": 500_000, "max_returns": 5})
    assert s.beam.divergence_mrad == (0.4, 0.4) and isinstance(s.emitter.prf_hz, float)
    assert s.detector.max_returns == 5
    s = scanner_from_preset("riegl_minivux1uav", {"beam_divergence_mrad": [1.6, 0.5], "beam_orientation_deg": 90})
    assert s.beam.divergence_mrad == (1.6, 0.5) and s.beam.orientation_deg == 90.0
    hash(s)  # stays hashable


#: every overridable flat key: a valid value that differs from the VZ-400 preset's, and where
#: the settings' records hold it
FLAT_OVERRIDES = {
    "prf_hz": (123_000.0, lambda s: s.emitter.prf_hz),
    "wavelength_nm": (905.0, lambda s: s.emitter.wavelength_nm),
    "pulse_length_ns": (3.5, lambda s: s.emitter.pulse_length_ns),
    "average_power_w": (2.5, lambda s: s.emitter.average_power_w),
    "scan_freq_hz": (33.0, lambda s: s.deflector.scan_freq_hz),
    "scan_angle_deg": (20.0, lambda s: s.deflector.scan_angle_deg),
    "max_scan_angle_deg": (40.0, lambda s: s.deflector.max_scan_angle_deg),
    "effective_max_scan_angle_deg": (30.0, lambda s: s.deflector.effective_max_scan_angle_deg),
    "beam_divergence_mrad": ((0.4, 0.3), lambda s: s.beam.divergence_mrad),
    "beam_orientation_deg": (15.0, lambda s: s.beam.orientation_deg),
    "beam_sample_quality": (5, lambda s: s.beam.sample_quality),
    "beam_quality_factor": (1.3, lambda s: s.beam.quality_factor),
    "beam_exit_diameter_m": (0.004, lambda s: s.beam.exit_diameter_m),
    "bin_size_ns": (0.5, lambda s: s.detector.bin_size_ns),
    "window_size_ns": (2.25, lambda s: s.detector.window_size_ns),
    "min_energy": (7.0, lambda s: s.detector.min_energy),
    "max_returns": (4, lambda s: s.detector.max_returns),
    "range_min_m": (2.5, lambda s: s.detector.range_min_m),
    "range_noise_m": (0.03, lambda s: s.detector.range_noise_m),
    "optical_efficiency": (0.7, lambda s: s.detector.optical_efficiency),
    "receiver_diameter_m": (0.08, lambda s: s.detector.receiver_diameter_m),
    "atmosphere": (True, lambda s: s.atmosphere.enabled),
    "visibility_km": (12.0, lambda s: s.atmosphere.visibility_km),
    "tls_h_fov_deg": ((-60.0, 60.0), lambda s: s.tls.h_fov_deg),
    "tls_v_fov_deg": ((-30.0, 45.0), lambda s: s.tls.v_fov_deg),
    "tls_h_step_deg": (0.25, lambda s: s.tls.h_step_deg),
    "tls_v_step_deg": (0.125, lambda s: s.tls.v_step_deg),
}


def test_every_flat_key_sets_its_record_field():
    """The flat keys of survey files reach the fields of the part records; the settings read
    back as the same flat mapping, and build again from it."""
    assert set(INPUT_KEYS) == set(FLAT_OVERRIDES) | {"name", "deflector", "beam_divergence_full_1e2_mrad",
                                                     "beam_divergence_fwhm_mrad"}
    base = PRESETS["riegl_vz400"]
    ov = {k: list(v) if isinstance(v, tuple) else v for k, (v, _) in FLAT_OVERRIDES.items()}
    s = scanner_from_preset("riegl_vz400", ov)
    for key, (value, read) in FLAT_OVERRIDES.items():
        assert read(base) != value, key
        assert read(s) == value, key
        assert s.flat()[key] == value
        # one key changes one field
        one = base.replaced(**{key: value})
        assert read(one) == value and sum(one.flat()[k] != base.flat()[k] for k in FLAT_KEYS) == 1, key
    assert (s.name, s.deflector.kind) == ("riegl_vz400", "tls")
    assert ScannerSettings.from_flat(**s.flat()) == s
    for name, preset in PRESETS.items():
        assert ScannerSettings.from_flat(**preset.flat()) == preset and preset.replaced() == preset, name
    # each record field is set by one key
    assert len(set(FLAT_KEYS.values())) == len(FLAT_KEYS)
    assert input_key("detector", "window_size_ns") == "window_size_ns"
    assert input_key("beam", "divergence_mrad") == "beam_divergence_mrad"
    assert input_key("atmosphere", "enabled") == "atmosphere"
    with pytest.raises(TypeError, match="window_ns"):
        base.replaced(window_ns=1.0)


def test_settings_are_frozen_hashable_and_picklable():
    """Settings cross process boundaries (forked or spawned workers) and serve as keys."""
    s = scanner_from_preset("riegl_minivux1uav", {"beam_divergence_fwhm_mrad": [1.6, 0.5], "max_returns": 5})
    back = pickle.loads(pickle.dumps(s))
    assert back == s and hash(back) == hash(s) and {s: 1}[back] == 1
    assert back != s.replaced(max_returns=4)
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.detector.max_returns = 3
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.beam = s.beam
    # the other parts of a replaced copy are shared, not copied
    r = s.replaced(window_size_ns=3.0)
    assert r.detector.window_size_ns == 3.0 and r.beam is s.beam and r.emitter is s.emitter


BAD_OVERRIDES = [
    ("riegl_vq780i", {"prf_hz": 0}, "overrides.prf_hz"),
    ("riegl_vq780i", {"prf_hz": -5.0}, "overrides.prf_hz"),
    ("riegl_vq780i", {"prf_hz": "fast"}, "overrides.prf_hz"),
    ("riegl_vq780i", {"prf_hz": float("nan")}, "overrides.prf_hz"),
    ("riegl_vq780i", {"scan_freq_hz": 0}, "overrides.scan_freq_hz"),
    ("riegl_vq780i", {"beam_divergence_mrad": 0}, "overrides.beam_divergence_mrad"),
    ("riegl_vq780i", {"beam_divergence_mrad": [0.5, 1.6]}, "overrides.beam_divergence_mrad"),
    ("riegl_vq780i", {"beam_divergence_mrad": [0.5, 0.2, 0.1]}, "overrides.beam_divergence_mrad"),
    ("riegl_vq780i", {"bin_size_ns": 0}, "overrides.bin_size_ns"),
    ("riegl_vq780i", {"pulse_length_ns": -1}, "overrides.pulse_length_ns"),
    ("riegl_vq780i", {"beam_sample_quality": 0}, "overrides.beam_sample_quality"),
    ("riegl_vq780i", {"beam_sample_quality": 11}, "overrides.beam_sample_quality"),
    ("riegl_vq780i", {"beam_sample_quality": 2.5}, "overrides.beam_sample_quality"),
    ("riegl_vq780i", {"window_size_ns": -0.1}, "overrides.window_size_ns"),
    ("riegl_vq780i", {"scan_angle_deg": 31}, "overrides.scan_angle_deg"),
    ("riegl_vq780i", {"effective_max_scan_angle_deg": 46}, "overrides.effective_max_scan_angle_deg"),
    ("riegl_vq780i", {"max_scan_angle_deg": 91}, "overrides.max_scan_angle_deg"),
    ("riegl_vq780i", {"scan_angle_deg": 0}, "overrides.scan_angle_deg"),
    ("riegl_vq780i", {"max_returns": -1}, "overrides.max_returns"),
    ("riegl_vq780i", {"atmosphere": "yes"}, "overrides.atmosphere"),
    ("riegl_vq780i", {"range_noise_m": -0.01}, "overrides.range_noise_m"),
    ("riegl_vq780i", {"prf": 5}, "overrides.prf"),
    ("riegl_vq780i", {"deflector": "conic"}, "overrides.deflector"),
    ("riegl_vz400", {"tls_v_fov_deg": [60, -40]}, "overrides.tls_v_fov_deg"),
    ("riegl_vz400", {"tls_h_step_deg": 0}, "overrides.tls_h_step_deg"),
]


@pytest.mark.parametrize("preset,overrides,key", BAD_OVERRIDES)
def test_bad_overrides_name_the_key(preset, overrides, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        scanner_from_preset(preset, overrides)


def test_unknown_preset_lists_known_ones():
    with pytest.raises(ConfigError) as exc:
        scanner_from_preset("leica_als80")
    assert "scanner" in str(exc.value) and "riegl_vq780i" in str(exc.value) and "riegl_vz400" in str(exc.value)


def test_custom_scanner_mapping():
    s = scanner_from_dict(custom("conic", scan_angle_deg=15.0))
    assert s.deflector.kind == "conic" and s.deflector.max_scan_angle_deg == 15.0
    assert s.beam.divergence_mrad == (0.5, 0.5)
    with pytest.raises(ConfigError, match=r"scanner\.prf_hz"):
        scanner_from_dict({"deflector": "conic", "scan_freq_hz": 1, "scan_angle_deg": 5, "beam_divergence_mrad": 1})
    with pytest.raises(ConfigError, match=r"scanner\.deflector"):
        scanner_from_dict(custom("spiral"))


# --------------------------------------------------------------------------- deflectors


def test_polygon_line_has_prf_over_freq_pulses_evenly_spread():
    s = survey_from_dict(airborne(custom("polygon")))  # 1000 Hz / 10 Hz → 0.6° steps over ±30°
    assert s.n_slots == 10 * 1000  # 100 m at 10 m/s = 10 s at 1 kHz
    b = all_pulses(s)
    assert len(b) == s.n_slots  # scan angle = device max: everything emitted
    ref = helios_mirror_angles(30.0, 10.0, 1000.0, s.n_slots)
    np.testing.assert_allclose(b.scan_angle_deg, ref, atol=1e-9)
    # the first line runs from one step right of nadir, every later one from -30° in even steps
    starts = np.flatnonzero(np.isclose(b.scan_angle_deg, -30.0, atol=1e-9))
    period = int(np.diff(starts)[0])
    assert period in (100, 101) and np.all(np.diff(starts) == period)
    line = b.scan_angle_deg[starts[0]:starts[1]]
    np.testing.assert_allclose(line, -30.0 + 0.6 * np.arange(period), atol=1e-9)
    assert b.scan_angle_deg[0] == pytest.approx(0.6) and b.scan_angle_deg.max() < 30.0


def test_polygon_loses_pulses_beyond_the_survey_angle():
    sc = custom("polygon", max_scan_angle_deg=40.0, scan_angle_deg=20.0)
    s = survey_from_dict(airborne(sc))
    b = all_pulses(s)
    assert np.all(np.abs(b.scan_angle_deg) <= 20.0 + 1e-9)
    # mirror steps 0.8° over [-40, 40): the nodes -19.2 … 19.2 are emitted, and the nodes ±20 on
    # the window's edge as HELIOS++'s rounded sum decides: 49 to 51 per line
    ref, on = helios_mirror_angles(40.0, 10.0, 1000.0, s.n_slots, 20.0)
    np.testing.assert_array_equal(b.slot, np.flatnonzero(on))
    starts = np.flatnonzero(np.isclose(ref, -40.0))
    assert np.all(np.isin(np.add.reduceat(on, starts)[:-1], (49, 50, 51)))
    assert len(b) / s.n_slots == pytest.approx(20.0 / 40.0, abs=1.0 / 100 + 1e-12)


def test_rotating_window_emits_half_the_slots():
    s = survey_from_dict(airborne("riegl_minivux1uav", legs=[{"start": [0, 0, 70], "end": [0, 50, 70]}], speed=5.0))
    assert s.n_slots == 10 * 100_000
    b = all_pulses(s)
    assert len(b) / s.n_slots == pytest.approx(0.5, rel=0.01)
    assert np.all(np.abs(b.scan_angle_deg) <= 90.0 + 1e-9)
    assert np.all(b.direction[:, 2] <= 1e-12)  # never looks up
    # per rotation: 2,001 slots, angular step 0.18°, nadir included
    steps = np.diff(b.scan_angle_deg)
    assert np.allclose(steps[steps > 0], 0.18)
    # a ±45° survey angle inside the ±90° window: a quarter of the slots
    s45 = survey_from_dict(airborne("riegl_minivux1uav", overrides={"scan_angle_deg": 45.0},
                                    legs=[{"start": [0, 0, 70], "end": [0, 50, 70]}], speed=5.0))
    assert s45.n_slots == s.n_slots
    assert len(all_pulses(s45)) / s45.n_slots == pytest.approx(0.25, rel=0.01)


def test_oscillating_triangle_wave():
    s = survey_from_dict(airborne(custom("oscillating", scan_angle_deg=20.0)))
    b = all_pulses(s)
    assert len(b) == s.n_slots
    a = b.scan_angle_deg.reshape(-1, 100)  # PRF/scan_freq pulses per line
    up = -20.0 + 40.0 * np.arange(100) / 100
    assert np.allclose(a[0::2], up, atol=1e-9) and np.allclose(a[1::2], -up, atol=1e-9)
    # scan_dir follows the sweep: +x (right) on even lines, -x on odd lines (heading 0)
    sx = b.scan_dir[:, 0].reshape(-1, 100)
    assert np.all(sx[0::2] > 0) and np.all(sx[1::2] < 0)


def test_conic_directions_lie_on_the_cone():
    s = survey_from_dict(airborne(custom("conic", scan_angle_deg=15.0, scan_freq_hz=7.0),
                                  legs=[{"start": [0, 0, 100], "end": [60, 60, 120]}]))
    b = all_pulses(s)
    assert len(b) == s.n_slots
    off_nadir = np.degrees(np.arccos(np.clip(-b.direction[:, 2], -1, 1)))
    assert np.allclose(off_nadir, 15.0, atol=1e-6)
    # azimuth covers the full circle evenly
    az = np.degrees(np.arctan2(b.direction[:, 0], b.direction[:, 1])) % 360
    counts, _ = np.histogram(az, bins=36, range=(0, 360))
    assert counts.min() > 0.9 * counts.mean()


def _documented_pattern(sc, k):
    """The deflector patterns of vlsforest.sim.deflector's docstring, slot by slot in plain Python:
    (emitted, direction, scan_dir, scan angle) in the body frame."""
    out = []
    mirror = None
    if sc.deflector.kind in ("polygon", "rotating"):
        m = sc.deflector.max_scan_angle_deg if sc.deflector.kind == "polygon" else 180.0
        window = min(sc.deflector.effective_max_scan_angle_deg, sc.deflector.scan_angle_deg)
        mirror, mirror_on = helios_mirror_angles(m, sc.deflector.scan_freq_hz, sc.emitter.prf_hz, int(k.max()) + 1,
                                                 window)
    for kk in k.tolist():
        if sc.deflector.kind == "tls":
            n_el = int(round((sc.tls.v_fov_deg[1] - sc.tls.v_fov_deg[0]) / sc.tls.v_step_deg)) + 1
            az = math.radians(sc.tls.h_fov_deg[0] + (kk // n_el) * sc.tls.h_step_deg)
            el_deg = sc.tls.v_fov_deg[0] + (kk % n_el) * sc.tls.v_step_deg
            el = math.radians(el_deg)
            out.append((True, (math.cos(el) * math.sin(az), math.cos(el) * math.cos(az), math.sin(el)),
                        (-math.sin(el) * math.sin(az), -math.sin(el) * math.cos(az), math.cos(el)), el_deg))
            continue
        lines = kk * sc.deflector.scan_freq_hz / sc.emitter.prf_hz
        line, phase = math.floor(lines + 1e-12), (lines + 1e-12) % 1.0 - 1e-12
        if sc.deflector.kind == "conic":
            phi, c = 2 * math.pi * phase, math.radians(sc.deflector.scan_angle_deg)
            d = (math.sin(c) * math.sin(phi), math.sin(c) * math.cos(phi), -math.cos(c))
            out.append((True, d, (math.cos(phi), -math.sin(phi), 0.0), math.degrees(math.atan2(d[0], -d[2]))))
            continue
        sign = 1.0
        if mirror is not None:
            a = mirror[kk]
        else:  # oscillating: a triangle wave, back on odd lines
            t = sc.deflector.scan_angle_deg
            sign = -1.0 if line % 2 else 1.0
            a = sign * (-t + 2 * t * phase)
        if mirror is not None and not mirror_on[kk]:
            out.append((False, None, None, None))
            continue
        r = math.radians(a)
        out.append((True, (math.sin(r), 0.0, -math.cos(r)), (sign * math.cos(r), 0.0, sign * math.sin(r)), a))
    return out


@pytest.mark.parametrize("scanner", [
    "riegl_vq780i", "riegl_minivux1uav",
    custom("polygon", max_scan_angle_deg=35.0, scan_freq_hz=13.0),
    custom("rotating", scan_angle_deg=80.0, max_scan_angle_deg=90.0, scan_freq_hz=9.0),
    custom("oscillating", scan_freq_hz=11.0),
    custom("conic", scan_angle_deg=12.0, scan_freq_hz=3.0),
    "tls",
])
def test_deflect_follows_the_documented_patterns(scanner):
    """The compiled deflectors against the docstring's formulas evaluated slot by slot."""
    if scanner == "tls":
        sc = survey_from_dict(tls_survey()).scanner
        k = np.arange(0, 180 * 101, 7)
    else:
        sc = survey_from_dict(airborne(scanner)).scanner
        k = np.arange(0, 30_000, 3)
    emitted, direction, scan_dir, angle = deflect(sc, k)
    ref = _documented_pattern(sc, k)
    sure = np.ones(len(ref), bool)
    np.testing.assert_array_equal(emitted[sure], np.array([e for e, _, _, _ in ref])[sure])
    rows = np.cumsum(emitted) - 1
    keep = sure & emitted
    ref_e = [r for r, s in zip(ref, keep) if s]
    np.testing.assert_allclose(direction[rows[keep]], [r[1] for r in ref_e], atol=1e-12)
    np.testing.assert_allclose(scan_dir[rows[keep]], [r[2] for r in ref_e], atol=1e-12)
    np.testing.assert_allclose(angle[rows[keep]], [r[3] for r in ref_e], atol=1e-9)


DEFLECTOR_SURVEYS = {
    "polygon": lambda: airborne(custom("polygon", max_scan_angle_deg=35.0, scan_freq_hz=13.0)),
    "rotating": lambda: airborne(custom("rotating", scan_angle_deg=80.0, max_scan_angle_deg=90.0, scan_freq_hz=9.0)),
    "oscillating": lambda: airborne(custom("oscillating", scan_freq_hz=11.0)),
    "conic": lambda: airborne(custom("conic", scan_angle_deg=12.0, scan_freq_hz=3.0)),
    "tls": tls_survey,
}
TWO_LEGS = [
    {"start": [0, 0, 100], "end": [0, 30, 100]},
    {"start": [0, 30, 100], "end": [20, 30, 100], "active": False},
    {"start": [20, 30, 100], "end": [20, 0, 105]},
]


@pytest.mark.parametrize("kind", sorted(DEFLECTOR_SURVEYS))
@pytest.mark.parametrize("noisy", [False, True])
def test_pulses_do_not_depend_on_chunking(kind, noisy):
    d = DEFLECTOR_SURVEYS[kind]()
    if kind != "tls":
        d["platform"]["legs"] = TWO_LEGS
    if noisy:
        d["trajectory_noise"] = {"position_sigma_m": 0.2, "attitude_sigma_deg": 0.05, "correlation_s": 0.7}
        d["seed"] = 5
    s = survey_from_dict(d)
    whole = all_pulses(s)
    cuts = np.sort(np.random.default_rng(1).choice(np.arange(1, s.n_slots), 17, replace=False))
    edges = [0, *cuts.tolist(), s.n_slots]
    parts = PulseBatch.concat([s.pulses(a, b) for a, b in zip(edges[:-1], edges[1:])])
    assert len(parts) == len(whole)
    for f in FIELDS:
        np.testing.assert_array_equal(getattr(parts, f), getattr(whole, f), err_msg=f)
    # scan_dir is a unit vector perpendicular to the unit direction, for every deflector
    assert np.allclose(np.linalg.norm(whole.direction, axis=1), 1.0, atol=1e-12)
    assert np.allclose(np.linalg.norm(whole.scan_dir, axis=1), 1.0, atol=1e-12)
    assert np.abs(np.einsum("ij,ij->i", whole.direction, whole.scan_dir)).max() < 1e-12
    assert whole.slot.dtype == np.int64 and whole.source_id.dtype == np.uint16
    assert np.all(np.diff(whole.slot) > 0) and np.all(np.diff(whole.gps_time) > 0)


@pytest.mark.parametrize("kind", sorted(DEFLECTOR_SURVEYS))
@pytest.mark.parametrize("noisy", [False, True])
def test_pulses_toward_equals_pulses_then_cone_test(kind, noisy):
    """The compiled emitted-and-culled pulses are bit-identical to pulses() + the cone test."""
    from vlsforest.sim.engine import _beam_meets_box

    d = DEFLECTOR_SURVEYS[kind]()
    if kind != "tls":
        d["platform"]["legs"] = TWO_LEGS
    if noisy:
        d["trajectory_noise"] = {"position_sigma_m": 0.2, "attitude_sigma_deg": 0.05, "correlation_s": 0.7}
    s = survey_from_dict(d)
    boxes = [(np.array([-30.0, 5.0, -2.0]), np.array([10.0, 25.0, 20.0])),  # part of the swath / scene
             (np.array([-5.0, -1.0, -2.0]), np.array([5.0, 1.0, 2.0])),  # below the leg's first lines
             (np.array([-1e4, -1e4, -1e4]), np.array([1e4, 1e4, 1e4])),  # everything
             (np.array([500.0, 500.0, 0.0]), np.array([510.0, 510.0, 5.0])),  # far away
             (np.array([0.0, 0.0, -np.inf]), np.array([1.0, 1.0, 1.0]))]  # not finite: nothing
    tan_off = float(np.tan(0.0021))
    edges = [0, 7, s.n_slots // 3, s.n_slots // 3, s.n_slots]
    n_live = []
    for lo, hi in boxes:
        for a, b in zip(edges[:-1], edges[1:]):
            slot, live, batch = s.pulses_toward(a, b, lo, hi, tan_off)
            ref = s.pulses(a, b)
            ref_live = np.flatnonzero(_beam_meets_box(ref.origin, ref.direction, lo, hi, 0.0021))
            np.testing.assert_array_equal(slot, ref.slot)
            np.testing.assert_array_equal(live, ref_live)
            sub = ref.subset(ref_live)
            for f in FIELDS:
                x, y = getattr(batch, f), getattr(sub, f)
                assert x.dtype == y.dtype and x.tobytes() == y.tobytes(), f
            n_live.append(len(live))
    assert sum(n_live[8:12]) == len(s.pulses(0, s.n_slots)) and sum(n_live[16:]) == 0  # all; none


@pytest.mark.parametrize("kind", ["polygon", "rotating", "oscillating"])
def test_scan_line_bound_never_drops_a_pulse_that_meets_the_box(kind):
    """The per-scan-line angle bound skips only pulses whose cone misses the box: with many small
    boxes in and beside the swath (where it skips most), every box and every chunking gives the
    pulses of pulses() + the exact cone test, bit for bit; a wide cone too."""
    from vlsforest.sim.engine import _beam_meets_box

    d = DEFLECTOR_SURVEYS[kind]()
    d["platform"]["legs"] = TWO_LEGS
    s = survey_from_dict(d)
    rng = np.random.default_rng(7)
    ref = s.pulses(0, s.n_slots)
    for i in range(24):
        c = np.array([rng.uniform(-80, 100), rng.uniform(-20, 50), rng.uniform(-5, 60)])
        h = rng.uniform(0.05, 4.0, 3)
        lo, hi = c - h, c + h
        off = 0.0021 if i % 3 else 0.05
        ref_live = np.flatnonzero(_beam_meets_box(ref.origin, ref.direction, lo, hi, off))
        cut = int(rng.integers(1, s.n_slots))
        got = [s.pulses_toward(a, b, lo, hi, float(np.tan(off))) for a, b in ((0, cut), (cut, s.n_slots))]
        slot = np.concatenate([g[0] for g in got])
        live = np.concatenate([got[0][1], got[1][1] + len(got[0][0])])
        np.testing.assert_array_equal(slot, ref.slot)
        np.testing.assert_array_equal(live, ref_live)
        for f in FIELDS:
            x = np.concatenate([getattr(g[2], f) for g in got])
            assert x.tobytes() == getattr(ref.subset(ref_live), f).tobytes(), f


def test_scan_line_bound_is_tight_for_a_small_far_box():
    """The bound of one scan line from 100 m up to a 2 m box below: the passing angles lie within
    a few box-radii / range of the direction to the box; a box beside the scan plane: none pass;
    the platform inside the box: no bound."""
    from vlsforest.sim.pulses import _line_window

    s = survey_from_dict(airborne(custom("rotating", scan_angle_deg=80.0, max_scan_angle_deg=90.0, scan_freq_hz=9.0),
                                  legs=[{"start": [0, 0, 100], "end": [0, 100, 100]}]))
    m = s.motion
    pattern = deflector_pattern(s.scanner)
    first, period = int(pattern.lines[0]), int(pattern.lines[1])
    args = (m.p0, m.vel, m.rot, pattern.prf, pattern.freq, first, period)
    n_k = int(m.offsets[1] - m.offsets[0])
    # the line at t ≈ 0.5 s (platform at y ≈ 5 m) and a 2 m box straight below it
    line = float(sweep(pattern.kind, int(0.5 * pattern.prf), *pattern.args()[1:6])[0])
    assert line >= 1
    mode, phi, beta = _line_window(0, line, n_k, *args, np.array([-1.0, 4.0, -1.0]), np.array([1.0, 6.0, 1.0]), 1e-3)
    assert mode == 2
    b = s.pulses(0, s.n_slots)
    k_lo = first + (line - 1) * period
    in_line = np.flatnonzero((b.slot >= k_lo) & (b.slot < k_lo + period))
    below = in_line[np.argmin(np.abs(b.direction[in_line, 2] + 1))]
    r_below = np.radians(b.scan_angle_deg[below])
    # the window is centred on nadir: the line's beam nearest to it lies within half a step
    assert abs(r_below - phi) <= 0.5 * np.radians(pattern.b) + 1e-9
    assert np.sqrt(3) / 101 < beta < 3 * np.sqrt(3) / 99  # half-diagonal / range, with the line's motion and padding
    mode, _, _ = _line_window(0, line, n_k, *args, np.array([-1.0, 40.0, -1.0]), np.array([1.0, 42.0, 1.0]), 1e-3)
    assert mode == 0  # 35 m ahead of a line that sweeps across track
    mode, _, _ = _line_window(0, line, n_k, *args, np.array([-10.0, -10.0, 90.0]), np.array([10.0, 20.0, 110.0]), 1e-3)
    assert mode == 1


def test_scan_dir_points_the_way_the_beam_sweeps():
    for kind in ("polygon", "rotating", "conic", "tls"):
        s = survey_from_dict(DEFLECTOR_SURVEYS[kind]())
        b = s.pulses(0, 2000)
        same_line = np.diff(b.slot) == 1
        step = np.diff(b.direction, axis=0)[same_line]
        along = np.einsum("ij,ij->i", step, b.scan_dir[:-1][same_line])
        # most consecutive pulses move along scan_dir (line wraps move backwards)
        assert np.mean(along > 0) > 0.9, kind


# --------------------------------------------------------------------------- platform


def test_platform_advances_speed_over_prf_per_slot():
    s = survey_from_dict(airborne(custom("oscillating"), legs=TWO_LEGS, speed=12.5))
    prf = 1000.0
    b = all_pulses(s)
    first = b.source_id == 1
    o = b.origin[first]
    step = np.diff(o, axis=0)
    assert np.allclose(step, [0.0, 12.5 / prf, 0.0], atol=1e-12)
    assert np.allclose(np.diff(b.gps_time[first]), 1 / prf, atol=1e-12)
    assert b.gps_time[0] == 0.0 and np.array_equal(b.origin[0], [0.0, 0.0, 100.0])
    # slot counts: 30 m and the 30.41 m climbing leg at 12.5 m/s and 1 kHz
    n1 = math.ceil(30 / 12.5 * prf)
    n3 = math.ceil(math.hypot(30, 5) / 12.5 * prf)
    assert s.n_slots == n1 + n3
    assert s.source_slot_ranges() == [(1, 0, n1), (2, n1, n1 + n3)]
    # the inactive 20 m leg passes time without slots; source ids count active legs only
    second = b.source_id == 2
    t2 = (30 + 20) / 12.5
    assert b.gps_time[second][0] == pytest.approx(t2, abs=1e-12)
    assert b.slot[second][0] == n1
    assert np.array_equal(np.unique(b.source_id), [1, 2])
    # the climbing leg: origin moves along the leg at speed, attitude stays level
    u = np.array([0, -30, 5]) / math.hypot(30, 5)
    dt = b.gps_time[second] - t2
    assert np.allclose(b.origin[second], np.array([20, 30, 100]) + dt[:, None] * 12.5 * u, atol=1e-9)
    assert np.allclose(b.direction[second][:, 0] ** 2 + b.direction[second][:, 2] ** 2, 1.0)  # no pitch


def test_transit_between_disjoint_legs_takes_time():
    legs = [{"start": [0, 0, 100], "end": [0, 40, 100]}, {"start": [30, 40, 100], "end": [30, 0, 100]}]
    s = survey_from_dict(airborne(custom("polygon"), legs=legs, speed=10.0))
    assert s.legs[1].t_start == pytest.approx((40 + 30) / 10)
    assert s.duration_s == pytest.approx((40 + 30 + 40) / 10)


def test_heading_follows_the_leg():
    # flying +y (north): across-track sweep along ±x, positive angles to the right (east)
    s = survey_from_dict(airborne(custom("polygon")))
    b = all_pulses(s)
    assert np.all(b.direction[:, 1] == 0.0)
    assert np.all(np.sign(b.direction[:, 0]) == np.sign(b.scan_angle_deg))
    assert s.legs[0].heading_deg == 0.0
    # flying +x (east): sweep along ±y, right of track is south (-y)
    s = survey_from_dict(airborne(custom("polygon"), legs=[{"start": [0, 0, 100], "end": [100, 0, 100]}]))
    b = all_pulses(s)
    assert np.abs(b.direction[:, 0]).max() < 1e-15
    right = b.scan_angle_deg > 1
    assert np.all(b.direction[right, 1] < 0)
    assert s.legs[0].heading_deg == pytest.approx(90.0)
    # flying south-west: sweep perpendicular to the track
    s = survey_from_dict(airborne(custom("polygon"), legs=[{"start": [0, 0, 100], "end": [-50, -50, 100]}]))
    b = all_pulses(s)
    track = np.array([-1.0, -1.0, 0.0]) / math.sqrt(2)
    assert np.abs(b.direction @ track).max() < 1e-12
    assert s.legs[0].heading_deg == pytest.approx(225.0)
    traj = s.trajectory()
    assert np.allclose(traj.heading_deg, 225.0) and np.all(traj.roll_deg == 0) and np.all(traj.pitch_deg == 0)


def test_flat_ground_footprint_spacing():
    h, speed = 700.0, 51.0
    s = survey_from_dict(airborne("riegl_vq780i", legs=[{"start": [0, 0, h], "end": [0, 10.2, h]}], speed=speed))
    b = all_pulses(s)
    p = ground_hits(b)
    # across track at nadir: altitude × angular step (the mirror's 90° in steps of 90°/4000)
    dtheta = math.radians(90.0 / 4000)
    starts = np.flatnonzero(np.diff(b.scan_angle_deg) < 0) + 1  # a line after the first starts at -30°
    line0, line1 = p[starts[0]:starts[1]], p[starts[1]:starts[2]]
    assert len(line0) == len(line1) == 2667
    mid = np.argmin(np.abs(line0[:, 0]))
    spacing = line0[mid + 1, 0] - line0[mid, 0]
    assert spacing == pytest.approx(h * dtheta, rel=1e-3)
    # along track: lines are speed × (slots per line) / PRF apart, 4,001 slots as HELIOS++ steps them
    assert line1[mid, 1] - line0[mid, 1] == pytest.approx(speed * 4001 / 1e6, rel=1e-9)
    # within one line the spot drifts by speed/PRF per slot
    assert line0[mid + 1, 1] - line0[mid, 1] == pytest.approx(speed / 1e6, rel=1e-6)
    # swath: ±30° → 2 h tan 30°; the ground points span it up to one across-track step
    sw = s.swath_width(0.0)
    assert sw.shape == (1,) and sw[0] == pytest.approx(2 * h * math.tan(math.radians(30)))
    extent = p[:, 0].max() - p[:, 0].min()
    assert sw[0] - extent == pytest.approx(0, abs=2 * h * dtheta)
    assert s.swath_width(100.0)[0] == pytest.approx(2 * 600 * math.tan(math.radians(30)))


def test_rotating_swath_is_unbounded():
    s = survey_from_dict(airborne("riegl_minivux1uav", legs=[{"start": [0, 0, 70], "end": [0, 5, 70]}]))
    assert math.isinf(s.swath_width(0.0)[0])


# --------------------------------------------------------------------------- trajectory and noise


def test_trajectory_columns_and_sampling():
    s = survey_from_dict(airborne(custom("polygon"), legs=TWO_LEGS, speed=12.5))
    traj = s.trajectory()
    assert list(traj.columns) == ["gps_time", "x", "y", "z", "roll_deg", "pitch_deg", "heading_deg", "source_id"]
    t1 = traj[traj.source_id == 1]
    assert np.allclose(np.diff(t1.gps_time), 0.1)
    assert t1.gps_time.iloc[-1] == pytest.approx(30 / 12.5)
    assert np.allclose(t1.y, t1.gps_time * 12.5)
    t2 = traj[traj.source_id == 2]
    assert t2.gps_time.iloc[0] == pytest.approx(50 / 12.5)
    assert np.allclose(t2.heading_deg, 180.0)
    assert t2.z.iloc[-1] == pytest.approx(105.0)


def _noisy_survey(pos=0.5, att=0.2, tau=1.0, seconds=2000.0, seed=3):
    speed = 10.0
    legs = [{"start": [0, 0, 500], "end": [0, speed * seconds, 500]}]
    d = airborne(custom("conic", prf_hz=200.0, scan_freq_hz=5.0), legs=legs, speed=speed, seed=seed)
    d["trajectory_noise"] = {"position_sigma_m": pos, "attitude_sigma_deg": att, "correlation_s": tau}
    return survey_from_dict(d), speed


def test_trajectory_noise_sigma_and_correlation():
    s, speed = _noisy_survey()
    traj = s.trajectory()
    nominal = s.trajectory(nominal=True)
    assert np.array_equal(traj.gps_time, nominal.gps_time)
    dev = {
        "x": traj.x - nominal.x,
        "y": traj.y - nominal.y,
        "z": traj.z - nominal.z,
        "roll": traj.roll_deg,
        "pitch": traj.pitch_deg,
        "yaw": (traj.heading_deg + 180) % 360 - 180,
    }
    for name, v in dev.items():
        sigma = 0.5 if name in "xyz" else 0.2
        v = np.asarray(v)
        assert abs(v.mean()) < 0.1 * sigma, name
        assert np.std(v) == pytest.approx(sigma, rel=0.10), name
    # autocorrelation at one correlation time ≈ exp(-1/2) (Gaussian kernel), averaged over channels
    lag = 10  # 1 s at 10 Hz
    rho = [np.corrcoef(np.asarray(v)[:-lag], np.asarray(v)[lag:])[0, 1] for v in dev.values()]
    assert np.mean(rho) == pytest.approx(math.exp(-0.5), abs=0.1)
    # a different seed gives a different realisation
    s2, _ = _noisy_survey(seed=4)
    assert not np.allclose(s2.trajectory().x, traj.x)


def test_trajectory_noise_moves_pulses_like_the_trajectory():
    s, speed = _noisy_survey(seconds=20.0)
    clean, _ = _noisy_survey(pos=0.0, att=0.0, seconds=20.0)
    traj = s.trajectory()
    b = all_pulses(s)
    b0 = all_pulses(clean)
    # the pulse at t = 0.1·j coincides with trajectory sample j
    idx = np.searchsorted(b.gps_time, traj.gps_time.to_numpy()[:-1] - 1e-9)
    assert np.allclose(b.gps_time[idx], traj.gps_time.to_numpy()[:-1], atol=1e-12)
    assert np.allclose(b.origin[idx], traj[["x", "y", "z"]].to_numpy()[:-1], atol=1e-12)
    # attitude noise turns the beam by about sqrt(3)·σ at most a few σ
    ang = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", b.direction, b0.direction), -1, 1)))
    assert 0.05 < np.median(ang) < 0.6


def test_no_noise_is_exactly_zero():
    d = airborne(custom("polygon"), seed=9)
    s = survey_from_dict(d)
    b = all_pulses(s)
    assert np.all(b.origin[:, 0] == 0.0) and np.all(b.origin[:, 2] == 100.0)
    d["trajectory_noise"] = {"position_sigma_m": 0.0, "attitude_sigma_deg": 0.0}
    b2 = all_pulses(survey_from_dict(d))
    for f in FIELDS:
        np.testing.assert_array_equal(getattr(b, f), getattr(b2, f))
    traj = s.trajectory()
    assert np.all(traj.x == 0.0) and np.all(traj.roll_deg == 0.0)


# --------------------------------------------------------------------------- TLS


def test_tls_slots_and_field_of_view():
    s = survey_from_dict(tls_survey())
    sc = s.scanner
    az, el = tls_grid(sc.tls)
    assert len(az) == 180 and len(el) == 101  # 360° / 2°, -40…60° in 1° steps
    assert s.n_slots == 2 * len(az) * len(el)
    b = all_pulses(s)
    assert len(b) == s.n_slots
    first = b.subset(b.source_id == 1)
    elev = np.degrees(np.arcsin(first.direction[:, 2]))
    assert elev.min() == pytest.approx(-40.0) and elev.max() == pytest.approx(60.0)
    assert np.allclose(elev, first.scan_angle_deg)
    azim = np.degrees(np.arctan2(first.direction[:, 0], first.direction[:, 1])) % 360
    nodes, counts = np.unique(np.round(azim, 6) % 360, return_counts=True)
    assert np.allclose(nodes, az) and np.all(counts == len(el))  # every azimuth node, a full line each
    # slot order: azimuth-major, vertical lines from v min to v max
    assert np.allclose(first.scan_angle_deg[:101], el) and np.allclose(azim[:101], 0.0)
    assert np.allclose(first.scan_dir[:101], [[0, -math.sin(math.radians(e)), math.cos(math.radians(e))] for e in el])
    # scans follow each other in time at 1/PRF per slot
    n = len(az) * len(el)
    assert b.gps_time[n] == pytest.approx(n / sc.emitter.prf_hz)
    assert np.array_equal(b.origin[n], [10.0, 0.0, 1.5])


def test_tls_heading_and_tilt():
    s = survey_from_dict(tls_survey())
    b = all_pulses(s).subset(slice(s.n_slots // 2, None))  # second scan: heading 90°, tilt 30°
    az, el = tls_grid(s.scanner.tls)
    j0 = int(np.argmin(np.abs(el)))  # azimuth 0, elevation 0 → the head's forward axis
    tilt = math.radians(30)
    # tilt about the head's x axis raises forward by 30°, heading 90° turns forward to east
    assert np.allclose(b.direction[j0], [math.cos(tilt), 0.0, math.sin(tilt)], atol=1e-12)
    # azimuth 90° (head right) stays horizontal under the tilt and points south
    k = 45 * len(el) + j0
    assert np.allclose(b.direction[k], [0.0, -1.0, 0.0], atol=1e-12)


def test_tls_partial_fov_counts():
    s = survey_from_dict(tls_survey(tls_h_fov_deg=[30, 130], tls_h_step_deg=0.5, tls_v_fov_deg=[-10, 50],
                                    tls_v_step_deg=0.25))
    assert s.n_slots == 2 * 201 * 241
    b = s.pulses(0, 201 * 241)
    azim = np.degrees(np.arctan2(b.direction[:, 0], b.direction[:, 1])) % 360
    assert azim.min() == pytest.approx(30.0) and azim.max() == pytest.approx(130.0)


# --------------------------------------------------------------------------- parsing and errors


def test_load_survey_yaml(tmp_path):
    p = tmp_path / "SURVEY.yaml"
    p.write_text(
        "scanner: riegl_vq780i\n"
        "overrides: {prf_hz: 2e5, beam_divergence_mrad: [0.3, 0.2], max_returns: 5}\n"
        "platform:\n"
        "  type: linear\n"
        "  speed_mps: 51\n"
        "  legs:\n"
        "    - {start: [0, 0, 700], end: [0, 102, 700]}\n"
        "    - {start: [0, 102, 700], end: [175, 102, 700], active: false}\n"
        "    - {start: [175, 102, 700], end: [175, 0, 700]}\n"
        "trajectory_noise: {position_sigma_m: 0.05}\n"
        "seed: 7\n"
        "detector: {mode: paper, window_rule: helios}\n"
        "output: {dir: out}\n"
    )
    s = load_survey(p)
    sc = s.scanner
    assert sc.emitter.prf_hz == 2e5 and sc.beam.divergence_mrad == (0.3, 0.2) and sc.detector.max_returns == 5
    assert s.seed == 7 and s.detector == {"mode": "paper", "window_rule": "helios"} and s.output == {"dir": "out"}
    assert s.noise.position_sigma_m == 0.05 and s.noise.attitude_sigma_deg == 0.0 and s.noise.correlation_s == 1.0
    assert s.n_slots == 2 * 400_000 and s.n_sources == 2
    assert s.base_dir == tmp_path.resolve()


def test_yaml_errors_give_the_line(tmp_path):
    p = tmp_path / "SURVEY.yaml"
    p.write_text("scanner: riegl_vq780i\nplatform:\n  legs: [{start: [0, 0, 1]\n  speed_mps: 3\n")
    with pytest.raises(ConfigError, match=r"line \d+"):
        load_survey(p)
    p.write_text("scanner: riegl_vq780i\nseed: 1\nseed: 2\n")
    with pytest.raises(ConfigError, match=r"line 3.*duplicate key 'seed'"):
        load_survey(p)
    p.write_text("")
    with pytest.raises(ConfigError, match="empty"):
        load_survey(p)
    with pytest.raises(ConfigError, match="not found"):
        load_survey(tmp_path / "missing.yaml")


GOOD = airborne("riegl_vq780i", legs=[
    {"start": [0, 0, 700], "end": [0, 100, 700]},
    {"start": [0, 100, 700], "end": [100, 100, 700], "active": False},
    {"start": [100, 100, 700], "end": [100, 0, 700]},
], speed=51.0)


def _set(path, value):
    d = copy.deepcopy(GOOD)
    *parents, last = path
    node = d
    for k in parents:
        node = node[k]
    if value is _DELETE:
        del node[last]
    else:
        node[last] = value
    return d


_DELETE = object()
BAD_SURVEYS = [
    (_set(["colour"], "red"), "colour"),
    (_set(["scanner"], _DELETE), "scanner"),
    (_set(["platform"], _DELETE), "platform"),
    (_set(["scanner"], "nope"), "scanner"),
    (_set(["overrides"], {"prf_hz": -1}), r"overrides\.prf_hz"),
    (_set(["overrides"], [1, 2]), "overrides"),
    (_set(["platform", "legs"], []), r"platform\.legs"),
    (_set(["platform", "legs"], _DELETE), r"platform\.legs"),
    (_set(["platform", "legs", 2, "end"], [1, 2]), r"platform\.legs\[2\]\.end"),
    (_set(["platform", "legs", 2, "end"], [1, 2, float("nan")]), r"platform\.legs\[2\]\.end"),
    (_set(["platform", "legs", 0, "start"], [0, "a", 0]), r"platform\.legs\[0\]\.start"),
    (_set(["platform", "legs", 1, "end"], [0, 100, 700]), r"platform\.legs\[1\]"),
    (_set(["platform", "legs", 1, "active"], "no"), r"platform\.legs\[1\]\.active"),
    (_set(["platform", "legs", 1, "speed"], 3), r"platform\.legs\[1\]\.speed"),
    (_set(["platform", "speed_mps"], 0), r"platform\.speed_mps"),
    (_set(["platform", "speed_mps"], float("nan")), r"platform\.speed_mps"),
    (_set(["platform", "speed_mps"], _DELETE), r"platform\.speed_mps"),
    (_set(["platform", "type"], "helicopter"), r"platform\.type"),
    (_set(["platform", "type"], "static"), r"platform\.type"),
    (_set(["platform", "altitude"], 5), r"platform\.altitude"),
    (_set(["trajectory_noise"], {"position_sigma_m": -1}), r"trajectory_noise\.position_sigma_m"),
    (_set(["trajectory_noise"], {"correlation_s": 0}), r"trajectory_noise\.correlation_s"),
    (_set(["trajectory_noise"], {"sigma": 1}), r"trajectory_noise\.sigma"),
    (_set(["seed"], -1), "seed"),
    (_set(["seed"], 1.5), "seed"),
    (_set(["detector"], "paper"), "detector"),
    ({**tls_survey(), "platform": {"type": "static", "positions": [{"position": [0, 0]}]}},
     r"platform\.positions\[0\]\.position"),
    ({**tls_survey(), "platform": {"type": "static", "positions": []}}, r"platform\.positions"),
    ({**tls_survey(), "platform": {"type": "static", "positions": [{"position": [0, 0, 1], "tilt_deg": 100}]}},
     r"platform\.positions\[0\]\.tilt_deg"),
    ({**tls_survey(), "platform": {"type": "linear", "speed_mps": 1, "legs": GOOD["platform"]["legs"]}},
     r"platform\.type"),
]


@pytest.mark.parametrize("d,key", BAD_SURVEYS)
def test_bad_surveys_name_the_key(d, key):
    with pytest.raises(ConfigError, match=key):
        survey_from_dict(d)


def test_no_active_leg_is_an_error():
    d = copy.deepcopy(GOOD)
    for leg in d["platform"]["legs"]:
        leg["active"] = False
    with pytest.raises(ConfigError, match=r"platform\.legs"):
        survey_from_dict(d)


def test_pulse_range_is_checked():
    s = survey_from_dict(GOOD)
    with pytest.raises(ValueError):
        s.pulses(-1, 5)
    with pytest.raises(ValueError):
        s.pulses(0, s.n_slots + 1)
    assert len(s.pulses(3, 3)) == 0
