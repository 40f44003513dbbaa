"""The simulate/detect/plan/demo commands end to end: files, fields, errors, determinism."""

import hashlib

import laspy
import numpy as np
import pytest
import yaml

from vlsforest.cli import main


def _write(tmp_path, name, obj):
    p = tmp_path / name
    p.write_text(yaml.safe_dump(obj, sort_keys=False))
    return p


@pytest.fixture
def demo(tmp_path):
    assert main(["demo", "-o", str(tmp_path / "scene" / "scene.yaml"), "--seed", "1"]) == 0
    scenario = {"scanner": "riegl_minivux1uav", "pattern": "double_grid", "altitude_m": 40, "speed_mps": 8,
                "line_spacing_m": 28, "n_lines": 1, "margin_m": 0, "overrides": {"prf_hz": 20000}}
    sc = _write(tmp_path, "scenario.yaml", scenario)
    assert main(["plan", "--scene", str(tmp_path / "scene" / "scene.yaml"), "--scenario", str(sc),
                 "-o", str(tmp_path / "survey.yaml")]) == 0
    return tmp_path


def test_simulate_writes_las14_with_fields(demo):
    out = demo / "sim.laz"
    rc = main(["simulate", str(demo / "scene" / "scene.yaml"), str(demo / "survey.yaml"), "-o", str(out),
               "--pulses", str(demo / "pulses.csv"), "--hits", str(demo / "hits.npz"), "--quiet", "--workers", "1"])
    assert rc == 0
    las = laspy.read(out)
    assert str(las.header.version) == "1.4" and las.header.point_format.id == 6
    dims = set(las.point_format.dimension_names)
    assert {"object_id", "amplitude", "gps_time", "return_number", "number_of_returns", "point_source_id"} <= dims
    assert set(np.unique(las.object_id)) <= {1, 2, 3} and 3 in set(np.unique(las.object_id))
    rn, nr = np.asarray(las.return_number), np.asarray(las.number_of_returns)
    assert (rn >= 1).all() and (rn <= nr).all()
    assert np.abs(np.asarray(las.scan_angle) * 0.006).max() <= 90.0
    # ground returns carry the plane's class
    assert (np.asarray(las.classification)[np.asarray(las.object_id) == 1] == 2).all()
    import pandas as pd

    pulses = pd.read_csv(demo / "pulses.csv")
    assert (pulses.n_returns == 0).any()  # zero-return pulses are in the table
    assert pulses.n_returns.sum() == len(las.points)
    # detect on the stored hits reproduces the cloud exactly
    out2 = demo / "again.laz"
    assert main(["detect", str(demo / "hits.npz"), str(demo / "survey.yaml"), "-o", str(out2)]) == 0
    assert hashlib.sha256(out.read_bytes()).hexdigest() == hashlib.sha256(out2.read_bytes()).hexdigest()


def test_simulate_deterministic_bytes(demo):
    a, b = demo / "a.laz", demo / "b.laz"
    args = [str(demo / "scene" / "scene.yaml"), str(demo / "survey.yaml"), "--quiet", "--seed", "5"]
    assert main(["simulate", *args, "-o", str(a), "--workers", "1"]) == 0
    assert main(["simulate", *args, "-o", str(b), "--workers", "2"]) == 0
    assert a.read_bytes() == b.read_bytes()


def test_detect_with_wider_window_merges_returns(demo):
    main(["simulate", str(demo / "scene" / "scene.yaml"), str(demo / "survey.yaml"), "-o", str(demo / "s.laz"),
          "--hits", str(demo / "hits.npz"), "--quiet", "--workers", "1"])
    sv = yaml.safe_load((demo / "survey.yaml").read_text())
    sv.setdefault("overrides", {})["window_size_ns"] = 6.0
    _write(demo, "wide.yaml", sv)
    assert main(["detect", str(demo / "hits.npz"), str(demo / "wide.yaml"), "-o", str(demo / "w.laz")]) == 0
    n_base = len(laspy.read(demo / "s.laz").points)
    n_wide = len(laspy.read(demo / "w.laz").points)
    assert n_wide < n_base  # a longer dead zone merges echoes


@pytest.mark.parametrize("bad,needle", [
    ({"overrides": {"prf_hz": -1}}, "prf_hz"),
    ({"overrides": {"warp_speed": 1}}, "warp_speed"),
    ({"scanner": "riegl_nope"}, "riegl_nope"),
    ({"detector": {"peak_rule": "magic"}}, "peak_rule"),
])
def test_bad_survey_exit_2_names_key(demo, capsys, bad, needle):
    sv = yaml.safe_load((demo / "survey.yaml").read_text())
    for k, v in bad.items():
        if isinstance(v, dict):
            sv.setdefault(k, {}).update(v)
        else:
            sv[k] = v
    p = _write(demo, "bad.yaml", sv)
    out = demo / "bad.laz"
    rc = main(["simulate", str(demo / "scene" / "scene.yaml"), str(p), "-o", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and needle in err and "Traceback" not in err
    assert not out.exists()


def test_detect_rejects_non_hits_file(tmp_path, capsys):
    (tmp_path / "x.npz").write_bytes(b"not a zip")
    (tmp_path / "s.yaml").write_text("scanner: riegl_vq780i\nplatform: {speed_mps: 1, legs: [{start: [0,0,1], end: [0,1,1]}]}\n")
    rc = main(["detect", str(tmp_path / "x.npz"), str(tmp_path / "s.yaml"), "-o", str(tmp_path / "o.laz")])
    assert rc == 2 and "x.npz" in capsys.readouterr().err


@pytest.mark.parametrize("margin", ["-1", "nan"])
def test_negative_region_margin_exit_2(demo, capsys, margin):
    site = demo / "site.json"
    site.write_text('{"targets_extent": [-5, -5, 5, 5]}')
    out = demo / "m.laz"
    rc = main(["simulate", str(demo / "scene" / "scene.yaml"), str(demo / "survey.yaml"), "-o", str(out),
               "--quiet", "--region-from", str(site), "--region-margin", margin])
    err = capsys.readouterr().err
    assert rc == 2 and "--region-margin must be ≥ 0" in err and "Traceback" not in err
    assert not out.exists()


def test_region_margin_is_widened_to_the_scene_cells(demo, capsys):
    # the demo crowns are 0.25 m cells: a margin below their diagonal (0.354 m) would cut the
    # outermost cells of a target, so it is widened (and said so); a wider one is kept
    site = demo / "site.json"
    site.write_text('{"targets_extent": [-5, -5, 5, 5]}')
    args = [str(demo / "scene" / "scene.yaml"), str(demo / "survey.yaml"), "--quiet", "--workers", "1",
            "--region-from", str(site)]
    outs = {}
    for m in ("0", "0.354", "1"):
        outs[m] = demo / f"r{m}.laz"
        assert main(["simulate", *args, "--region-margin", m, "-o", str(outs[m])]) == 0
        err = capsys.readouterr().err
        assert ("region margin widened from 0 to 0.354 m" in err) == (m == "0"), err
    # widened to the diagonal: the same region (to the rounding of the printed value) as asked for it
    a, b = laspy.read(outs["0"]), laspy.read(outs["0.354"])
    assert len(a.points) == len(b.points) > 0
    assert len(laspy.read(outs["1"]).points) >= len(a.points)


@pytest.mark.parametrize("workers", ["0", "-2"])
def test_workers_below_one_exit_2(demo, capsys, workers):
    """``--workers`` 0 or negative is an error, not "all CPUs" in disguise; the API says so too."""
    from vlsforest.errors import ConfigError
    from vlsforest.sim import Scene, load_survey, simulate

    out = demo / "w.laz"
    rc = main(["simulate", str(demo / "scene" / "scene.yaml"), str(demo / "survey.yaml"), "-o", str(out),
               "--quiet", "--workers", workers])
    err = capsys.readouterr().err
    assert rc == 2 and f"--workers must be ≥ 1, got {workers}" in err and "Traceback" not in err
    assert not out.exists()
    scene, survey = Scene.from_yaml(demo / "scene" / "scene.yaml"), load_survey(demo / "survey.yaml")
    for bad in (0, -1, 1.5, True, "2"):
        with pytest.raises(ConfigError, match="workers must be an integer ≥ 1"):
            simulate(scene, survey, workers=bad)
    cfg = demo / "synth.yaml"
    cfg.write_text(yaml.safe_dump({"forest": {"preset": "quick"}}))
    assert main(["synth", str(cfg), "-o", str(demo / "forest"), "--workers", workers]) == 2
    err = capsys.readouterr().err
    assert f"--workers must be ≥ 1, got {workers}" in err and not (demo / "forest").exists()
