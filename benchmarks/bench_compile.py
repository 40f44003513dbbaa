"""Benchmark: what the simulator spends compiling its kernels in a process that finds no cache.

The simulator's numerical kernels are numba functions, compiled at their first call and cached
(``cache=True``: in ``__pycache__`` beside the sources, or under ``NUMBA_CACHE_DIR``). A process
that finds no cache compiles them; on a fresh checkout each workflow job that starts before the
cache is written does. Measured here: one process that runs ``vlsforest simulate`` twice on the
demo scene (``vlsforest demo``, its crown traced in the sparse voxel grid) and a ULS flight over it
(``vlsforest plan``), once with HELIOS++ 1.0.8's peak rule and once with the physical detector:

- **cold**: with an empty cache folder (a new one for each of ``--repeats`` runs; the least CPU
  time is kept), and the seconds numba's compile events report per kernel compiled from Python
  (its callees' compilation included);
- **warm**: the same process again with the cache a cold run wrote;
- their CPU seconds (user + system) and the difference, the compilation's cost per cold process.

    python benchmarks/bench_compile.py [--repeats 2] [--top 12]

``PYTHONPATH`` decides which ``vlsforest`` is measured (the checkout's ``workflow/`` for a
checkout's code).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
from pathlib import Path

import benchresult

#: the child: run the simulations in-process and write numba's compile events (seconds per
#: dispatcher, outermost compilations only) as JSON to argv[1]
CHILD = r"""
import json, sys, time
from numba.core import event
from vlsforest.cli import main

depth, starts, seconds = [0], [], {}

class Listener(event.Listener):
    def on_start(self, ev):
        depth[0] += 1
        starts.append(time.process_time())
    def on_end(self, ev):
        depth[0] -= 1
        t = time.process_time() - starts.pop()
        if depth[0] == 0:
            d = ev.data["dispatcher"].py_func
            name = f"{d.__module__}.{d.__qualname__}"
            seconds[name] = seconds.get(name, 0.0) + t

out, work = sys.argv[1], sys.argv[2]
with event.install_listener("numba:compile", Listener()):
    for survey in ("survey.yaml", "survey_physical.yaml"):
        rc = main(["simulate", f"{work}/scene/scene.yaml", f"{work}/{survey}", "-o", f"{work}/{survey}.laz",
                   "--quiet", "--workers", "1"])
        if rc != 0:
            sys.exit(rc)
with open(out, "w") as fh:
    json.dump(seconds, fh)
"""

SCENARIO = {"scanner": "riegl_minivux1uav", "pattern": "double_grid", "altitude_m": 40, "speed_mps": 8,
            "line_spacing_m": 28, "n_lines": 1, "margin_m": 0, "overrides": {"prf_hz": 20000}}


def _prepare(work: Path) -> None:
    """The demo scene (crown in the sparse grid) and the flight in both detector modes."""
    import yaml

    from vlsforest.cli import main

    if main(["demo", "-o", str(work / "scene" / "scene.yaml"), "--seed", "1"]) != 0:
        raise SystemExit("vlsforest demo failed")
    scene = yaml.safe_load((work / "scene" / "scene.yaml").read_text())
    scene["voxel_backend"] = "grid"
    (work / "scene" / "scene.yaml").write_text(yaml.safe_dump(scene, sort_keys=False))
    (work / "scenario.yaml").write_text(yaml.safe_dump(SCENARIO, sort_keys=False))
    if main(["plan", "--scene", str(work / "scene" / "scene.yaml"), "--scenario", str(work / "scenario.yaml"),
             "-o", str(work / "survey.yaml")]) != 0:
        raise SystemExit("vlsforest plan failed")
    for mode, name in (("helios_v1", "survey.yaml"), ("physical", "survey_physical.yaml")):
        sv = yaml.safe_load((work / "survey.yaml").read_text())
        sv["detector"] = {**(sv.get("detector") or {}), "mode": mode}
        (work / name).write_text(yaml.safe_dump(sv, sort_keys=False))


def _child(work: Path, cache: Path, events: Path) -> float:
    """CPU seconds (user + system) of one child process with numba's cache in ``cache``."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    proc = subprocess.run([sys.executable, "-c", CHILD, str(events), str(work)], env=env)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise SystemExit(f"the simulation failed (exit {proc.returncode})")
    return (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=2, help="cold runs, each with a new cache; the least is kept")
    ap.add_argument("--top", type=int, default=12, help="kernels listed, by compile seconds")
    a = ap.parse_args(argv)
    if a.repeats < 1:
        ap.error("--repeats must be at least 1")
    with tempfile.TemporaryDirectory(prefix="bench-compile-") as tmp:
        work = Path(tmp)
        _prepare(work)
        cold, warm, kernels = [], [], None
        for r in range(a.repeats):
            cache = work / f"cache{r}"
            events = work / f"events{r}.json"
            cold.append(_child(work, cache, events))
            got = json.loads(events.read_text())
            if kernels is None or sum(got.values()) < sum(kernels.values()):
                kernels = got
            warm.append(_child(work, cache, work / f"warm{r}.json"))
    top = sorted(kernels.items(), key=lambda kv: -kv[1])[:a.top]
    cold_s, warm_s = min(cold), min(warm)
    print(f"cold {cold_s:.1f} CPU-s, warm {warm_s:.1f} CPU-s: compiling costs {cold_s - warm_s:.1f} CPU-s "
          f"per process without a cache (numba's compile events: {sum(kernels.values()):.1f} s)")
    for name, s in top:
        print(f"  {s:7.2f} s  {name}")
    benchresult.record(cold_cpu_s=round(cold_s, 2), warm_cpu_s=round(warm_s, 2),
                       compile_cpu_s=round(cold_s - warm_s, 2), repeats=a.repeats,
                       compile_events_s=round(sum(kernels.values()), 2),
                       kernels=[{"kernel": n, "compile_s": round(s, 2)} for n, s in top])
    return 0


if __name__ == "__main__":
    raise SystemExit(benchresult.run("bench_compile", main))
