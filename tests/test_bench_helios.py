"""benchmarks/bench_helios.py: the benchmark against HELIOS++, run with a stand-in HELIOS++ binary."""

from __future__ import annotations

import importlib.util
import json
import os
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
BENCH = REPO / "benchmarks" / "bench_helios.py"
REAL = REPO.parent / "shared" / "data" / "real"

#: points the stand-in HELIOS++ writes (one .xyz file per leg, split 700 + 534)
FAKE_POINTS = (700, 534)

#: a stand-in for the HELIOS++ binary: answers --version as HELIOS++ 2.x does, checks that it runs
#: inside an exported folder, writes its point files where HELIOS++ 2.x does
#: (OUTPUT/<survey name>/<date>/legNNN_points.xyz) with a trajectory file beside them, and
#: keeps its arguments
FAKE_HELIOS = """#!{python}
import sys, time
from pathlib import Path
args = sys.argv[1:]
if args == ["--version"]:
    print("2.0.1")
    sys.exit(0)
assert args[0] == "survey.xml" and Path("survey.xml").is_file() and Path("scene.xml").is_file(), args
out = Path(args[args.index("--output") + 1])
legs = out / "uls" / "2026-01-01_00-00-00"
legs.mkdir(parents=True)
for i, n in enumerate({points}):
    with open(legs / f"leg{{i:03d}}_points.xyz", "w") as fh:
        for k in range(n):
            fh.write(f"{{k * 0.01:.3f}} 1.000 2.000 0.5 1 1 1 0 0 3 0\\n")
    (legs / f"leg{{i:03d}}_trajectory.txt").write_text("0 0 300 0 0 0 0\\n" * 50)
t = time.process_time()
while time.process_time() - t < 0.05:  # some CPU time to measure
    pass
with open("{argv_log}", "a") as fh:
    fh.write(" ".join(args) + "\\n")
"""


def _load():
    sys.path.insert(0, str(BENCH.parent))
    try:
        spec = importlib.util.spec_from_file_location("bench_helios_under_test", BENCH)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(BENCH.parent))
    return module


def _run(args, results_dir: Path):
    env = dict(os.environ, VLSFOREST_BENCH_RESULTS=str(results_dir),
               PYTHONPATH=os.pathsep.join([str(REPO / "workflow"), os.environ.get("PYTHONPATH", "")]))
    return subprocess.run([sys.executable, str(BENCH), *map(str, args)], capture_output=True, text=True, env=env,
                          cwd=REPO, timeout=600)


def _rows(results_dir: Path) -> list[dict]:
    return [json.loads(ln) for ln in (results_dir / "bench_helios.jsonl").read_text().splitlines()]


def _need_real():
    if not (REAL / "F_BR08_08_crown_250.vox").is_file():
        pytest.skip(f"real data absent ({REAL})")


QUICK = ["--quick", "--surveys", "uls", "--threads", "1", "--repeats", "1", "--warmup", "0"]


@pytest.mark.realdata
def test_with_a_helios_binary_one_row_holds_both_tools_and_their_ratios(tmp_path):
    _need_real()
    fake = tmp_path / "helios"
    argv_log = tmp_path / "helios_args.txt"
    fake.write_text(FAKE_HELIOS.format(python=sys.executable, points=FAKE_POINTS, argv_log=argv_log))
    fake.chmod(fake.stat().st_mode | stat.S_IXUSR)
    r = _run([*QUICK, "--helios", fake, "--workdir", tmp_path / "work"], tmp_path / "res")
    assert r.returncode == 0, r.stderr
    (row,) = _rows(tmp_path / "res")
    assert row["exit_code"] == 0 and row["results"]["helios_version"] == "2.0.1"
    (res,) = row["results"]["rows"]
    assert (res["scene"], res["survey"], res["threads"]) == ("F_BR08_08 (quick)", "uls", 1)
    ours, helios = res["vlsforest"], res["helios"]
    assert helios["n_points"] == sum(FAKE_POINTS)  # the trajectory files are not points
    assert sorted(helios["point_files"]) == [f"uls/2026-01-01_00-00-00/leg00{i}_points.xyz" for i in (0, 1)]
    assert ours["n_points"] > 1000 and res["n_pulses"] == ours["n_pulses"] > 100_000
    for d in (ours, helios):
        assert d["wall_s"] > 0 and d["cpu_s"] > 0 and d["max_rss_mb"] > 1
        assert d["pulses_per_cpu_s"] == round(res["n_pulses"] / d["cpu_s"])
    assert ours["engine_s"] > 0 and ours["outside_engine_s"] == pytest.approx(ours["wall_s"] - ours["engine_s"], abs=2e-3)
    # the ratios are stored rounded to 3 decimals
    assert res["speedup_cpu"] == pytest.approx(helios["cpu_s"] / ours["cpu_s"], abs=5e-4)
    assert res["speedup_wall"] == pytest.approx(helios["wall_s"] / ours["wall_s"], abs=5e-4)
    assert res["points_ratio"] == pytest.approx(ours["n_points"] / sum(FAKE_POINTS), rel=1e-3, abs=5e-4)
    assert res["rss_ratio"] == pytest.approx(ours["max_rss_mb"] / helios["max_rss_mb"], rel=1e-2, abs=5e-4)
    if res["speedup_cpu"] < 1:  # the stand-in is faster than any simulation: the row says where our time goes
        assert "engine_s" in res["slower"]
    # HELIOS++ 2.x ran the exported survey with one thread and the 1.0.8 energy model
    (args,) = argv_log.read_text().splitlines()
    args = args.split()
    assert args[0] == "survey.xml" and args[args.index("-j") + 1] == "1" and args[args.index("--seed") + 1] == "1"
    assert {"--legacyEnergyModel", "--lasOutput", "--rebuildScene", "--noSceneWriting"} <= set(args)
    assert (tmp_path / "work" / "F_BR08_08" / "helios_uls" / "survey.xml").is_file()
    # the flat table rendered on the results page
    (flat,) = row["results"]["table"]
    assert flat["helios.n_points"] == sum(FAKE_POINTS) and flat["vlsforest.cpu_s"] == ours["cpu_s"]


@pytest.mark.realdata
def test_without_helios_only_our_side_is_recorded(tmp_path):
    _need_real()
    r = _run(QUICK, tmp_path / "res")
    assert r.returncode == 0, r.stderr
    (row,) = _rows(tmp_path / "res")
    assert row["results"]["helios_binary"] is None
    (res,) = row["results"]["rows"]
    assert res["helios"] is None and "no HELIOS++ binary" in res["helios_note"]
    assert res["vlsforest"]["n_points"] > 1000 and "speedup_cpu" not in res
    assert "our side only" in "\n".join(row["output"])


@pytest.mark.parametrize("args, says", [
    (["--data", "/nonexistent/real"], "no data folder /nonexistent/real"),
    (["--helios", "/nonexistent/helios"], "--helios /nonexistent/helios: not an executable file"),
    (["--surveys", "tls"], "--surveys takes als, uls"),
    (["--threads", "0"], "--threads takes integers"),
    (["--study-only"], "--study-only needs --study-results DIR"),
])
def test_bad_input_is_one_line_and_exit_2_without_a_row(tmp_path, args, says):
    r = _run([*args, "--data", REAL] if args[0] != "--data" else args, tmp_path / "res")
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("bench_helios: error: ") and says in lines[0], r.stderr
    assert not (tmp_path / "res").exists()


def test_point_files_are_counted_from_las_and_xyz_not_trajectories(tmp_path):
    import laspy

    bench = _load()
    header = laspy.LasHeader(point_format=1, version="1.4")
    las = laspy.LasData(header)
    las.x, las.y, las.z = np.arange(17.0), np.zeros(17), np.ones(17)
    (tmp_path / "a" / "b").mkdir(parents=True)
    las.write(tmp_path / "a" / "leg000_points.las")
    (tmp_path / "a" / "b" / "leg001_points.xyz").write_text("1 2 3\n\n4 5 6\n# comment\n7 8 9")
    (tmp_path / "a" / "leg000_trajectory.txt").write_text("1 2 3\n")
    (tmp_path / "a" / "b" / "leg001_trajectory.xyz").write_text("1 2 3\n")
    (tmp_path / "a" / "leg000_fullwave.txt").write_text("1 2 3\n")
    n, files = bench.count_points(tmp_path)
    assert n == 17 + 3
    assert files == ["a/b/leg001_points.xyz", "a/leg000_points.las"]


def test_helios_command_by_version(tmp_path):
    bench = _load()
    one = bench.helios_command("/h", "1.0.8", tmp_path, 5, 2, ["--silent"])
    assert one == ["/h", "survey.xml", "--output", str(tmp_path), "--seed", "5", "-j", "2", "--lasOutput",
                   "--rebuildScene", "--silent"]
    two = bench.helios_command("/h", "2.2.2", tmp_path, 5, 2, [])
    assert two[:len(one) - 1] == one[:-1]
    assert two[len(one) - 1:] == ["--legacyEnergyModel", "--noSceneWriting", "--kdtJobs", "2", "--assets", "."]


def test_study_plot_cases_take_the_surveys_that_exist(tmp_path):
    bench = _load()
    res = tmp_path / "results"
    (res / "P3" / "scaled" / "scene").mkdir(parents=True)
    (res / "P3" / "surveys").mkdir(parents=True)
    with pytest.raises(bench.BenchError, match="no study scene"):
        bench.study_cases(res, "P3", "scaled", ["uls"], tmp_path / "w")
    (res / "P3" / "scaled" / "scene" / "scene.yaml").write_text("parts: []\n")
    with pytest.raises(bench.BenchError, match="no survey als.yaml, uls.yaml"):
        bench.study_cases(res, "P3", "scaled", ["als", "uls"], tmp_path / "w")
    (res / "P3" / "surveys" / "uls.yaml").write_text("scanner: riegl_minivux1uav\n")
    (case,) = bench.study_cases(res, "P3", "scaled", ["als", "uls"], tmp_path / "w")
    assert (case["scene"], case["survey"]) == ("P3/scaled", "uls")
    assert case["scene_yaml"] == res / "P3" / "scaled" / "scene" / "scene.yaml"
    assert case["survey_yaml"] == res / "P3" / "surveys" / "uls.yaml"


def test_rows_flatten_and_render_in_the_results_page(tmp_path):
    bench = _load()
    spec = importlib.util.spec_from_file_location("gen_reference_under_test", REPO / "scripts" / "gen_reference.py")
    gen = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gen)
    row = {"scene": "F_BR08_08", "survey": "als", "threads": 2, "n_pulses": 100,
           "vlsforest": {"wall_s": 1.5, "cpu_s": 2.5, "command": "vlsforest simulate …"},
           "helios": None, "helios_note": "no HELIOS++ binary given"}
    flat = bench.flat(row)
    assert flat == {"scene": "F_BR08_08", "survey": "als", "threads": 2, "n_pulses": 100, "vlsforest.wall_s": 1.5,
                    "vlsforest.cpu_s": 2.5, "helios": None, "helios_note": "no HELIOS++ binary given"}
    line = {"benchmark": "bench_helios", "date": "2026-01-01T00:00:00+00:00", "commit": "abc",
            "machine": {"host": "m", "cpus": 2}, "results": {"rows": [row], "table": [flat, dict(flat, threads=1)]}}
    (tmp_path / "bench_helios.jsonl").write_text(json.dumps(line) + "\n")
    text = gen.benchmark_results(tmp_path)
    assert "2 record(s)." in text
    assert ("| date | commit | host | cpus | scene | survey | threads | n_pulses | vlsforest.wall_s | vlsforest.cpu_s "
            "| helios | helios_note |") in text
    assert "| 2026-01-01T00:00:00+00:00 | abc | m | 2 | F_BR08_08 | als | 2 | 100 | 1.5 | 2.5 |  | no HELIOS++ binary given |" in text


def test_point_summary_and_agreement_by_hand():
    """Four tree pulses on two lines (two share a GPS time on different lines): pulse (0, 1.0)
    with 2 returns, (1, 1.0) with 1, (0, 2.0) with 3 (one of them on the ground), (1, 3.0) with
    1: two of four pulses have more than one return, 50 %."""
    xyz = np.array([[0, 0, 11.0], [0, 0, 12.0], [0, 0, 13.0], [0, 0, 14.0], [0, 0, 15.0], [0, 0, 10.0],
                    [0, 0, 10.0]])
    oid = np.array([2, 3, 3, 3, 3, 1, 1])
    nret = np.array([2, 2, 1, 3, 1, 3, 1])
    gps = np.array([1.0, 1.0, 1.0, 2.0, 3.0, 2.0, 4.0])
    line = np.array([0, 0, 1, 0, 1, 0, 0])
    bench = _load()
    s = bench.point_summary(xyz, oid, nret, gps, line, ground_z=10.0)
    assert s["ground_points"] == 2 and s["tree_points"] == 5
    assert s["tree_multi_return_pct"] == 50.0
    # tree heights 1, 2, 3, 4, 5 m: median 3 m; 99th percentile 4 + 0.96 m (linear interpolation)
    assert s["tree_height_p50_m"] == 3.0 and s["tree_height_p99_m"] == pytest.approx(4.96)
    other = dict(s, ground_points=100, tree_points=5, tree_multi_return_pct=53.0, tree_height_p99_m=5.0)
    a = bench.agreement(dict(s, ground_points=101), other)
    assert a["ground_points_diff"] == pytest.approx(0.01) and a["ground_points_within"]
    assert a["tree_multi_return_pct_diff"] == pytest.approx(-3.0) and not a["tree_multi_return_pct_within"]
    assert a["tree_height_p99_m_diff"] == pytest.approx(-0.04) and a["tree_height_p99_m_within"]


def test_phase_agreement_judges_the_mean_over_phases_by_hand():
    """Three phases whose multiple-return shares differ by +3, −1 and +1 pp: the mean +1 pp is
    within the 2 pp bound although one phase alone is not; SE = sd / √3 = 2 / √3."""
    bench = _load()
    base = {"ground_points": 100, "tree_points": 50, "tree_multi_return_pct": 20.0,
            "tree_height_p50_m": 10.0, "tree_height_p99_m": 20.0}
    pairs = [(dict(base, tree_multi_return_pct=23.0, ground_points=103), base),
             (dict(base, tree_multi_return_pct=19.0, ground_points=101), base),
             (dict(base, tree_multi_return_pct=21.0, ground_points=101), base)]
    ph = bench.phase_agreement(pairs)
    assert ph["n_phases"] == 3
    mr = ph["tree_multi_return_pct"]
    assert mr["diffs"] == [3.0, -1.0, 1.0] and mr["mean_diff"] == pytest.approx(1.0) and mr["within"]
    assert mr["se"] == pytest.approx(2.0 / np.sqrt(3.0), abs=1e-4)
    # counts relative to HELIOS++'s: +3 %, +1 %, +1 % → mean +1.67 %, within the 2 % bound
    assert ph["ground_points"]["mean_diff"] == pytest.approx(0.0167, abs=1e-4) and ph["ground_points"]["within"]
    assert ph["tree_height_p50_m"]["mean_diff"] == 0.0


def test_phase_case_moves_every_leg_within_a_voxel(tmp_path):
    import yaml

    bench = _load()
    legs = [{"start": [0.0, -10.0, 100.0], "end": [0.0, 10.0, 100.0], "active": True},
            {"start": [0.0, 10.0, 100.0], "end": [5.0, 10.0, 100.0], "active": False}]
    survey = tmp_path / "als.yaml"
    survey.write_text(yaml.safe_dump({"scanner": "riegl_vq780i", "platform": {"type": "linear", "legs": legs}}))
    case = {"survey": "als", "survey_yaml": survey, "folder": tmp_path, "scene": "s"}
    pc = bench.phase_case(case, 2, 4)
    dx, dy = pc["shift_m"]
    assert dx == pytest.approx(0.125) and dy == pytest.approx(0.25 * ((0.618 * 2) % 1.0), abs=1e-4)
    moved = yaml.safe_load(pc["survey_yaml"].read_text())["platform"]["legs"]
    for a, b in zip(legs, moved):
        for end in ("start", "end"):
            assert b[end] == pytest.approx([a[end][0] + dx, a[end][1] + dy, a[end][2]], abs=1e-4)
    assert pc["folder"] == tmp_path / "phase_2" and yaml.safe_load(survey.read_text())["platform"]["legs"] == legs
