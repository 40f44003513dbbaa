"""Scene assembly: parts from YAML, voxel placement, back-end equivalence, clear errors."""

import numpy as np
import pytest
import yaml

from vlsforest.cli import main
from vlsforest.errors import ConfigError, InputDataError
from vlsforest.io.vox import make_vox, write_vox
from vlsforest.sim import Scene


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
    monkeypatch.setattr(Scene, "EMBREE_VOXEL_LIMIT", 500)
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
        in_embree = sc._routing()
        if backend == "auto":
            assert in_embree == [False, False, True]
            assert len(sc.grids) == 1 and sc.grids[0].n_voxels == len(a) + len(b)
        lo, hi = sc.bounds()
        res[backend] = sc.trace(*_rays(3000, np.random.default_rng(4), lo, hi))
    (t1, p1, c1), (t2, p2, c2) = res["auto"], res["embree"]
    hit = np.isfinite(t2)
    assert hit.mean() > 0.3 and {0, 1, 2} <= set(p2[hit].tolist())
    assert np.array_equal(np.isfinite(t1), hit) and (p1 == p2).all()
    assert np.abs(t1[hit] - t2[hit]).max() < 1e-4


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
    v = sc._voxelsets[0]
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
    assert other._embree is sc._embree  # the BVH is shared
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
