"""Scene assembly: parts from YAML, voxel placement, back-end equivalence, clear errors."""

import numpy as np
import pytest
import yaml
from scipy.spatial import cKDTree

from vlsforest.cli import main
from vlsforest.errors import ConfigError, InputDataError
from vlsforest.io.vox import make_vox, write_vox
from vlsforest.sim import Scene, routing


def _rays(n, rng, lo, hi):
    o = rng.uniform(lo - 3, hi + 3, size=(n, 3))
    o[:, 2] = hi[2] + 5
    tgt = rng.uniform(lo, hi, size=(n, 3))
    d = tgt - o
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


@pytest.mark.parametrize("scaled", [False, True])
def test_embree_and_grid_backends_agree(scaled):
    rng = np.random.default_rng(1)
    ijk = np.unique(rng.integers(-8, 8, size=(600, 3)), axis=0)
    size = 0.25
    origin = np.array([0.1, -0.05, 3.0])
    half = centre = None
    if scaled:
        half = rng.uniform(0.02, 0.125, len(ijk))
        centre = origin + (ijk + 0.5) * size + rng.uniform(-1, 1, (len(ijk), 3)) * (0.125 - half)[:, None]
    res = []
    for backend in ("embree", "grid"):
        sc = Scene(voxel_backend=backend)
        sc.add_voxels(5, ijk, origin, size, half, centre)
        lo, hi = sc.bounds()
        o, d = _rays(4000, np.random.default_rng(2), lo, hi)
        res.append(sc.trace(o, d))
    (t1, p1, c1), (t2, p2, c2) = res
    assert np.array_equal(np.isfinite(t1), np.isfinite(t2))
    hit = np.isfinite(t1)
    assert hit.mean() > 0.3
    assert np.abs(t1[hit] - t2[hit]).max() < 1e-4  # Embree is float32
    assert (p1 == p2).all()
    assert np.abs(c1[hit] - c2[hit]).max() < 1e-3


def test_auto_backend_sends_a_crowded_lattice_to_one_grid(monkeypatch):
    monkeypatch.setattr(routing, "EMBREE_VOXEL_LIMIT", 500)
    rng = np.random.default_rng(3)
    a = np.unique(rng.integers(0, 12, size=(400, 3)), axis=0)          # < 500 alone
    b = np.unique(rng.integers(20, 32, size=(400, 3)), axis=0)         # same lattice: 2 × ~390 > 500
    c = np.unique(rng.integers(0, 6, size=(100, 3)), axis=0)           # another lattice
    size = 0.1
    res = {}
    for backend in ("auto", "embree"):
        sc = Scene(voxel_backend=backend)
        sc.add_voxels(1, a, [0.0, 0.0, 0.0], size)
        sc.add_voxels(2, b, [0.3, 0.0, 0.0], size)        # congruent origin: same lattice
        sc.add_voxels(3, c, [0.0, 0.0, 5.03], 0.25)
        in_embree = sc.tracer.routing
        if backend == "auto":
            assert in_embree == [False, False, True]
            assert len(sc.grids) == 1 and sc.grids[0].n_voxels == len(a) + len(b)
        lo, hi = sc.bounds()
        res[backend] = sc.trace(*_rays(3000, np.random.default_rng(4), lo, hi))
    (t1, p1, _), (t2, p2, _) = res["auto"], res["embree"]
    hit = np.isfinite(t2)
    assert hit.mean() > 0.3 and {0, 1, 2} <= set(p2[hit].tolist())
    assert np.array_equal(np.isfinite(t1), hit) and (p1 == p2).all()
    assert np.abs(t1[hit] - t2[hit]).max() < 1e-4


def test_planned_routing_weighs_embree_build_against_rays(monkeypatch):
    """With the number of rays known, a lattice goes to Embree only when the rays repay its
    build, never beyond EMBREE_VOXEL_MAX cubes; a re-plan rebuilds and traces the same hits."""
    rng = np.random.default_rng(5)
    ijk = np.unique(rng.integers(0, 10, size=(300, 3)), axis=0)
    n = len(ijk)
    sc = Scene(voxel_backend="auto")
    sc.add_voxels(1, ijk, [0.0, 0.0, 0.0], 0.1)
    assert sc.tracer.routing == [True]                  # no plan: n <= EMBREE_VOXEL_LIMIT
    lo, hi = sc.bounds()
    o, d = _rays(3000, np.random.default_rng(6), lo, hi)
    t_e, p_e, _ = sc.trace(o, d)
    # break-even: rays · 0.16 µs · (0.25/0.1)^0.6 = 1.25 · 6 µs · n
    assert routing.EMBREE_BUILD_S_PER_CUBE == 6e-6 and routing.EMBREE_SAVES_S_PER_RAY == 0.16e-6
    assert routing.EMBREE_BUILD_MARGIN == 1.25
    even = 1.25 * 6e-6 * n / (0.16e-6 * 2.5 ** 0.6)
    sc.plan_for_rays(0.9 * even)
    assert sc.tracer.routing == [False] and len(sc.grids) == 1
    t_g, p_g, _ = sc.trace(o, d)
    hit = np.isfinite(t_e)
    assert hit.mean() > 0.3 and np.array_equal(np.isfinite(t_g), hit) and (p_g == p_e).all()
    assert np.abs(t_g[hit] - t_e[hit]).max() < 1e-4
    sc.plan_for_rays(1.1 * even)
    assert sc.tracer.routing == [True] and sc.grids == []
    t_e2 = sc.trace(o, d)[0]
    assert np.abs(t_e2[hit] - t_e[hit]).max() < 1e-6
    monkeypatch.setattr(routing, "EMBREE_VOXEL_MAX", n - 1)
    sc.plan_for_rays(1e12)
    assert sc.tracer.routing == [False]
    with pytest.raises(ConfigError, match="expected number of rays"):
        sc.plan_for_rays(float("nan"))
    fixed = Scene(voxel_backend="grid")
    fixed.add_voxels(1, ijk, [0.0, 0.0, 0.0], 0.1)
    fixed.plan_for_rays(1e12)
    assert fixed.tracer.routing == [False]


def test_simulate_plans_the_routing_from_the_survey():
    """The simulator estimates the survey's sub-rays and routes the voxels by them: a short
    survey over many cubes keeps them in the grid, a long one sends them to Embree, where the
    points are those of the grid (positions to float32 precision; a pulse grazing a cube edge
    may resolve differently in the two)."""
    from vlsforest.sim import simulate, survey_from_dict

    rng = np.random.default_rng(7)
    ijk = np.unique(np.c_[rng.integers(-20, 20, (60000, 2)), rng.integers(40, 60, 60000)], axis=0)

    def run(length, backend="auto"):
        sc = Scene(voxel_backend=backend)
        sc.add_plane(1, 0.0, (-40, -40, 40, 40))
        sc.add_voxels(2, ijk, [0.0137, 0.0291, 0.0053], 0.25)  # off the scan planes: few grazing rays
        survey = survey_from_dict({
            "scanner": "riegl_minivux1uav",
            "platform": {"type": "linear", "speed_mps": 5.0,
                         "legs": [{"start": [0.37, -length / 2, 60.0], "end": [0.37, length / 2, 60.0]}]}})
        res = simulate(sc, survey, seed=1, workers=1)
        saves = res.timings["n_rays"] * 0.16e-6
        build = 1.25 * 6e-6 * len(ijk)
        return sc.tracer.routing, saves > build, res

    in_embree, pays, _ = run(2.0)
    assert in_embree == [False] and not pays
    in_embree, pays, res = run(30.0)
    assert in_embree == [True] and pays
    grid = run(30.0, "grid")[2]
    a, b = res.points["xyz"], grid.points["xyz"]
    assert len(a) > 100000 and abs(len(a) - len(b)) <= 1e-4 * len(b)
    d, _ = cKDTree(b).query(a)
    assert (d < 1e-3).mean() > 0.9999


def test_vox_scaled_placement(tmp_path):
    ijk = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0]])
    pad = np.array([8.0, 2.0, 0.0])
    vox = make_vox(ijk, 1.0, [10.0, 20.0, 30.0], columns={"PadBVTotal": pad}, max_pad=8.0)
    write_vox(tmp_path / "c.vox", vox)
    (tmp_path / "s.yaml").write_text(yaml.safe_dump({"parts": [
        {"id": 1, "type": "vox", "path": "c.vox", "mode": "scaled", "alpha": 0.5}]}))
    sc = Scene.from_yaml(tmp_path / "s.yaml")
    assert sc.n_voxels == 2  # the PAD-0 voxel carries no cube
    # nadir rays through the cell centres: top faces at centre z + half size
    o = np.array([[10.5, 20.5, 40.0], [11.5, 20.5, 40.0], [12.5, 20.5, 40.0]])
    d = np.tile([0.0, 0.0, -1.0], (3, 1))
    t, part, cos = sc.trace(o, d)
    half = 0.5 * (pad[:2] / 8.0) ** 0.5
    assert t[:2] == pytest.approx(40.0 - (30.5 + half), abs=1e-5)
    assert np.isinf(t[2])
    assert cos[:2] == pytest.approx(1.0)


def test_random_shift_stays_in_cell(tmp_path):
    rng = np.random.default_rng(0)
    ijk = np.unique(rng.integers(0, 20, size=(500, 3)), axis=0)
    pad = rng.uniform(0.1, 5.0, len(ijk))
    write_vox(tmp_path / "c.vox", make_vox(ijk, 0.25, [0, 0, 0], columns={"PadBVTotal": pad}, max_pad=5.0))
    cfg = {"parts": [{"id": 1, "type": "vox", "path": "c.vox", "mode": "scaled", "random_shift": True,
                      "seed": 4}]}
    (tmp_path / "s.yaml").write_text(yaml.safe_dump(cfg))
    sc = Scene.from_yaml(tmp_path / "s.yaml")
    v = sc.geometry.voxels[0]
    lo = (v.ijk * 0.25)
    assert ((v.centre - v.half[:, None]) >= lo - 1e-12).all()
    assert ((v.centre + v.half[:, None]) <= lo + 0.25 + 1e-12).all()
    assert np.abs(v.centre - (lo + 0.125)).max() > 0.01  # really shifted
    assert (v.half <= 0.125 + 1e-15).all()


def test_real_vox_fixed_reads():
    from pathlib import Path

    real = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"
    if not (real / "F_BR08_08_crown_250.vox").is_file():
        pytest.skip("real data absent")
    sc = Scene.from_dict({"parts": [{"id": 1, "type": "vox", "path": str(real / "F_BR08_08_crown_250.vox")},
                                    {"id": 2, "type": "mesh", "path": str(real / "F_BR08_08_stem_Poisson.obj")}]})
    assert sc.n_voxels == 6185
    lo, hi = sc.bounds()
    assert hi[2] == pytest.approx(247.875 + 87 * 0.25, abs=0.25)


@pytest.mark.parametrize("cfg,msg", [
    ({"parts": []}, "non-empty"),
    ({"parts": [{"id": 1, "type": "cone"}]}, "type"),
    ({"parts": [{"id": 1, "type": "plane", "z": 0, "extent": [1, 0, 0, 1]}]}, "extent"),
    ({"parts": [{"id": 1, "type": "plane", "z": 0, "extent": [0, 0, 1, 1], "reflectance": 50}]}, "reflectance"),
    ({"parts": [{"id": 1, "type": "plane", "z": 0, "extent": [0, 0, 1, 1], "colour": 1}]}, "colour"),
    ({"parts": [{"id": 1, "type": "plane", "z": 0, "extent": [0, 0, 1, 1]},
                {"id": 1, "type": "plane", "z": 1, "extent": [0, 0, 1, 1]}]}, "twice"),
    ({"parts": [{"id": 1, "type": "voxels", "path": "x.csv", "size": 0}]}, "size"),
    ({"parts": [], "extra": 1}, "extra"),
])
def test_scene_config_errors(cfg, msg):
    with pytest.raises(ConfigError, match=msg):
        Scene.from_dict(cfg)


def test_missing_mesh_file_is_input_error(tmp_path):
    with pytest.raises(InputDataError, match="nope.obj"):
        Scene.from_dict({"parts": [{"id": 1, "type": "mesh", "path": "nope.obj"}]}, base_dir=tmp_path)


def test_cli_bad_scene_exit_2(tmp_path, capsys):
    (tmp_path / "scene.yaml").write_text("parts:\n  - {id: 1, type: plane, z: 0\n")  # broken YAML
    (tmp_path / "survey.yaml").write_text("scanner: riegl_vq780i\n")
    rc = main(["simulate", str(tmp_path / "scene.yaml"), str(tmp_path / "survey.yaml"), "-o", str(tmp_path / "o.laz")])
    err = capsys.readouterr().err
    assert rc == 2
    assert "line" in err and "Traceback" not in err
    assert not (tmp_path / "o.laz").exists()


def test_restyled_scene_shares_geometry_changes_energy():
    from vlsforest.sim import Material, simulate
    from vlsforest.sim.survey import survey_from_dict

    sc = Scene()
    sc.add_plane(1, 0.0, [-50, -50, 50, 50], Material(0.2))
    v = np.array([[-5, -5, 3], [5, -5, 3], [5, 5, 3], [-5, 5, 3]], float)
    sc.add_mesh(2, v, [[0, 1, 2], [0, 2, 3]], Material(0.4))
    other = sc.restyled({2: Material(0.1)})
    assert other.tracer.embree is sc.tracer.embree  # the BVH is shared
    assert sc.parts[1].material.reflectance == 0.4  # the original is unchanged
    sv = survey_from_dict({"scanner": "riegl_vq780i", "overrides": {"prf_hz": 5000, "scan_freq_hz": 10,
                          "scan_angle_deg": 10.0, "max_scan_angle_deg": 10.0, "range_min_m": 0.0},
                           "platform": {"speed_mps": 2, "legs": [{"start": [0, -1, 50], "end": [0, 1, 50]}]}})
    a, b = simulate(sc, sv, workers=1), simulate(other, sv, workers=1)
    assert np.array_equal(a.points["xyz"], b.points["xyz"])
    on = a.points["object_id"] == 2
    assert on.any()
    assert np.allclose(b.points["amplitude"][on] / a.points["amplitude"][on], 0.25, rtol=1e-5)
    with pytest.raises(ConfigError):
        sc.restyled({99: Material(0.1)})


def test_restyled_copy_plans_and_grows_on_its_own():
    """A restyled copy starts from the original's built grid; planning for other rays or adding
    a part changes the one it is done to, and the other keeps its routing, parts and hits."""
    from vlsforest.sim import Material

    rng = np.random.default_rng(8)
    ijk = np.unique(rng.integers(0, 10, size=(300, 3)), axis=0)
    sc = Scene(voxel_backend="auto")
    sc.add_plane(1, -1.0, (-5, -5, 5, 5))
    sc.add_voxels(2, ijk, [0.0, 0.0, 0.0], 0.1)
    sc.plan_for_rays(1.0)  # one ray never repays an Embree build: the grid
    lo, hi = sc.bounds()
    o, d = _rays(2000, np.random.default_rng(9), lo, hi)
    before = sc.trace(o, d)
    other = sc.restyled({2: Material(0.1)})
    assert other.tracer.routing == [False] and other.grids[0] is sc.grids[0]
    other.plan_for_rays(1e12)  # many rays: Embree
    assert other.tracer.routing == [True] and other.grids == []
    assert sc.tracer.routing == [False] and len(sc.grids) == 1
    other.add_mesh(3, [[-1, -1, 2.0], [1, -1, 2.0], [0, 1, 2.0]], [[0, 1, 2]])
    assert [p.object_id for p in other.parts] == [1, 2, 3] and other.n_triangles == 1
    assert [p.object_id for p in sc.parts] == [1, 2] and sc.n_triangles == 0
    for a, b in zip(sc.trace(o, d), before):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("content, needle", [
    (None, "no such voxel centres file"),
    ("x,y,z\n0.1,0.1\n0.1,0.1,0.1,0.1,0.1\n", "not a readable CSV"),
    ("x,y\n0.1,0.1\n", "needs columns x, y, z"),
])
def test_bad_voxel_centres_csv_names_the_file(tmp_path, content, needle):
    if content is not None:
        (tmp_path / "c.csv").write_text(content)
    cfg = {"parts": [{"id": 1, "type": "voxels", "path": "c.csv", "size": 0.2}]}
    with pytest.raises(InputDataError, match="c.csv: " + needle):
        Scene.from_dict(cfg, base_dir=tmp_path)


def test_bad_trajectory_csv_is_one_line(tmp_path, capsys):
    (tmp_path / "traj.csv").write_text("gps_time,x\n0,1\n0,1,2\n")
    out = tmp_path / "survey.yaml"
    rc = main(["plan", "--trajectory", str(tmp_path / "traj.csv"), "--scenario-json",
               '{"pattern": "trajectory", "scanner": "riegl_vq780i"}', "-o", str(out)])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "\n" not in err
    assert err.startswith(f"vlsforest plan: error: {tmp_path / 'traj.csv'}: not a readable CSV")
    assert not out.exists()


def test_targets_table_without_tree_id_is_one_line(tmp_path, capsys):
    (tmp_path / "targets.csv").write_text("target_id,z\n301,0.0\n")
    out = tmp_path / "crowns.npz"
    rc = main(["scene", "crowns", str(tmp_path), "--stems", str(tmp_path), "--targets", str(tmp_path / "targets.csv"),
               "-o", str(out)])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "\n" not in err
    assert err == f"vlsforest scene: error: {tmp_path / 'targets.csv'}: targets table lacks column(s) ['tree_id']"
    assert not out.exists()


def test_restyled_keeps_the_subclass():
    from vlsforest.sim import Material

    class Sub(Scene):
        pass

    sc = Sub()
    sc.add_plane(1, 0.0, (-5, -5, 5, 5))
    other = sc.restyled({1: Material(0.1)})
    assert type(other) is Sub
    assert other.parts[0].material.reflectance == 0.1


def test_one_worker_traces_the_grid_on_one_cpu(monkeypatch):
    """``workers=1`` (a one-thread workflow job) runs the voxel-grid kernel without threads, then
    restores the module's setting; the points equal those of two worker processes."""
    from vlsforest.sim import _voxelgrid, simulate, survey_from_dict

    sc = Scene(voxel_backend="grid")
    sc.add_plane(1, 0.0, (-10, -10, 10, 10))
    ijk = np.array([[i, j, 40] for i in range(-8, 8) for j in range(-8, 8)])
    sc.add_voxels(2, ijk, [0.0, 0.0, 0.0], 0.25)
    survey = survey_from_dict({
        "scanner": "riegl_minivux1uav",
        "platform": {"type": "linear", "speed_mps": 5.0, "legs": [{"start": [0.1, -1, 30.0], "end": [0.1, 1, 30.0]}]}})
    two = simulate(sc, survey, seed=1, workers=2, block_slots=2000)
    kernels = []
    parallel, serial = _voxelgrid._trace_kernel, _voxelgrid._trace_kernel_serial
    monkeypatch.setattr(_voxelgrid, "_trace_kernel", lambda *a: (kernels.append("parallel"), parallel(*a))[1])
    monkeypatch.setattr(_voxelgrid, "_trace_kernel_serial", lambda *a: (kernels.append("serial"), serial(*a))[1])
    one = simulate(sc, survey, seed=1, workers=1, block_slots=2000)
    assert kernels and set(kernels) == {"serial"}
    assert (one.points["object_id"] == 2).sum() > 1000
    for k in ("xyz", "amplitude", "return_number", "object_id"):
        assert np.array_equal(one.points[k], two.points[k])
