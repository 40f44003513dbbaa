"""Benchmark: where the memory of a single-tree simulation goes, and what a voxel and a triangle cost.

Every measurement runs in a fresh process and reads its peak resident size twice: ``ru_maxrss``
(``getrusage``) and ``VmHWM`` (``/proc/self/status``); the resident size is split into
anonymous memory (heap, arrays) and file pages (shared libraries), which forked workers share.

1. **Imports**: ``python -c pass``, ``import vlsforest``, ``import vlsforest.cli``, everything
   ``vlsforest simulate`` imports (found by running it: the third-party packages in
   ``sys.modules`` at its end), each heavy dependency alone, and each one's share on top of the
   others (the same imports without it).
2. **Phases** of one simulation in one process, through the public API in the order of
   ``vlsforest simulate``: imports, ``Scene.from_yaml``, ``load_survey``, ``Scene.prepare``
   (Embree BVH), a first ``simulate`` (numba loads its compiled kernels), the same survey again,
   ``write_points`` (LAZ), and a survey three times as long. Per phase: the resident size after
   it and the peak during it (``VmHWM`` reset through ``/proc/self/clear_refs``).
3. **The command** ``vlsforest simulate --workers 1`` and ``--workers 2`` on both surveys: the
   peak of the summed resident size (RSS) and proportional set size (PSS, shared pages split
   between the processes that map them) of the command and its forked workers, sampled every
   20 ms (PSS every 100 ms), and ``ru_maxrss`` of the largest process; ``--workers 1`` once
   more with ``MALLOC_ARENA_MAX=1``.
4. **Scene structures**: scenes of N random unique cubes on a 0.05 m lattice (a quarter of their
   bounding box filled) traced by Embree (12 triangles each) and by the sparse voxel grid, and of
   N random small triangles (a triangle soup: 3 vertices each), each size in a fresh process
   that built a small scene of the same kind first (libraries and kernels loaded) and runs with
   glibc's ``MALLOC_MMAP_THRESHOLD_=65536`` (freed arrays leave the resident size at once). Over
   the process before the inputs were made: the Scene's own arrays (what it keeps of its
   inputs), the resident size retained after ``Scene.prepare`` and the peak during it, each
   fitted by least squares against N: bytes per voxel and per triangle (resident-size deltas
   see Embree's C++ memory, which tracemalloc does not).

The scene is the real spruce F_BR08_08 of ``<repo>/../shared/data/real`` (``--data``): its
0.25 m ``.vox`` crown as fixed cubes, its Poisson stem OBJ and a 100 m ground square at the stem
base; the surveys are the study's ULS scanner (miniVUX-1UAV, helios_v1 detector) at 68 m and
8 m/s, one 100 m line (``short``) and three lines 20 m apart (``long``), planned with
``vlsforest plan``.

    python benchmarks/bench_memory_floor.py            # about 2 minutes on 2 cores

The row's ``results.tables`` are rendered on the benchmark results page of the documentation
(docs/performance.md, "Memory").
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import benchresult

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
REAL = ROOT.parent / "shared" / "data" / "real"  # <repo>/../shared/data/real
MB = 1 << 20

#: what a fresh process prints: ru_maxrss and the /proc/self/status sizes (kB), as JSON
_PROBE_TAIL = """
import json as _j, resource as _r
_s = {}
for _l in open('/proc/self/status'):
    _k, _v = _l.split(':', 1)
    if _k in ('VmHWM', 'VmRSS', 'RssAnon', 'RssFile'):
        _s[_k] = int(_v.split()[0])
_s['ru_maxrss'] = _r.getrusage(_r.RUSAGE_SELF).ru_maxrss
print(_j.dumps(_s))
"""

#: the direct third-party imports of the simulate path whose share is measured on top of the others
_SHARED_IMPORTS = {
    "numpy": "import numpy", "numba": "import numba", "pandas": "import pandas", "laspy": "import laspy",
    "lazrs": "import lazrs", "yaml": "import yaml", "embreex": "import embreex.rtcore_scene",
}
#: packages whose top-level import loads little: the submodule the simulator loads instead
_IMPORT_OF = {"embreex": "import embreex.rtcore_scene"}

#: glibc: every allocation of 64 KiB or more is its own mapping, returned when freed (no dynamic
#: threshold), so that what a build frees leaves the resident size of the structure children
FIXED_MMAP = {"MALLOC_MMAP_THRESHOLD_": "65536"}

ULS = {"scanner": "riegl_minivux1uav", "pattern": "parallel", "altitude_m": 68, "speed_mps": 8,
       "line_spacing_m": 20, "margin_m": 0, "overrides": {"window_size_ns": 1.5, "beam_sample_quality": 3},
       "detector": {"mode": "helios_v1"}}


# ----------------------------------------------------------------------------- pure helpers
def status_kb(text: str) -> dict:
    """The ``kB`` fields of a ``/proc/<pid>/status`` or ``smaps_rollup`` text, in kB.

    Parameters
    ----------
    text : str
        The file's text.

    Returns
    -------
    dict
        Field name → kB (``VmHWM``, ``VmRSS``, ``RssAnon``, ``Pss`` …); other lines are skipped.
    """
    out = {}
    for line in text.splitlines():
        key, _, rest = line.partition(":")
        parts = rest.split()
        if len(parts) == 2 and parts[1] == "kB" and parts[0].isdigit():
            out[key.strip()] = int(parts[0])
    return out


def fit_per_element(ns, values) -> tuple[float, float]:
    """Least-squares line through ``(n, value)`` pairs: (value per element, value at n = 0).

    Parameters
    ----------
    ns : sequence of int
        Element counts (at least two different ones).
    values : sequence of float
        Measured totals (e.g. bytes) at those counts.

    Returns
    -------
    slope, intercept : float
    """
    if len(ns) != len(values) or len(set(ns)) < 2:
        raise ValueError("need at least two different element counts, one value each")
    k = len(ns)
    mx, my = sum(ns) / k, sum(values) / k
    sxx = sum((x - mx) ** 2 for x in ns)
    sxy = sum((x - mx) * (y - my) for x, y in zip(ns, values))
    slope = sxy / sxx
    return slope, my - slope * mx


def third_party(modules, stdlib=None) -> list[str]:
    """Top-level names of the third-party packages among ``modules`` (names from ``sys.modules``).

    Standard-library modules, private top-level names (``_ctypes``), ``__main__`` and
    ``vlsforest`` itself are left out.
    """
    stdlib = sys.stdlib_module_names if stdlib is None else stdlib
    tops = {m.split(".")[0] for m in modules}
    return sorted(t for t in tops if t not in stdlib and not t.startswith("_") and t != "vlsforest")


# ----------------------------------------------------------------------------- measuring
def _self_kb() -> dict:
    return status_kb(Path("/proc/self/status").read_text())


def _reset_peak() -> bool:
    """Reset this process's VmHWM to its current resident size (Linux ≥ 4.0)."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        return False
    return True


def _env() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT / "workflow") + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


def probe(code: str) -> dict:
    """Peak and current sizes (MB) of a fresh ``python -c CODE``."""
    out = subprocess.run([sys.executable, "-c", code + "\n" + _PROBE_TAIL], env=_env(), check=True,
                         capture_output=True, text=True).stdout
    kb = json.loads(out.strip().splitlines()[-1])
    return {"ru_maxrss_mb": round(kb["ru_maxrss"] / 1024, 1), "vmhwm_mb": round(kb["VmHWM"] / 1024, 1),
            "rss_anon_mb": round(kb["RssAnon"] / 1024, 1), "rss_file_mb": round(kb["RssFile"] / 1024, 1)}


def _children(pid: int) -> list[int]:
    kids = []
    try:
        for task in os.listdir(f"/proc/{pid}/task"):
            kids += [int(c) for c in Path(f"/proc/{pid}/task/{task}/children").read_text().split()]
    except OSError:
        pass
    return kids


def _tree(pid: int) -> list[int]:
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        todo += _children(p)
    return out


def run_sampled(cmd: list[str], env: dict, every_s: float = 0.02, pss_every: int = 5) -> dict:
    """Run ``cmd``; sample the summed RSS (and every ``pss_every``-th time the PSS) of it and its
    descendants. Returns the peaks (MB), the most processes seen at once and ``ru_maxrss`` of the
    largest process (its own or a reaped descendant's)."""
    page = os.sysconf("SC_PAGE_SIZE")
    errfile = tempfile.TemporaryFile(mode="w+")
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=errfile, text=True)
    peak = {"rss": 0, "pss": 0, "procs": 0}
    stop = threading.Event()

    def sample():
        k = 0
        while not stop.is_set():
            pids = _tree(proc.pid)
            rss = pss = 0
            for p in pids:
                try:
                    rss += int(Path(f"/proc/{p}/statm").read_text().split()[1]) * page
                    if k % pss_every == 0:
                        pss += status_kb(Path(f"/proc/{p}/smaps_rollup").read_text()).get("Pss", 0) * 1024
                except (OSError, IndexError, ValueError):
                    pass
            peak["rss"] = max(peak["rss"], rss)
            peak["pss"] = max(peak["pss"], pss)
            peak["procs"] = max(peak["procs"], len(pids))
            k += 1
            stop.wait(every_s)

    th = threading.Thread(target=sample, daemon=True)
    t0 = time.perf_counter()
    th.start()
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    stop.set()
    th.join()
    errfile.seek(0)
    err = errfile.read()
    errfile.close()
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({proc.returncode}): {err.strip()[-500:]}")
    return {"peak_rss_sum_mb": round(peak["rss"] / MB, 1), "peak_pss_sum_mb": round(peak["pss"] / MB, 1),
            "ru_maxrss_largest_mb": round(usage.ru_maxrss / 1024, 1), "processes": peak["procs"],
            "wall_s": round(wall, 2), "last_line": err.strip().splitlines()[-1] if err.strip() else ""}


# ----------------------------------------------------------------------------- children
def _mappings(top: int = 10) -> list[dict]:
    """This process's resident size by mapping (file name, ``[heap]``, ``[anon]``), largest first."""
    agg: dict = {}
    name = "[anon]"
    for line in Path("/proc/self/smaps").read_text().splitlines():
        head = line.split()
        if not head:
            continue
        if not head[0].endswith(":"):
            name = os.path.basename(head[5]) if len(head) > 5 else "[anon]"
        elif head[0] == "Rss:":
            agg[name] = agg.get(name, 0) + int(head[1])
    rows = sorted(agg.items(), key=lambda kv: -kv[1])[:top]
    return [{"mapping": k, "rss_mb": round(v / 1024, 1)} for k, v in rows]


def _sizes(res) -> dict:
    """Pulses, points and the bytes of a simulation result's arrays (points, per-pulse table)."""
    return {"pulses": res.timings["n_pulses"], "points": res.timings["n_points"],
            "points_bytes": int(sum(v.nbytes for v in res.points.values())),
            "pulses_bytes": int(sum(v.nbytes for v in res.pulses.values()))}


def _child_phases(scene_yaml: str, short: str, long: str, out_las: str) -> dict:
    """The simulation of ``vlsforest simulate`` phase by phase, through the public API."""
    phases = []
    can_reset = _reset_peak()

    def mark(name, **extra):
        kb = _self_kb()
        phases.append({"phase": name, "rss_mb": round(kb["VmRSS"] / 1024, 1),
                       "peak_mb": round(kb["VmHWM"] / 1024, 1), "anon_mb": round(kb["RssAnon"] / 1024, 1),
                       "file_mb": round(kb["RssFile"] / 1024, 1), "modules": len(sys.modules), **extra})
        gc.collect()
        _reset_peak()

    mark("start")
    import vlsforest.cli  # noqa: F401  (what the command line imports first)

    mark("import vlsforest.cli")
    import vlsforest.commands.simulate  # noqa: F401
    from vlsforest.sim import Scene, load_survey, simulate, write_points

    mark("import the simulate command (vlsforest.sim)")
    scene = Scene.from_yaml(scene_yaml)
    mark("Scene.from_yaml", voxels=scene.n_voxels, triangles=scene.n_triangles)
    survey = load_survey(short)
    mark("load_survey")
    scene.prepare()
    mark("Scene.prepare (Embree BVH)", embree=bool(scene.uses_embree), grids=len(scene.grids))
    res = simulate(scene, survey, workers=1, keep_pulses=False)
    mark("simulate, first (numba loads its kernels)", **_sizes(res))
    del res
    mark("result freed")
    res = simulate(scene, survey, workers=1, keep_pulses=False)
    mark("simulate, again", **_sizes(res))
    write_points(out_las, res)
    mark("write_points (LAZ)")
    del res
    mark("result freed")
    res = simulate(scene, load_survey(long), workers=1, keep_pulses=False)
    mark("simulate, long survey", **_sizes(res))
    write_points(out_las, res)
    mark("write_points (LAZ), long survey")
    return {"phases": phases, "peak_reset": can_reset, "mappings": _mappings(),
            "imports": third_party(m for m in list(sys.modules) if m != "benchresult"
                                   and getattr(sys.modules.get(m.split(".")[0]), "__file__", None))}


def _cells(n: int, seed: int = 0):
    """``n`` random unique cells filling a quarter of their bounding cube (int64, shape (n, 3))."""
    import numpy as np

    rng = np.random.default_rng(seed)
    side = int(round((n * 4) ** (1 / 3))) + 1
    ijk = np.unique(rng.integers(0, side, (int(n * 1.3), 3)), axis=0)
    return ijk[rng.permutation(len(ijk))[:n]]


def _soup(n: int, seed: int = 0):
    """``n`` random small triangles (0.1 m) in a 100 m cube: vertices (3n, 3), faces (n, 3)."""
    import numpy as np

    rng = np.random.default_rng(seed)
    c = rng.uniform(0.0, 100.0, (n, 1, 3))
    v = (c + rng.uniform(-0.05, 0.05, (n, 3, 3))).reshape(-1, 3)
    return v, np.arange(3 * n, dtype=np.int64).reshape(n, 3)


def _scene_of(kind: str, n: int):
    from vlsforest.sim.scene import Scene

    if kind == "triangles":
        sc = Scene(voxel_backend="auto")
        v, f = _soup(n)
        sc.add_mesh(1, v, f)
        return sc
    sc = Scene(voxel_backend="embree" if kind == "voxels_embree" else "grid")
    sc.add_voxels(1, _cells(n), (0.0, 0.0, 0.0), 0.05)
    return sc


def _child_structure(kind: str, n: int) -> dict:
    """Resident size of a scene of ``n`` elements of ``kind`` over the process before it."""
    small = _scene_of(kind, 1000)
    small.prepare()  # libraries and compiled kernels loaded before the baseline
    del small
    gc.collect()
    base = _self_kb()["VmRSS"]
    scene = _scene_of(kind, n)  # the inputs are made here; the scene keeps what it keeps of them
    gc.collect()
    before_build = _self_kb()["VmRSS"]
    _reset_peak()
    scene.prepare()
    gc.collect()
    kb = _self_kb()
    out = {"n": n, "arrays_kb": before_build - base, "retained_kb": kb["VmRSS"] - base, "peak_kb": kb["VmHWM"] - base}
    if kind == "voxels_grid":
        out["grid_nbytes"] = int(sum(g.nbytes for g in scene.grids))
    return out


# ----------------------------------------------------------------------------- parent
def _child(*args: str, env: dict | None = None) -> dict:
    out = subprocess.run([sys.executable, __file__, "--child", *args], env=env or _env(), check=True,
                         capture_output=True, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def _write_scene(folder: Path, data: Path) -> Path:
    """SCENE.yaml of F_BR08_08 with a 100 m ground square at the stem base."""
    obj, vox = data / "F_BR08_08_stem_Poisson.obj", data / "F_BR08_08_crown_250.vox"
    if not (obj.is_file() and vox.is_file()):
        raise SystemExit(f"bench_memory_floor: real data absent ({data}); needs F_BR08_08's .vox and .obj")
    xyz = [tuple(map(float, line.split()[1:4])) for line in obj.read_text().splitlines() if line.startswith("v ")]
    x, y, z = zip(*xyz)
    cx, cy, gz = 0.5 * (min(x) + max(x)), 0.5 * (min(y) + max(y)), min(z)
    ext = [round(cx - 50, 3), round(cy - 50, 3), round(cx + 50, 3), round(cy + 50, 3)]
    path = folder / "scene.yaml"
    path.write_text("parts:\n"
                    f"  - {{id: 1, type: plane, z: {gz:.3f}, extent: {ext}, reflectance: 0.3, name: ground}}\n"
                    f"  - {{id: 2, type: mesh, path: {obj}, reflectance: 0.3, name: stem}}\n"
                    f"  - {{id: 3, type: vox, path: {vox}, mode: fixed, name: crown}}\n")
    return path


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "vlsforest.cli", *args]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=REAL, help="folder with F_BR08_08's .vox and .obj")
    ap.add_argument("--voxels-embree", type=int, nargs="+", default=[50_000, 100_000, 200_000])
    ap.add_argument("--voxels-grid", type=int, nargs="+", default=[500_000, 1_000_000, 2_000_000])
    ap.add_argument("--triangles", type=int, nargs="+", default=[250_000, 500_000, 1_000_000])
    ap.add_argument("--child", nargs="+", default=None, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.child:
        kind, *rest = a.child
        out = _child_phases(*rest) if kind == "phases" else _child_structure(kind, int(rest[0]))
        print(json.dumps(out))
        return 0
    with tempfile.TemporaryDirectory(prefix="bench-memory-") as tmp:
        _run(a, Path(tmp))
    return 0


def _run(a, tmp: Path) -> None:
    env = _env()
    scene = _write_scene(tmp, a.data)
    surveys = {}
    for name, lines in (("short", 1), ("long", 3)):
        surveys[name] = tmp / f"{name}.yaml"
        subprocess.run(_cli("plan", "--scene", str(scene), "--scenario-json", json.dumps(dict(ULS, n_lines=lines)),
                            "-o", str(surveys[name])), env=env, check=True, capture_output=True)
    las = str(tmp / "out.laz")
    # numba's cache filled (compiled once) before anything is measured
    subprocess.run(_cli("simulate", str(scene), str(surveys["short"]), "-o", las, "--workers", "1", "--quiet"),
                   env=env, check=True, capture_output=True)

    # 2. phases (first: its sys.modules says what the simulation imports)
    ph = _child("phases", str(scene), str(surveys["short"]), str(surveys["long"]), las)
    print("phases of one simulation (vlsforest.sim API, one process):")
    print(f"  {'phase':46s} {'RSS after':>9s} {'peak':>7s} {'anon':>7s} {'file':>7s}  MB")
    for p in ph["phases"]:
        print(f"  {p['phase']:46s} {p['rss_mb']:9.1f} {p['peak_mb']:7.1f} {p['anon_mb']:7.1f} {p['file_mb']:7.1f}"
              + (f"  result {p['pulses']:,} pulses {p['pulses_bytes'] / MB:.1f} MB, {p['points']:,} points "
                 f"{p['points_bytes'] / MB:.1f} MB" if "pulses" in p else ""))
    print("  resident at the end by mapping: " + ", ".join(f"{m['mapping']} {m['rss_mb']:.0f}" for m in ph["mappings"][:6]))

    # 1. imports
    sim_imports = "import vlsforest.cli, vlsforest.commands.simulate, vlsforest.sim"
    stmts = {"python -c pass": "pass", "import vlsforest": "import vlsforest",
             "import vlsforest.cli": "import vlsforest.cli", "the simulate command's imports": sim_imports,
             "... and embreex.rtcore_scene (loaded by the first trace)": sim_imports + ", embreex.rtcore_scene"}
    for pkg in ph["imports"]:
        stmts[pkg] = _IMPORT_OF.get(pkg, f"import {pkg}")
    stmts["the simulate command's imports + numba's first compiled kernel (a one-voxel grid scene)"] = (
        sim_imports + "\nfrom vlsforest.sim import Scene\ns = Scene(voxel_backend='grid')\n"
        "s.add_voxels(1, [[0, 0, 0]], [0.0, 0.0, 0.0], 1.0)\ns.prepare()")
    stmts["laspy, requests blocked"] = "import sys; sys.modules['requests'] = None; import laspy"
    stmts["the simulate command's imports, requests blocked"] = "import sys; sys.modules['requests'] = None; " + sim_imports
    imports = {name: probe(code) for name, code in stmts.items()}
    everything = "; ".join(_SHARED_IMPORTS.values())
    imports["all direct third-party imports"] = probe(everything)
    share = {}
    for pkg in _SHARED_IMPORTS:
        rest = "; ".join(v for k, v in _SHARED_IMPORTS.items() if k != pkg)
        share[pkg] = round(imports["all direct third-party imports"]["vmhwm_mb"] - probe(rest)["vmhwm_mb"], 1)
    # Linux carries a process's ru_maxrss over exec: a fresh process reports at least the size of
    # the process that started it (this one), so only VmHWM is a small process's own peak
    own = _self_kb()["VmRSS"] / 1024
    gap = max((abs(r["ru_maxrss_mb"] - r["vmhwm_mb"]) for r in imports.values() if r["vmhwm_mb"] > own + 5),
              default=0.0)
    print(f"imports (fresh processes; peak MB = VmHWM; ru_maxrss reports at least this benchmark's own "
          f"{own:.0f} MB, above that it differs by at most {gap:.1f} MB):")
    for name, r in imports.items():
        print(f"  {name:58s} {r['vmhwm_mb']:7.1f}  (anon {r['rss_anon_mb']:.1f}, file {r['rss_file_mb']:.1f})")
    print("  share on top of the other direct imports: " + ", ".join(f"{k} {v:.1f}" for k, v in share.items()))

    # 3. the command, 1 and 2 workers
    cli = {}
    for name in ("short", "long"):
        for w in (1, 2):
            cmd = _cli("simulate", str(scene), str(surveys[name]), "-o", las, "--workers", str(w))
            cli[f"{name}, --workers {w}"] = run_sampled(cmd, env)
    cmd = _cli("simulate", str(scene), str(surveys["short"]), "-o", las, "--workers", "1")
    cli["short, --workers 1, MALLOC_ARENA_MAX=1"] = run_sampled(cmd, dict(env, MALLOC_ARENA_MAX="1"))
    print("vlsforest simulate (peak of the summed RSS / PSS of the command and its workers, MB):")
    for name, r in cli.items():
        print(f"  {name:40s} RSS {r['peak_rss_sum_mb']:7.1f}  PSS {r['peak_pss_sum_mb']:7.1f}  "
              f"largest process {r['ru_maxrss_largest_mb']:7.1f}  ({r['processes']} processes, {r['wall_s']:.1f} s)")

    # 4. scene structures
    struct = {}
    for kind, sizes in (("voxels_embree", a.voxels_embree), ("voxels_grid", a.voxels_grid),
                        ("triangles", a.triangles)):
        runs = [_child(kind, str(n), env=dict(env, **FIXED_MMAP)) for n in sizes]
        ns = [r["n"] for r in runs]
        per = {}
        for key in ("arrays_kb", "retained_kb", "peak_kb"):
            slope, icpt = fit_per_element(ns, [r[key] * 1024 for r in runs])
            per[key.replace("_kb", "_bytes_per")] = round(slope, 1)
            per[key.replace("_kb", "_intercept_mb")] = round(icpt / MB, 1)
        if kind == "voxels_grid":
            per["grid_nbytes_per"] = round(fit_per_element(ns, [r["grid_nbytes"] for r in runs])[0], 1)
        struct[kind] = {"runs": runs, **per}
        print(f"{kind}: {per['retained_bytes_per']:.0f} B each retained after Scene.prepare, "
              f"{per['peak_bytes_per']:.0f} B at the peak of the build (the Scene's own arrays "
              f"{per['arrays_bytes_per']:.0f} B; "
              f"N = {', '.join(f'{n:,}' for n in ns)})")

    tables = _tables(ph, imports, share, cli, struct)
    benchresult.record(scene="F_BR08_08: 0.25 m .vox crown (fixed cubes) + Poisson stem OBJ + 100 m ground",
                       surveys={k: dict(ULS, n_lines=1 if k == "short" else 3) for k in surveys},
                       simulate_imports=ph["imports"], phases=ph["phases"], mappings=ph["mappings"],
                       peak_reset=ph["peak_reset"], imports=imports, import_share_mb=share, cli=cli,
                       scene_structures=struct, tables=tables)


def _tables(ph, imports, share, cli, struct) -> dict:
    """The row's summary tables (rendered on the documentation's benchmark results page)."""
    rows, prev = [], None
    for p in ph["phases"]:
        rows.append({"phase": p["phase"], "RSS after (MB)": p["rss_mb"], "peak during (MB)": p["peak_mb"],
                     "added (MB)": None if prev is None else round(p["rss_mb"] - prev, 1),
                     "anon / file (MB)": f"{p['anon_mb']:.0f} / {p['file_mb']:.0f}", "modules": p["modules"],
                     "pulses / points": f"{p['pulses']:,} / {p['points']:,}" if "pulses" in p else "",
                     "result arrays (MB)": (round((p["points_bytes"] + p["pulses_bytes"]) / MB, 1)
                                            if "pulses" in p else None)})
        prev = p["rss_mb"]
    imp = [{"imports": k, "peak (MB)": v["vmhwm_mb"], "anon / file (MB)": f"{v['rss_anon_mb']:.0f} / {v['rss_file_mb']:.0f}",
            "share on top of the others (MB)": share.get(k.split()[-1] if k.startswith("import ") else k)}
           for k, v in imports.items()]
    cmd = [{"vlsforest simulate": k, "peak RSS, all processes (MB)": v["peak_rss_sum_mb"],
            "peak PSS, all processes (MB)": v["peak_pss_sum_mb"], "largest process (MB)": v["ru_maxrss_largest_mb"],
            "processes": v["processes"], "wall (s)": v["wall_s"]} for k, v in cli.items()]
    what = {"voxels_embree": "voxel (Embree: 12 triangles per cube)", "voxels_grid": "voxel (sparse grid)",
            "triangles": "triangle (mesh, 3 vertices each)"}
    per = [{"bytes per": what[k], "retained after prepare": v["retained_bytes_per"],
            "peak during the build": v["peak_bytes_per"], "of which the Scene's own arrays": v["arrays_bytes_per"],
            "N": ", ".join(f"{r['n']:,}" for r in v["runs"])} for k, v in struct.items()]
    return {"where the memory of one simulation goes": rows, "imports": imp, "the command": cmd,
            "scene structures": per, "resident at the end by mapping": ph["mappings"]}


if __name__ == "__main__":
    # a --child run is part of its parent's row
    sys.exit(main() if "--child" in sys.argv else benchresult.run("bench_memory_floor", main))
