"""benchmarks/: every benchmark writes its machine-readable row through benchmarks/benchresult.py."""

from __future__ import annotations

import importlib
import importlib.util
import json
import re
import os
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
BENCHMARKS = REPO / "benchmarks"


def _benchresult():
    spec = importlib.util.spec_from_file_location("benchresult_under_test", BENCHMARKS / "benchresult.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_every_benchmark_ends_through_the_results_helper():
    scripts = sorted(BENCHMARKS.glob("bench_*.py"))
    assert scripts
    for path in scripts:
        text = path.read_text()
        assert re.search(rf'benchresult\.run\("{path.stem}", main\)', text), path.name
        assert "benchresult.record(" in text, path.name


def test_a_run_appends_one_row_with_its_provenance_and_results(tmp_path):
    br = _benchresult()

    def main(argv):
        print("line one")
        br.record(seconds_total=1.5, argv=argv)
        return 3

    assert br.run("bench_toy", main, ["--x", "1 2"], results_dir=tmp_path) == 3
    assert br.run("bench_toy", lambda argv: None, [], results_dir=tmp_path) == 0
    rows = [json.loads(line) for line in (tmp_path / "bench_toy.jsonl").read_text().splitlines()]
    assert len(rows) == 2
    row = rows[0]
    assert row["benchmark"] == "bench_toy" and row["exit_code"] == 3
    assert row["command"] == "python benchmarks/bench_toy.py --x '1 2'"
    assert row["results"] == {"seconds_total": 1.5, "argv": ["--x", "1 2"]}
    assert row["output"] == ["line one"]
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\+00:00", row["date"])
    assert {"host", "os", "cpu", "cpus", "memory_gb", "python"} <= set(row["machine"])
    assert "commit" in row
    assert rows[1]["results"] == {} and rows[1]["output"] == []


def test_help_and_usage_errors_append_no_row(tmp_path):
    import argparse

    br = _benchresult()

    def main(argv):
        ap = argparse.ArgumentParser()
        ap.add_argument("--n", type=int)
        ap.parse_args(argv)
        br.record(n=1)
        return 0

    assert br.run("bench_toy", main, ["--help"], results_dir=tmp_path) == 0
    assert br.run("bench_toy", main, ["--hel"], results_dir=tmp_path) == 0
    assert br.run("bench_toy", main, ["--n", "x"], results_dir=tmp_path) == 2
    assert not (tmp_path / "bench_toy.jsonl").exists()
    assert br.run("bench_toy", main, ["--n", "3"], results_dir=tmp_path) == 0
    assert len((tmp_path / "bench_toy.jsonl").read_text().splitlines()) == 1


def test_a_benchmark_that_exits_keeps_its_code(tmp_path):
    br = _benchresult()

    def main(argv):
        raise SystemExit(4)

    assert br.run("bench_toy", main, [], results_dir=tmp_path) == 4
    assert json.loads((tmp_path / "bench_toy.jsonl").read_text())["exit_code"] == 4


def test_study_benchmark_sums_the_benchmark_files_of_the_jobs_run_by_rule(tmp_path):
    sys.path.insert(0, str(BENCHMARKS))
    try:
        import bench_study
    finally:
        sys.path.remove(str(BENCHMARKS))
    log = "\n".join([
        "rule simulate:",
        "    input: results/P1/a/scene",
        "    output: results/P1/a/als/sim.laz",
        "    log: logs/simulate/P1_a_als.log",
        "    jobid: 3",
        "    benchmark: logs/benchmarks/simulate/P1_a_als.tsv",
        "rule simulate:",
        "    benchmark: logs/benchmarks/simulate/P2_a_als.tsv",
        "rule synth_plot:",
        "    benchmark: logs/benchmarks/synth/P1.tsv",
        "rule diagnose:",
        "    benchmark: logs/benchmarks/diagnose_uls.tsv",
        "rule targets:",
        "    benchmark: logs/benchmarks/targets/P1.tsv",
        "localrule all:",
        "    input: results/summary/tree_metrics.csv",
        "    jobid: 0",
    ])
    jobs = bench_study.jobs_of_run(log)
    assert jobs[0] == ("simulate", "logs/benchmarks/simulate/P1_a_als.tsv")
    assert jobs[-1] == ("all", None) and len(jobs) == 6
    head = "s\th:m:s\tmax_rss\tmax_vms\tmax_uss\tmax_pss\tio_in\tio_out\tmean_load\tcpu_time\n"
    bench = tmp_path / "logs" / "benchmarks"
    for folder in ("simulate", "synth", "targets"):
        (bench / folder).mkdir(parents=True)
    (bench / "simulate" / "P1_a_als.tsv").write_text(head + "10.0\t0:00:10\t500.5\t1\t1\t1\t0\t0\t90\t9.5\n")
    (bench / "simulate" / "P2_a_als.tsv").write_text(head + "20.0\t0:00:20\t800.0\t1\t1\t1\t0\t0\t90\t19.0\n")
    (bench / "simulate" / "P3_a_als.tsv").write_text(head + "50.0\t0:00:50\t900.0\t1\t1\t1\t0\t0\t90\t49.0\n")
    (bench / "synth" / "P1.tsv").write_text(head)  # a job without a row
    (bench / "diagnose_uls.tsv").write_text(head + "100.0\t0:01:40\t9000.0\t1\t1\t1\t0\t0\t90\t95.0\n")
    (bench / "targets" / "P1.tsv").write_text(head + "0.4\t0:00:00\tNA\tNA\tNA\tNA\tNA\tNA\tNA\tNA\n")
    table = bench_study.rule_table(tmp_path, jobs)
    # P3's file is from another run: not one of this run's jobs
    assert table["simulate"] == {"jobs": 2, "cpu_s": 28.5, "wall_s": 30.0, "max_rss_mb": 800.0}
    assert table["diagnose"] == {"jobs": 1, "cpu_s": 95.0, "wall_s": 100.0, "max_rss_mb": 9000.0}
    assert table["synth_plot"] == {"jobs": 1, "cpu_s": 0.0, "wall_s": 0.0, "max_rss_mb": 0.0}
    assert table["targets"] == {"jobs": 1, "cpu_s": 0.0, "wall_s": 0.4, "max_rss_mb": 0.0}
    assert table["all"] == {"jobs": 1}
    assert bench_study.rule_table(tmp_path, []) == {}


def test_study_benchmark_reruns_without_its_force_flags(tmp_path):
    """The no-op rerun is the run's own command less --forceall / --forcerun RULE …; its jobs
    come from Snakemake's summary line (none when it prints none)."""
    import types

    sys.path.insert(0, str(BENCHMARKS))
    try:
        import bench_study
    finally:
        sys.path.remove(str(BENCHMARKS))
    echo = [sys.executable, "-c", "import sys; open('argv.txt', 'w').write(' '.join(sys.argv[1:]))"]
    for flags, forcerun in ((["--forceall"], []), (["--forcerun", "stats", "figures"], ["stats", "figures"])):
        args = types.SimpleNamespace(forcerun=forcerun, workdir=tmp_path)
        got = bench_study.noop_rerun(echo + ["--cores", "2"] + flags + ["--configfile", "q.yaml"], args, dict(os.environ))
        assert got["noop_rerun_jobs"] == 0 and got["noop_rerun_exit_code"] == 0 and got["noop_rerun_wall_s"] >= 0
        assert (tmp_path / "argv.txt").read_text() == "--cores 2 --configfile q.yaml"
    said = [sys.executable, "-c", "print('Nothing to be done.'); print('3 of 3 steps (100%) done')", "--forceall"]
    got = bench_study.noop_rerun(said, types.SimpleNamespace(forcerun=[], workdir=tmp_path), dict(os.environ))
    assert got["noop_rerun_jobs"] == 3


def test_every_rule_that_runs_a_command_writes_a_benchmark_file():
    """Every rule with a shell command or a script declares a benchmark file under
    logs/benchmarks/ (the per-rule CPU table of bench_study reads them)."""
    files = sorted((REPO / "workflow" / "rules").rglob("*.smk"))
    checked = 0
    for path in files:
        blocks = re.split(r"^(?=(?:rule|checkpoint) \w+:)", path.read_text(), flags=re.M)
        for block in blocks[1:]:
            name = block.split(":", 1)[0].split()[1]
            runs = re.search(r"^    (?:shell|script|run):", block, flags=re.M)
            if not runs:
                continue
            checked += 1
            m = re.search(r'^    benchmark:\n\s+"(logs/benchmarks/[^"]+\.tsv)"', block, flags=re.M)
            assert m, f"{path.name}: rule {name} has no benchmark file under logs/benchmarks/"
    assert checked >= 20


def test_compare_runs_finds_changed_and_one_sided_files(tmp_path):
    spec = importlib.util.spec_from_file_location("compare_runs", REPO / "validation" / "compare_runs.py")
    cr = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(cr)
    for side, extra in (("a", b"1"), ("b", b"2")):
        (tmp_path / side / "P1" / "m" / "als").mkdir(parents=True)
        (tmp_path / side / "P1" / "m" / "als" / "sim.laz").write_bytes(b"same")
        (tmp_path / side / "P1" / "m" / "als" / "timing.json").write_bytes(extra)
        (tmp_path / side / "summary").mkdir()
        (tmp_path / side / "summary" / "findings.md").write_bytes(extra)
    (tmp_path / "b" / "new.csv").write_bytes(b"x")
    res = cr.compare(tmp_path / "a", tmp_path / "b", skip=cr.TIMING_FILES)
    assert res["compared"] == 2 and res["equal"] == 1
    assert res["different"] == ["summary/findings.md"] and res["only_b"] == ["new.csv"]
    assert res["skipped"] == ["P1/m/als/timing.json"]
    res = cr.compare(tmp_path / "a", tmp_path / "b", skip=cr.TIMING_FILES, expect=["summary/*"])
    assert res["different"] == [] and res["expected_different"] == ["summary/findings.md"]
    out = tmp_path / "rows.jsonl"
    assert cr.main([str(tmp_path / "a"), str(tmp_path / "b"), "--expect-changed", "summary/*", "--out", str(out)]) == 0
    assert cr.main([str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(out)]) == 1
    assert len(out.read_text().splitlines()) == 2
    assert cr.main([str(tmp_path / "nope"), str(tmp_path / "b"), "--out", str(out)]) == 2

def _bench(name: str):
    """The benchmark module ``benchmarks/<name>.py``, imported with its folder on the path."""
    sys.path.insert(0, str(BENCHMARKS))
    try:
        return importlib.import_module(name)
    finally:
        sys.path.remove(str(BENCHMARKS))


def _bench_memory_floor():
    return _bench("bench_memory_floor")


def test_memory_floor_fits_bytes_per_element_by_least_squares():
    fit = _bench_memory_floor().fit_per_element
    # 1000 B each on top of 5 MB, exactly
    slope, icpt = fit([100, 200, 400], [5e6 + 1e5, 5e6 + 2e5, 5e6 + 4e5])
    assert slope == pytest.approx(1000.0) and icpt == pytest.approx(5e6)
    # by hand: mean n 2, mean y 4; Sxy = (-1)(-3) + 0(1) + 1(2) = 5, Sxx = 2 → 2.5 each, 4 − 5 = −1 at 0
    slope, icpt = fit([1, 2, 3], [1.0, 5.0, 6.0])
    assert slope == pytest.approx(2.5) and icpt == pytest.approx(-1.0)
    with pytest.raises(ValueError):
        fit([5, 5], [1.0, 2.0])
    with pytest.raises(ValueError):
        fit([1, 2], [1.0])


def test_memory_floor_reads_the_kb_fields_of_proc_files():
    text = ("Name:\tpython\nVmHWM:\t  412344 kB\nVmRSS:\t  400000 kB\nThreads:\t3\n"
            "Rss:                1616 kB\nPss:                 224 kB\n")
    assert _bench_memory_floor().status_kb(text) == {"VmHWM": 412344, "VmRSS": 400000, "Rss": 1616, "Pss": 224}


def test_memory_floor_names_the_third_party_packages_of_a_module_list():
    names = ["numpy", "numpy.linalg", "json", "_ctypes", "vlsforest.sim", "laspy.copc", "yaml", "os.path"]
    assert _bench_memory_floor().third_party(names, stdlib={"json", "os"}) == ["laspy", "numpy", "yaml"]


def _bench_job_startup():
    return _bench("bench_job_startup")


def test_job_startup_reads_the_job_stats_table():
    bench = _bench_job_startup()
    text = "\n".join(["Building DAG of jobs...", "Job stats:", "job          count", "---------  -------",
                      "synth_plot         6", "simulate          84", "all                1", "total             91",
                      "", "Job stats:", "job  count", "---  -----", "simulate 1"])
    assert bench.job_counts(text) == {"synth_plot": 6, "simulate": 84, "all": 1}
    assert bench.job_counts("no table") == {}


def test_job_startup_covers_every_rule_with_a_shell_command():
    """Every rule that runs `vlsforest <stage>` has its imports listed, with that stage."""
    bench = _bench_job_startup()
    checked = 0
    for path in sorted((REPO / "workflow" / "rules").rglob("*.smk")):
        blocks = re.split(r"^(?=rule \w+:)", path.read_text(), flags=re.M)
        for block in blocks[1:]:
            name = block.split(":", 1)[0].split()[1]
            m = re.search(r'^    shell:\n\s+"vlsforest ([a-z-]+)', block, flags=re.M)
            if not m:
                continue
            assert name in bench.RULE_IMPORTS, f"{path.name}: rule {name} not in RULE_IMPORTS"
            assert bench.RULE_IMPORTS[name][0] == m.group(1), name
            checked += 1
    assert checked >= 20
