"""Benchmark: the start-up of the workflow's jobs, and how many jobs of each rule a study runs.

Each job of the workflow is one ``vlsforest <stage>`` process. Measured here, without running
the study:

1. **Start-up per rule**: the CPU seconds (user + system) of a fresh Python that imports what the
   rule's command imports on its way to its work (:data:`RULE_IMPORTS`: the CLI, the command's
   module and the library modules and packages its path through ``run`` imports), the least of
   ``--repeats`` processes; beside it ``python -c pass`` and ``vlsforest <stage> --help`` (the
   command's parser alone).
2. **Jobs per rule** of the study: ``snakemake -n --forceall`` with this checkout's ``Snakefile``
   and its default config (or ``--configfile``) in an empty temporary folder: nothing runs and
   nothing is written beside it; its CPU seconds are Snakemake's start-up and DAG build.
3. **The estimate**: jobs × start-up per rule, and its sum over the study (``startup_cpu_s``).
4. With ``--snakemake-jobs N``: **Snakemake's own CPU per job**, from a workflow of N independent
   jobs that each sleep ``--job-seconds`` (and write a benchmark file, as the study's jobs do)
   run on ``--cores`` in a temporary folder, once with Snakemake's scheduler as installed
   (``VLSFOREST_SCHEDULER_PATCH=0``) and once with the workflow's scheduler patch
   (``workflow/rules/scheduler_patch.py``, on by default): wall time and the
   CPU seconds of the Snakemake process itself (``bench_study.own_cpu_s``; its start-up and DAG
   build included) per run.

    python benchmarks/bench_job_startup.py [--configfile config/quick.yaml] [--repeats 3]
                                           [--snakemake-jobs 322 --job-seconds 1 --cores 2]

The Python and Snakemake are those of this interpreter's environment; ``PYTHONPATH`` decides
which ``vlsforest`` is imported (the checkout's ``workflow/`` for a checkout's code).
"""

from __future__ import annotations

import argparse
import os
import re
import resource
import subprocess
import sys
import tempfile
from pathlib import Path

import benchresult
from bench_study import SNAKEMAKE_MAIN, own_cpu_s

#: the workflow of ``--snakemake-jobs``: N sleeping jobs, the scheduler patch applied as the study applies it
SLEEP_WORKFLOW = """\
import importlib.util
spec = importlib.util.spec_from_file_location("scheduler_patch", {patch!r})
patch = importlib.util.module_from_spec(spec)
spec.loader.exec_module(patch)
patch.apply_if_enabled()

rule all:
    input: expand("out/{{i}}.txt", i=range({n}))

rule job:
    output: "out/{{i}}.txt"
    log: "logs/job/{{i}}.log"
    benchmark: "logs/benchmarks/job/{{i}}.tsv"
    resources: mem_mb=lambda wc: 1000
    params: x=lambda wc: int(wc.i) * 2
    shell: "sleep {seconds}; echo {{params.x}} > {{output}} 2> {{log}}"
"""

#: per rule: its stage (``vlsforest <stage> --help``) and the modules its command imports
RULE_IMPORTS = {
    "synth_plot": ("synth", ["vlsforest.commands.synth", "vlsforest.synth.record"]),
    "forest_truth": ("collect", ["vlsforest.commands.collect", "vlsforest.synth.record", "pandas"]),
    "segment": ("segment", ["vlsforest.commands.segment", "vlsforest.segment"]),
    "targets": ("scene", ["vlsforest.commands.scene", "vlsforest.extract", "vlsforest.io.las", "pandas"]),
    "stems": ("stems", ["vlsforest.commands.stems", "vlsforest.stems", "vlsforest.io.las", "vlsforest.io.mesh",
                        "pandas"]),
    "crowns": ("scene", ["vlsforest.commands.scene", "vlsforest.scene", "vlsforest.io.las", "vlsforest.io.npz",
                         "pandas"]),
    "pad": ("pad", ["vlsforest.commands.pad", "vlsforest.pad", "vlsforest.io.vox"]),
    "pad_virtual": ("pad", ["vlsforest.commands.pad", "vlsforest.pad", "vlsforest.pad_validation",
                            "vlsforest.io.vox"]),
    "pad_summary": ("collect", ["vlsforest.commands.collect", "vlsforest.pad_validation", "pandas"]),
    "voxels": ("voxels", ["vlsforest.commands.voxels", "vlsforest.voxels", "vlsforest.io.voxel_model", "pandas"]),
    "voxel_counts": ("collect", ["vlsforest.commands.collect", "vlsforest.io.voxel_model", "pandas"]),
    "scene": ("scene", ["vlsforest.commands.scene", "vlsforest.scene", "vlsforest.io.voxel_model",
                        "vlsforest.io.las", "pandas"]),
    "survey": ("plan", ["vlsforest.commands.plan", "vlsforest.sim.planning", "vlsforest.sim.scene",
                        "vlsforest.sim.survey", "pandas"]),
    "simulate": ("simulate", ["vlsforest.commands.simulate", "vlsforest.sim", "vlsforest.io.las"]),
    "sim_trees": ("extract", ["vlsforest.commands.extract", "vlsforest.extract", "vlsforest.metrics",
                              "vlsforest.io.las"]),
    "extract_reference": ("extract", ["vlsforest.commands.extract", "vlsforest.extract", "vlsforest.metrics",
                                      "vlsforest.io.las", "vlsforest._treecells"]),
    "sim_times": ("collect", ["vlsforest.commands.collect", "pandas"]),
    "collect_metrics": ("collect", ["vlsforest.commands.collect", "pandas"]),
    "stats": ("stats", ["vlsforest.commands.stats", "vlsforest.stats"]),
    "figures": ("report", ["vlsforest.commands.report", "vlsforest.report.figures", "vlsforest.stats"]),
    "diagnose": ("diagnose", ["vlsforest.commands.diagnose", "vlsforest.diagnose", "vlsforest.diagnose.figure"]),
    "experiment_tls_step": ("experiment", ["vlsforest.commands.experiment", "vlsforest.experiments.tls_step"]),
    "experiment_recording_detector": ("experiment", ["vlsforest.commands.experiment",
                                                     "vlsforest.experiments.recording_detector"]),
    "experiment_crown_outline": ("experiment", ["vlsforest.commands.experiment",
                                                "vlsforest.experiments.crown_outline"]),
    "experiment_shift_room": ("experiment", ["vlsforest.commands.experiment", "vlsforest.experiments.shift_room"]),
    "experiment_cog_shift": ("experiment", ["vlsforest.commands.experiment", "vlsforest.experiments.cog_shift"]),
    "experiment_cog_parts": ("experiment", ["vlsforest.commands.experiment", "vlsforest.experiments.cog_parts",
                                            "vlsforest.sim"]),
    "experiment_reseed": ("experiment", ["vlsforest.commands.experiment", "vlsforest.experiments.reseed",
                                         "vlsforest.sim"]),
}


def cpu_of(cmd: list[str], repeats: int, env: dict | None = None) -> float:
    """The least user + system CPU seconds of ``repeats`` runs of ``cmd`` (a failed run raises)."""
    best = float("inf")
    for _ in range(repeats):
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        best = min(best, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime))
    return best


def snakemake_overhead(n: int, seconds: float, cores: int, patched: bool, env: dict) -> dict:
    """Run :data:`SLEEP_WORKFLOW` with ``n`` jobs in a temporary folder: wall time, the Snakemake
    process's own CPU seconds and those of everything it started."""
    import time

    run_env = dict(env)
    run_env["VLSFOREST_SCHEDULER_PATCH"] = "1" if patched else "0"
    patch = str(benchresult.REPO / "workflow" / "rules" / "scheduler_patch.py")
    with tempfile.TemporaryDirectory(prefix="bench_snakemake_") as tmp:
        Path(tmp, "Snakefile").write_text(SLEEP_WORKFLOW.format(patch=patch, n=n, seconds=seconds))
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        proc = subprocess.Popen([sys.executable, "-c", SNAKEMAKE_MAIN, "0.5", "--cores", str(cores)], cwd=tmp,
                                env=run_env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        own = 0.0
        while proc.poll() is None:
            own = max(own, own_cpu_s(proc.pid) or 0.0)
            time.sleep(0.25)
        wall = time.perf_counter() - t0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode:
        raise RuntimeError(f"the sleeping workflow failed (exit {proc.returncode})")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"scheduler_patch": patched, "jobs": n, "job_seconds": seconds, "cores": cores, "wall_s": round(wall, 1),
            "snakemake_cpu_s": round(own, 1), "cpu_s": round(cpu, 1),
            "snakemake_cpu_s_per_job": round(own / max(n, 1), 4)}


def job_counts(text: str) -> dict[str, int]:
    """Jobs per rule from the first ``Job stats:`` table of Snakemake's output."""
    counts: dict[str, int] = {}
    lines = text.splitlines()
    try:
        start = lines.index("Job stats:") + 3  # title, header, rule of dashes
    except ValueError:
        return counts
    for line in lines[start:]:
        m = re.match(r"^(\S+)\s+(\d+)$", line)
        if not m or m.group(1) == "total":
            break
        counts[m.group(1)] = int(m.group(2))
    return counts


def main(argv) -> int:
    ap = argparse.ArgumentParser(prog="bench_job_startup", description=__doc__.split("\n\n")[0])
    ap.add_argument("--configfile", default=None, help="config file of the study (default: config/config.yaml)")
    ap.add_argument("--repeats", type=int, default=3, help="fresh processes per measurement (the least counts)")
    ap.add_argument("--snakemake-jobs", type=int, default=0, help="also time Snakemake on this many sleeping jobs")
    ap.add_argument("--job-seconds", type=float, default=1.0, help="seconds each sleeping job sleeps")
    ap.add_argument("--cores", type=int, default=2, help="cores of the sleeping workflow's runs")
    args = ap.parse_args(argv)
    py = sys.executable
    bindir = Path(py).parent
    env = dict(os.environ, PATH=f"{bindir}{os.pathsep}{os.environ.get('PATH', '')}")
    with tempfile.TemporaryDirectory(prefix="bench_job_startup_") as tmp:
        cmd = [str(bindir / "snakemake"), "-s", str(benchresult.REPO / "Snakefile"), "-n", "--forceall",
               "--cores", "2"]
        if args.configfile:
            cmd += ["--configfile", str(Path(args.configfile).resolve())]
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        proc = subprocess.run(cmd, cwd=tmp, env=env, capture_output=True, text=True)
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode:
        print(proc.stderr[-3000:], file=sys.stderr)
        return 1
    dag_cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    counts = job_counts(proc.stdout + "\n" + proc.stderr)
    bare = cpu_of([py, "-c", "pass"], args.repeats, env)
    helps: dict[str, float] = {}
    rows = []
    for rule, n in counts.items():
        if rule not in RULE_IMPORTS:
            rows.append({"rule": rule, "jobs": n, "startup_cpu_s": None, "help_cpu_s": None, "total_cpu_s": None})
            continue
        stage, modules = RULE_IMPORTS[rule]
        if stage not in helps:
            helps[stage] = cpu_of([py, "-m", "vlsforest.cli", stage, "--help"], args.repeats, env)
        startup = cpu_of([py, "-c", "import " + ", ".join(["vlsforest.cli", *modules])], args.repeats, env)
        rows.append({"rule": rule, "jobs": n, "startup_cpu_s": round(startup, 2), "help_cpu_s": round(helps[stage], 2),
                     "total_cpu_s": round(n * startup, 1)})
    total = sum(r["total_cpu_s"] or 0.0 for r in rows)
    jobs = sum(r["jobs"] for r in rows)
    print(f"study DAG: {jobs} jobs (dry run {dag_cpu:.1f} CPU-s); python -c pass {bare:.2f} CPU-s")
    for r in rows:
        if r["startup_cpu_s"] is None:
            print(f"  {r['rule']:30s} {r['jobs']:4d} jobs (runs no command)")
        else:
            print(f"  {r['rule']:30s} {r['jobs']:4d} jobs × {r['startup_cpu_s']:5.2f} CPU-s start-up "
                  f"= {r['total_cpu_s']:6.1f} (parser alone {r['help_cpu_s']:.2f})")
    print(f"start-up of all jobs: {total:.0f} CPU-s")
    tables = {"rules": rows}
    if args.snakemake_jobs > 0:
        tables["snakemake"] = []
        for patched in (False, True):
            r = snakemake_overhead(args.snakemake_jobs, args.job_seconds, args.cores, patched, env)
            tables["snakemake"].append(r)
            print(f"Snakemake, {r['jobs']} jobs of {r['job_seconds']:g} s on {r['cores']} cores, scheduler patch "
                  f"{'on' if patched else 'off'}: {r['wall_s']:.0f} s wall, itself {r['snakemake_cpu_s']:.1f} CPU-s "
                  f"({r['snakemake_cpu_s_per_job']:.3f} per job)")
    benchresult.record(configfile=args.configfile, repeats=args.repeats, jobs=jobs, dry_run_cpu_s=round(dag_cpu, 1),
                       python_bare_cpu_s=round(bare, 3), startup_cpu_s=round(total, 1), tables=tables)
    return 0


if __name__ == "__main__":
    raise SystemExit(benchresult.run("bench_job_startup", main))
