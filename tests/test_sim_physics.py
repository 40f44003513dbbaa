"""End-to-end physics of the simulator on analytic scenes (planes, step edges, wires)."""

import numpy as np
import pytest

from vlsforest.errors import InputDataError
from vlsforest.sim import Material, Scene, hit_offsets, redetect, simulate, trace_hits
from vlsforest.sim.survey import survey_from_dict


def _survey(overrides, legs, speed=5.0, scanner="riegl_vq780i", detector=None, seed=0):
    d = {"scanner": scanner, "overrides": dict(overrides), "platform": {"speed_mps": speed, "legs": legs},
         "seed": seed}
    if detector:
        d["detector"] = detector
    return survey_from_dict(d)


def _line(y0, y1, z, x=0.0):
    return [{"start": [x, y0, z], "end": [x, y1, z], "active": True}]


def _wire_box(x_c, width, y0, y1, z):
    """A thin box (wire) along y centred at x_c, as 12 triangles."""
    h = width / 2
    v = np.array([[x, y, zz] for x in (x_c - h, x_c + h) for y in (y0, y1) for zz in (z - h, z + h)], float)
    f = [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
         [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]
    return v, np.array(f)


# geometry tests: a nadir beam without range noise (the presets carry their datasheet accuracy)
NADIR = {"prf_hz": 20000, "scan_freq_hz": 20, "scan_angle_deg": 0.02, "max_scan_angle_deg": 0.02,
         "range_min_m": 0.0, "range_noise_m": 0.0}


def test_plane_at_nadir_one_return_exact_range():
    sc = Scene()
    sc.add_plane(1, 12.5, [-50, -50, 50, 50])
    sv = _survey(NADIR, _line(-2, 2, 512.5))
    res = simulate(sc, sv, workers=1)
    pu, pt = res.pulses, res.points
    assert len(pu["slot"]) > 1000
    assert (pu["n_returns"] == 1).all()
    # range on the central axis: |z - plane| / cos
    p = np.searchsorted(pu["slot"], pt["pulse"])
    true_range = (pu["origin"][p, 2] - 12.5) / -pu["direction"][p, 2]
    rng = np.linalg.norm(pt["xyz"] - pu["origin"][p], axis=1)
    assert np.abs(rng - true_range).max() < 1e-3
    assert np.abs(pt["xyz"][:, 2] - 12.5).max() < 1e-3


def test_trajectory_noise_moves_the_points_like_a_gnss_ins_error():
    """The beam really goes from the perturbed trajectory, the returns are placed from the
    nominal one: a flat ground then shows the trajectory's z error (position) and
    range × attitude error, smooth along the strip; traced and georeferenced geometry differ."""
    sc = Scene()
    sc.add_plane(1, 0.0, [-200, -200, 200, 200])
    ov = dict(NADIR, prf_hz=4000)
    legs = _line(-60, 60, 100.0)
    d = {"scanner": "riegl_vq780i", "overrides": ov, "platform": {"speed_mps": 10.0, "legs": legs}, "seed": 3,
         "trajectory_noise": {"position_sigma_m": 0.1, "attitude_sigma_deg": 0.0, "correlation_s": 1.0}}
    res = simulate(sc, survey_from_dict(d), workers=1)
    z = res.points["xyz"][:, 2]
    assert 0.05 < z.std() < 0.2 and abs(z).max() > 0.1          # the trajectory's z error
    t = res.points["gps_time"]
    o = np.argsort(t)
    # smooth: neighbouring pulses (0.25 ms apart, correlation 1 s) share their error
    assert np.abs(np.diff(z[o])).max() < 0.01
    # the recorded pulse origins are the nominal trajectory (x = 0, z = 100 m exactly)
    assert np.abs(res.pulses["origin"][:, 2] - 100.0).max() < 1e-9
    # attitude error: the beam hits beside the nominal spot (range × angle, ≈ 8.7 cm), the point
    # is placed along the nominal beam: on a ground sloping 0.5 in x it lies off the surface by
    # ≈ 0.5 × that; on flat ground it would not show
    slope = Scene()
    v = np.array([[-200, -200, -100], [200, -200, 100], [200, 200, 100], [-200, 200, -100]], float)
    slope.add_mesh(1, v, [[0, 1, 2], [0, 2, 3]])
    d["trajectory_noise"] = {"position_sigma_m": 0.0, "attitude_sigma_deg": 0.05, "correlation_s": 1.0}
    xyz = simulate(slope, survey_from_dict(d), workers=1).points["xyz"]
    off = xyz[:, 2] - 0.5 * xyz[:, 0]
    expect = 0.5 * 100.0 * np.radians(0.05)
    assert 0.4 * expect < off.std() < 2.0 * expect
    d.pop("trajectory_noise")
    xyz = simulate(slope, survey_from_dict(d), workers=1).points["xyz"]
    off0 = xyz[:, 2] - 0.5 * xyz[:, 0]  # constant (the peak of a sloped footprint), no scatter
    assert off0.std() < 1e-3
    # without noise, everything lies on the plane and under the line
    res = simulate(sc, survey_from_dict(d), workers=1)
    assert np.abs(res.points["xyz"][:, 2]).max() < 1e-4 and np.abs(res.points["xyz"][:, 0]).max() < 0.04


def _step_scene(delta):
    sc = Scene()
    sc.add_plane(1, 0.0, [-20, -20, 0.0, 20])          # upper plane, x < 0
    sc.add_plane(2, -delta, [0.0, -20, 20, 20])         # lower plane, x ≥ 0
    return sc


def _step_survey(rule="physical"):
    # nadir pulses flying along x across the edge at x = 0; 0.5 mrad beam at 300 m
    ov = dict(NADIR, prf_hz=2000, scan_freq_hz=2, beam_divergence_mrad=0.5, window_size_ns=1.5)
    legs = [{"start": [-0.5, 0.0, 300.0], "end": [0.5, 0.0, 300.0], "active": True}]
    return _survey(ov, legs, speed=1.0, detector={"peak_rule": rule})


def test_step_edge_two_returns_where_footprint_straddles():
    delta = 2.0  # farther apart than the 0.45 m dead zone (and the 1.2 m pulse)
    res = simulate(_step_scene(delta), _step_survey(), workers=1)
    pu = res.pulses
    x_c = pu["origin"][:, 0] + pu["direction"][:, 0] / -pu["direction"][:, 2] * 300.0
    # hand calculation: the outer ring reaches 2/3·div·R across the beam axis in every direction
    r_out = 2 / 3 * 0.5e-3 * 300.0
    expected = np.abs(x_c) < r_out
    n_two = int((pu["n_returns"] == 2).sum())
    assert n_two == pytest.approx(int(expected.sum()), abs=1)
    assert n_two >= 100
    assert set(np.unique(pu["n_returns"])) == {1, 2}
    two = pu["n_returns"] == 2
    assert np.abs(x_c[two]).max() < r_out * 1.001


def test_step_edge_closer_than_dead_zone_one_return():
    res = simulate(_step_scene(0.2), _step_survey(), workers=1)
    assert (res.pulses["n_returns"] == 1).all()


def test_step_edge_helios_rule_suppresses_isolated_echo():
    # HELIOS++ v1.0 quirk: at window 1.5 ns an echo that does not overlap earlier energy is lost
    res = simulate(_step_scene(2.0), _step_survey("helios"), workers=1)
    assert (res.pulses["n_returns"] == 1).all()


def _wire_hits(orientation_deg):
    sc = Scene()
    v, f = _wire_box(0.0, 0.001, -5, 5, 0.0)
    sc.add_mesh(7, v, f)
    # one scan line sweeping across the wire (the scan direction is along x), 1 mm pulse spacing
    ov = {"prf_hz": 100000, "scan_freq_hz": 100, "scan_angle_deg": 0.2, "max_scan_angle_deg": 0.2,
          "beam_divergence_mrad": [1.6, 0.5], "beam_orientation_deg": orientation_deg, "range_min_m": 0.0}
    legs = [{"start": [0.0, 0.0, 100.0], "end": [0.0, 0.0101, 100.0], "active": True}]
    sv = _survey(ov, legs, speed=1.0)
    res = simulate(sc, sv, workers=1)
    pu = res.pulses
    hit = pu["n_returns"] > 0
    x_c = pu["origin"][:, 0] + pu["direction"][:, 0] / -pu["direction"][:, 2] * 100.0
    return x_c[hit].max() - x_c[hit].min()


def test_elliptical_beam_wire_widths_ratio():
    wide = _wire_hits(0.0)      # major axis along the scan direction, across the wire
    narrow = _wire_hits(90.0)   # minor axis across the wire
    assert wide / narrow == pytest.approx(1.6 / 0.5, rel=0.05)
    assert wide == pytest.approx(2 * 2 / 3 * 1.6e-3 * 100.0, rel=0.05)


@pytest.mark.parametrize("scanner,ov,share", [
    # the polygon mirror sweeps the device's ±45° and emits within ±30°
    ("riegl_vq780i", {"prf_hz": 20000, "scan_freq_hz": 50, "scan_angle_deg": 30.0}, 60 / 90),
    ("riegl_minivux1uav", {"prf_hz": 20000, "scan_freq_hz": 50, "scan_angle_deg": 30.0}, 60 / 360),
])
def test_ground_density_matches_analytic(scanner, ov, share):
    h, v = 60.0, 4.0
    sc = Scene()
    sc.add_plane(1, 0.0, [-200, -200, 200, 200])
    ov = dict(ov, range_min_m=0.0)
    sv = _survey(ov, _line(-20, 20, h), speed=v, scanner=scanner)
    res = simulate(sc, sv, workers=1)
    xyz = res.points["xyz"]
    swath = 2 * h * np.tan(np.deg2rad(30.0))
    sel = (np.abs(xyz[:, 1]) < 10.0) & (np.abs(xyz[:, 0]) <= swath / 2)
    density = sel.sum() / (20.0 * swath)
    analytic = ov["prf_hz"] * share / (v * swath)
    assert density == pytest.approx(analytic, rel=0.05)


def test_range_noise_sigma():
    sc = Scene()
    sc.add_plane(1, 0.0, [-50, -50, 50, 50])
    ov = dict(NADIR, prf_hz=10000, scan_freq_hz=10, range_noise_m=0.05)
    sv = _survey(ov, _line(-0.6, 0.6, 300.0), speed=1.0)
    res = simulate(sc, sv, workers=1, seed=3)
    z = res.points["xyz"][:, 2]
    assert len(z) >= 10000
    assert np.std(z, ddof=1) == pytest.approx(0.05, rel=0.03)
    assert abs(z.mean()) < 3 * 0.05 / np.sqrt(len(z)) + 1e-4
    # deterministic: same seed, same numbers; other seed, other numbers
    again = simulate(sc, sv, workers=2, seed=3)
    assert np.array_equal(again.points["xyz"], res.points["xyz"])
    other = simulate(sc, sv, workers=1, seed=4)
    assert not np.array_equal(other.points["xyz"], res.points["xyz"])


def test_hit_pulses_keep_what_redetect_needs():
    rng = np.random.default_rng(1)
    sc = Scene()  # a voxel crown and no ground: most pulses miss
    ijk = np.unique(np.floor(rng.uniform([-2, -2, 5], [2, 2, 12], size=(300, 3)) / 0.5).astype(int), axis=0)
    sc.add_voxels(2, ijk, np.zeros(3), 0.5, material=Material(0.6))
    ov = {"prf_hz": 20000, "scan_freq_hz": 40, "scan_angle_deg": 20.0, "max_scan_angle_deg": 20.0,
          "range_min_m": 0.0}
    sv = _survey(ov, _line(-4, 4, 80.0), speed=4.0)
    base = simulate(sc, sv, workers=1, keep_hits=True)
    pulses, hits = base.hit_pulses()
    assert 0 < len(pulses["slot"]) < 0.5 * len(base.pulses["slot"])
    assert np.array_equal(pulses["slot"], np.unique(base.pulses["slot"][base.hits["pulse"]]))
    assert np.array_equal(pulses["slot"][hits["pulse"]], base.pulses["slot"][base.hits["pulse"]])
    again = redetect(sc.part_table(), pulses, hits, sv)
    assert len(again.points["xyz"]) > 100
    assert np.array_equal(again.points["xyz"], base.points["xyz"])
    assert np.array_equal(again.points["object_id"], base.points["object_id"])
    with pytest.raises(InputDataError, match="keep_hits"):
        simulate(sc, sv, workers=1).hit_pulses()



@pytest.mark.parametrize("backend", ["grid", "embree"])
def test_worker_processes_give_the_serial_result(backend):
    """Forked workers (which inherit the kernels the parent warmed up, voxel grids included)
    give the 1-worker points bit for bit; with ``grid`` the fine crown is traced by the sparse
    voxel grid, the path the default study's 0.02–0.10 m methods take."""
    rng = np.random.default_rng(7)
    sc = Scene(voxel_backend=backend)
    sc.add_plane(1, 0.0, [-30, -30, 30, 30])
    ijk = np.unique(np.floor(rng.uniform([-2, -2, 4], [2, 2, 10], size=(4000, 3)) / 0.1).astype(int), axis=0)
    sc.add_voxels(2, ijk, np.zeros(3), 0.1, material=Material(0.5))
    assert len(sc.grids) == (1 if backend == "grid" else 0)
    ov = {"prf_hz": 20000, "scan_freq_hz": 40, "scan_angle_deg": 20.0, "max_scan_angle_deg": 20.0,
          "range_min_m": 0.0, "beam_sample_quality": 2}
    sv = _survey(ov, _line(-5, 5, 60.0), speed=4.0)
    one = simulate(sc, sv, workers=1, seed=2, block_slots=2000)
    two = simulate(sc, sv, workers=2, seed=2, block_slots=2000)
    crown = one.points["object_id"] == 2
    assert crown.sum() > 500 and (~crown).sum() > 500
    for k in ("xyz", "object_id", "return_number", "amplitude"):
        assert np.array_equal(one.points[k], two.points[k])


@pytest.mark.parametrize("workers", [1, 2])
def test_simulate_to_las_writes_what_simulate_and_write_points_write(tmp_path, workers):
    """The returns written block by block are the bytes of the joined result written at once,
    with the same counts, over a region and without one; a survey whose pulses all miss the
    region still writes an (empty) file."""
    from vlsforest.sim import simulate_to_las, write_points

    rng = np.random.default_rng(5)
    sc = Scene()
    sc.add_plane(1, 0.0, [-30, -30, 30, 30])
    ijk = np.unique(np.floor(rng.uniform([-2, -2, 4], [2, 2, 10], size=(2000, 3)) / 0.25).astype(int), axis=0)
    sc.add_voxels(2, ijk, np.zeros(3), 0.25, material=Material(0.5))
    ov = {"prf_hz": 20000, "scan_freq_hz": 40, "scan_angle_deg": 20.0, "max_scan_angle_deg": 20.0,
          "range_min_m": 0.0}
    sv = _survey(ov, _line(-5, 5, 60.0), speed=4.0)
    for region in (None, [-3.0, -3.0, 3.0, 3.0], [100.0, 100.0, 101.0, 101.0]):
        res = simulate(sc, sv, workers=workers, seed=4, block_slots=3000, keep_pulses=False, region=region)
        write_points(tmp_path / "joined.laz", res)
        t = simulate_to_las(sc, sv, tmp_path / "blocks.laz", seed=4, workers=workers, block_slots=3000,
                            region=region)
        assert (tmp_path / "blocks.laz").read_bytes() == (tmp_path / "joined.laz").read_bytes()
        assert {k: t[k] for k in ("n_pulses", "n_rays", "n_points")} == \
               {k: res.timings[k] for k in ("n_pulses", "n_rays", "n_points")}
        assert t["n_pulses"] > 10000 and (t["n_points"] > 1000) == (region != [100.0, 100.0, 101.0, 101.0])


@pytest.mark.parametrize("workers", [1, 2])
def test_trace_hits_equals_hit_pulses_without_detection(workers):
    rng = np.random.default_rng(2)
    sc = Scene()
    ijk = np.unique(np.floor(rng.uniform([-2, -2, 5], [2, 2, 12], size=(300, 3)) / 0.5).astype(int), axis=0)
    sc.add_voxels(2, ijk, np.zeros(3), 0.5, material=Material(0.6))
    ov = {"prf_hz": 20000, "scan_freq_hz": 40, "scan_angle_deg": 20.0, "max_scan_angle_deg": 20.0,
          "range_min_m": 0.0}
    sv = _survey(ov, _line(-4, 4, 80.0), speed=4.0)
    # small blocks: several of them, some without any hit
    base = simulate(sc, sv, workers=1, keep_hits=True, block_slots=997)
    want_p, want_h = base.hit_pulses()
    pulses, hits = trace_hits(sc, sv, workers=workers, block_slots=997)
    assert hits["pulse"].dtype == np.int32
    assert set(pulses) == set(want_p) - {"n_returns"} and set(hits) == set(want_h)
    for k in pulses:
        assert np.array_equal(pulses[k], want_p[k]), k
    for k in hits:
        assert np.array_equal(hits[k], want_h[k]), k
    again = redetect(sc.part_table(), pulses, hits, sv, block_slots=997)
    assert len(again.points["xyz"]) > 100
    assert np.array_equal(again.points["xyz"], base.points["xyz"])
    # the hits' index given once (as the diagnosis does for many re-detections): the same points
    ptr = hit_offsets(pulses, hits)
    assert ptr[0] == 0 and ptr[-1] == len(hits["pulse"]) and np.all(np.diff(ptr) >= 0)
    for i in np.flatnonzero(np.diff(ptr))[:50]:
        assert (hits["pulse"][ptr[i]:ptr[i + 1]] == i).all()
    given = redetect(sc.part_table(), pulses, hits, sv, block_slots=997, hit_ptr=ptr)
    for k in again.points:
        assert np.array_equal(given.points[k], again.points[k]), k
    with pytest.raises(InputDataError, match="hit_ptr"):
        redetect(sc.part_table(), pulses, hits, sv, hit_ptr=ptr[:-1])


def test_hit_offsets_refuse_hits_out_of_pulse_order():
    pulses = {"slot": np.array([3, 5, 9])}
    with pytest.raises(InputDataError, match="grouped by pulse"):
        hit_offsets(pulses, {"pulse": np.array([0, 2, 1], np.int32)})
    with pytest.raises(InputDataError, match="ascending slot order"):
        hit_offsets({"slot": np.array([3, 3, 9])}, {"pulse": np.array([0, 1], np.int32)})
    assert hit_offsets(pulses, {"pulse": np.array([0, 0, 2], np.int32)}).tolist() == [0, 2, 2, 3]
    with pytest.raises(InputDataError, match="outside 0…2"):
        hit_offsets(pulses, {"pulse": np.array([0, 3], np.int32)})


def test_threshold_removes_weakest_first():
    rng = np.random.default_rng(0)
    sc = Scene()
    sc.add_plane(1, 0.0, [-30, -30, 30, 30], Material(0.2))
    cen = rng.uniform([-3, -3, 5], [3, 3, 15], size=(400, 3))
    ijk = np.unique(np.floor(cen / 0.5).astype(int), axis=0)
    sc.add_voxels(2, ijk, np.zeros(3), 0.5, material=Material(0.6))
    ov = {"prf_hz": 20000, "scan_freq_hz": 40, "scan_angle_deg": 10.0, "max_scan_angle_deg": 10.0,
          "range_min_m": 0.0, "range_noise_m": 0.0}
    sv = _survey(ov, _line(-4, 4, 80.0), speed=4.0)
    base = simulate(sc, sv, workers=1, keep_hits=True)
    amp = base.points["amplitude"]
    assert len(amp) > 1000
    parts = dict(object_id=np.array([1, 2]), classification=np.array([2, 1]), reflectance=np.array([0.2, 0.6]),
                 specularity=np.zeros(2), shininess=np.full(2, 10.0))
    same = redetect(parts, base.pulses, base.hits, sv)
    assert np.array_equal(same.points["xyz"], base.points["xyz"])
    u = np.unique(amp.astype(np.float64))
    k = np.searchsorted(u, np.quantile(u, 0.3))
    thr = 0.5 * (u[k] + u[k + 1])  # between two distinct amplitudes (no ties at the threshold)
    sv_t = _survey(dict(ov, min_energy=thr), _line(-4, 4, 80.0), speed=4.0)
    cut = redetect(parts, base.pulses, base.hits, sv_t)
    assert (cut.points["amplitude"] >= thr).all()
    kept = set(zip(base.points["pulse"][amp >= thr].tolist(), np.round(base.points["xyz"][amp >= thr, 2], 6)))
    now = set(zip(cut.points["pulse"].tolist(), np.round(cut.points["xyz"][:, 2], 6)))
    assert now == kept  # exactly the returns below the threshold were removed


def test_weighted_return_position_lies_on_the_hit_surface():
    # a plane patch covering x ≥ 0 only; pulses whose central ray just misses it (x_c < 0)
    sc = Scene()
    sc.add_plane(1, 0.0, [0.0, -20, 20, 20])
    ov = dict(NADIR, prf_hz=2000, scan_freq_hz=2, beam_divergence_mrad=0.5)
    legs = [{"start": [-0.05, 0.0, 300.0], "end": [-0.0001, 0.0, 300.0], "active": True}]
    axis = simulate(sc, _survey(ov, legs, speed=0.5), workers=1)
    weighted = simulate(sc, _survey(ov, legs, speed=0.5, detector={"return_position": "weighted"}), workers=1)
    assert len(axis.points["xyz"]) == len(weighted.points["xyz"]) > 10
    # HELIOS convention: on the central axis, i.e. beside the patch
    assert (axis.points["xyz"][:, 0] < 0).all()
    # energy-weighted sub-ray hits: on the patch, within the footprint
    xw = weighted.points["xyz"][:, 0]
    assert (xw >= 0).all() and (xw <= 2 / 3 * 0.5e-3 * 300 + 1e-9).all()
    assert np.abs(weighted.points["xyz"][:, 2]).max() < 1e-6


def test_face_labels_reach_the_returns(tmp_path):
    from vlsforest.io.las import read_las
    from vlsforest.sim import write_points

    sc = Scene()
    sc.add_plane(1, 0.0, [-50, -50, 50, 50])
    # a horizontal square at z = 5 over x < 0 made of two triangles labelled 7 and 9
    v = np.array([[-10, -10, 5], [0, -10, 5], [0, 10, 5], [-10, 10, 5]], float)
    sc.add_mesh(2, v, [[0, 1, 2], [0, 2, 3]], face_labels=np.array([7, 9]))
    ov = {"prf_hz": 20000, "scan_freq_hz": 20, "scan_angle_deg": 20.0, "max_scan_angle_deg": 20.0,
          "range_min_m": 0.0}
    res = simulate(sc, _survey(ov, _line(-1, 1, 100.0)), workers=1)
    p = res.points
    on_mesh = p["object_id"] == 2
    assert on_mesh.any() and (~on_mesh).any()
    assert set(np.unique(p["label"][on_mesh])) == {7, 9}
    assert (p["label"][~on_mesh] == 0).all()
    # triangle 0 is the one below the diagonal y < x + 10 … check the geometry
    xy = p["xyz"][on_mesh, :2]
    lab = p["label"][on_mesh]
    below = (xy[:, 1] + 10) * 10 < (xy[:, 0] + 10) * 20 + 1e-6
    assert (lab[below] == 7).mean() > 0.99
    write_points(tmp_path / "l.laz", res)
    assert np.array_equal(read_las(tmp_path / "l.laz").attrs["label"], p["label"])


def test_face_labels_of_several_meshes_come_from_each_hit_face():
    """Labels are looked up per geometry and face: meshes with, without and again with labels
    (the flat label table's offsets), a plane (no labels) and rays that miss."""
    sc = Scene()
    sc.add_plane(1, 0.0, [-50, -50, 50, 50])
    labels = {0.0: [3, 4], 20.0: None, 40.0: [11, 12]}
    for k, (x0, lab) in enumerate(labels.items()):
        v = np.array([[x0, -10, 5 + k], [x0 + 10, -10, 5 + k], [x0 + 10, 10, 5 + k], [x0, 10, 5 + k]], float)
        sc.add_mesh(2 + k, v, [[0, 1, 2], [0, 2, 3]], face_labels=None if lab is None else np.array(lab))
    rng = np.random.default_rng(3)
    xy = np.column_stack([rng.uniform(-5, 60, 4000), rng.uniform(-12, 12, 4000)])
    o = np.column_stack([xy, np.full(len(xy), 20.0)])
    d = np.tile([0.0, 0.0, -1.0], (len(xy), 1))
    d[:200] = [0.0, 0.0, 1.0]  # upwards: no hit at all
    t, part, _, label = sc.trace(o, d, with_labels=True)
    want = np.zeros(len(xy), dtype=np.uint8)
    for x0, lab in labels.items():
        if lab is None:
            continue
        inside = (xy[:, 0] > x0) & (xy[:, 0] < x0 + 10) & (np.abs(xy[:, 1]) < 10)
        below = (xy[:, 1] + 10) < 2 * (xy[:, 0] - x0)  # triangle [0, 1, 2]
        want[inside & below] = lab[0]
        want[inside & ~below] = lab[1]
    want[:200] = 0
    near_edge = np.abs((xy[:, 1] + 10) - 2 * (xy[:, 0] % 20)) < 1e-3
    assert np.isinf(t[:200]).all() and (part[:200] == -1).all()
    assert np.array_equal(label[~near_edge], want[~near_edge])
    assert {3, 4, 11, 12} <= set(np.unique(label)) and (label == 0).sum() > 1000


def test_region_traces_only_pulses_reaching_it():
    sc = Scene()
    sc.add_plane(1, 0.0, [-100, -100, 100, 100])
    ov = {"prf_hz": 20000, "scan_freq_hz": 50, "scan_angle_deg": 30.0, "range_min_m": 0.0}
    sv = _survey(ov, _line(-5, 5, 60.0), speed=5.0)
    full = simulate(sc, sv, workers=1)
    part = simulate(sc, sv, workers=1, region=(0.0, -100, 100, 100))
    assert len(part.pulses["slot"]) == len(full.pulses["slot"])  # every pulse is still emitted
    x = part.points["xyz"][:, 0]
    assert len(x) < 0.6 * len(full.points["xyz"]) and x.min() > -0.1  # beams that miss x ≥ 0: not traced
    keep = full.points["xyz"][:, 0] > 0.1
    assert np.array_equal(np.sort(full.points["pulse"][keep]), np.sort(part.points["pulse"][part.points["xyz"][:, 0] > 0.1]))


@pytest.mark.parametrize("scanner,convention,datasheet", [
    ("riegl_vq780i", "beam_divergence_full_1e2_mrad", (0.25, 0.25)),      # full angle at 1/e²
    ("riegl_minivux1uav", "beam_divergence_fwhm_mrad", (1.6, 0.5)),       # full angle at 50 % peak
])
def test_real_beam_footprint_has_the_datasheet_diameter(scanner, convention, datasheet):
    """A datasheet beam entered in its convention lights a plane with a Gaussian energy footprint
    whose 1/e² diameter is θ·R on both axes (θ the full angle at 1/e²)."""
    from vlsforest.sim.beam import subray_directions, subray_pattern
    from vlsforest.sim.waveform import hit_energy

    # θ at 1/e² from the datasheet: a Gaussian I = exp(-2 r²/w²) is at half maximum at
    # r = w·sqrt(ln 2 / 2), so θ_1/e² = FWHM · 2 / sqrt(2 ln 2)
    factor = 1.0 if convention == "beam_divergence_full_1e2_mrad" else 2.0 / np.sqrt(2.0 * np.log(2.0))
    theta = np.array(datasheet) * 1e-3 * factor
    h = 100.0
    sc = Scene()
    sc.add_plane(1, 0.0, [-50, -50, 50, 50])
    ov = dict(NADIR, beam_sample_quality=10, range_noise_m=0.0, **{convention: list(datasheet)})
    sv = _survey(ov, _line(-0.5, 0.5, h), scanner=scanner)
    pulses, hits = trace_hits(sc, sv, workers=1)
    s = sv.scanner
    pat = subray_pattern(s.beam.sample_quality, s.beam.divergence_mrad, s.beam.orientation_deg)
    assert pat.n == 271 and len(pulses["slot"]) >= 3
    dirs = subray_directions(pulses["direction"], pulses["scan_dir"], pat)
    p, k = hits["pulse"], hits["subray"]
    xyz = pulses["origin"][p] + hits["range"][:, None] * dirs[p, k]
    assert np.allclose(xyz[:, 2], 0.0, atol=1e-6)
    centre = pulses["origin"][p] + (h / -pulses["direction"][p, 2])[:, None] * pulses["direction"][p]
    along = np.einsum("ij,ij->i", xyz - centre, pulses["scan_dir"][p])   # the major axis (orientation 0)
    across = np.einsum("ij,ij->i", xyz - centre, np.cross(pulses["direction"][p], pulses["scan_dir"][p]))
    energy = hit_energy(hits["range"], k, hits["cos_inc"], hits["part"], pat.frac, np.array([30.0]),
                        np.array([0.0]), np.array([10.0]), pat.n, average_power_w=s.emitter.average_power_w,
                        receiver_diameter_m=s.detector.receiver_diameter_m,
                        optical_efficiency=s.detector.optical_efficiency, range0=s.detector.range_min_m,
                        m2=s.beam.quality_factor)
    # ln E = c − 2 x²/wx² − 2 y²/wy²: least squares for the 1/e² radii
    a = np.column_stack([np.ones(len(energy)), along ** 2, across ** 2])
    coef = np.linalg.lstsq(a, np.log(energy), rcond=None)[0]
    wx, wy = np.sqrt(-2.0 / coef[1]), np.sqrt(-2.0 / coef[2])
    assert 2 * wx == pytest.approx(theta[0] * h, rel=0.05)
    assert 2 * wy == pytest.approx(theta[1] * h, rel=0.05)


def test_uls_canopy_intensities_do_not_saturate():
    """The study's ULS over a foliage canopy: LAS intensities follow the amplitudes without
    clipping (HELIOS++'s scale 65,535 / 10⁶), the float amplitude is kept."""
    from vlsforest.sim.waveform import las_intensity

    rng = np.random.default_rng(1)
    sc = Scene()
    sc.add_plane(1, 0.0, [-30, -30, 30, 30], Material(0.3))
    cen = rng.uniform([-8, -8, 8], [8, 8, 20], size=(3000, 3))
    ijk = np.unique(np.floor(cen / 0.25).astype(int), axis=0)
    sc.add_voxels(2, ijk, np.zeros(3), 0.25, material=Material(0.45))
    ov = {"prf_hz": 20000, "window_size_ns": 1.5}
    sv = _survey(ov, _line(-3, 3, 70.0), speed=5.0, scanner="riegl_minivux1uav", detector={"mode": "helios_v1"})
    pts = simulate(sc, sv, workers=1).points
    amp = pts["amplitude"].astype(np.float64)
    assert len(amp) > 500
    # echoes strong enough to have saturated a 16-bit count of raw amplitudes exist ...
    assert (amp > 65535).mean() > 0.1
    # ... and none is clipped: the intensity is the amplitude scaled, in the amplitude's order
    assert amp.max() < 1e6 and pts["intensity"].max() < 65535
    assert np.array_equal(pts["intensity"], las_intensity(amp))
    assert np.abs(pts["intensity"] - amp * 65535 / 1e6).max() < 1.0
    order = np.argsort(amp, kind="stable")
    assert np.all(np.diff(pts["intensity"][order].astype(int)) >= 0)


def test_range_noise_depends_on_the_return_alone():
    """A return's range noise is drawn from its seed, pulse slot and return number: the same
    whatever the region traced or the block size, other for another seed, slot or return."""
    from vlsforest.sim.waveform import range_noise

    slots = np.arange(200_000)
    z = range_noise(7, slots, np.ones_like(slots), 1.0)
    assert abs(z.mean()) < 0.01 and z.std() == pytest.approx(1.0, abs=0.01)
    # normal tails: 4.55 % beyond 2σ, 0.27 % beyond 3σ
    assert (np.abs(z) > 2).mean() == pytest.approx(0.0455, abs=0.003)
    assert (np.abs(z) > 3).mean() == pytest.approx(0.0027, abs=0.0008)
    # returns of one pulse, neighbouring slots and seeds: uncorrelated
    z2 = range_noise(7, slots, np.full_like(slots, 2), 1.0)
    assert abs(np.corrcoef(z, z2)[0, 1]) < 0.01 and abs(np.corrcoef(z[:-1], z[1:])[0, 1]) < 0.01
    assert abs(np.corrcoef(z, range_noise(8, slots, np.ones_like(slots), 1.0))[0, 1]) < 0.01
    assert np.array_equal(range_noise(7, slots[::-1], np.ones_like(slots), 1.0), z[::-1])
    # through the simulator: a plane traced whole and within a region, in blocks of two sizes
    sc = Scene()
    sc.add_plane(1, 0.0, [-50, -50, 50, 50])
    sv = _survey(dict(NADIR, scan_angle_deg=5.0, max_scan_angle_deg=5.0, range_noise_m=0.05),
                 _line(-2, 2, 100.0))
    a = simulate(sc, sv, workers=1, block_slots=20000)
    b = simulate(sc, sv, workers=1, block_slots=777, region=[-3.0, -50.0, 3.0, 50.0])
    inside = np.abs(a.points["xyz"][:, 0]) < 2.0
    key_a = {(s, r): z for s, r, z in zip(a.points["pulse"][inside], a.points["return_number"][inside],
                                          a.points["xyz"][inside, 2])}
    key_b = {(s, r): z for s, r, z in zip(b.points["pulse"], b.points["return_number"], b.points["xyz"][:, 2])}
    assert len(key_a) > 1000 and key_a.keys() <= key_b.keys()
    assert all(key_b[k] == v for k, v in key_a.items())
    assert np.std(a.points["xyz"][:, 2]) == pytest.approx(0.05, rel=0.1)


@pytest.mark.parametrize("detector, outside", [({"box_test": "cone"}, True), ({"box_test": "axis"}, False),
                                               ({"mode": "helios_v1"}, False)])
def test_box_test_axis_skips_pulses_whose_central_ray_misses_the_scene(detector, outside):
    """A lone 2 m square seen by a wide nadir beam along a line that runs off it: with the cone
    test the pulses just off the square still return from its edge (the returns lie on their
    central rays, outside the square); with the axis test (HELIOS++) only pulses whose central
    ray meets the square's bounding box are traced."""
    sc = Scene()
    sc.add_plane(1, 0.0, [-1, -1, 1, 1])
    sv = _survey(dict(NADIR, beam_divergence_mrad=2.0), _line(-3, 3, 500.0), speed=1.0, detector=detector)
    pt = simulate(sc, sv, workers=1).points
    assert len(pt["xyz"]) > 100
    beyond = np.abs(pt["xyz"][:, 1]) > 1.0 + 1e-6
    assert beyond.any() == outside
    if outside:  # the beam's outer rings reach the square from up to (Q−1)/Q · 2 mrad · 500 m away
        assert np.abs(pt["xyz"][:, 1]).max() < 1.0 + 0.7
