"""The whole study as one measured run: wall time, CPU seconds, peak memory, per-rule CPU.

Runs the workflow's default target (``snakemake --cores N [--configfile …]``) in a checkout and
records one row in ``benchmarks/results/bench_study.jsonl`` (:mod:`benchresult`):

- ``wall_s``: wall time of the Snakemake process and everything it started;
- ``cpu_s``: user + system CPU seconds of all of it (``getrusage(RUSAGE_CHILDREN)``);
- ``snakemake_cpu_s``: the CPU seconds of the Snakemake process itself (its scheduler, its job
  threads and its benchmark sampling; read from ``/proc/<pid>/stat`` every ``--poll`` seconds
  while it runs), and ``jobs_cpu_s``: the rest, the CPU seconds of the jobs' processes;
- ``scheduler_patch_env``: the value of ``VLSFOREST_SCHEDULER_PATCH`` the run saw (None: unset,
  the workflow's default, the patch on; ``workflow/rules/scheduler_patch.py``);
- ``max_rss_mb``: the largest resident set of any one process it waited for;
- ``jobs``: the jobs Snakemake ran (from its summary line);
- ``noop_rerun_wall_s`` and ``noop_rerun_jobs``: after a successful run, the wall time of the
  same command again without ``--forceall``/``--forcerun`` (a rerun with nothing to do: its
  start-up, the DAG build and the check of every output), and the jobs that rerun started (0);
- ``rules``: per rule of the jobs this run ran (read from Snakemake's job lines: ``rule NAME:``
  and its ``benchmark:`` file), the number of jobs, their summed ``cpu_time`` and wall ``s`` and
  the largest ``max_rss`` (MB) from those benchmark files; a rule whose jobs have no benchmark
  file has ``jobs`` only (the ``all`` target runs no command). The CPU seconds of the jobs outside
  their benchmark files follow as ``cpu_s_outside_benchmarked_rules`` (the total less the
  benchmark files' sum, Snakemake's own time included) and ``jobs_cpu_s_unsampled`` (the jobs'
  CPU seconds less that sum: the CPU a benchmark file misses after its job's last sample).

Snakemake samples a job's CPU time every 0.5 s for its first 15 s and every 30 s after that, so a
long job's benchmark file misses up to 30 s of its end; this script runs Snakemake with its
sampling interval set to ``--sample-interval`` seconds (default 0.5) throughout, which bounds the
miss to that interval per job. The outputs do not depend on it.

Usage::

    python benchmarks/bench_study.py [--workdir DIR] [--cores 2] [--configfile config/quick.yaml]
                                     [--forceall | --forcerun RULE …] [--sample-interval 0.5]
                                     [--note TEXT]

The run starts from what ``results/`` already holds; ``--forceall`` reruns every job (``rm -rf
results logs .snakemake`` gives a fresh-clone run), ``--forcerun`` the named rules' jobs and
those that depend on them (one rule measured on a finished study). The Snakemake is the one
installed for this Python (``.venv/bin/snakemake``), and that folder goes first on ``PATH`` so
that the jobs call the project's ``vlsforest``.
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

#: the first line of Snakemake's report of a job it starts
JOB_LINE = re.compile(r"^(?:local)?(?:rule|checkpoint) ([A-Za-z_][A-Za-z0-9_]*):$")
#: the benchmark file in that report
BENCHMARK_LINE = re.compile(r"^ {4}benchmark: (.+)$")

#: runs Snakemake's command line with its benchmark sampling interval set (argv[1]: seconds)
SNAKEMAKE_MAIN = (
    "import sys\n"
    "import snakemake.benchmark as b\n"
    "interval = float(sys.argv.pop(1))\n"
    "if interval > 0 and getattr(b.benchmarked, '__defaults__', None) and len(b.benchmarked.__defaults__) == 3:\n"
    "    b.benchmarked.__defaults__ = b.benchmarked.__defaults__[:2] + (interval,)\n"
    "from snakemake.cli import main\n"
    "sys.argv[0] = 'snakemake'\n"
    "sys.exit(main())\n"
)


def jobs_of_run(log: str) -> list[tuple[str, str | None]]:
    """The jobs a Snakemake run started, in order: (rule, benchmark file or None)."""
    jobs: list[list] = []
    for line in log.splitlines():
        m = JOB_LINE.match(line)
        if m:
            jobs.append([m.group(1), None])
            continue
        m = BENCHMARK_LINE.match(line)
        if m and jobs:
            jobs[-1][1] = m.group(1).strip()
    return [(rule, bench) for rule, bench in jobs]


def last_row(tsv: Path) -> dict | None:
    """The last record of a Snakemake benchmark file (None: no file or no record)."""
    try:
        with open(tsv, newline="") as fh:
            rows = list(csv.DictReader(fh, delimiter="\t"))
    except OSError:
        return None
    return rows[-1] if rows else None


def _number(value) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):  # Snakemake writes NA for a job faster than one sample
        return 0.0


def rule_table(workdir: Path, jobs: list[tuple[str, str | None]]) -> dict:
    """Per rule of ``jobs`` (from :func:`jobs_of_run`): jobs, and from their benchmark files
    (relative to ``workdir``) the summed cpu_time and s and the largest max_rss (MB); a rule
    without benchmark files has ``jobs`` only."""
    out: dict = {}
    for rule, bench in jobs:
        entry = out.setdefault(rule, {"jobs": 0})
        entry["jobs"] += 1
        if bench is None:
            continue
        r = last_row(workdir / bench) or {}
        entry["cpu_s"] = round(entry.get("cpu_s", 0.0) + _number(r.get("cpu_time")), 1)
        entry["wall_s"] = round(entry.get("wall_s", 0.0) + _number(r.get("s")), 1)
        entry["max_rss_mb"] = round(max(entry.get("max_rss_mb", 0.0), _number(r.get("max_rss"))), 1)
    return dict(sorted(out.items()))


def own_cpu_s(pid: int) -> float | None:
    """User + system CPU seconds of process ``pid`` itself (not its children), or None."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def noop_rerun(cmd: list, args, env: dict) -> dict:
    """Wall time and jobs of ``cmd`` again without its force flags, on the finished run."""
    again = [c for c in cmd if c != "--forceall"]
    if args.forcerun:
        i = again.index("--forcerun")
        again = again[:i] + again[i + 1 + len(args.forcerun):]
    t0 = time.perf_counter()
    proc = subprocess.run(again, cwd=args.workdir, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    out = proc.stdout + proc.stderr
    m = re.findall(r"(\d+) of (\d+) steps \(100%\) done", out)
    return {"noop_rerun_wall_s": round(wall, 2), "noop_rerun_jobs": int(m[-1][1]) if m else 0,
            "noop_rerun_exit_code": proc.returncode}


def main(argv) -> int:
    ap = argparse.ArgumentParser(prog="bench_study", description=__doc__.split("\n\n")[0])
    ap.add_argument("--workdir", type=Path, default=benchresult.REPO, help="the checkout to run in")
    ap.add_argument("--cores", type=int, default=2)
    ap.add_argument("--configfile", action="append", default=[], help="config file(s) over config/config.yaml")
    ap.add_argument("--forceall", action="store_true", help="rerun every job")
    ap.add_argument("--forcerun", nargs="+", default=[], metavar="RULE",
                    help="rerun these rules' jobs (and what depends on them)")
    ap.add_argument("--sample-interval", type=float, default=0.5,
                    help="seconds between Snakemake's samples of a job's CPU (0: Snakemake's own default)")
    ap.add_argument("--poll", type=float, default=0.25, help="seconds between reads of Snakemake's own CPU time")
    ap.add_argument("--note", default=None, help="a remark stored with the row")
    args = ap.parse_args(argv)
    bindir = Path(sys.executable).parent
    cmd = [sys.executable, "-c", SNAKEMAKE_MAIN, str(args.sample_interval), "--cores", str(args.cores)]
    for c in args.configfile:
        cmd += ["--configfile", c]
    if args.forceall:
        cmd.append("--forceall")
    if args.forcerun:
        cmd += ["--forcerun", *args.forcerun]
    env = dict(os.environ, PATH=f"{bindir}{os.pathsep}{os.environ.get('PATH', '')}")
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    log_path = args.workdir / "logs" / "bench_study.log"
    log_path.parent.mkdir(parents=True, exist_ok=True)
    with open(log_path, "w") as log_fh:
        proc = subprocess.Popen(cmd, cwd=args.workdir, env=env, stdout=log_fh, stderr=subprocess.STDOUT, text=True)
        own = 0.0
        while proc.poll() is None:
            own = max(own, own_cpu_s(proc.pid) or 0.0)
            time.sleep(args.poll)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    log = log_path.read_text()
    m = re.findall(r"(\d+) of (\d+) steps \(100%\) done", log)
    jobs = int(m[-1][1]) if m else 0
    rules = rule_table(args.workdir, jobs_of_run(log))
    inside = sum(r.get("cpu_s", 0.0) for r in rules.values())
    print(f"study: {wall:.0f} s wall, {cpu:.0f} CPU-s ({100 * cpu / max(wall, 1e-9):.0f} % of one core), "
          f"{jobs} jobs, exit {proc.returncode}")
    print(f"  Snakemake itself {own:.1f} CPU-s; jobs {cpu - own:.1f} CPU-s, of which {inside:.1f} in the "
          f"benchmark files")
    for name, r in rules.items():
        if "cpu_s" in r:
            print(f"  {name:28s} {r['jobs']:4d} jobs {r['cpu_s']:8.1f} CPU-s {r['wall_s']:8.1f} s "
                  f"max {r['max_rss_mb']:8.1f} MB")
        else:
            print(f"  {name:28s} {r['jobs']:4d} jobs (no benchmark file)")
    row = dict(workdir=str(args.workdir), configfiles=args.configfile, cores=args.cores,
               forceall=args.forceall, forcerun=args.forcerun, sample_interval_s=args.sample_interval,
               wall_s=round(wall, 1), cpu_s=round(cpu, 1), snakemake_cpu_s=round(own, 1),
               jobs_cpu_s=round(cpu - own, 1), max_rss_mb=round(after.ru_maxrss / 1024.0, 1), jobs=jobs,
               rules=rules, cpu_s_outside_benchmarked_rules=round(cpu - inside, 1),
               jobs_cpu_s_unsampled=round(cpu - own - inside, 1), exit_code=proc.returncode,
               scheduler_patch_env=os.environ.get("VLSFOREST_SCHEDULER_PATCH"))
    if proc.returncode == 0:
        row.update(noop_rerun(cmd, args, env))
        print(f"  no-op rerun: {row['noop_rerun_wall_s']:.1f} s, {row['noop_rerun_jobs']} jobs")
    if args.note:
        row["note"] = args.note
    benchresult.record(**row)
    if proc.returncode:
        print(log[-4000:], file=sys.stderr)
    return proc.returncode


if __name__ == "__main__":
    raise SystemExit(benchresult.run("bench_study", main))
