"""Benchmark: one diagnosis trace and one stored-hit evaluation on a plot of a finished study.

The diagnosis job keeps ray traces of a plot in memory (``sim.trace_hits``) and re-renders
detection candidates from them; this measures, for one plot of a workflow run's outputs, the
set-up (real observables), the trace of the simulation as given (time, sub-ray hits, memory held
after it), and one evaluation from stored hits (re-detection + observables), with the same
inputs the ``diagnose`` rule passes (scaled method, the scenario's extraction radius, the
config's region margin), and the split of that evaluation into re-detection and observables.
The evaluation (``evaluation_s``) is what the diagnosis pays per candidate it renders: its trace's
index of hits per pulse (``sim.hit_offsets``, ``index_s`` to make) is kept from the first
evaluation; the split re-detects without it (``redetect_s`` includes the indexing).

    python benchmarks/bench_diagnose_trace.py /path/to/study --plot P3 --scenario uls

``/path/to/study`` is a workflow directory after ``snakemake`` (``results/`` inside, default
config). About 3 min for P3 of the default forest on 2 cores.
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import time
from pathlib import Path

import benchresult


def _rss_gb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS"):
                return int(line.split()[1]) / 1e6
    return float("nan")


def _peak_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("study", type=Path, help="workflow directory with results/")
    ap.add_argument("--plot", default="P3")
    ap.add_argument("--scenario", default="uls", help="the scenario's name (its survey and recording)")
    ap.add_argument("--radius", type=float, default=None,
                    help="extraction radius (default: the scenario's extraction_radius_m in config/config.yaml)")
    ap.add_argument("--margin", type=float, default=1.0, help="region margin (config diagnosis.region_margin_m)")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)

    from vlsforest.diagnose import load_setup
    from vlsforest.diagnose.simulation import PlotSim

    study = a.study.resolve()
    if not (study / "results" / a.plot / "segment").is_dir():
        print(f"bench_diagnose_trace: {study}/results/{a.plot}/segment not found (run the workflow first)",
              file=sys.stderr)
        return 2
    radius = a.radius
    if radius is None:
        import yaml

        scenarios = yaml.safe_load((Path(__file__).resolve().parents[1] / "config" / "config.yaml").read_text())[
            "scenarios"]
        if a.scenario not in scenarios:
            print(f"bench_diagnose_trace: no scenario {a.scenario!r} in config/config.yaml (give --radius)",
                  file=sys.stderr)
            return 2
        radius = scenarios[a.scenario]["extraction_radius_m"]
    os.chdir(study)
    r = f"results/{a.plot}"
    setup = load_setup({"scenario": a.scenario, "seed": a.seed, "plots": {a.plot: {
        "real": f"results/forest/plots/{a.plot}/{a.scenario}.laz", "scene": f"{r}/scaled/scene/scene.yaml",
        "survey": f"{r}/surveys/{a.scenario}.yaml", "segment": f"{r}/segment",
        "radius": radius, "margin": a.margin}}})
    t0 = time.perf_counter()
    ps = PlotSim(setup.plots[0], setup.seed, setup.workers, lambda m: print(m, flush=True))
    print(f"set-up (real observables of {len(ps.trees)} trees): {time.perf_counter() - t0:.1f} s")
    t0 = time.perf_counter()
    ps.pin({})
    ps.features({})
    print(f"trace + first evaluation: {time.perf_counter() - t0:.1f} s; held after it {_rss_gb():.2f} GB, "
          f"peak {_peak_gb():.2f} GB")
    pulses, hits = ps.trace({})  # the pinned baseline's trace, held in memory
    held = sum(v.nbytes for d in (pulses, hits) for v in d.values()) / 1e9
    print(f"the trace: {len(pulses['slot']):,} pulses with hits, {len(hits['pulse']):,} sub-ray hits, {held:.2f} GB")
    t0 = time.perf_counter()
    ps.features({"range_noise": {"sigma_m": 0.02}})
    evaluation_s = time.perf_counter() - t0
    print(f"one evaluation from stored hits (range noise 2 cm): {evaluation_s:.1f} s; "
          f"peak {_peak_gb():.2f} GB")
    # its two parts: re-detection, then the observables of the re-detected cloud
    from vlsforest.diagnose.features import cloud_arrays
    from vlsforest.sim import hit_offsets, redetect

    _, sv, _ = ps.setting({"range_noise": {"sigma_m": 0.02}})
    t0 = time.perf_counter()
    hit_offsets(pulses, hits)
    index_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    res = redetect(ps.parts, pulses, hits, sv, seed=ps.seed)
    t1 = time.perf_counter()
    ps.observables(cloud_arrays(res))
    t2 = time.perf_counter()
    print(f"  re-detection {t1 - t0:.1f} s ({len(res.points['xyz']):,} points; indexing the hits alone "
          f"{index_s:.2f} s), observables {t2 - t1:.1f} s")
    benchresult.record(plot=a.plot, scenario=a.scenario, trace_gb=held, evaluation_s=evaluation_s,
                       index_s=index_s, redetect_s=t1 - t0, observables_s=t2 - t1, peak_gb=_peak_gb())
    del res
    return 0


if __name__ == "__main__":
    sys.exit(benchresult.run("bench_diagnose_trace", main))
