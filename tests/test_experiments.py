"""Tests of the experiments (vlsforest.experiments) and ``vlsforest experiment``."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from vlsforest.errors import ConfigError
from vlsforest.experiments import tls_step


def test_filled_cells_counts_distinct_cells():
    xyz = np.array([[0.001, 0.001, 0.001], [0.019, 0.019, 0.019], [0.021, 0.0, 0.0], [-0.001, 0.0, 0.0]])
    # 0.02 m: (0,0,0) twice, (1,0,0), (-1,0,0); 0.25 m: (0,0,0) and (-1,0,0)
    assert len(tls_step.filled_cells(xyz, 0.02)) == 3
    assert len(tls_step.filled_cells(xyz, 0.25)) == 2
    assert tls_step.filled_cells(np.zeros((0, 3)), 0.02).shape == (0, 3)


def test_tree_fov_points_at_the_box():
    # a 2 m wide, 10 m tall box 20 m north of a scanner at 1.5 m height
    lo, hi = np.array([-1.0, 19.0, 0.0]), np.array([1.0, 21.0, 10.0])
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    fov = tls_step.tree_fov([0.0, 0.0, 1.5], corners, (-40.0, 60.0))
    assert fov["heading_deg"] == pytest.approx(0.0, abs=1e-9)
    # widest corner: atan(1/19)
    assert fov["h_half_deg"] == pytest.approx(math.degrees(math.atan2(1.0, 19.0)) + tls_step.FOV_MARGIN_DEG)
    # from the box's lowest corner seen at the nearest distance 19 m to its top seen at 19 m
    assert fov["v_fov_deg"][0] == pytest.approx(math.degrees(math.atan2(-1.5, 19.0)) - tls_step.FOV_MARGIN_DEG)
    assert fov["v_fov_deg"][1] == pytest.approx(math.degrees(math.atan2(8.5, 19.0)) + tls_step.FOV_MARGIN_DEG)
    # a box entirely above the vertical limits is not scanned
    assert tls_step.tree_fov([0.0, 0.0, 1.5], corners + [0, 0, 100.0], (-40.0, 5.0)) is None


def test_run_rejects_bad_arguments():
    with pytest.raises(ConfigError, match="steps"):
        tls_step.run_tls_step({"forest": {"preset": "quick"}}, "Q1", [0.0])
    with pytest.raises(ConfigError, match="band_m"):
        tls_step.run_tls_step({"forest": {"preset": "quick"}}, "Q1", [0.5], band_m=0.0)
    with pytest.raises(ConfigError, match="unknown plot"):
        tls_step.run_tls_step({"forest": {"preset": "quick"}}, "nope", [0.5])


@pytest.mark.e2e
def test_finer_step_fills_more_fine_cells(tmp_path):
    """On the quick forest: a finer step fills more 0.02 m cells per filled 0.25 m cell; the CLI
    writes the same bytes twice."""
    from vlsforest.cli import main

    cfg = json.dumps({"forest": {"preset": "quick"}, "seed": 0})
    outs = []
    for name in ("a.json", "b.json"):
        rc = main(["experiment", "tls-step", "--config-json", cfg, "--plot", "Q1", "--steps", "0.4", "0.2",
                   "--trees", "1", "--band", "1.5", "--cells", "0.1", "-o", str(tmp_path / name)])
        assert rc == 0
        outs.append((tmp_path / name).read_bytes())
    assert outs[0] == outs[1]
    res = json.loads(outs[0])
    coarse, fine = res["steps"]
    assert coarse["step_deg"] == 0.4 and fine["step_deg"] == 0.2
    assert fine["n_returns"] > 2 * coarse["n_returns"]
    assert fine["cells_fine"] > coarse["cells_fine"]
    assert fine["ratio"] > coarse["ratio"]
    assert res["n_trees"] == 1 and res["band_m"] == 1.5
    # the fill of each cell size, by the definition: n·h³ / (n_0.25·0.25³); the 0.25 m grid fills itself
    for rec in (coarse, fine):
        assert set(rec["cells"]) == {"0.02", "0.1", "0.25"}
        assert rec["fill"]["0.25"] == 1.0
        assert rec["fill"]["0.1"] == pytest.approx(rec["cells"]["0.1"] * 0.1 ** 3 / (rec["cells"]["0.25"] * 0.25 ** 3))
        assert 0 < rec["fill"]["0.02"] < rec["fill"]["0.1"]
        (group,) = rec["groups"].values()
        assert group["n_trees"] == 1 and group["cells"] == rec["cells"]
        # one CoG offset per filled 0.25 m cell, each within half a cell of its centre
        cog = rec["cog_offset"]
        assert cog["n_cells"] == rec["cells"]["0.25"] and group["cog_offset"] == cog
        assert abs(cog["z_m"]) < 0.125 and abs(cog["radial_m"]) < 0.125 and cog["z_se_m"] > 0
    # a finer step fills more of the crown with small cells
    assert fine["fill"]["0.02"] > coarse["fill"]["0.02"]


def test_cli_bad_config_is_one_line(tmp_path, capsys):
    from vlsforest.cli import main

    assert main(["experiment", "tls-step", "--config-json", "{", "--plot", "Q1", "-o", str(tmp_path / "x.json")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("vlsforest experiment: error: --config-json") and "\n" not in err
    assert not (tmp_path / "x.json").exists()


@pytest.mark.parametrize("option, values", [("--cells", ["0.1", "0"]), ("--band", ["0"]), ("--steps", ["0"])])
def test_cli_bad_option_names_the_option(tmp_path, capsys, option, values):
    from vlsforest.cli import main

    out = tmp_path / "x.json"
    argv = ["experiment", "tls-step", "--config-json", '{"forest": {"preset": "quick"}}', "--plot", "Q1",
            option, *values, "-o", str(out)]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"vlsforest experiment: error: {option}: ") and "\n" not in err
    assert "_m" not in err
    assert not out.exists()


@pytest.mark.e2e
def test_recording_detector_helios_rule_drops_isolated_echoes():
    """On the quick forest's ULS (one grid): HELIOS++ 1.0.8's peak rule, which also requires the
    window's neighbours above the threshold, records fewer multi-return pulses than the physical
    detector, and a 4× threshold fewer too; the recording row comes first."""
    from vlsforest.experiments.recording_detector import run_recording_detector

    cfg = {"forest": {"preset": "quick"}, "recordings": {"uls": {"cross_margin_m": 30, "repeats": 1}}}
    res = run_recording_detector(cfg, "Q1", "uls", {"helios": {"peak_rule": {"physical": 0}},
                                                    "x4": {"detection_threshold": {"min_energy": 40000}}})
    rows = {r["name"]: r for r in res["variants"]}
    assert [r["name"] for r in res["variants"]] == ["recording", "helios", "x4"]
    for g in ("conifer", "broadleaf"):
        assert rows["recording"][g]["n"] == 2
        assert rows["helios"][g]["mean_pct"] < rows["recording"][g]["mean_pct"]
        assert rows["x4"][g]["mean_pct"] < rows["recording"][g]["mean_pct"]


def test_recording_detector_rejects_bad_variants():
    from vlsforest.experiments.recording_detector import run_recording_detector

    with pytest.raises(ConfigError, match="sensor"):
        run_recording_detector({}, "Q1", "tls", {})
    with pytest.raises(ConfigError, match="variants"):
        run_recording_detector({"forest": {"preset": "quick"}}, "Q1", "uls", {"recording": {}})
    with pytest.raises(ConfigError, match="unknown physics candidate"):
        run_recording_detector({"forest": {"preset": "quick"}}, "Q1", "uls", {"v": {"nonsense": {}}})


def test_fill_is_the_volume_share_of_the_coarse_cells():
    # eight 0.125 m cells fill one 0.25 m cell; one 0.05 m cell fills 0.05³ / 0.25³ = 1/125 of it
    assert tls_step.fill(8, 0.125, 1) == pytest.approx(1.0)
    assert tls_step.fill(1, 0.05, 1) == pytest.approx(1 / 125)
    assert tls_step.fill(10, 0.1, 4) == pytest.approx(10 * 0.001 / (4 * 0.015625))
    assert math.isnan(tls_step.fill(3, 0.1, 0))
    assert tls_step.cell_key(0.10) == "0.1" and tls_step.cell_key(0.25) == "0.25"


def test_run_rejects_bad_cell_sizes():
    with pytest.raises(ConfigError, match="cells_m"):
        tls_step.run_tls_step({"forest": {"preset": "quick"}}, "Q1", [0.5], cells_m=[0.1, 0.0])


def test_cog_offsets_vertical_and_radial():
    # cell (0, 0, 0) of 0.25 m, centre (0.125, 0.125, 0.125): two points low in the cell and towards
    # +x; the stem axis at x = -10 lies on the -x side, so +x is outward
    xyz = np.array([[0.20, 0.125, 0.05], [0.20, 0.125, 0.07]])
    off = tls_step.cog_offsets(xyz, (-10.0, 0.125))
    assert off.shape == (1, 2)
    assert off[0, 0] == pytest.approx(0.06 - 0.125)       # centroid z 0.06
    assert off[0, 1] == pytest.approx(0.20 - 0.125)       # outward along +x
    # seen from an axis at x = +10 the same offset points inward
    assert tls_step.cog_offsets(xyz, (10.0, 0.125))[0, 1] == pytest.approx(-(0.20 - 0.125))
    # a cell centred on the axis has no radial direction
    assert tls_step.cog_offsets(xyz, (0.125, 0.125))[0, 1] == 0.0
    assert tls_step.cog_offsets(np.zeros((0, 3)), (0, 0)).shape == (0, 2)
