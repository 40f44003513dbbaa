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


@pytest.mark.e2e
def test_recording_detector_redetection_equals_a_full_simulation():
    """A detector variant is detected on the recording's trace; the same physics with a
    trace-side key restating the recording's value (its beam sampling) is simulated in full:
    both give the same points and shares."""
    from vlsforest.experiments.recording_detector import run_recording_detector
    from vlsforest.synth.record import DEFAULT_RECORDING_PHYSICS

    quality = DEFAULT_RECORDING_PHYSICS["uls"]["beam_sample_quality"]
    cfg = {"forest": {"preset": "quick"}, "recordings": {"uls": {"cross_margin_m": 30, "repeats": 1}}}
    x2 = {"detection_threshold": {"min_energy": 20000}}
    res = run_recording_detector(cfg, "Q1", "uls", {"redetected": x2,
                                                    "traced": dict(x2, beam_sample_quality=quality)})
    rows = {r["name"]: r for r in res["variants"]}
    assert rows["redetected"]["n_points"] == rows["traced"]["n_points"] != rows["recording"]["n_points"]
    for t in res["trees"]:
        assert t["shares_pct"]["redetected"] == t["shares_pct"]["traced"]


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


# --------------------------------------------------------------------------- analyses of a run's files


def _grid(x0, x1, y0, y1, zs, step=0.25):
    """Points on a regular xy grid over [x0, x1] × [y0, y1] at each height of ``zs``."""
    xs = np.arange(x0, x1 + 1e-9, step)
    ys = np.arange(y0, y1 + 1e-9, step)
    return np.array([[x, y, z] for z in zs for x in xs for y in ys])


def _write_run(tmp_path, ref_xyz, sim_xyz, cubes_ijk, cell=0.5, sides=None, ground_z=100.0):
    """A one-plot, one-tree run: targets, a reference and a simulated tree cloud, a voxel model."""
    from vlsforest.io.las import PointCloud, write_las
    from vlsforest.io.voxel_model import VoxelModel

    d = tmp_path / "P1"
    d.mkdir()
    (d / "targets.csv").write_text(f"target_id,tree_id,species,group,x,y,z\n7,3,picea_abies,conifer,0,0,{ground_z}\n")
    for name, xyz in (("ref", ref_xyz), ("sim", sim_xyz)):
        xyz = np.asarray(xyz, float) + [0, 0, ground_z]
        write_las(d / f"{name}.laz", PointCloud(xyz, {"tree_id": np.full(len(xyz), 7, np.int64)}))
    half = None if sides is None else np.asarray(sides, float) / 2
    VoxelModel(cell, np.asarray(cubes_ijk) + [0, 0, int(round(ground_z / cell))], np.full(len(cubes_ijk), 3),
               half=half).save(d / "vox.npz")
    return {"P1": {"targets": str(d / "targets.csv"), "reference": {"als": str(d / "ref.laz")},
                   "methods": {"m": {"voxels": str(d / "vox.npz"), "trees": {"als": str(d / "sim.laz")}}}}}


def test_crown_projection_area_is_tree_metrics_cpa_at_a_given_base():
    from vlsforest.metrics import crown_projection_area, tree_metrics

    rng = np.random.default_rng(4)
    xyz = rng.normal(size=(400, 3)) * [2.0, 2.0, 3.0] + [500.0, 300.0, 12.0]
    m = tree_metrics(xyz, ground_z=2.0)
    assert crown_projection_area(xyz, m["cbh"], ground_z=2.0) == m["cpa"]
    # a 2 × 2 m square at 5 m and a 1 × 1 m square at 9 m: a base above 5 m keeps the small one only
    sq = np.array([[x, y, z] for z, h in ((5.0, 1.0), (9.0, 0.5)) for x in (-h, h) for y in (-h, h)])
    assert crown_projection_area(sq, 4.0) == pytest.approx(4.0)
    assert crown_projection_area(sq, 6.0) == pytest.approx(1.0)
    assert crown_projection_area(np.zeros((0, 3)), 1.0) == 0.0


def test_model_outline_area_is_the_hull_of_the_cube_corners_above_the_base():
    from vlsforest.experiments.crown_outline import model_outline_area
    from vlsforest.io.voxel_model import VoxelModel

    # full 0.5 m cells (0,0,4) and (2,0,4): corners span x 0..1.5, y 0..0.5 → 0.75 m²; a cell
    # (0,3,0) whose top (0.5 m) lies below a 1 m base is left out
    model = VoxelModel(0.5, [[0, 0, 4], [2, 0, 4], [0, 3, 0]], [1, 1, 1])
    assert model_outline_area(model, 1.0, 0.0) == pytest.approx(0.75)
    # all three: hull (0,0) (1.5,0) (1.5,0.5) (0.5,2) (0,2); shoelace ½·(0.75 + 2.75 + 1) = 2.25 m²
    assert model_outline_area(model, 0.0, 0.0) == pytest.approx(2.25)
    # cubes of 0.2 m centred in their cells: x 0.15..1.35, y 0.15..0.35 → 1.2 × 0.2
    small = VoxelModel(0.5, [[0, 0, 4], [2, 0, 4]], [1, 1], half=np.array([0.1, 0.1]))
    assert model_outline_area(small, 1.0, 0.0) == pytest.approx(0.24)
    assert model_outline_area(VoxelModel(0.5, np.zeros((0, 3)), []), 1.0, 0.0) == 0.0


def test_crown_outline_splits_the_cpa_error(tmp_path):
    from scipy.spatial import ConvexHull

    from vlsforest.experiments.crown_outline import run_crown_outline

    zs = np.arange(3.0, 8.01, 0.5)
    ref = _grid(-1.0, 1.0, -1.0, 1.0, zs)               # a 2 × 2 m crown from 3 m
    # the simulation: a 3 × 3 m crown from 5 m and a thin branch at 3–4 m beside it (too narrow to
    # start the crown there, so its own base is at 5 m and the branch is left out of its CPA)
    branch = _grid(2.0, 2.5, -0.5, 0.0, [3.0, 3.5, 4.0])
    sim = np.vstack([_grid(-1.5, 1.5, -1.5, 1.5, np.arange(5.0, 8.01, 0.5)), branch])
    # the model: 0.5 m cells over x, y −1.5..1.5 at 2.5–8.5 m: its outline is 3 × 3 m
    cubes = [[i, j, k] for i in range(-3, 3) for j in range(-3, 3) for k in range(5, 17)]
    man = _write_run(tmp_path, ref, sim, cubes)
    res = run_crown_outline(man, ["m"], ["als"])
    (row,) = res["trees"]
    assert row["cpa_ref"] == pytest.approx(4.0) and row["cpa_model"] == pytest.approx(9.0)
    seen = ConvexHull(sim[:, :2]).volume  # at the reference's base (≈ 3 m) the branch is in
    assert row["cpa_seen"] == pytest.approx(seen) and seen > 9.0
    assert row["cpa_sim"] == pytest.approx(9.0)
    assert row["cbh_sim"] > 4.0 > 3.0 >= row["cbh_ref"] - 0.1
    s = res["summary"]["m"]["als"]
    assert s["outline"]["mean"] == pytest.approx(5.0)
    assert s["unseen"]["mean"] == pytest.approx(seen - 9.0)
    assert s["base"]["mean"] == pytest.approx(9.0 - seen)
    assert s["error"]["mean"] == pytest.approx(5.0)
    assert s["outline"]["mean"] + s["unseen"]["mean"] + s["base"]["mean"] == pytest.approx(s["error"]["mean"])
    # the model's own crown starts in the slice of its lowest cubes' bottom (2.5 m): 2.55 m
    assert row["cbh_model"] == pytest.approx(2.55)
    c = s["cbh"]
    assert c["own_base"]["mean"] == pytest.approx(2.55 - row["cbh_ref"])
    assert c["seen_base"]["mean"] == pytest.approx(row["cbh_sim"] - 2.55)
    assert c["own_base"]["mean"] + c["seen_base"]["mean"] == pytest.approx(c["error"]["mean"])
    assert c["error"]["mean"] == pytest.approx(row["cbh_sim"] - row["cbh_ref"])


def test_model_crown_base_is_the_first_wide_slice_of_the_cubes():
    from vlsforest.experiments.crown_outline import model_crown_base
    from vlsforest.io.voxel_model import VoxelModel

    ground = 100.0
    base = int(round(ground / 0.5))
    # a 0.5 m stem column from 0 to 5 m, a 2 × 2 m crown of 0.5 m cells from 5 to 8 m
    stem = [[0, 0, k] for k in range(10)]
    crown = [[i, j, k] for i in range(-2, 2) for j in range(-2, 2) for k in range(10, 16)]
    ijk = np.array(stem + crown) + [0, 0, base]
    model = VoxelModel(0.5, ijk, np.ones(len(ijk), int))
    assert model_crown_base(model, ground) == pytest.approx(5.05)
    # 0.2 m cubes centred in their cells: the crown's lowest cubes span 5.15–5.35 m, so the first
    # slice they widen is 5.1–5.2 m
    small = VoxelModel(0.5, ijk, np.ones(len(ijk), int), half=np.full(len(ijk), 0.1))
    assert model_crown_base(small, ground) == pytest.approx(5.15)
    # no slice wider than 1.5 m: the paper's rule gives 0
    assert model_crown_base(VoxelModel(0.5, np.array(stem) + [0, 0, base], np.ones(10, int)), ground) == 0.0
    assert np.isnan(model_crown_base(VoxelModel(0.5, np.zeros((0, 3)), []), ground))


def test_line_fit_matches_scipy():
    from scipy.stats import linregress

    from vlsforest.experiments.shift_room import line_fit

    rng = np.random.default_rng(2)
    x = rng.uniform(0.08, 0.16, 20)
    y = 10 - 60 * x + rng.normal(0, 0.5, 20)
    f, ref = line_fit(np.r_[x, np.nan], np.r_[y, 1.0]), linregress(x, y)
    assert f["n"] == 20
    assert (f["slope"], f["intercept"], f["r"]) == pytest.approx((ref.slope, ref.intercept, ref.rvalue), rel=1e-10)
    assert f["slope_se"] == pytest.approx(ref.stderr, rel=1e-10)
    assert math.isnan(line_fit([1, 1, 1], [1, 2, 3])["slope"])


def test_shift_room_relates_each_trees_cubes_to_its_change(tmp_path):
    from vlsforest.experiments.shift_room import run_shift_room
    from vlsforest.io.voxel_model import VoxelModel

    d = tmp_path / "P1"
    d.mkdir()
    sides = {1: 0.10, 2: 0.12, 3: 0.14, 4: 0.20}
    (d / "targets.csv").write_text("target_id,tree_id,group,z\n"
                                   + "".join(f"{10 + t},{t},{'conifer' if t < 3 else 'broadleaf'},0\n" for t in sides))
    ijk = [[t, 0, k] for t in sides for k in range(3)]
    owner = [t for t in sides for _ in range(3)]
    half = [sides[t] / 2 for t in owner]
    VoxelModel(0.25, ijk, owner, half=np.array(half)).save(d / "vox.npz")
    # the change falls linearly with the side: +5 pp at 0.10 m, 0 at 0.20 m
    (d / "a.csv").write_text("tree_id,multi_return_pct\n" + "".join(f"{10 + t},50\n" for t in sides))
    (d / "b.csv").write_text("tree_id,multi_return_pct\n"
                             + "".join(f"{10 + t},{50 + 5 * (0.20 - s) / 0.10}\n" for t, s in sides.items()))
    man = {"P1": {"targets": str(d / "targets.csv"),
                  "methods": {"s": {"voxels": str(d / "vox.npz"), "metrics": {"als": str(d / "a.csv")}},
                              "r": {"metrics": {"als": str(d / "b.csv")}}}}}
    res = run_shift_room(man, "s", "r", ["als"], ["multi_return_pct"])
    v = res["summary"]["als"]["multi_return_pct"]
    assert v["fit"]["slope"] == pytest.approx(-50.0) and v["fit"]["r"] == pytest.approx(-1.0)
    assert v["change"]["mean"] == pytest.approx(np.mean([5 * (0.20 - s) / 0.10 for s in sides.values()]))
    assert v["groups"]["conifer"]["side_m"] == pytest.approx(0.11)
    assert [r["side_m"] for r in res["trees"]] == pytest.approx(list(sides.values()))
    with pytest.raises(ConfigError, match="differ"):
        run_shift_room(man, "s", "s", ["als"])
    with pytest.raises(ConfigError, match="does not name the s metrics of scenario uls"):
        run_shift_room(man, "s", "r", ["uls"], ["multi_return_pct"])


def test_cog_shift_carries_the_returns_with_their_cubes(tmp_path):
    """The returns on the top cubes move down with them: the predicted Hmean change is their
    displacement times their share of the returns; returns off the cubes (a stem far off) stay;
    the columns' top cubes and all cubes give the crown's own displacement."""
    from vlsforest.experiments.cog_shift import carried_returns, run_cog_shift
    from vlsforest.io.las import PointCloud, write_las
    from vlsforest.io.voxel_model import VoxelModel

    d = tmp_path / "P1"
    d.mkdir()
    (d / "targets.csv").write_text("target_id,tree_id,group,z\n11,1,conifer,0\n")
    ijk = np.array([[i, j, k] for i in range(3) for j in range(3) for k in range(40, 44)])
    base = VoxelModel(0.25, ijk, np.ones(len(ijk), int), half=np.full(len(ijk), 0.05))
    centre = base.centres().copy()
    top = ijk[:, 2] == 43
    centre[top, 2] -= 0.03
    VoxelModel(0.25, ijk, base.owner, half=base.half, centre=centre).save(d / "cog.npz")
    base.save(d / "base.npz")
    c = base.centres()
    on_top = c[top] + [0.0, 0.0, 0.05]                    # 9 returns on the top cubes' top faces
    on_side = c[~top][:9] + [0.05, 0.0, 0.0]             # 9 on lower cubes' sides
    off = np.array([[5.0, 5.0, 10.5]] * 2)               # 2 on no cube
    xyz = np.concatenate([on_top, on_side, off])
    write_las(d / "trees.laz", PointCloud(xyz, {"tree_id": np.full(len(xyz), 11, np.int32)}))
    # the shifted model's run: twice the returns on the (lowered) top cubes, none on the sides
    xyz_s = np.concatenate([centre[top] + [0.0, 0.0, 0.05]] * 2 + [off])
    write_las(d / "trees_c.laz", PointCloud(xyz_s, {"tree_id": np.full(len(xyz_s), 11, np.int32)}))
    for name, h in (("a", 10.0), ("b", 9.9)):
        (d / f"{name}.csv").write_text("tree_id,hmean,height,cpa,multi_return_pct\n" f"11,{h},11,1.0,50\n")
    man = {"P1": {"targets": str(d / "targets.csv"),
                  "methods": {"s": {"voxels": str(d / "base.npz"), "trees": {"als": str(d / "trees.laz")},
                                    "metrics": {"als": str(d / "a.csv")}},
                              "c": {"voxels": str(d / "cog.npz"), "trees": {"als": str(d / "trees_c.laz")},
                                    "metrics": {"als": str(d / "b.csv")}}}}}
    moved, on = carried_returns(xyz, base, VoxelModel.load(d / "cog.npz"))
    assert on.tolist() == [True] * 18 + [False] * 2
    assert np.allclose(moved - xyz, np.r_[np.tile([0, 0, -0.03], (9, 1)), np.zeros((11, 3))])
    res = run_cog_shift(man, "s", "c", ["als"])
    tree = res["trees"][0]
    assert tree["surface_dz_m"] == pytest.approx(-0.03) and tree["all_cubes_dz_m"] == pytest.approx(-0.03 / 4)
    rec = tree["scenarios"]["als"]
    assert rec["on_cubes"] == pytest.approx(0.9)
    assert rec["predicted"]["hmean"] == pytest.approx(-0.03 * 9 / 20)
    assert rec["predicted"]["height"] == pytest.approx(-0.03)  # the highest returns lie on the top cubes
    assert rec["simulated"]["hmean"] == pytest.approx(-0.1) and rec["simulated"]["height"] == 0.0
    assert "predicted" not in res["summary"]["als"]["multi_return_pct"]
    assert res["summary"]["als"]["hmean"]["difference"]["mean"] == pytest.approx(-0.1 + 0.03 * 9 / 20)
    assert res["on_cubes"]["als"]["mean"] == pytest.approx(0.9) and res["margin_m"] == 0.125
    # carried back to the unshifted cubes, the shifted run's returns lie on the top faces where
    # the unshifted run had half of them on lower cubes' sides: the reached change is that
    back_z = np.r_[np.tile(c[top, 2] + 0.05, 2), off[:, 2]]
    assert rec["reached"]["hmean"] == pytest.approx(back_z.mean() - xyz[:, 2].mean())
    assert rec["reached"]["height"] == pytest.approx(0.0)
    assert res["summary"]["als"]["hmean"]["reached"]["mean"] == pytest.approx(back_z.mean() - xyz[:, 2].mean())
    assert rec["top_share"] == pytest.approx([0.45, 0.9])
    assert res["top_share"]["als"]["change"]["mean"] == pytest.approx(0.45)
    # the cubes moved only vertically: nine 0.1 m squares in vertical view in both models
    assert tree["cover_m2"] == pytest.approx([0.09, 0.09])
    assert res["cover"]["change_pct"]["mean"] == pytest.approx(0.0)
    with pytest.raises(ConfigError, match="differ"):
        run_cog_shift(man, "s", "s", ["als"])
    man["P1"]["methods"]["c"]["voxels"] = str(d / "other.npz")
    VoxelModel(0.25, ijk[:-1], base.owner[:-1], half=base.half[:-1]).save(d / "other.npz")
    with pytest.raises(ConfigError, match="same cells"):
        run_cog_shift(man, "s", "c", ["als"])


def test_cover_area_is_the_union_of_the_cubes_squares_seen_from_above():
    """Two cubes of one column hide one another from above until the shift moves them apart;
    a cube alone covers its square whatever the raster's pixel."""
    from vlsforest.experiments.cog_shift import column_tops, cover_area
    from vlsforest.io.voxel_model import VoxelModel

    ijk = np.array([[0, 0, 10], [0, 0, 11], [3, 0, 10]])
    stacked = VoxelModel(0.25, ijk, np.ones(3, int), half=np.full(3, 0.05))
    assert cover_area(stacked) == pytest.approx(2 * 0.01)
    centre = stacked.centres().copy()
    centre[1, 0] += 0.05  # the upper cube half a side to the side: 0.1 × 0.15 m for the column
    apart = VoxelModel(0.25, ijk, stacked.owner, half=stacked.half, centre=centre)
    assert cover_area(apart) == pytest.approx(0.015 + 0.01)
    assert cover_area(apart, pixel_m=0.001) == pytest.approx(0.025)
    assert column_tops(stacked).tolist() == [False, True, True]
    with pytest.raises(ConfigError, match="pixel_m"):
        cover_area(stacked, pixel_m=0.0)


def test_cli_run_experiments_refuse_bad_inputs_in_one_line(tmp_path, capsys):
    from vlsforest.cli import main

    out = tmp_path / "x.json"
    for argv, needle in (
        (["crown-outline", "--inputs-json", "[1]", "--methods", "m", "--scenarios", "als"], "--inputs-json"),
        (["crown-outline", "--inputs-json", '{"P1": {}}', "--methods", "m", "--scenarios", "als"], "'targets'"),
        (["crown-outline", "--inputs-json", json.dumps({"P1": {"targets": str(tmp_path / "none.csv")}}),
          "--methods", "m", "--scenarios", "als"], "none.csv"),
        (["shift-room", "--inputs-json", '{"P1": {"targets": "t.csv"}}', "--base", "a", "--shifted", "a",
          "--scenarios", "als"], "differ"),
        (["cog-shift", "--inputs-json", '{"P1": {"targets": "t.csv"}}', "--base", "a", "--shifted", "b",
          "--scenarios", "als", "--margin", "-1"], "margin_m"),
    ):
        assert main(["experiment", *argv, "-o", str(out)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("vlsforest experiment: error:") and needle in err[0], err
        assert not out.exists()


def test_cli_unknown_plot_names_the_option(tmp_path, capsys):
    from vlsforest.cli import main

    out = tmp_path / "x.json"
    for name in ("tls-step", "recording-detector"):
        extra = ["--variants-json", "{}"] if name == "recording-detector" else []
        argv = ["experiment", name, "--config-json", '{"forest": {"preset": "quick"}}', "--plot", "Z9", *extra,
                "-o", str(out)]
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("vlsforest experiment: error: --plot: unknown plot 'Z9' (known: Q1)"), err
        assert not out.exists()


def test_partial_shift_moves_the_cubes_by_the_chosen_components():
    """The vertical part keeps each cube's horizontal place and takes the shifted height, the
    horizontal part the reverse, whatever the order of the shifted model's cells (a superset of
    the unshifted ones); other cells or cube sizes are refused, naming the file."""
    from vlsforest.errors import InputDataError
    from vlsforest.experiments.cog_parts import partial_shift
    from vlsforest.io.voxel_model import VoxelModel

    ijk = np.array([[0, 0, 40], [0, 1, 40], [2, 1, 41]])
    half = np.array([0.05, 0.08, 0.1])
    base = VoxelModel(0.25, ijk, np.array([1, 1, 2]), half=half)
    disp = np.array([[0.02, -0.01, -0.03], [0.0, 0.04, 0.01], [-0.02, 0.0, -0.02]])
    extra = np.array([[5, 5, 5]])
    order = [2, 0, 1]  # the shifted model's cells in another order, with one more cell
    shifted = VoxelModel(0.25, np.vstack([ijk[order], extra]), np.array([2, 1, 1, 3]),
                         half=np.append(half[order], 0.1),
                         centre=np.vstack([(base.centres() + disp)[order], (extra + 0.5) * 0.25]))
    c = base.centres()
    v = partial_shift(base, shifted, (0, 0, 1))
    assert np.allclose(v.centres()[:, :2], c[:, :2]) and np.allclose(v.centres()[:, 2], c[:, 2] + disp[:, 2])
    h = partial_shift(base, shifted, (1, 1, 0))
    assert np.allclose(h.centres()[:, :2], c[:, :2] + disp[:, :2]) and np.allclose(h.centres()[:, 2], c[:, 2])
    assert np.array_equal(v.ijk, base.ijk) and np.array_equal(v.owner, base.owner) and np.array_equal(v.half, half)
    assert np.allclose(partial_shift(base, shifted, (1, 1, 1)).centres(), c + disp)
    with pytest.raises(InputDataError, match="cog.npz: 1 of the unshifted model's cells are not in it"):
        partial_shift(VoxelModel(0.25, np.vstack([ijk, [[9, 9, 9]]]), np.ones(4, int), half=np.append(half, 0.1)),
                      shifted, (0, 0, 1), "cog.npz")
    with pytest.raises(InputDataError, match="cog.npz: its cubes are not the unshifted model's sizes"):
        partial_shift(VoxelModel(0.25, ijk, np.ones(3, int), half=half * 0.5), shifted, (0, 0, 1), "cog.npz")
    with pytest.raises(InputDataError, match="cell size 0.25 m, the unshifted model's 0.1 m"):
        partial_shift(VoxelModel(0.1, ijk, np.ones(3, int)), shifted, (0, 0, 1), "cog.npz")


def _cog_parts_manifest(workdir, plot="Q1", base="scaled", shifted="scaled_cog_shift", scenarios=("als", "uls")):
    r = workdir / "results" / plot
    return {plot: {"targets": str(r / "targets.csv"), "site": str(r / "site.json"),
                   "surveys": {sc: str(r / "surveys" / f"{sc}.yaml") for sc in scenarios},
                   "methods": {base: {"scene": str(r / base / "scene"), "voxels": str(r / base / "voxels.npz"),
                                      "metrics": {sc: str(r / base / sc / "metrics.csv") for sc in scenarios}},
                               shifted: {"voxels": str(r / shifted / "voxels.npz"),
                                         "metrics": {sc: str(r / shifted / sc / "metrics.csv") for sc in scenarios}}}}}


def test_cog_parts_simulates_as_the_run_does(quick_run, tmp_path):
    """With no part of the shift and with all of it, the experiment's simulations give the run's
    own metrics of the unshifted and the shifted model, tree by tree and digit for digit (the same
    surveys, seeds, region and extraction); the parts' changes and the interaction add up to the
    whole change; nothing is left in the temporary folder."""
    from vlsforest.experiments.cog_parts import METRICS, run_cog_parts

    workdir, _, _ = quick_run
    res = run_cog_parts(_cog_parts_manifest(workdir), "scaled", "scaled_cog_shift", ["als", "uls"],
                        {"als": 0, "uls": 0}, 1.0, tmp_path, parts={"none": (0, 0, 0), "all": (1, 1, 1)}, workers=2)
    assert len(res["trees"]) == 4 and list(tmp_path.iterdir()) == []
    for row in res["trees"]:
        for sc, v in row["scenarios"].items():
            for part, run in (("none", "base"), ("all", "shifted")):
                for k in METRICS:
                    a, b = v[part][k], v[run][k]
                    assert a == b or (math.isnan(a) and math.isnan(b)), (row["target_id"], sc, part, k, a, b)
    for sc in ("als", "uls"):
        for k in METRICS:
            s = res["summary"][sc][k]
            assert s["none"]["mean"] == 0.0
            assert s["all"]["mean"] == pytest.approx(s["whole"]["mean"], abs=1e-9)
            assert s["interaction"]["mean"] == pytest.approx(s["whole"]["mean"] - s["all"]["mean"], abs=1e-9)


def test_reseed_repeats_the_run_and_draws_anew(quick_run, tmp_path):
    """With the seed offset 0 the reseed experiment gives the run's own metrics of the method,
    tree by tree and digit for digit (its simulation and measurement are the run's); with another
    seed the range noise is drawn anew and the trees' Hmean moves. The workflow's own result of
    the quick run holds every target tree."""
    from vlsforest.experiments.reseed import METRICS, changes, run_reseed

    workdir, _, _ = quick_run
    manifest = _cog_parts_manifest(workdir, scenarios=("als",))
    same = run_reseed(manifest, "scaled", ["als"], {"als": 0}, 1.0, tmp_path, seed_offset=0, workers=2)
    assert len(same["trees"]) == 4 and list(tmp_path.iterdir()) == []
    assert same["seeds"] == {"als": {"run": 0, "reseeded": 0}}
    for row in same["trees"]:
        for k in METRICS:
            a, b = row["scenarios"]["als"]["reseeded"][k], row["scenarios"]["als"]["run"][k]
            assert a == b or (math.isnan(a) and math.isnan(b)), (row["target_id"], k, a, b)
            c = row["scenarios"]["als"]["change"][k]
            assert c == 0.0 or (math.isnan(a) and math.isnan(c)), (row["target_id"], k, c)
    other = run_reseed(manifest, "scaled", ["als"], {"als": 0}, 1.0, tmp_path, seed_offset=1, workers=1)
    moved = [c for c in changes(other, "als", "hmean") if c != 0.0]
    assert len(moved) == 4 and all(abs(c) < 0.1 for c in moved), moved
    for row, c in zip(other["trees"], changes(other, "als", "hmean")):
        s = row["scenarios"]["als"]
        assert c == s["reseeded"]["hmean"] - s["run"]["hmean"]
    assert other["summary"]["als"]["hmean"]["n"] == 4
    wf = json.loads((workdir / "results" / "experiments" / "reseed.json").read_text())
    assert wf["method"] == "scaled" and wf["seed_offset"] == 1 and len(wf["trees"]) == 4


def test_reseed_refuses_bad_arguments(tmp_path):
    from vlsforest.experiments.reseed import run_reseed

    m = _cog_parts_manifest(tmp_path, scenarios=("als",))
    with pytest.raises(ConfigError, match="--seed-offset: -3 makes the seed of als negative"):
        run_reseed(m, "scaled", ["als"], {"als": 2}, 1.0, tmp_path, seed_offset=-3)
    with pytest.raises(ConfigError, match="--seeds-json: no seed for uls"):
        run_reseed(m, "scaled", ["als", "uls"], {"als": 2}, 1.0, tmp_path)
    with pytest.raises(ConfigError, match="--region-margin"):
        run_reseed(m, "scaled", ["als"], {"als": 2}, -1.0, tmp_path)
    with pytest.raises(ConfigError, match="plot 'Q1' does not name the fixed_0.25 scene"):
        run_reseed(m, "fixed_0.25", ["als"], {"als": 2}, 1.0, tmp_path)
