"""Benchmark of the whole simulator (a script, not a test): pulses/s, sub-rays/s, overhead
over the raw ray cast, peak memory.

Cases (each runs in its own process, so that peak RSS is per case):

- ``uls``: the real Bretten spruce F_BR08_08 (0.25 m ``.vox`` crown, fixed cubes, 6,185
  voxels → Embree triangles; Poisson stem OBJ; ground plane at the stem base, tree ± 20 m)
  scanned by the study's ULS (miniVUX-1UAV preset, 70 m, 5 m/s, one double grid of lines
  28 m apart over the plot ± 5 m), 19 sub-rays, full waveform, LAS written.
  Yardsticks: HELIOS++ 2.0.1 ≈ 300 k pulses/s (one core); raw embreex ≈ 670 k pulses/s
  (12.8 M sub-rays/s, one core) over the same tree.
- ``als``: a simple ALS scene: VQ-780i at 700 m, 51 m/s, one 100 m line over a ground plane
  wider than the ±30° swath (every pulse meets the scene) with the same tree in the middle.
  Yardstick: HELIOS++ 2.0.1 ≈ 160 k pulses/s for simple ALS scenes (one core).
- ``crown20m``: a synthetic 0.02 m crown of ≈ 20 M voxels (``bench_voxelgrid.crown_cells``),
  traced by the sparse voxel grid, + ground plane, scanned by a short ULS (two crossing
  lines). Target: peak RSS ≤ 4 GB.

Each case runs the survey with 1 worker pinned to one CPU (comparable with the one-core
yardsticks), then with 2 workers (both cores). In the 1-worker process it also rebuilds exactly
the sub-rays the engine traces (same pulses, same beam-box cull, same sub-ray fan, same
blocks) and times only the cast: ``Scene.trace`` (our combined Embree + plane + grid cast) and,
where the scene fits in triangles, a bare ``embreex`` scene with the same triangles (voxels as
12 triangles each, stem, 2 ground triangles) ``run(..., output=1)``. The ratio sim-rate /
raw-rate is the share of time spent in the cast (target ≥ 0.5: everything beyond the cast costs
at most as much as the cast).

Pulses/s are over *emitted* pulses (the engine, like HELIOS++, skips pulses whose beam cone
misses the scene box; both counts are printed); sub-rays/s are over *traced* sub-rays.

Run: ``python benchmarks/bench_sim.py`` (all cases), or ``--case uls|als|crown20m``;
``--profile`` adds a cProfile summary of the 1-worker simulation.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import benchresult

HERE = Path(__file__).resolve().parent
REAL = HERE.parent.parent / "shared" / "data" / "real"  # <repo>/../shared/data/real
CASES = ("uls", "als", "crown20m")
YARDSTICK = {
    "uls": "HELIOS++ 300 k pulses/s; raw embreex 670 k pulses/s = 12.8 M sub-rays/s (1 core)",
    "als": "HELIOS++ 160 k pulses/s (1 core)",
    "crown20m": "peak RSS <= 4 GB",
}


def _rss_gb(who=None) -> float:
    """Peak RSS in GB (ru_maxrss is KiB on Linux); ``who`` RUSAGE_SELF or RUSAGE_CHILDREN."""
    who = resource.RUSAGE_SELF if who is None else who
    return resource.getrusage(who).ru_maxrss * 1024 / 1e9


# ----------------------------------------------------------------------------- scenes
def _bretten_parts(ground_extent_half=(20.0, 20.0)):
    """Scene parts of F_BR08_08 with a ground plane at the stem base; returns (cfg, ground_z, centre)."""
    from vlsforest.io.mesh import read_mesh

    obj = REAL / "F_BR08_08_stem_Poisson.obj"
    vox = REAL / "F_BR08_08_crown_250.vox"
    if not (obj.is_file() and vox.is_file()):
        sys.exit(f"bench_sim: real data absent ({REAL}); the uls/als cases need F_BR08_08")
    v = read_mesh(obj).vertices
    gz = float(v[:, 2].min())
    cx = 0.5 * float(v[:, 0].min() + v[:, 0].max())
    cy = 0.5 * float(v[:, 1].min() + v[:, 1].max())
    hx, hy = ground_extent_half
    cfg = {"parts": [
        {"id": 1, "type": "plane", "z": gz, "extent": [cx - hx, cy - hy, cx + hx, cy + hy], "name": "ground"},
        {"id": 2, "type": "mesh", "path": str(obj), "name": "stem"},
        {"id": 3, "type": "vox", "path": str(vox), "mode": "fixed", "name": "crown"},
    ]}
    return cfg, gz, (cx, cy)


def build_case(case: str):
    """(scene, survey, warm-up survey, description) of a benchmark case; the warm-up survey is a
    short pass over the middle of the scene (its pulses hit the tree, so that every compiled
    kernel is loaded before the timed runs)."""
    from vlsforest.sim import Scene, survey_from_dict
    from vlsforest.sim.planning import plan_survey

    if case == "uls":
        cfg, gz, (cx, cy) = _bretten_parts()
        scene = Scene.from_dict(cfg)
        scen = dict(scanner="riegl_minivux1uav", pattern="double_grid", altitude_m=70.0, speed_mps=5.0,
                    line_spacing_m=28.0, margin_m=5.0)
        survey = survey_from_dict(plan_survey(scen, [cx - 20, cy - 20, cx + 20, cy + 20], gz))
        warm = survey_from_dict(plan_survey(dict(scen, margin_m=0.3, n_lines=1), [cx, cy, cx, cy], gz))
        desc = ("F_BR08_08 (6,185 fixed 0.25 m voxels as triangles + stem OBJ + ground ±20 m); "
                "miniVUX-1UAV 70 m, 5 m/s, double grid 3+3 lines 28 m apart")
    elif case == "als":
        cfg, gz, (cx, cy) = _bretten_parts(ground_extent_half=(450.0, 60.0))
        scene = Scene.from_dict(cfg)
        scen = dict(scanner="riegl_vq780i", pattern="parallel", altitude_m=700.0, speed_mps=51.0,
                    line_spacing_m=175.0, margin_m=10.0, n_lines=1)
        survey = survey_from_dict(plan_survey(scen, [cx - 40, cy - 40, cx + 40, cy + 40], gz))
        warm = survey_from_dict(plan_survey(dict(scen, margin_m=0.3), [cx, cy, cx, cy], gz))
        desc = ("ground plane 900 m × 120 m (wider than the ±30° swath: every pulse is traced) + F_BR08_08; "
                "VQ-780i 700 m, 51 m/s, 1 MHz, one 100 m line")
    elif case == "crown20m":
        sys.path.insert(0, str(HERE))
        from bench_voxelgrid import CROWN_CENTRE, CROWN_HALF, crown_cells

        t0 = time.perf_counter()
        ijk, origin = crown_cells(0.02, 0.04, 0.26, seed=1)
        t_gen = time.perf_counter() - t0
        scene = Scene()
        scene.add_plane(1, 0.0, [-20.0, -20.0, 20.0, 20.0])
        scene.add_voxels(3, ijk, origin, 0.02)
        n_vox = len(ijk)
        del ijk
        t0 = time.perf_counter()
        scene.grids  # build the sparse grid now, not inside the timed run
        t_build = time.perf_counter() - t0
        scen = dict(scanner="riegl_minivux1uav", pattern="double_grid", altitude_m=70.0, speed_mps=5.0,
                    line_spacing_m=28.0, margin_m=5.0, n_lines=1)
        survey = survey_from_dict(plan_survey(scen, [-20, -20, 20, 20], 0.0))
        warm = survey_from_dict(plan_survey(dict(scen, margin_m=0.3), [0, 0, 0, 0], 0.0))
        desc = (f"synthetic 0.02 m crown {2 * CROWN_HALF[0]:.0f}×{2 * CROWN_HALF[1]:.0f}×{2 * CROWN_HALF[2]:.0f} m "
                f"centred at z {CROWN_CENTRE[2]:.0f} m: {n_vox:,} voxels (generated {t_gen:.1f} s, grid built "
                f"{t_build:.1f} s, {sum(g.nbytes for g in scene.grids) / 1e6:.0f} MB) + ground ±20 m; "
                "miniVUX 70 m, two crossing 50 m lines")
    else:
        raise ValueError(case)
    return scene, survey, warm, desc


# ----------------------------------------------------------------------------- raw cast
def _bare_embree(scene):
    """A bare embreex scene with the scene's triangles (voxels as 12 triangles, planes as 2), or None."""
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh
    import numpy as np

    from vlsforest.sim.scene_geometry import PLANE_FACES

    if not all(scene.tracer.routing):
        return None, None  # the big voxel sets are traced by the grid: no triangle equivalent
    lo, hi = scene.bounds()
    shift = 0.5 * (lo + hi)
    sc = rtcore_scene.EmbreeScene()
    parts = []
    for m in scene.geometry.meshes:
        TriangleMesh(sc, (m.vertices - shift).astype(np.float32), m.faces.astype(np.int32))
        parts.append(m.part)
    for v in scene.geometry.voxels:
        pieces = list(v.triangle_chunks(shift))
        TriangleMesh(sc, np.concatenate([c[0] for c in pieces]), np.concatenate([c[1] for c in pieces]))
        parts.append(v.part)
    for p in scene.geometry.planes:
        TriangleMesh(sc, (p.corners() - shift).astype(np.float32), PLANE_FACES)
        parts.append(p.part)
    return (sc, shift), np.asarray(parts, dtype=np.int32)


def raw_cast(scene, survey, block_slots: int = 20000, repeat: int = 2):
    """Rebuild the engine's traced sub-rays block by block (same pulses, cull, fan and blocks),
    time each stage of their making and the bare casts (each cast ``repeat`` times per block,
    keeping the fastest, to damp interference from other processes). Returns seconds and counts."""
    import numpy as np

    from vlsforest.sim.beam import subray_directions, subray_pattern
    from vlsforest.sim.engine import DetectorOptions, _beam_meets_box

    beam = survey.scanner.beam
    pat = subray_pattern(beam.sample_quality, beam.divergence_mrad, beam.orientation_deg,
                         ring_scale=DetectorOptions.from_dict(survey.detector).ring_scale)
    max_off = float(np.abs(pat.offsets).max()) * np.sqrt(2.0)  # as the engine
    lo, hi = scene.bounds()
    bare, bare_parts = _bare_embree(scene)
    out = dict(t_pulses=0.0, t_cull=0.0, t_fan=0.0, t_trace=0.0, t_embree=0.0, n_rays=0, n_hit_trace=0,
               n_hit_embree=0, n_same_part=0, has_embree=bare is not None)
    if bare is not None:  # build the BVH outside the timing
        bare[0].run(np.zeros((1, 3), np.float32), np.array([[0, 0, -1]], np.float32), output=1)
    scene.trace(np.zeros((1, 3)), np.array([[0.0, 0.0, -1.0]]))
    for start in range(0, survey.n_slots, block_slots):
        t0 = time.perf_counter()
        b = survey.pulses(start, min(start + block_slots, survey.n_slots))
        t1 = time.perf_counter()
        live = np.flatnonzero(_beam_meets_box(b.origin, b.direction, lo, hi, max_off))
        t2 = time.perf_counter()
        d = subray_directions(b.direction[live], b.scan_dir[live], pat).reshape(-1, 3)
        o = np.repeat(b.origin[live], pat.n, axis=0)
        t3 = time.perf_counter()
        best = np.inf
        for _ in range(repeat):
            t4 = time.perf_counter()
            t, part, _ = scene.trace(o, d, serial=True)  # as one worker traces
            best = min(best, time.perf_counter() - t4)
        out["t_pulses"] += t1 - t0
        out["t_cull"] += t2 - t1
        out["t_fan"] += t3 - t2
        out["t_trace"] += best
        out["n_rays"] += len(d)
        out["n_hit_trace"] += int(np.isfinite(t).sum())
        if bare is not None:
            o32 = (o - bare[1]).astype(np.float32)
            d32 = d.astype(np.float32)
            best = np.inf
            for _ in range(repeat):
                t5 = time.perf_counter()
                res = bare[0].run(o32, d32, output=1)
                best = min(best, time.perf_counter() - t5)
            out["t_embree"] += best
            gid = res["geomID"]
            out["n_hit_embree"] += int((gid >= 0).sum())
            pe = np.where(gid >= 0, bare_parts[np.maximum(gid, 0)], -1)
            out["n_same_part"] += int((pe == part).sum())
    return out


# ----------------------------------------------------------------------------- one case
def _cpu_s() -> float:
    """User + system CPU seconds of this process and its reaped children."""
    a = resource.getrusage(resource.RUSAGE_SELF)
    b = resource.getrusage(resource.RUSAGE_CHILDREN)
    return a.ru_utime + a.ru_stime + b.ru_utime + b.ru_stime


def _timed_run(scene, survey, workers: int, las_path: Path, repeat: int = 1, profile: bool = False):
    """Simulate + write LAS ``repeat`` times; the figures of the fastest repetition."""
    from vlsforest.sim import simulate, write_points

    best = None
    for _ in range(repeat):
        prof = None
        if profile:
            import cProfile

            prof = cProfile.Profile()
            prof.enable()
        c0 = _cpu_s()
        t0 = time.perf_counter()
        r = simulate(scene, survey, seed=1, workers=workers, keep_pulses=False)
        t1 = time.perf_counter()
        write_points(las_path, r)
        t2 = time.perf_counter()
        cpu = _cpu_s() - c0
        if prof is not None:
            prof.disable()
            import io
            import pstats

            s = io.StringIO()
            pstats.Stats(prof, stream=s).sort_stats("tottime").print_stats(16)
            print("  cProfile (1 worker, sorted by own time):")
            print("\n".join("    " + ln for ln in s.getvalue().splitlines()[4:32] if ln.strip()))
            profile = False
        run = dict(workers=workers, t_sim=t1 - t0, t_write=t2 - t1, t_total=t2 - t0, cpu=cpu,
                   n_pulses=int(r.timings["n_pulses"]), n_slots=int(survey.n_slots),
                   n_rays=int(r.timings["n_rays"]), n_points=int(r.timings["n_points"]),
                   las_mb=las_path.stat().st_size / 1e6)
        del r
        if best is None or run["t_total"] < best["t_total"]:
            best = run
    return best


def run_case(case: str, profile: bool = False, repeat: int = 2) -> dict:
    """Run one case: 1 worker pinned to one CPU + raw cast, then 2 workers. Returns the figures."""
    import numba

    cpus = sorted(os.sched_getaffinity(0))
    print(f"=== case {case}")
    t0 = time.perf_counter()
    scene, survey, warm, desc = build_case(case)
    t_setup = time.perf_counter() - t0
    sc = survey.scanner
    print(f"  {desc}")
    print(f"  scanner {sc.name}: {sc.emitter.prf_hz / 1e3:.0f} kHz, {sc.deflector.scan_freq_hz:.0f} lines/s, "
          f"±{sc.deflector.scan_angle_deg:.0f}°, BSQ {sc.beam.sample_quality}, "
          f"window {sc.detector.window_size_ns} ns; {survey.n_slots:,} pulse slots; "
          f"setup {t_setup:.1f} s; peak RSS after setup {_rss_gb():.2f} GB")
    # warm-up over the tree, with the serial (one worker) and the parallel grid kernel (numba
    # compilation is cached on disk but loaded per process; the Embree BVH is built lazily per
    # process)
    from vlsforest.sim import simulate

    for workers in (2, 1):
        w = simulate(scene, warm, seed=1, workers=workers)
    print(f"  warm-up: {w.timings['n_rays']:,} sub-rays, {w.timings['n_points']:,} points")
    res = dict(case=case, desc=desc, runs=[])
    with tempfile.TemporaryDirectory() as tmp:
        # ---- one worker on one CPU (numba threads and our grid kernel serial as well)
        os.sched_setaffinity(0, {cpus[0]})
        numba.set_num_threads(1)
        r1 = _timed_run(scene, survey, 1, Path(tmp) / "w1.las", repeat, profile)  # one worker: serial kernel
        raw = raw_cast(scene, survey, repeat=repeat)
        numba.set_num_threads(min(len(cpus), numba.config.NUMBA_NUM_THREADS))
        os.sched_setaffinity(0, set(cpus))
        r1["raw"] = raw
        res["runs"].append(r1)
        # ---- two workers (forked processes, one core each)
        if len(cpus) >= 2:
            res["runs"].append(_timed_run(scene, survey, 2, Path(tmp) / "w2.las", repeat))
    res["rss_self_gb"] = _rss_gb()
    res["rss_children_gb"] = _rss_gb(resource.RUSAGE_CHILDREN)
    _print_case(res)
    return res


def _print_case(res: dict) -> None:
    for r in res["runs"]:
        ns = r["n_rays"] / max(1, r["n_pulses"])
        traced = r["n_rays"] / 19.0
        print(f"  {r['workers']} worker(s): {r['n_pulses']:,} pulses emitted of {r['n_slots']:,} slots, "
              f"{r['n_rays']:,} sub-rays traced ({traced:,.0f} pulses × 19; {ns:.1f} per emitted pulse), "
              f"{r['n_points']:,} points")
        print(f"    simulate {r['t_sim']:.2f} s + LAS write {r['t_write']:.2f} s ({r['las_mb']:.0f} MB) = "
              f"{r['t_total']:.2f} s wall (CPU {r['cpu']:.2f} s) → {r['n_pulses'] / r['t_total'] / 1e3:,.0f} k emitted pulses/s, "
              f"{traced / r['t_total'] / 1e3:,.0f} k traced pulses/s, {r['n_rays'] / r['t_total'] / 1e6:.2f} M sub-rays/s")
        raw = r.get("raw")
        if raw:
            assert raw["n_rays"] == r["n_rays"], "raw cast rebuilt a different number of rays"
            tr = raw["n_rays"] / raw["t_trace"]
            print(f"    raw cast of the same {raw['n_rays']:,} sub-rays (1 core): Scene.trace {raw['t_trace']:.2f} s = "
                  f"{tr / 1e6:.2f} M rays/s ({tr / 19 / 1e3:,.0f} k pulses/s)")
            if raw["has_embree"]:
                te = raw["n_rays"] / raw["t_embree"]
                print(f"      bare embreex run(output=1) {raw['t_embree']:.2f} s = {te / 1e6:.2f} M rays/s "
                      f"({te / 19 / 1e3:,.0f} k pulses/s); hits {raw['n_hit_embree']:,} vs Scene.trace "
                      f"{raw['n_hit_trace']:,}; same part for {100 * raw['n_same_part'] / raw['n_rays']:.3f} % of rays")
            rest = r["t_sim"] - raw["t_pulses"] - raw["t_cull"] - raw["t_fan"] - raw["t_trace"]
            print(f"    time split (stages re-timed on their own, approximate): pulses {raw['t_pulses']:.2f} s, beam-box cull "
                  f"{raw['t_cull']:.2f} s, sub-ray fan {raw['t_fan']:.2f} s, cast {raw['t_trace']:.2f} s, "
                  f"energy+waveform+peaks+gather ≈ {rest:.2f} s, LAS {r['t_write']:.2f} s")
            rate = r["n_rays"] / r["t_total"]
            print(f"    ratio sim-rate / raw-rate: {rate / tr:.2f} vs Scene.trace"
                  + (f", {rate / te:.2f} vs bare embreex" if raw["has_embree"] else "") + " (target ≥ 0.50)")
    print(f"  peak RSS: this process {res['rss_self_gb']:.2f} GB, largest worker {res['rss_children_gb']:.2f} GB")


# ----------------------------------------------------------------------------- driver
def _table(results: list[dict]) -> str:
    head = (f"{'case':<9} {'wk':>2} {'emitted':>10} {'sub-rays':>11} {'time s':>7} {'k pulses/s':>10} "
            f"{'M rays/s':>8} {'CPU s':>6} {'k p/CPU-s':>9} {'raw trace':>9} {'raw embree':>10} {'ratio':>5} {'RSS GB':>6}  yardstick")
    lines = [head, "-" * len(head)]
    for res in results:
        for r in res["runs"]:
            raw = r.get("raw")
            rate = r["n_rays"] / r["t_total"]
            tr = raw["n_rays"] / raw["t_trace"] / 1e6 if raw else None
            te = raw["n_rays"] / raw["t_embree"] / 1e6 if raw and raw["has_embree"] else None
            ratio = rate / 1e6 / (te or tr) if raw else None
            rss = res["rss_self_gb"] if r["workers"] == 1 else max(res["rss_self_gb"], res["rss_children_gb"])
            lines.append(
                f"{res['case']:<9} {r['workers']:>2} {r['n_pulses']:>10,} {r['n_rays']:>11,} {r['t_total']:>7.2f} "
                f"{r['n_pulses'] / r['t_total'] / 1e3:>10,.0f} {rate / 1e6:>8.2f} {r['cpu']:>6.2f} "
                f"{r['n_pulses'] / r['cpu'] / 1e3:>9,.0f} "
                f"{(f'{tr:.2f}' if tr else '-'):>9} {(f'{te:.2f}' if te else '-'):>10} "
                f"{(f'{ratio:.2f}' if ratio else '-'):>5} {rss:>6.2f}  "
                + (YARDSTICK[res["case"]] if r["workers"] == 1 else ""))
    lines.append("k pulses/s over emitted pulses, wall clock; M rays/s over traced sub-rays; CPU s = user+system "
                 "seconds of all processes (k p/CPU-s: emitted pulses per CPU second, robust to other load on the "
                 "machine); raw = the same sub-rays cast alone on one core (M rays/s); ratio = sim rays/s ÷ raw "
                 "rays/s (bare embreex where available, else Scene.trace), target ≥ 0.50; times include the LAS write.")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", choices=("all",) + CASES, default="all")
    ap.add_argument("--profile", action="store_true", help="cProfile the 1-worker simulation")
    ap.add_argument("--repeat", type=int, default=2, help="repetitions per timing; the fastest is kept")
    ap.add_argument("--json", type=Path, help="write the figures of --case here (used by --case all)")
    args = ap.parse_args(argv)
    if args.case != "all":
        res = run_case(args.case, args.profile, args.repeat)
        if args.json:
            args.json.write_text(json.dumps(res))
        else:
            benchresult.record(cases=[res])
        return 0
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for case in CASES:  # one process per case: separate peak RSS
            out = Path(tmp) / f"{case}.json"
            cmd = [sys.executable, str(Path(__file__).resolve()), "--case", case, "--json", str(out),
                   "--repeat", str(args.repeat)]
            if args.profile:
                cmd.append("--profile")
            rc = subprocess.run(cmd).returncode
            if rc != 0 or not out.is_file():
                print(f"case {case} failed (exit {rc})", file=sys.stderr)
                continue
            results.append(json.loads(out.read_text()))
    print()
    print(f"Summary ({os.cpu_count()} CPUs; python {sys.version.split()[0]})")
    print(_table(results))
    crown = [r for r in results if r["case"] == "crown20m"]
    if crown:
        peak = max(crown[0]["rss_self_gb"], crown[0]["rss_children_gb"])
        print(f"20 M-voxel crown peak RSS {peak:.2f} GB: {'within' if peak <= 4.0 else 'OVER'} the 4 GB target")
    print("Reproduce: . .venv/bin/activate && python benchmarks/bench_sim.py")
    benchresult.record(cases=results)
    return 0


if __name__ == "__main__":
    # a case run for --case all (--json) is part of that run's row
    sys.exit(main() if "--json" in sys.argv else benchresult.run("bench_sim", main))
