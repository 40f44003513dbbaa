"""The whole study as one measured run: wall time, CPU seconds, peak memory, per-rule CPU.

Runs the workflow's default target (``snakemake --cores N [--configfile …]``) in a checkout and
records one row in ``benchmarks/results/bench_study.jsonl`` (:mod:`benchresult`):

- ``wall_s``: wall time of the Snakemake process and everything it started;
- ``cpu_s``: user + system CPU seconds of all of it (``getrusage(RUSAGE_CHILDREN)``);
- ``max_rss_mb``: the largest resident set of any one process it waited for;
- ``jobs``: the jobs Snakemake ran (from its summary line);
- ``rules``: per rule that declares a ``benchmark:`` file, the number of jobs, their summed
  ``cpu_time`` and wall ``s`` and the largest ``max_rss`` (MB), read from
  ``logs/benchmarks/<rule folder>/*.tsv`` (or a single ``logs/benchmarks/<name>.tsv``); the CPU seconds outside those rules (Snakemake
  itself and the small jobs) follow as ``cpu_s_outside_benchmarked_rules``.

Usage::

    python benchmarks/bench_study.py [--workdir DIR] [--cores 2] [--configfile config/quick.yaml]
                                     [--forceall]

The run starts from what ``results/`` already holds; ``--forceall`` reruns every job (``rm -rf
results logs .snakemake`` gives a fresh-clone run). The Snakemake binary is the one next to this
Python (``.venv/bin/snakemake``), and that folder goes first on ``PATH`` so that the jobs call the
project's ``vlsforest``.
"""

from __future__ import annotations

import argparse
import csv
import os
import re
import resource
import subprocess
import sys
import time
from pathlib import Path

import benchresult

def rule_table(bench_dir: Path) -> dict:
    """Per folder of Snakemake benchmark files (and per single file beside them): jobs, summed
    cpu_time and s, largest max_rss (MB)."""
    out = {}
    groups = {}
    for p in sorted(bench_dir.iterdir()) if bench_dir.is_dir() else []:
        if p.is_dir():
            groups[p.name] = sorted(p.rglob("*.tsv"))
        elif p.suffix == ".tsv":  # a rule's single benchmark file, e.g. diagnose_uls.tsv
            groups[p.stem] = [p]
    for name, files in groups.items():
        jobs = cpu = wall = 0.0
        rss = 0.0
        for tsv in files:
            with open(tsv, newline="") as fh:
                rows = list(csv.DictReader(fh, delimiter="\t"))
            if not rows:
                continue
            r = rows[-1]
            jobs += 1
            cpu += float(r.get("cpu_time") or 0.0)
            wall += float(r.get("s") or 0.0)
            try:
                rss = max(rss, float(r.get("max_rss") or 0.0))
            except ValueError:
                pass
        out[name] = {"jobs": int(jobs), "cpu_s": round(cpu, 1), "wall_s": round(wall, 1),
                            "max_rss_mb": round(rss, 1)}
    return out


def main(argv) -> int:
    ap = argparse.ArgumentParser(prog="bench_study", description=__doc__.split("\n\n")[0])
    ap.add_argument("--workdir", type=Path, default=benchresult.REPO, help="the checkout to run in")
    ap.add_argument("--cores", type=int, default=2)
    ap.add_argument("--configfile", action="append", default=[], help="config file(s) over config/config.yaml")
    ap.add_argument("--forceall", action="store_true", help="rerun every job")
    args = ap.parse_args(argv)
    bindir = Path(sys.executable).parent
    cmd = [str(bindir / "snakemake"), "--cores", str(args.cores)]
    for c in args.configfile:
        cmd += ["--configfile", c]
    if args.forceall:
        cmd.append("--forceall")
    env = dict(os.environ, PATH=f"{bindir}{os.pathsep}{os.environ.get('PATH', '')}")
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=args.workdir, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    m = re.findall(r"(\d+) of (\d+) steps \(100%\) done", proc.stderr)
    jobs = int(m[-1][1]) if m else 0
    rules = rule_table(args.workdir / "logs" / "benchmarks")
    inside = sum(r["cpu_s"] for r in rules.values())
    print(f"study: {wall:.0f} s wall, {cpu:.0f} CPU-s ({100 * cpu / max(wall, 1e-9):.0f} % of one core), "
          f"{jobs} jobs, exit {proc.returncode}")
    for name, r in rules.items():
        print(f"  {name:12s} {r['jobs']:4d} jobs {r['cpu_s']:8.1f} CPU-s {r['wall_s']:8.1f} s "
              f"max {r['max_rss_mb']:8.1f} MB")
    benchresult.record(workdir=str(args.workdir), configfiles=args.configfile, cores=args.cores,
                       wall_s=round(wall, 1), cpu_s=round(cpu, 1),
                       max_rss_mb=round(after.ru_maxrss / 1024.0, 1), jobs=jobs, rules=rules,
                       cpu_s_outside_benchmarked_rules=round(cpu - inside, 1), exit_code=proc.returncode)
    if proc.returncode:
        print(proc.stderr[-4000:], file=sys.stderr)
    return proc.returncode


if __name__ == "__main__":
    raise SystemExit(benchresult.run("bench_study", main))
