"""Bad inputs across every command: one line ``vlsforest <stage>: error: …`` naming the file,
key or line, exit code 2, no traceback, and nothing left at the output paths.

The cases run in-process through :func:`vlsforest.cli.main` (a few through a subprocess or
Snakemake). They cover the classes of the reliability issue: output paths checked before the
work, whole-or-nothing outputs (interrupts and failing side outputs included), validated
binary inputs, refused silent wrong results, one-line messages, and the HELIOS++ export of
every part type.
"""

from __future__ import annotations

import os
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
import yaml

from vlsforest.cli import main
from vlsforest.io.las import PointCloud, write_las
from vlsforest.io.npz import save_npz

REPO = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------------------------------ fixtures
@pytest.fixture(scope="module")
def ws(tmp_path_factory):
    """A small workspace: the demo scene, a survey, one simulation with hits and pulses, clouds,
    tables and npz files that are valid (each case spoils one thing)."""
    d = tmp_path_factory.mktemp("bad_inputs")
    assert main(["demo", "-o", str(d / "scene" / "scene.yaml"), "--seed", "1"]) == 0
    scenario = {"scanner": "riegl_minivux1uav", "pattern": "double_grid", "altitude_m": 40, "speed_mps": 8,
                "line_spacing_m": 28, "n_lines": 1, "margin_m": 0, "overrides": {"prf_hz": 5000}}
    (d / "scenario.yaml").write_text(yaml.safe_dump(scenario))
    assert main(["plan", "--scene", str(d / "scene" / "scene.yaml"), "--scenario", str(d / "scenario.yaml"),
                 "-o", str(d / "survey.yaml")]) == 0
    assert main(["simulate", str(d / "scene" / "scene.yaml"), str(d / "survey.yaml"), "-o", str(d / "sim.laz"),
                 "--hits", str(d / "hits.npz"), "--pulses", str(d / "pulses.npz"), "--quiet", "--workers", "1"]) == 0
    rng = np.random.default_rng(0)
    n = 300
    xyz = np.c_[rng.uniform(-2, 2, n), rng.uniform(-2, 2, n), rng.uniform(0, 20, n)]
    oid = rng.choice([71, 72, 1], n).astype(np.int32)
    attrs = {"object_id": oid, "tree_id": np.where(oid > 1, 7, 0).astype(np.int32),
             "return_number": np.ones(n, np.uint8), "number_of_returns": np.ones(n, np.uint8),
             "gps_time": np.arange(n, dtype=np.float64)}
    write_las(d / "cloud.las", PointCloud(xyz, attrs))
    write_las(d / "noobj.las", PointCloud(xyz, {k: v for k, v in attrs.items() if k != "object_id"}))
    (d / "targets.csv").write_text("target_id,tree_id,z\n301,7,0.0\n")
    (d / "absent_targets.csv").write_text("target_id,tree_id,z\n401,40,0.0\n402,41,0.0\n")
    save_npz(d / "crowns.npz", {"xyz": xyz, "owner": np.full(n, 7, np.int64)})
    save_npz(d / "model.npz", {"size": np.float64(0.5), "ijk": np.array([[0, 0, 10], [1, 0, 10]]),
                               "owner": np.array([7, 7])})
    (d / "site.json").write_text('{"ground_z": 0.0, "extent": [-5, -5, 5, 5]}\n')
    (d / "a_folder").mkdir()
    return d


def _hits(ws) -> dict:
    with np.load(ws / "hits.npz") as z:
        return {k: z[k] for k in z.files}


def _crowns(ws) -> dict:
    with np.load(ws / "crowns.npz") as z:
        return {k: z[k] for k in z.files}


def _model(ws) -> dict:
    with np.load(ws / "model.npz") as z:
        return {k: z[k] for k in z.files}


def _npz_variant(name: str, base, change):
    """A builder writing a spoilt copy of an npz kind: ``change(arrays)`` edits the dict."""
    def build(ws, tmp):
        arrays = dict(base(ws))
        change(arrays)
        path = tmp / name
        save_npz(path, arrays)
        return path
    return build


def _bytes_file(name: str, data: bytes):
    def build(ws, tmp):
        path = tmp / name
        path.write_bytes(data)
        return path
    return build


def _truncated(name: str, source: str, keep: float = 0.5):
    def build(ws, tmp):
        data = (ws / source).read_bytes()
        path = tmp / name
        path.write_bytes(data[: int(len(data) * keep)])
        return path
    return build


def _check(rc, err, stage, needles, outputs, code=2):
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert rc == code, err
    assert "Traceback" not in err, err
    assert len(lines) == 1, err
    assert lines[0].startswith(f"vlsforest {stage}: error:"), err
    for needle in needles:
        assert str(needle) in lines[0], (needle, err)
    for path in outputs:
        assert not Path(path).exists(), path
        leftovers = [p.name for p in Path(path).parent.glob(".tmp-*")] if Path(path).parent.is_dir() else []
        assert not leftovers, leftovers


# ------------------------------------------------------------------------ class 1: output paths
# (stage argv before the output option, output option, the bad output) — inputs need not exist:
# the output is checked before anything is read
_IN = "in_does_not_matter"
FILE_OUTPUTS = [
    ("simulate", ["simulate", _IN, _IN, "--quiet"], "-o", ".laz"),
    ("simulate", ["simulate", _IN, _IN, "-o", "ok.laz", "--quiet"], "--pulses", ".npz"),
    ("simulate", ["simulate", _IN, _IN, "-o", "ok.laz", "--quiet"], "--hits", ".npz"),
    ("simulate", ["simulate", _IN, _IN, "-o", "ok.laz", "--quiet"], "--timing", ".json"),
    ("detect", ["detect", _IN, _IN], "-o", ".laz"),
    ("detect", ["detect", _IN, _IN, "-o", "ok.laz"], "--pulses", ".csv"),
    ("demo", ["demo"], "-o", ".yaml"),
    ("plan", ["plan", "--scenario", _IN], "-o", ".yaml"),
    ("metrics", ["metrics", _IN, "--tree-id", "tree_id"], "-o", ".csv"),
    ("extract", ["extract", "sim", _IN, "--targets", _IN], "-o", ".laz"),
    ("extract", ["extract", "reference", _IN, "--segment", _IN, "--targets", _IN, "--radius", "1"], "-o", ".laz"),
    ("extract", ["extract", "sim", _IN, "--targets", _IN, "-o", "ok.laz"], "--metrics", ".csv"),
    ("voxels", ["voxels", _IN, "--method-json", "{}"], "-o", ".npz"),
    ("voxels", ["voxels", _IN, "--method-json", "{}", "-o", "ok.npz"], "--vox", ".vox"),
    ("pad", ["pad", _IN], "-o", ".vox"),
    ("scene", ["scene", "targets", _IN, "--plot-json", _IN], "-o", ".csv"),
    ("scene", ["scene", "crowns", _IN, "--stems", _IN, "--targets", _IN], "-o", ".npz"),
    ("scene", ["scene", "build", "--voxels", _IN, "--targets", _IN, "--site", _IN, "--stems", _IN], "-o", ".yaml"),
    ("collect", ["collect", "metrics", _IN], "-o", ".csv"),
    ("diagnose", ["diagnose", "--real", _IN, "--sim-config", _IN, "--scenario", "als"], "-o", ".json"),
    ("diagnose", ["diagnose", "--real", _IN, "--sim-config", _IN, "--scenario", "als", "-o", "ok.json"],
     "--figure", ".png"),
]
FOLDER_OUTPUTS = [
    ("segment", ["segment", _IN]),
    ("stems", ["stems", _IN, "--scans", _IN, "--base", "0", "0", "0"]),
    ("synth", ["synth"]),
    ("scene", ["scene", "helios", _IN]),
    ("report", ["report", "figures", "--metrics", _IN, "--errors", _IN, "--voxel-counts", _IN]),
    ("stats", ["stats", "--metrics", _IN, "--voxel-counts", _IN, "--sim-times", _IN]),
]


def _abs(argv, tmp):
    """Relative output names of a case become names in the case's folder."""
    return [str(tmp / a) if a.startswith("ok.") else a for a in argv]


@pytest.mark.parametrize("stage, argv, option, suffix", FILE_OUTPUTS,
                         ids=[f"{c[0]}{c[2]}" for c in FILE_OUTPUTS])
@pytest.mark.parametrize("problem", ["folder", "proc", "suffix", "under_a_file"])
def test_bad_output_file_is_refused_before_the_work(ws, tmp_path, capsys, stage, argv, option, suffix, problem):
    if problem == "folder":
        out = ws / "a_folder"
    elif problem == "proc":
        out = Path("/proc/vlsforest_no/out" + suffix)
    elif problem == "suffix":
        out = tmp_path / ("out" + suffix + ".txt")
    else:
        out = ws / "targets.csv" / ("out" + suffix)
    rc = main([*_abs(argv, tmp_path), option, str(out)])
    _check(rc, capsys.readouterr().err, stage, [option, out], [] if problem == "folder" else [out])
    assert ws.joinpath("a_folder").is_dir() and not any(ws.joinpath("a_folder").iterdir())
    assert not any(p for p in tmp_path.iterdir())  # not even the main output of a side-output case


@pytest.mark.parametrize("stage, argv", FOLDER_OUTPUTS, ids=[c[0] for c in FOLDER_OUTPUTS])
@pytest.mark.parametrize("problem", ["file", "proc"])
def test_bad_output_folder_is_refused_before_the_work(ws, capsys, stage, argv, problem):
    out = ws / "targets.csv" if problem == "file" else Path("/proc/vlsforest_no/out")
    rc = main([*argv, "-o", str(out)])
    _check(rc, capsys.readouterr().err, stage, ["-o", out], [] if problem == "file" else [out])


# ----------------------------------------------------------------- class 3: binary inputs
HITS_CASES = [
    ("empty", _bytes_file("h.npz", b""), "empty"),
    ("text", _bytes_file("h.npz", b"pulse_slot,hit_range\n1,2\n"), "not a zip"),
    ("truncated", _truncated("h.npz", "hits.npz", 0.6), "h.npz"),
    ("missing_array", _npz_variant("h.npz", _hits, lambda a: a.pop("hit_range")), "'hit_range'"),
    ("missing_beam", _npz_variant("h.npz", _hits, lambda a: a.pop("beam_sample_quality")), "'beam_sample_quality'"),
    ("float_index", _npz_variant("h.npz", _hits, lambda a: a.update(hit_pulse=a["hit_pulse"] + 0.5)), "'hit_pulse'"),
    ("bad_shape", _npz_variant("h.npz", _hits, lambda a: a.update(pulse_origin=a["pulse_origin"][:, :2])),
     "'pulse_origin'"),
    ("length_mismatch", _npz_variant("h.npz", _hits, lambda a: a.update(hit_range=a["hit_range"][:-1])), "rows"),
    ("nan", _npz_variant("h.npz", _hits, lambda a: a["hit_range"].__setitem__(0, np.nan)), "NaN"),
    ("pulse_out_of_range", _npz_variant("h.npz", _hits, lambda a: a["hit_pulse"].__setitem__(-1, 10**6)),
     "'hit_pulse'"),
    ("string_array", _npz_variant("h.npz", _hits, lambda a: a.update(part_reflectance=np.array(["a"] * 3))),
     "'part_reflectance'"),
]


@pytest.mark.parametrize("case, build, needle", HITS_CASES, ids=[c[0] for c in HITS_CASES])
def test_bad_hits_file(ws, tmp_path, capsys, case, build, needle):
    hits = build(ws, tmp_path)
    out = tmp_path / "o.laz"
    rc = main(["detect", str(hits), str(ws / "survey.yaml"), "-o", str(out)])
    _check(rc, capsys.readouterr().err, "detect", [hits, needle], [out])


CROWN_CASES = [
    ("empty", _bytes_file("c.npz", b""), "empty"),
    ("text", _bytes_file("c.npz", b"x y z\n1 2 3\n"), "not a zip"),
    ("truncated", _truncated("c.npz", "crowns.npz", 0.5), "c.npz"),
    ("no_owner", _npz_variant("c.npz", _crowns, lambda a: a.pop("owner")), "'owner'"),
    ("nan", _npz_variant("c.npz", _crowns, lambda a: a["xyz"].__setitem__((3, 1), np.nan)), "NaN"),
    ("two_columns", _npz_variant("c.npz", _crowns, lambda a: a.update(xyz=a["xyz"][:, :2])), "'xyz'"),
    ("length_mismatch", _npz_variant("c.npz", _crowns, lambda a: a.update(owner=a["owner"][:5])), "rows"),
    ("no_points", _npz_variant("c.npz", _crowns, lambda a: a.update(xyz=np.zeros((0, 3)),
                                                                    owner=np.zeros(0, np.int64))), "no points"),
    ("float_owner", _npz_variant("c.npz", _crowns, lambda a: a.update(owner=a["owner"] + 0.25)), "'owner'"),
]


@pytest.mark.parametrize("case, build, needle", CROWN_CASES, ids=[c[0] for c in CROWN_CASES])
def test_bad_crowns_file(ws, tmp_path, capsys, case, build, needle):
    crowns = build(ws, tmp_path)
    out = tmp_path / "v.npz"
    rc = main(["voxels", str(crowns), "--method-json", '{"kind": "fixed", "voxel_size": 0.5}', "-o", str(out),
               "--vox", str(tmp_path / "v.vox")])
    _check(rc, capsys.readouterr().err, "voxels", [crowns, needle], [out, tmp_path / "v.vox"])


MODEL_CASES = [
    ("empty", _bytes_file("m.npz", b""), "empty"),
    ("text", _bytes_file("m.npz", b"size: 0.5\n"), "not a zip"),
    ("truncated", _truncated("m.npz", "model.npz", 0.7), "m.npz"),
    ("no_ijk", _npz_variant("m.npz", _model, lambda a: a.pop("ijk")), "'ijk'"),
    ("float_ijk", _npz_variant("m.npz", _model, lambda a: a.update(ijk=a["ijk"] + 0.5)), "'ijk'"),
    ("owner_mismatch", _npz_variant("m.npz", _model, lambda a: a.update(owner=np.array([7]))), "rows"),
    ("zero_size", _npz_variant("m.npz", _model, lambda a: a.update(size=np.float64(0.0))), "'size'"),
    ("nan_centre", _npz_variant("m.npz", _model, lambda a: a.update(centre=np.full((2, 3), np.nan),
                                                                    half=np.full(2, 0.1))), "'centre'"),
    ("vector_size", _npz_variant("m.npz", _model, lambda a: a.update(size=np.array([0.5, 0.5]))), "'size'"),
]


@pytest.mark.parametrize("case, build, needle", MODEL_CASES, ids=[c[0] for c in MODEL_CASES])
def test_bad_voxel_model_file(ws, tmp_path, capsys, case, build, needle):
    model = build(ws, tmp_path)
    out = tmp_path / "scene.yaml"
    rc = main(["scene", "build", "--voxels", str(model), "--targets", str(ws / "targets.csv"),
               "--site", str(ws / "site.json"), "--stems", str(tmp_path), "-o", str(out)])
    _check(rc, capsys.readouterr().err, "scene", [model, needle], [out])


def test_bad_voxel_model_in_a_scene_part(ws, tmp_path, capsys):
    """The simulator reads voxel parts through the same loader."""
    (tmp_path / "m.npz").write_bytes(b"PK\x03\x04 broken")
    scene = {"parts": [{"id": 3, "type": "voxels", "path": "m.npz"}]}
    (tmp_path / "s.yaml").write_text(yaml.safe_dump(scene))
    out = tmp_path / "o.laz"
    rc = main(["simulate", str(tmp_path / "s.yaml"), str(ws / "survey.yaml"), "-o", str(out), "--quiet"])
    _check(rc, capsys.readouterr().err, "simulate", [tmp_path / "m.npz"], [out])


# -------------------------------------------------------------- class 4: silent wrong results
@pytest.mark.parametrize("key, value", [("beam_sample_quality", 1), ("beam_sample_quality", 5),
                                        ("beam_divergence_mrad", 0.9), ("beam_orientation_deg", 30.0)])
def test_detect_refuses_another_beam_geometry(ws, tmp_path, capsys, key, value):
    sv = yaml.safe_load((ws / "survey.yaml").read_text())
    sv.setdefault("overrides", {})[key] = value
    (tmp_path / "sv.yaml").write_text(yaml.safe_dump(sv))
    out = tmp_path / "o.laz"
    rc = main(["detect", str(ws / "hits.npz"), str(tmp_path / "sv.yaml"), "-o", str(out)])
    _check(rc, capsys.readouterr().err, "detect", [key, "beam"], [out])


def test_detect_with_the_traced_beam_still_runs(ws, tmp_path):
    assert main(["detect", str(ws / "hits.npz"), str(ws / "survey.yaml"), "-o", str(tmp_path / "o.laz")]) == 0
    assert (tmp_path / "o.laz").read_bytes() == (ws / "sim.laz").read_bytes()


@pytest.mark.parametrize("offset", [1e18, 3e15])
def test_coordinates_beyond_float64_centimetres_are_refused(ws, tmp_path, capsys, offset):
    import laspy

    las = laspy.read(ws / "cloud.las")
    las.header.offsets = np.array([offset, 0.0, 0.0])
    las.write(tmp_path / "far.las")
    out = tmp_path / "m.csv"
    rc = main(["metrics", str(tmp_path / "far.las"), "--tree-id", "tree_id", "-o", str(out)])
    _check(rc, capsys.readouterr().err, "metrics", [tmp_path / "far.las", "float64 resolves"], [out])


@pytest.mark.parametrize("records", [-4, 3])
def test_header_point_count_mismatch_warns_in_one_line(ws, tmp_path, capsys, records):
    data = (ws / "cloud.las").read_bytes()
    rec = 30 + 4 + 4  # point format 6 with the int32 extra dimensions object_id and tree_id
    data = data[: len(data) + records * rec] if records < 0 else data + data[-records * rec:]
    (tmp_path / "c.las").write_bytes(data)
    assert main(["metrics", str(tmp_path / "c.las"), "--tree-id", "tree_id", "-o", str(tmp_path / "m.csv")]) == 0
    err = capsys.readouterr().err
    warn = [ln for ln in err.splitlines() if "point records" in ln]
    assert len(warn) == 1 and warn[0].startswith("vlsforest metrics: warning:") and "c.las" in warn[0], err


def test_extract_sim_with_no_target_in_the_cloud(ws, tmp_path, capsys):
    out, met = tmp_path / "t.laz", tmp_path / "m.csv"
    rc = main(["extract", "sim", str(ws / "cloud.las"), "--targets", str(ws / "absent_targets.csv"),
               "-o", str(out), "--metrics", str(met)])
    _check(rc, capsys.readouterr().err, "extract", ["401", "402", "40", "41"], [out, met])


def test_metrics_with_no_listed_tree_in_the_cloud(ws, tmp_path, capsys):
    """The same outcome as extract sim: an error naming the missing trees."""
    out = tmp_path / "m.csv"
    rc = main(["metrics", str(ws / "cloud.las"), "--tree-id", "tree_id", "--ground-table",
               str(ws / "absent_targets.csv"), "--ground-key", "target_id", "-o", str(out)])
    _check(rc, capsys.readouterr().err, "metrics", ["401", "402"], [out])


STEMS_ARGV_TARGETS = ["stems", "--segment", "{ws}", "--targets", "{table}", "--scans", "{scans}", "-o", "{out}"]
STEMS_ARGV_SCANS = ["stems", "--segment", "{ws}", "--targets", "{ws}/targets.csv", "--scans", "{table}", "-o", "{out}"]
TABLE_CASES = [
    # (case, stage, argv with {table} for the spoilt table, table text, needle)
    ("extract_ids_not_integers", "extract", ["extract", "sim", "{cloud}", "--targets", "{table}", "-o", "{out}"],
     "target_id,tree_id,z\n301,7.5,0.0\n", "'tree_id' that are not integers"),
    ("extract_no_rows", "extract", ["extract", "sim", "{cloud}", "--targets", "{table}", "-o", "{out}"],
     "target_id,tree_id,z\n", "has no rows"),
    ("extract_no_column", "extract", ["extract", "sim", "{cloud}", "--targets", "{table}", "-o", "{out}"],
     "target_id,z\n301,0.0\n", "lacks column(s) ['tree_id']"),
    ("voxels_ids_not_integers", "voxels",
     ["voxels", "{crowns}", "--method-json", '{{"kind": "fixed", "voxel_size": 0.5}}', "--targets", "{table}",
      "-o", "{out}"], "tree_id,group\nseven,conifer\n", "'tree_id' that are not integers"),
    ("voxels_no_group", "voxels",
     ["voxels", "{crowns}", "--method-json", '{{"kind": "fixed", "voxel_size": 0.5}}', "--targets", "{table}",
      "-o", "{out}"], "tree_id\n7\n", "lacks column(s) ['group']"),
    ("voxels_unreadable", "voxels",
     ["voxels", "{crowns}", "--method-json", '{{"kind": "fixed", "voxel_size": 0.5}}', "--targets", "{table}",
      "-o", "{out}"], "tree_id,group\n7,conifer\n7,conifer,extra,more\n", "not a readable CSV"),
    ("scene_crowns_ids_not_integers", "scene",
     ["scene", "crowns", "{ws}", "--stems", "{ws}", "--targets", "{table}", "-o", "{out}"],
     "tree_id\n7\n\n8.5\n", "'tree_id' that are not integers"),
    *[(f"stems_targets_{case}", "stems", STEMS_ARGV_TARGETS, text, needle) for case, text, needle in (
        ("ids_not_integers", "tree_id,x,y,z\n7.5,0,0,0\n", "'tree_id' that are not integers"),
        ("position_not_finite", "tree_id,x,y,z\n7,nan,0,0\n", "column 'x' that are not finite numbers"),
        ("dbh_not_a_number", "tree_id,x,y,z,dbh\n7,0,0,0,thick\n", "column 'dbh' that are not numbers"))],
    *[(f"stems_scans_{case}", "stems", STEMS_ARGV_SCANS, text, needle) for case, text, needle in (
        ("ids_not_integers", "scan_id,x,y,z\n1.5,0,0,1.5\n", "'scan_id' that are not integers"),
        ("position_not_finite", "scan_id,x,y,z\n1,0,inf,1.5\n", "column 'y' that are not finite numbers"))],
]


@pytest.mark.parametrize("case, stage, argv, text, needle", TABLE_CASES, ids=[c[0] for c in TABLE_CASES])
def test_bad_table_is_one_line_naming_the_file(ws, tmp_path, capsys, case, stage, argv, text, needle):
    table, out = tmp_path / "table.csv", tmp_path / ("out.laz" if stage == "extract" else "out.npz")
    table.write_text(text)
    scans = tmp_path / "scans.csv"
    scans.write_text("scan_id,x,y,z\n1,0,0,1.5\n")
    names = {"table": table, "out": out, "cloud": ws / "cloud.las", "crowns": ws / "crowns.npz", "ws": ws,
             "scans": scans}
    rc = main([a.format(**names) for a in argv])
    _check(rc, capsys.readouterr().err, stage, [table, needle], [out])


def test_collect_metrics_with_a_bad_targets_table_names_it(tmp_path, capsys):
    """``collect metrics`` reads each plot's targets table beside its metrics (two folders up)."""
    metrics = tmp_path / "P1" / "fixed_0.25" / "als" / "metrics.csv"
    metrics.parent.mkdir(parents=True)
    metrics.write_text("tree_id,height\n7,20.0\n")
    targets = tmp_path / "P1" / "targets.csv"
    targets.write_text("target_id,species\nx,spruce\n")
    out = tmp_path / "all.csv"
    rc = main(["collect", "metrics", str(metrics), "-o", str(out)])
    _check(rc, capsys.readouterr().err, "collect", [targets, "'target_id' that are not integers"], [out])


# ------------------------------------------------------------------- class 5: messages
def test_extract_sim_without_object_id_names_the_file(ws, tmp_path, capsys):
    out = tmp_path / "t.laz"
    rc = main(["extract", "sim", str(ws / "noobj.las"), "--targets", str(ws / "targets.csv"), "-o", str(out)])
    _check(rc, capsys.readouterr().err, "extract", [ws / "noobj.las", "object_id"], [out])


@pytest.mark.parametrize("method, needle", [
    ('{"kind": "fixed", "voxelsize": 0.2}', "'voxelsize'"),
    ('{"kind": "scaled", "a_0": 0.2}', "'a_0'"),
    ('{"kind": "fixed", "voxel_size": 0.5, "colour": 1}', "'colour'"),
    ('{"kind": "fixed", "voxel_size": "big"}', "voxel_size"),
    ('{"kind": "scaled", "shift": 3}', "shift"),
    ('{"kind": "fixed", "min_points": true}', "min_points"),
])
def test_unknown_method_key_names_the_key(ws, tmp_path, capsys, method, needle):
    out = tmp_path / "v.npz"
    rc = main(["voxels", str(ws / "crowns.npz"), "--method-json", method, "--method", "m1", "-o", str(out)])
    err = capsys.readouterr().err
    _check(rc, err, "voxels", ["methods.m1", needle], [out])
    assert "unexpected keyword" not in err


YAML_SYNTAX = "parts: [\n  {id: 1, type: plane\n"
LIST = "- a\n- b\n"
#: (stage, argv with {bad} for the bad file, its content, words the message holds besides the file)
YAML_CASES = [
    ("diagnose", ["diagnose", "--real", "REAL", "--scenario", "als", "--sim-config", "{bad}"], YAML_SYNTAX, "line 3"),
    ("diagnose", ["diagnose", "--real", "REAL", "--scenario", "als", "--sim-config", "{bad}"], LIST, "mapping"),
    ("simulate", ["simulate", "{bad}", "SURVEY", "--quiet"], YAML_SYNTAX, "line 3"),
    ("simulate", ["simulate", "{bad}", "SURVEY", "--quiet"], "", "empty"),
    ("simulate", ["simulate", "SCENE", "{bad}", "--quiet"], YAML_SYNTAX, "line 3"),
    ("simulate", ["simulate", "SCENE", "{bad}", "--quiet"], LIST, "mapping"),
    ("simulate", ["simulate", "SCENE", "{bad}", "--quiet"], "", "empty"),
    ("plan", ["plan", "--scenario", "{bad}"], YAML_SYNTAX, "line 3"),
    ("plan", ["plan", "--scenario", "{bad}"], LIST, "mapping"),
    ("plan", ["plan", "--scenario", "{bad}"], "", "empty"),
    ("synth", ["synth", "{bad}"], YAML_SYNTAX, "line 3"),
    ("synth", ["synth", "{bad}"], LIST, "mapping"),
    ("synth", ["synth", "--config-json", "{}", "--recording-physics", "{bad}"], YAML_SYNTAX, "line 3"),
    ("synth", ["synth", "--config-json", "{}", "--recording-physics", "{bad}"], LIST, "mapping"),
    ("scene", ["scene", "helios", "{bad}"], YAML_SYNTAX, "line 3"),
    ("scene", ["scene", "helios", "{bad}"], "", "empty"),
]
_OUT_NAME = {"diagnose": "o.json", "simulate": "o.laz", "plan": "o.yaml", "synth": "out", "scene": "out"}


@pytest.mark.parametrize("stage, argv, content, needle", YAML_CASES,
                         ids=[f"{c[0]}-{i}" for i, c in enumerate(YAML_CASES)])
def test_bad_yaml_is_one_line_naming_the_file(ws, tmp_path, capsys, stage, argv, content, needle):
    bad = tmp_path / "bad.yaml"
    bad.write_text(content)
    (tmp_path / "real").mkdir()
    subst = {"{bad}": str(bad), "SCENE": str(ws / "scene" / "scene.yaml"), "SURVEY": str(ws / "survey.yaml"),
             "REAL": str(tmp_path / "real")}
    out = tmp_path / _OUT_NAME[stage]
    rc = main([*[subst.get(a, a) for a in argv], "-o", str(out)])
    _check(rc, capsys.readouterr().err, stage, [bad, needle], [out])


def test_pad_survey_yaml_that_is_a_list_names_the_file(tmp_path, capsys):
    """A TLS scan's survey file that is a list: the message names the survey file."""
    tls = tmp_path / "tls"
    xyz = np.c_[np.zeros(20), np.zeros(20), np.arange(20.0)]
    write_las(tls / "scan_1.laz", PointCloud(xyz, {"gps_time": np.arange(20.0),
                                                   "return_number": np.ones(20, np.uint8),
                                                   "number_of_returns": np.ones(20, np.uint8)}))
    (tls / "scans.csv").write_text("scan_id,x,y,z,gps_time_start\n1,0,0,1.5,0\n")
    (tls / "scan_1.survey.yaml").write_text("- scanner\n- platform\n")
    out = tmp_path / "p.vox"
    rc = main(["pad", str(tls), "-o", str(out)])
    _check(rc, capsys.readouterr().err, "pad", [tls / "scan_1.survey.yaml"], [out])


# ------------------------------------------------------ class 2: whole or nothing on failure
def test_failing_side_output_leaves_no_main_output(ws, tmp_path, capsys, monkeypatch):
    import vlsforest.sim.output as output
    from vlsforest.errors import InputDataError

    def broken(*a, **k):
        raise InputDataError(f"{tmp_path / 'h.npz'}: disk full")

    monkeypatch.setattr(output, "save_hits", broken)
    import vlsforest.sim as sim

    monkeypatch.setattr(sim, "save_hits", broken)
    outs = [tmp_path / "o.laz", tmp_path / "p.npz", tmp_path / "h.npz"]
    rc = main(["simulate", str(ws / "scene" / "scene.yaml"), str(ws / "survey.yaml"), "-o", str(outs[0]),
               "--pulses", str(outs[1]), "--hits", str(outs[2]), "--quiet", "--workers", "1"])
    _check(rc, capsys.readouterr().err, "simulate", [tmp_path / "h.npz"], outs)
    assert not any(tmp_path.iterdir())


def _interrupt_after(monkeypatch, module, name, after: int = 0):
    """Make ``module.name`` raise KeyboardInterrupt on its call number ``after`` + 1, once it has
    begun writing (the original runs and the interrupt comes from inside the write)."""
    original = getattr(module, name)
    calls = {"n": 0}

    def wrapper(*a, **k):
        calls["n"] += 1
        if calls["n"] > after:
            raise KeyboardInterrupt
        return original(*a, **k)

    monkeypatch.setattr(module, name, wrapper)
    return calls


@pytest.mark.parametrize("after", [0, 5, 20])
def test_interrupt_while_writing_the_npz_side_outputs(ws, tmp_path, capsys, monkeypatch, after):
    """KeyboardInterrupt inside the npz writer (after ``after`` arrays): no output at all."""
    _interrupt_after(monkeypatch, np.lib.format, "write_array", after)
    outs = [tmp_path / "o.laz", tmp_path / "p.npz", tmp_path / "h.npz"]
    rc = main(["simulate", str(ws / "scene" / "scene.yaml"), str(ws / "survey.yaml"), "-o", str(outs[0]),
               "--pulses", str(outs[1]), "--hits", str(outs[2]), "--quiet", "--workers", "1"])
    _check(rc, capsys.readouterr().err, "simulate", ["interrupted"], outs, code=130)
    assert not any(tmp_path.iterdir())


def test_interrupt_while_writing_the_las(ws, tmp_path, capsys, monkeypatch):
    import laspy

    _interrupt_after(monkeypatch, laspy.LasWriter, "write_points")
    out = tmp_path / "sub" / "o.laz"
    rc = main(["detect", str(ws / "hits.npz"), str(ws / "survey.yaml"), "-o", str(out)])
    _check(rc, capsys.readouterr().err, "detect", ["interrupted"], [out], code=130)
    assert not any(tmp_path.iterdir())  # the folder made for it is gone too


def test_interrupt_while_exporting_helios_leaves_no_folder(ws, tmp_path, capsys, monkeypatch):
    import vlsforest.io.vox as vox

    _interrupt_after(monkeypatch, vox, "join_rows")
    out = tmp_path / "helios"
    rc = main(["scene", "helios", str(ws / "scene" / "scene.yaml"), "-o", str(out)])
    _check(rc, capsys.readouterr().err, "scene", ["interrupted"], [out], code=130)
    assert not any(tmp_path.iterdir())


def test_interrupt_while_writing_the_demo_scene(tmp_path, capsys, monkeypatch):
    import vlsforest.io.mesh as mesh

    _interrupt_after(monkeypatch, mesh, "write_bytes")
    out = tmp_path / "d" / "scene.yaml"
    rc = main(["demo", "-o", str(out)])
    _check(rc, capsys.readouterr().err, "demo", ["interrupted"], [out], code=130)
    assert not any(tmp_path.iterdir())


def test_sigint_during_the_write_phase_of_a_subprocess(ws, tmp_path):
    """A real SIGINT, sent while simulate writes its hits file: no output file remains.

    The child restores Python's own SIGINT handler first: a process started by a test worker may
    inherit SIGINT as ignored (as a background job of a shell does), and then the signal would
    never arrive."""
    script = (
        "import os, signal, sys\n"
        "signal.signal(signal.SIGINT, signal.default_int_handler)\n"
        "import numpy as np\n"
        "from vlsforest import cli\n"
        "orig = np.lib.format.write_array\n"
        "n = [0]\n"
        "def slow(*a, **k):\n"
        "    n[0] += 1\n"
        "    if n[0] == 12:\n"
        "        os.kill(os.getpid(), signal.SIGINT)\n"
        "    return orig(*a, **k)\n"
        "np.lib.format.write_array = slow\n"
        "sys.exit(cli.main(sys.argv[1:]))\n"
    )
    outs = [tmp_path / "o.laz", tmp_path / "p.csv", tmp_path / "h.npz"]
    env = {**os.environ, "PYTHONPATH": str(REPO / "workflow")}
    proc = subprocess.run([sys.executable, "-c", script, "simulate", str(ws / "scene" / "scene.yaml"),
                           str(ws / "survey.yaml"), "-o", str(outs[0]), "--pulses", str(outs[1]),
                           "--hits", str(outs[2]), "--quiet", "--workers", "1"],
                          capture_output=True, text=True, env=env, timeout=300)
    _check(proc.returncode, proc.stderr, "simulate", ["interrupted"], outs, code=130)
    assert not any(tmp_path.iterdir())


def test_kill_9_during_the_write_phase_then_the_same_command_again(ws, tmp_path):
    """``kill -9`` while simulate writes its hits file leaves no output under a final name; running
    the command again gives the uninterrupted bytes and removes what the killed process left."""
    import signal
    import time

    script = (
        "import sys, time\n"
        "import numpy as np\n"
        "from pathlib import Path\n"
        "from vlsforest import cli\n"
        "orig = np.lib.format.write_array\n"
        "n = [0]\n"
        "def stall(*a, **k):\n"
        "    n[0] += 1\n"
        "    if n[0] == 12:\n"
        "        Path(sys.argv[1]).write_text('writing')\n"
        "        time.sleep(120)\n"
        "    return orig(*a, **k)\n"
        "np.lib.format.write_array = stall\n"
        "sys.exit(cli.main(sys.argv[2:]))\n"
    )
    outs = [tmp_path / "o.laz", tmp_path / "p.npz", tmp_path / "h.npz"]
    argv = ["simulate", str(ws / "scene" / "scene.yaml"), str(ws / "survey.yaml"), "-o", str(outs[0]),
            "--pulses", str(outs[1]), "--hits", str(outs[2]), "--quiet", "--workers", "1"]
    marker = tmp_path.parent / f"{tmp_path.name}.marker"
    env = {**os.environ, "PYTHONPATH": str(REPO / "workflow")}
    proc = subprocess.Popen([sys.executable, "-c", script, str(marker), *argv], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    t0 = time.monotonic()
    while not marker.exists() and proc.poll() is None and time.monotonic() - t0 < 240:
        time.sleep(0.1)
    assert marker.exists(), "the subprocess never reached its write phase"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=60)
    assert not any(p.exists() for p in outs)
    assert list(tmp_path.glob(".tmp-*"))  # what the killed process was writing, under temporary names
    assert main(argv) == 0
    assert outs[0].read_bytes() == (ws / "sim.laz").read_bytes()
    assert outs[1].read_bytes() == (ws / "pulses.npz").read_bytes()
    assert outs[2].read_bytes() == (ws / "hits.npz").read_bytes()
    assert not list(tmp_path.glob(".tmp-*"))


# -------------------------------------------------- class 6: HELIOS++ export of every part type
def test_scene_helios_exports_the_demo_scene(ws, tmp_path):
    import xml.etree.ElementTree as ET

    from vlsforest.io.vox import read_vox

    out = tmp_path / "helios"
    assert main(["scene", "helios", str(ws / "scene" / "scene.yaml"), "-o", str(out)]) == 0
    root = ET.parse(out / "scene.xml").getroot()
    files = {int(p.get("id")): p.find("./filter/param[@key='filepath']").get("value")
             for p in root.findall("./scene/part")}
    assert set(files) == {1, 2, 3}
    assert all((out / f).is_file() for f in files.values())
    crown = read_vox(out / files[3])
    import pandas as pd

    cen = pd.read_csv(ws / "scene" / "crown.csv").to_numpy()
    assert np.allclose(np.sort(crown.centres(), axis=0), np.sort(cen, axis=0))


def test_scene_helios_exports_points_and_vox_parts(ws, tmp_path):
    from vlsforest.io.vox import make_vox, write_vox

    write_vox(tmp_path / "c.vox", make_vox(np.array([[0, 0, 0], [1, 2, 3]]), 0.5, np.array([1.0, 2.0, 3.0])))
    write_las(tmp_path / "pts.las", PointCloud(np.array([[0.1, 0.1, 5.1], [0.2, 0.2, 5.2], [3.3, 0.1, 5.1]])))
    scene = {"parts": [{"id": 4, "type": "vox", "path": "c.vox"},
                       {"id": 5, "type": "voxels", "points": "pts.las", "size": 0.5}]}
    (tmp_path / "s.yaml").write_text(yaml.safe_dump(scene))
    out = tmp_path / "helios"
    assert main(["scene", "helios", str(tmp_path / "s.yaml"), "-o", str(out)]) == 0
    assert (out / "part_4.vox").is_file() and (out / "part_5.vox").is_file()


def test_scene_helios_with_a_bad_part_writes_nothing(ws, tmp_path, capsys):
    scene = {"parts": [{"id": 1, "type": "plane", "z": 0, "extent": [0, 0, 1, 1]},
                       {"id": 2, "type": "mesh", "path": "missing.obj"}]}
    (tmp_path / "s.yaml").write_text(yaml.safe_dump(scene))
    out = tmp_path / "helios"
    rc = main(["scene", "helios", str(tmp_path / "s.yaml"), "-o", str(out)])
    _check(rc, capsys.readouterr().err, "scene", ["missing.obj"], [out])


# ------------------------------------------------------------------ the workflow config
@pytest.mark.e2e  # Snakemake runs
@pytest.mark.parametrize("edit, key", [
    ({"scenarios": {"als": {"extraction_radius_m": -1}}}, "scenarios.als.extraction_radius_m"),
    ({"segment": {"stem_bridges": 3}}, "segment"),
])
def test_bad_workflow_config_stops_with_one_line(tmp_path, edit, key):
    from wfrun import QUICK, snakemake_cli

    cfg = yaml.safe_load(Path(QUICK).read_text())
    for top, val in edit.items():
        node = cfg.setdefault(top, {})
        for k, v in val.items():
            if isinstance(v, dict):
                node.setdefault(k, {}).update(v)
            else:
                node[k] = v
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump(cfg))
    proc = snakemake_cli("-n", "--cores", 1, "--configfile", tmp_path / "bad.yaml", cwd=tmp_path, timeout=120)
    assert proc.returncode != 0
    text = proc.stderr + proc.stdout
    lines = [ln for ln in text.splitlines() if ln.startswith("Invalid configuration")]
    assert len(lines) == 1 and f"'{key}'" in lines[0], text[-2000:]
    assert "Traceback" not in text
    assert not (tmp_path / "results").exists()


def test_npz_loader_rejects_a_zip_without_arrays(tmp_path):
    """A zip that is no npz is an InputDataError naming the file, not a KeyError."""
    from vlsforest.errors import InputDataError
    from vlsforest.sim.output import load_hits

    with zipfile.ZipFile(tmp_path / "z.npz", "w") as zf:
        zf.writestr("readme.txt", "hello")
    with pytest.raises(InputDataError, match="z.npz"):
        load_hits(tmp_path / "z.npz")


# ------------------------------------------------------------------ the atomic writer itself
def test_a_failed_write_keeps_the_previous_file_and_leaves_no_temporary(tmp_path):
    from vlsforest.io.atomic import atomic_path, write_text

    write_text(tmp_path / "a.txt", "old\n")
    with pytest.raises(KeyboardInterrupt):
        with atomic_path(tmp_path / "a.txt") as tmp:
            tmp.write_text("half")
            raise KeyboardInterrupt
    assert (tmp_path / "a.txt").read_text() == "old\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]


def test_a_transaction_installs_all_or_nothing_and_removes_the_folders_it_made(tmp_path):
    from vlsforest.io.atomic import output_transaction, write_text

    with pytest.raises(RuntimeError):
        with output_transaction():
            write_text(tmp_path / "x" / "y" / "one.txt", "1")
            write_text(tmp_path / "two.txt", "2")
            assert not (tmp_path / "two.txt").exists()  # deferred to the end
            raise RuntimeError("the third output failed")
    assert not any(tmp_path.iterdir())
    with output_transaction():
        write_text(tmp_path / "x" / "one.txt", "1")
        write_text(tmp_path / "two.txt", "2")
    assert (tmp_path / "x" / "one.txt").read_text() == "1" and (tmp_path / "two.txt").read_text() == "2"


def test_a_folder_output_replaces_the_old_folder_whole(tmp_path):
    from vlsforest.io.atomic import atomic_dir

    (tmp_path / "d").mkdir()
    (tmp_path / "d" / "stale.obj").write_text("old")
    with atomic_dir(tmp_path / "d") as tmp:
        (tmp / "new.obj").write_text("new")
    assert [p.name for p in (tmp_path / "d").iterdir()] == ["new.obj"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d"]


def _pulses_csv(ws, tmp, edit):
    import pandas as pd

    from vlsforest.sim.output import load_pulses

    p = load_pulses(ws / "pulses.npz")
    cols = {"slot": p["slot"], "gps_time": p["gps_time"]}
    for name in ("origin", "direction", "scan_dir"):
        for i, ax in enumerate("xyz"):
            cols[f"{name}_{ax}"] = p[name][:, i]
    cols.update(scan_angle=p["scan_angle"], source_id=p["source_id"], n_returns=p["n_returns"])
    df = pd.DataFrame(cols)
    edit(df)
    df.to_csv(tmp / "p.csv", index=False)
    return tmp / "p.csv"


@pytest.mark.parametrize("case, build, needle", [
    ("npz_text", _bytes_file("p.npz", b"slot\n1\n"), "not a zip"),
    ("npz_no_origin", _npz_variant("p.npz", lambda ws: dict(np.load(ws / "pulses.npz")),
                                   lambda a: a.pop("origin")), "'origin'"),
    ("npz_nan", _npz_variant("p.npz", lambda ws: dict(np.load(ws / "pulses.npz")),
                             lambda a: a["gps_time"].__setitem__(0, np.inf)), "'gps_time'"),
    ("csv_no_column", lambda ws, tmp: _pulses_csv(ws, tmp, lambda df: df.pop("direction_y")), "direction_y"),
    ("csv_text_value", lambda ws, tmp: _pulses_csv(ws, tmp, lambda df: df.__setitem__("slot", "x")), "slot"),
    ("csv_empty", _bytes_file("p.csv", b""), "p.csv"),
])
def test_bad_pulse_table(ws, tmp_path, case, build, needle):
    """The pulse-table loader: one InputDataError naming the file and the column."""
    from vlsforest.errors import InputDataError
    from vlsforest.sim.output import load_pulses

    path = build(ws, tmp_path)
    with pytest.raises(InputDataError) as info:
        load_pulses(path)
    msg = str(info.value)
    assert str(path) in msg and needle in msg and "\n" not in msg


def test_the_commands_declare_the_simulator_output_suffixes():
    """The suffixes the command line checks are those the simulator's writers accept."""
    from vlsforest.commands import LAS, NPZ, PULSES
    from vlsforest.sim.output import HITS_SUFFIXES, POINTS_SUFFIXES, PULSES_SUFFIXES

    assert (LAS, PULSES, NPZ) == (POINTS_SUFFIXES, PULSES_SUFFIXES, HITS_SUFFIXES)
