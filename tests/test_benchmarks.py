"""benchmarks/: every benchmark writes its machine-readable row through benchmarks/benchresult.py."""

from __future__ import annotations

import importlib.util
import json
import re
from pathlib import Path

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


def test_a_benchmark_that_exits_keeps_its_code(tmp_path):
    br = _benchresult()

    def main(argv):
        raise SystemExit(4)

    assert br.run("bench_toy", main, [], results_dir=tmp_path) == 4
    assert json.loads((tmp_path / "bench_toy.jsonl").read_text())["exit_code"] == 4
