"""Benchmark: loading voxel cubes into Embree, and tracing with and without its robust mode.

Part 1 builds a scene of ``--cubes`` cubes on a 0.05 m lattice (``voxel_backend="embree"``,
12 triangles per cube) twice: with the buffers filled by numpy (:mod:`vlsforest.sim._embree`,
the default) and by embreex's own ``TriangleMesh`` (element by element), and prints seconds and
µs per cube of :meth:`Scene.prepare` (cubes → triangles, upload, BVH build). Part 2 traces
``--rays`` downward rays through the same cubes with ``embree_robust`` on and off and checks
how many hits differ. Each variant runs in its own process.

    python benchmarks/bench_embree_build.py --cubes 1000000 --rays 4000000

The study-level effect (a leaf-level plot's ULS recording, a 0.05 m ULS simulation) is in the
docs/performance.md.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import benchresult

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "workflow"))


def _cells(n: int) -> np.ndarray:
    rng = np.random.default_rng(0)
    side = int(round((n * 4) ** (1 / 3)))  # a quarter of the box filled
    ijk = np.unique(rng.integers(0, side, (int(n * 1.2), 3)), axis=0)
    return ijk[rng.permutation(len(ijk))[:n]]


def _child(mode: str, n: int, n_rays: int, tmp: str) -> dict:
    from vlsforest.sim import _embree
    from vlsforest.sim.scene import Scene

    if mode == "embreex":
        _embree._api = False  # the fallback: embreex's TriangleMesh
    ijk = _cells(n)
    sc = Scene(voxel_backend="embree", embree_robust=(mode != "plain"))
    sc.add_voxels(1, ijk, np.zeros(3), 0.05)
    t = time.perf_counter()
    sc.prepare()
    build = time.perf_counter() - t
    out = {"mode": mode, "cubes": len(ijk), "build_s": build, "fast_upload": _embree.fast_upload_available()}
    if n_rays:
        rng = np.random.default_rng(1)
        hi = ijk.max() * 0.05
        o = np.column_stack([rng.uniform(0, hi, n_rays), rng.uniform(0, hi, n_rays), np.full(n_rays, hi + 5)])
        d = np.column_stack([rng.normal(0, 0.1, n_rays), rng.normal(0, 0.1, n_rays), -np.ones(n_rays)])
        d /= np.linalg.norm(d, axis=1)[:, None]
        t = time.perf_counter()
        tt, part, _ = sc.trace(o, d)
        out["trace_s"] = time.perf_counter() - t
        out["hits"] = int((part >= 0).sum())
        out["t_sum"] = float(np.sum(tt[np.isfinite(tt)]))
        np.save(Path(tmp) / f"{mode}.npy", tt)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cubes", type=int, default=1_000_000)
    ap.add_argument("--rays", type=int, default=4_000_000)
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--tmp", default=None, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.child:
        print(json.dumps(_child(a.child, a.cubes, a.rays, a.tmp)))
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        _run(a, tmp)
    return 0


def _run(a, tmp: str) -> None:
    res = {}
    for mode, rays in (("embreex", 0), ("fast", 0), ("plain", a.rays), ("robust", a.rays)):
        out = subprocess.run([sys.executable, __file__, "--child", mode, "--cubes", str(a.cubes),
                              "--rays", str(rays), "--tmp", tmp],
                             check=True, capture_output=True, text=True).stdout
        res[mode] = json.loads(out.strip().splitlines()[-1])
    n = res["fast"]["cubes"]
    for mode in ("embreex", "fast"):
        r = res[mode]
        print(f"build, {mode:8s}: {r['build_s']:6.2f} s  {r['build_s'] / n * 1e6:5.2f} µs/cube")
    print(f"build ratio embreex / numpy upload: {res['embreex']['build_s'] / res['fast']['build_s']:.2f}×"
          f"  (numpy upload active: {res['fast']['fast_upload']})")
    for mode in ("plain", "robust"):
        r = res[mode]
        print(f"trace {a.rays:,} rays, robust {mode == 'robust'!s:5s}: {r['trace_s']:6.2f} s, {r['hits']:,} hits")
    print(f"trace ratio robust / plain: {res['robust']['trace_s'] / res['plain']['trace_s']:.2f}×")
    benchresult.record(cubes=n, rays=a.rays, runs=res)
    tp = np.load(Path(tmp) / "plain.npy")
    tr = np.load(Path(tmp) / "robust.npy")
    both = np.isfinite(tp) & np.isfinite(tr)
    print(f"rays hit in one mode only: {int((np.isfinite(tp) != np.isfinite(tr)).sum()):,} of {len(tp):,}; "
          f"range differs by > 1 mm: {int((np.abs(tp[both] - tr[both]) > 1e-3).sum()):,}; "
          f"largest range difference: {np.abs(tp[both] - tr[both]).max():.2e} m")


if __name__ == "__main__":
    # a --child run is part of its parent's row
    sys.exit(main() if "--child" in sys.argv else benchresult.run("bench_embree_build", main))
