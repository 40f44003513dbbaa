"""Benchmark: Snakemake's own CPU use while it runs many jobs, with and without the workflow's
scheduler workaround (``_one_pending_reevaluation`` in ``workflow/rules/common.smk``).

Snakemake 9 starts a re-evaluation timer at the end of each scheduling pass, and each timer's
pass starts the next; every pass triggered by a job's start or end adds one such chain, so the
passes per second grow with the jobs run. This runs the same throw-away workflow twice — N
one-thread jobs that sleep, on 2 cores — once as Snakemake is and once with the workaround
(taken from common.smk), and prints the wall time, the CPU seconds of the Snakemake process
itself (not its jobs), and the ratios.

    python benchmarks/bench_scheduler.py --jobs 300 --sleep 0.3

About 2 × (jobs × sleep / 2 + overhead) seconds. Writes only into a temporary folder.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import psutil

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))
from wfrun import scheduler_workaround_source  # noqa: E402  (tests/ holds the shared helper)

SNAKEFILE = """
{workaround}
N = {jobs}
rule all:
    input: expand("out/{{i}}.txt", i=range(N))
rule job:
    output: "out/{{i}}.txt"
    params: p=lambda w: {{"i": int(w.i), "x": list(range(50))}}
    shell: "sleep {sleep}; echo {{wildcards.i}} > {{output}}"
"""


def _workaround_source() -> str:
    return scheduler_workaround_source()[0] + "\n_one_pending_reevaluation()\n"


def _run(workdir: Path, with_workaround: bool, jobs: int, sleep: float) -> dict:
    workdir.mkdir(parents=True)
    (workdir / "Snakefile").write_text(SNAKEFILE.format(
        workaround=_workaround_source() if with_workaround else "", jobs=jobs, sleep=sleep))
    cmd = [str(Path(sys.executable).parent / "snakemake"), "--cores", "2", "--quiet", "all",
           "--workflow-profile", "none"]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=workdir, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    ps = psutil.Process(proc.pid)
    cpu = 0.0
    while proc.poll() is None:
        try:
            t = ps.cpu_times()
            cpu = t.user + t.system  # the Snakemake process only (children: the jobs)
        except psutil.Error:
            pass
        time.sleep(0.2)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"bench_scheduler: snakemake failed:\n{proc.stderr.read()[-2000:]}")
    return {"wall": wall, "cpu": cpu}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, default=300)
    ap.add_argument("--sleep", type=float, default=0.3, help="seconds each job sleeps")
    a = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        _run(Path(tmp) / "warm_up", False, 4, 0.0)  # first-run costs (imports, caches) not counted
        rows = {}
        for label, on in (("as installed", False), ("with workaround", True)):
            rows[label] = r = _run(Path(tmp) / label.replace(" ", "_"), on, a.jobs, a.sleep)
            print(f"{label:16s}: {a.jobs} jobs in {r['wall']:6.1f} s wall; Snakemake process {r['cpu']:6.1f} CPU-s",
                  flush=True)
    old, new = rows["as installed"], rows["with workaround"]
    print(f"ratios (as installed / with workaround): CPU {old['cpu'] / max(new['cpu'], 1e-9):.1f}×, "
          f"wall {old['wall'] / new['wall']:.2f}×")
    return 0


if __name__ == "__main__":
    sys.exit(main())
