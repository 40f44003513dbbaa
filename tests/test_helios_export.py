"""HELIOS++ export of a survey (``vlsforest scene helios --survey``): the XML read back with
xml.etree and checked against values derived here, independently of the exporter.

The beam-direction tests rebuild HELIOS++'s beam from the written XML with its conventions,
learnt from its source (v1.0.8 and 2.x): ``Rotation(axis, angle)`` turns vectors right-handedly,
``<rot>`` children compose about fixed axes (each later one applied after), the beam is
``mount · head · beamOrigin · deflector · (0, 1, 0)``, a deflector turns about x, the head about
``headRotateAxis``, and the linear platform yaws about z to face its next waypoint. The expected
directions are the simulator's own pulses (:meth:`vlsforest.sim.Survey.pulses`).
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
import yaml

from vlsforest.cli import main
from vlsforest.sim import load_survey

HELIOS_V1 = {"mode": "helios_v1"}


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """The demo scene (a ground plane, a stem mesh, a voxel crown)."""
    d = tmp_path_factory.mktemp("helios_scene")
    assert main(["demo", "-o", str(d / "scene.yaml"), "--seed", "1"]) == 0
    return d / "scene.yaml"


def _write(path: Path, doc: dict) -> Path:
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def _export(scene, survey, out, *extra):
    return main(["scene", "helios", str(scene), "--survey", str(survey), "-o", str(out), *extra])


def _xml(out: Path):
    """The survey, its scanner and its platform elements, following the survey's references."""
    survey = ET.parse(out / "survey.xml").getroot().find("survey")

    def asset(ref, tag):
        fname, ident = ref.split("#")
        found = [e for e in ET.parse(out / fname).getroot().findall(tag) if e.get("id") == ident]
        assert len(found) == 1, (ref, tag)
        return found[0]

    scene_file, scene_id = survey.get("scene").split("#")
    assert ET.parse(out / scene_file).getroot().find("scene").get("id") == scene_id
    return survey, asset(survey.get("scanner"), "scanner"), asset(survey.get("platform"), "platform")


def _f(el, key):
    return float(el.get(key))


# ------------------------------------------------------------------ HELIOS++'s beam, rebuilt
_AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}
_FORWARD = np.array([0.0, 1.0, 0.0])


def _rot(axis, deg):
    """Right-handed rotation of vectors about ``axis`` by ``deg`` degrees (Rodrigues)."""
    a = np.asarray(axis, np.float64)
    a = a / np.linalg.norm(a)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    t = math.radians(deg)
    return np.eye(3) + math.sin(t) * k + (1 - math.cos(t)) * (k @ k)


def _rots(el):
    """The rotation of an element's ``<rot>`` children, composed about fixed axes."""
    r = np.eye(3)
    for rot in el.findall("rot"):
        r = _rot(_AXES[rot.get("axis").lower()], float(rot.get("angle_deg"))) @ r
    return r


def _vec(el):
    return np.array([_f(el, "x"), _f(el, "y"), _f(el, "z")])


# ------------------------------------------------------------------------- a linear survey
def _vq780i_survey(tmp_path):
    """Two active legs with their own speeds, the second not starting where the first ended."""
    return _write(tmp_path / "als.yaml", {
        "scanner": "riegl_vq780i", "overrides": {"window_size_ns": 1.75}, "detector": HELIOS_V1,
        "platform": {"type": "linear", "speed_mps": 51.0, "legs": [
            {"start": [-100.0, -300.0, 700.0], "end": [-100.0, 300.0, 700.0]},
            {"start": [80.0, 310.0, 710.0], "end": [80.0, -290.0, 710.0], "speed_mps": 45.5}]}})


def test_vq780i_survey_scanner_and_legs(scene, tmp_path):
    out = tmp_path / "helios"
    assert _export(scene, _vq780i_survey(tmp_path), out) == 0
    survey, scanner, platform = _xml(out)
    # the scanner entry: the RIEGL VQ-780i as the study ran it in HELIOS++ 1.0.8
    assert scanner.get("optics") == "rotating"
    assert scanner.get("pulseFreqs_Hz") == "1000000"
    assert _f(scanner, "scanAngleMax_deg") == 45.0
    assert _f(scanner, "scanAngleEffectiveMax_deg") == 30.0
    assert _f(scanner, "beamDivergence_rad") == pytest.approx(0.25e-3, rel=1e-15)  # the preset's 1/e² half angle
    assert _f(scanner, "accuracy_m") == 0.02 and _f(scanner, "rangeMin_m") == 100.0
    assert _f(scanner, "pulseLength_ns") == 4.0 and scanner.get("wavelength_nm") == "1064"
    assert _f(scanner, "scanFreqMax_Hz") == 250.0 and _f(scanner, "scanFreqMin_Hz") == 0.0
    assert scanner.get("maxNOR") == "0"
    # no atmosphere: a visibility so large that HELIOS++'s extinction vanishes
    assert _f(scanner, "atmosphericVisibility_km") >= 1e9
    fwf = survey.find("FWFSettings")
    assert (_f(fwf, "binSize_ns"), _f(fwf, "winSize_ns"), fwf.get("beamSampleQuality")) == (0.25, 1.75, "3")
    assert platform.get("type") == "linearpath"
    # waypoints: leg 0's start, the transit from leg 0's end, leg 1's start, leg 1's end
    legs = survey.findall("leg")
    expected = [((-100, -300, 700), True, 51.0), ((-100, 300, 700), False, 45.5),
                ((80, 310, 710), True, 45.5), ((80, -290, 710), False, 45.5)]
    assert len(legs) == len(expected)
    for leg, (xyz, active, speed) in zip(legs, expected):
        ps, ss = leg.find("platformSettings"), leg.find("scannerSettings")
        assert tuple(_vec(ps)) == xyz
        assert ps.get("onGround") == "false"
        assert _f(ps, "movePerSec_m") == speed
        assert ss.get("active") == ("true" if active else "false")
        assert ss.get("pulseFreq_hz") == "1000000"  # integers: HELIOS++ 1.0.8 reads them as int
        assert ss.get("scanFreq_hz") == "250"
        assert _f(ss, "scanAngle_deg") == 30.0
        assert _f(ss, "headRotatePerSec_deg") == 0.0
    # the scene written beside the survey is the scene export itself, byte for byte
    assert main(["scene", "helios", str(scene), "-o", str(tmp_path / "scene_only")]) == 0
    for f in (tmp_path / "scene_only").iterdir():
        assert (out / f.name).read_bytes() == f.read_bytes(), f.name


@pytest.mark.parametrize("preset", ["riegl_vq780i", "riegl_minivux1uav", "riegl_minivux1uav_helios1"])
def test_linear_beam_directions_match_the_simulator(scene, tmp_path, preset):
    doc = {"scanner": preset, "overrides": {"prf_hz": 20000, "scan_freq_hz": 40}, "detector": HELIOS_V1,
           "platform": {"speed_mps": 10.0, "legs": [{"start": [0.0, 0.0, 100.0], "end": [30.0, 40.0, 100.0]},
                                                    {"start": [30.0, 40.0, 100.0], "end": [-20.0, 40.0, 110.0]}]}}
    path = _write(tmp_path / "s.yaml", doc)
    out = tmp_path / "helios"
    assert _export(scene, path, out) == 0
    survey, scanner, platform = _xml(out)
    mount = _rots(platform.find("scannerMount"))
    emitter = _rots(scanner.find("beamOrigin"))
    assert _f(scanner, "headRotatePerSecMax_deg") == 0.0
    legs = survey.findall("leg")
    sim = load_survey(path)
    batch = sim.pulses(0, sim.n_slots)
    checked = 0
    for src in (1, 2):
        a, b = _vec(legs[src - 1].find("platformSettings")), _vec(legs[src].find("platformSettings"))
        yaw = _rot((0, 0, 1), math.degrees(math.atan2(-(b - a)[0], (b - a)[1])))  # forward faces b
        sel = np.flatnonzero(batch.source_id == src)
        for i in sel[:: max(1, len(sel) // 200)]:
            beam = yaw @ mount @ emitter @ _rot((1, 0, 0), batch.scan_angle_deg[i]) @ _FORWARD
            assert np.allclose(beam, batch.direction[i], atol=1e-12), (src, batch.scan_angle_deg[i])
            checked += 1
    assert checked > 100
    # the scan-angle window is the simulator's: every emitted pulse within the XML's limits
    limit = min(_f(scanner, "scanAngleEffectiveMax_deg"), _f(legs[0].find("scannerSettings"), "scanAngle_deg"))
    assert np.abs(batch.scan_angle_deg).max() <= limit + 1e-9
    assert np.abs(batch.scan_angle_deg).max() > limit - 2.0


def test_minivux_is_a_full_turn_mirror(scene, tmp_path):
    doc = {"scanner": "riegl_minivux1uav", "detector": HELIOS_V1,
           "platform": {"speed_mps": 5.0, "legs": [{"start": [0, -30, 70], "end": [0, 30, 70]}]}}
    out = tmp_path / "helios"
    assert _export(scene, _write(tmp_path / "uls.yaml", doc), out) == 0
    survey, scanner, _ = _xml(out)
    assert scanner.get("optics") == "rotating"
    assert (_f(scanner, "scanAngleMax_deg"), _f(scanner, "scanAngleEffectiveMax_deg")) == (180.0, 180.0)
    assert _f(scanner, "beamDivergence_rad") == pytest.approx(0.5e-3, rel=1e-15)
    assert scanner.get("wavelength_nm") == "905"
    ss = survey.find("leg/scannerSettings")
    assert (ss.get("pulseFreq_hz"), ss.get("scanFreq_hz"), _f(ss, "scanAngle_deg")) == ("100000", "50", 90.0)


def test_oscillating_and_conic_scanners(scene, tmp_path):
    base = {"prf_hz": 50000, "scan_freq_hz": 60, "scan_angle_deg": 20, "max_scan_angle_deg": 25,
            "beam_divergence_mrad": 0.3}
    legs = {"speed_mps": 50.0, "legs": [{"start": [0, -300, 500], "end": [0, 300, 500]}]}
    for deflector, optics, freq in (("oscillating", "oscillating", 30.0), ("conic", "conic", 60.0)):
        doc = {"scanner": {"deflector": deflector, **base}, "detector": HELIOS_V1, "platform": legs}
        out = tmp_path / deflector
        assert _export(scene, _write(tmp_path / f"{deflector}.yaml", doc), out) == 0
        survey, scanner, _ = _xml(out)
        assert scanner.get("optics") == optics
        assert _f(scanner, "scanAngleMax_deg") == 25.0
        # oscillating: HELIOS++ counts a period (there and back) as one line; conic: it turns
        # the cone at the device's maximum frequency, written as the survey's
        assert _f(survey.find("leg/scannerSettings"), "scanFreq_hz") == freq
        assert _f(scanner, "scanFreqMax_Hz") == freq
        if deflector == "oscillating":
            assert int(scanner.get("scanProduct")) >= 20 * 30


# ------------------------------------------------------------------------------ a TLS survey
def _tls_survey(tmp_path, positions):
    return _write(tmp_path / "tls.yaml", {
        "scanner": "riegl_vz400", "detector": HELIOS_V1,
        "overrides": {"prf_hz": 100000, "tls_h_step_deg": 0.5, "tls_v_step_deg": 0.25},
        "platform": {"type": "static", "positions": positions}})


def test_tls_survey_head_rotation(scene, tmp_path):
    positions = [{"position": [1.0, 2.0, 1.5]}, {"position": [-5.0, 3.0, 1.6], "heading_deg": 30.0}]
    path = _tls_survey(tmp_path, positions)
    out = tmp_path / "helios"
    assert _export(scene, path, out) == 0
    survey, scanner, platform = _xml(out)
    assert platform.get("type") == "static"
    assert scanner.get("optics") == "rotating"
    # the VZ-400's −40° … +60° field: a mirror sweeping ±50° about an emitter tilted by +10°
    assert (_f(scanner, "scanAngleMax_deg"), _f(scanner, "scanAngleEffectiveMax_deg")) == (50.0, 50.0)
    rots = scanner.findall("beamOrigin/rot")
    assert [(r.get("axis"), float(r.get("angle_deg"))) for r in rots] == [("x", 10.0)]
    assert tuple(_vec(scanner.find("headRotateAxis"))) == (0.0, 0.0, -1.0)  # clockwise azimuths
    legs = survey.findall("leg")
    assert len(legs) == 2
    # a line of 0.25° steps over 100° at 100 kHz: 250 lines/s; the head turns 0.5° per line
    for leg, pos in zip(legs, positions):
        ps, ss = leg.find("platformSettings"), leg.find("scannerSettings")
        assert list(_vec(ps)) == pos["position"]
        assert ss.get("pulseFreq_hz") == "100000" and ss.get("scanFreq_hz") == "250"
        assert _f(ss, "scanAngle_deg") == 50.0
        assert _f(ss, "headRotatePerSec_deg") == 125.0
        start = pos.get("heading_deg", 0.0)
        assert _f(ss, "headRotateStart_deg") == start
        assert _f(ss, "headRotateStop_deg") == start + 360.0
    assert _f(scanner, "headRotatePerSecMax_deg") >= 125.0
    # directions: head angle = start + 0.5° per vertical line, mirror = elevation − 10°
    sim = load_survey(path)
    mount = _rots(platform.find("scannerMount"))
    emitter = _rots(scanner.find("beamOrigin"))
    axis = _vec(scanner.find("headRotateAxis"))
    n_el = 401  # −40° … +60° in 0.25° steps
    for p, (leg, pos) in enumerate(zip(legs, sim.positions)):
        start = _f(leg.find("scannerSettings"), "headRotateStart_deg")
        ks = np.array([0, 1, 200, 400, 401, 12345, pos.n_slots - 1])
        batch = sim.pulses(pos.slot_offset + ks[0], pos.slot_offset + ks[-1] + 1)
        for k in ks:
            i, j = divmod(int(k), n_el)
            beam = mount @ _rot(axis, start + 0.5 * i) @ emitter @ _rot((1, 0, 0), -40.0 + 0.25 * j - 10.0) @ _FORWARD
            assert np.allclose(beam, batch.direction[k - ks[0]], atol=1e-12), (p, k)


def test_tls_common_tilt_goes_into_the_mount(scene, tmp_path):
    path = _tls_survey(tmp_path, [{"position": [0, 0, 1.5], "tilt_deg": 20.0},
                                  {"position": [3, 0, 1.5], "tilt_deg": 20.0}])
    out = tmp_path / "helios"
    assert _export(scene, path, out) == 0
    survey, scanner, platform = _xml(out)
    mount = _rots(platform.find("scannerMount"))
    emitter = _rots(scanner.find("beamOrigin"))
    axis = _vec(scanner.find("headRotateAxis"))
    sim = load_survey(path)
    k = 7 * 401 + 33  # line 7, elevation −40 + 33·0.25
    d = sim.pulses(k, k + 1).direction[0]
    beam = mount @ _rot(axis, 7 * 0.5) @ emitter @ _rot((1, 0, 0), -40.0 + 33 * 0.25 - 10.0) @ _FORWARD
    assert np.allclose(beam, d, atol=1e-12)


# ------------------------------------------------------------------- a planned survey, round trip
def test_planned_survey_round_trip(scene, tmp_path):
    scenario = {"scanner": "riegl_minivux1uav", "pattern": "double_grid", "altitude_m": 60, "speed_mps": 6,
                "line_spacing_m": 15, "margin_m": 10, "detector": HELIOS_V1}
    plan = tmp_path / "survey.yaml"
    assert main(["plan", "--scene", str(scene), "--scenario", str(_write(tmp_path / "sc.yaml", scenario)),
                 "-o", str(plan)]) == 0
    planned = yaml.safe_load(plan.read_text())["platform"]["legs"]
    assert len(planned) > 6 and any(not lg.get("active", True) for lg in planned)
    out = tmp_path / "helios"
    assert _export(scene, plan, out, "--name", "uls_plan") == 0
    survey, _, _ = _xml(out)
    assert survey.get("name") == "uls_plan"
    legs = survey.findall("leg")
    # every planned leg in order (contiguous legs: one waypoint each), then the last leg's end
    assert len(legs) == len(planned) + 1
    for leg, lg in zip(legs, planned):
        assert list(_vec(leg.find("platformSettings"))) == [float(v) for v in lg["start"]]
        assert leg.find("scannerSettings").get("active") == ("true" if lg.get("active", True) else "false")
        assert _f(leg.find("platformSettings"), "movePerSec_m") == 6.0
    assert list(_vec(legs[-1].find("platformSettings"))) == [float(v) for v in planned[-1]["end"]]
    assert legs[-1].find("scannerSettings").get("active") == "false"


# ------------------------------------------------------------------------------ bad input
def _one_line(err):
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("vlsforest scene: error:"), err
    assert "Traceback" not in err
    return lines[0]


_LEGS = {"speed_mps": 50.0, "legs": [{"start": [0, -300, 500], "end": [0, 300, 500]}]}


@pytest.mark.parametrize("doc, key, check", [
    ({"scanner": "riegl_vq780i", "overrides": {"beam_divergence_fwhm_mrad": [1.6, 0.5]}, "detector": HELIOS_V1},
     "scanner.beam_divergence_mrad",
     # the geometric mean of the 1/e² half angles of a 1.6 × 0.5 mrad FWHM beam
     lambda s, sv: _f(s, "beamDivergence_rad") == pytest.approx(
         math.sqrt(1.6 * 0.5) / math.sqrt(2 * math.log(2)) * 1e-3, rel=1e-12)),
    ({"scanner": "riegl_vq780i"}, "detector", None),  # the default detector is the physical one
    ({"scanner": "riegl_vq780i", "detector": {"mode": "helios_v1", "peak_rule": "physical"}}, "detector", None),
    ({"scanner": "riegl_vq780i", "detector": HELIOS_V1,
      "trajectory_noise": {"position_sigma_m": 0.05}}, "trajectory_noise", None),
    ({"scanner": "riegl_vq780i", "detector": HELIOS_V1, "overrides": {"min_energy": 0.5}}, "scanner.min_energy",
     lambda s, sv: _f(s, "receivedEnergyMin_W") == 0.5),
    ({"scanner": "riegl_vq780i", "detector": HELIOS_V1, "overrides": {"prf_hz": 300000.4}}, "scanner.prf_hz",
     lambda s, sv: sv.find("leg/scannerSettings").get("pulseFreq_hz") == "300000"),
    ({"scanner": "riegl_vq780i", "detector": HELIOS_V1, "overrides": {"scan_freq_hz": 222.5}}, "scanner.scan_freq_hz",
     lambda s, sv: sv.find("leg/scannerSettings").get("scanFreq_hz") in ("222", "223")),
])
def test_settings_helios_cannot_run(scene, tmp_path, capsys, doc, key, check):
    path = _write(tmp_path / "s.yaml", {**doc, "platform": _LEGS})
    out = tmp_path / "helios"
    capsys.readouterr()
    assert _export(scene, path, out) == 2
    line = _one_line(capsys.readouterr().err)
    assert key in line and "--allow-approximations" in line and str(path) in line
    assert not out.exists() and not list(tmp_path.glob(".tmp-*"))
    # allowed: written as the documented downgrade, with a warning and an XML comment
    assert _export(scene, path, out, "--allow-approximations") == 0
    err = capsys.readouterr().err
    assert f"approximation: {key}" in err
    text = (out / "survey.xml").read_text()
    assert f"approximation: {key}" in text
    survey, scanner, _ = _xml(out)
    if check is not None:
        assert check(scanner, survey)


def test_tls_tilts_that_differ_are_an_approximation(scene, tmp_path, capsys):
    path = _tls_survey(tmp_path, [{"position": [0, 0, 1.5], "tilt_deg": 10.0}, {"position": [3, 0, 1.5]}])
    out = tmp_path / "helios"
    assert _export(scene, path, out) == 2
    assert "tilt_deg" in _one_line(capsys.readouterr().err)
    assert _export(scene, path, out, "--allow-approximations") == 0
    _, _, platform = _xml(out)
    assert [(r.get("axis"), float(r.get("angle_deg"))) for r in platform.findall("scannerMount/rot")] == [("x", 10.0)]


def test_vertical_leg_is_refused(scene, tmp_path, capsys):
    doc = {"scanner": "riegl_vq780i", "detector": HELIOS_V1,
           "platform": {"speed_mps": 5.0, "legs": [{"start": [0, 0, 100], "end": [0, 50, 100]},
                                                   {"start": [0, 50, 100], "end": [0, 50, 200]}]}}
    out = tmp_path / "helios"
    assert _export(scene, _write(tmp_path / "v.yaml", doc), out, "--allow-approximations") == 2
    assert "platform.legs[1] is vertical" in _one_line(capsys.readouterr().err)
    assert not out.exists()


def test_bad_inputs_write_nothing(scene, tmp_path, capsys):
    out = tmp_path / "helios"
    assert _export(scene, tmp_path / "missing.yaml", out) == 2
    assert "missing.yaml" in _one_line(capsys.readouterr().err)
    bad = _write(tmp_path / "bad.yaml", {"scanner": "riegl_vq780i", "detector": {"mode": "nonsense"},
                                         "platform": _LEGS})
    assert _export(scene, bad, out, "--allow-approximations") == 2
    assert "detector.mode" in _one_line(capsys.readouterr().err)
    good = _vq780i_survey(tmp_path)
    broken = _write(tmp_path / "broken_scene.yaml", {"parts": [{"id": 2, "type": "mesh", "path": "missing.obj"}]})
    assert _export(broken, good, out) == 2
    assert "missing.obj" in _one_line(capsys.readouterr().err)
    assert _export(scene, good, out, "--trajectory-interval", "-1") == 2
    assert "trajectory interval" in _one_line(capsys.readouterr().err)
    assert main(["scene", "helios", str(scene), "-o", str(out), "--allow-approximations"]) == 2
    assert "--survey" in _one_line(capsys.readouterr().err)
    assert not out.exists() and not list(tmp_path.glob(".tmp-*"))
