"""Benchmark of the parametric tree generator.

Generates the study's 30 target trees (full budget, 150 000 triangles) and 150 surrounding trees
(drawn from the Bretten distributions, 40 000 triangles), then computes the true plant area of
all of them on a 0.25 m grid.  Prints times, triangle counts, memory of the meshes and the peak
RSS of the process.

Usage: ``python benchmarks/bench_trees.py [--seed N] [--n-surrounding 150]``
"""

from __future__ import annotations

import argparse
import resource
import sys
import time

import numpy as np

from vlsforest.synth import generate_tree, sample_tree_params, target_tree_params, true_plant_area

import benchresult

# species mix of the surrounding trees (roughly the Bretten plots' composition)
MIX = {"fagus_sylvatica": 0.4, "picea_abies": 0.2, "quercus_petraea": 0.12,
       "pseudotsuga_menziesii": 0.12, "carpinus_betulus": 0.08, "pinus_sylvestris": 0.08}


def _peak_rss_mib() -> float:
    kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return kb / 1024.0 if sys.platform != "darwin" else kb / 2**20


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=2021)
    ap.add_argument("--n-surrounding", type=int, default=150)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)

    t0 = time.perf_counter()
    targets = target_tree_params(rng)
    t_params = time.perf_counter() - t0
    t0 = time.perf_counter()
    tg = [generate_tree(p, (0.0, 0.0, 0.0), rng) for p in targets]
    t_targets = time.perf_counter() - t0

    names = list(MIX)
    species = rng.choice(names, size=args.n_surrounding, p=np.array(list(MIX.values())))
    t0 = time.perf_counter()
    sparams = [sample_tree_params(str(s), rng) for s in species]
    sg = [generate_tree(p, (0.0, 0.0, 0.0), rng) for p in sparams]
    t_sur = time.perf_counter() - t0

    def tri_stats(gs):
        n = np.array([g.n_triangles for g in gs])
        mem = sum(g.vertices.nbytes + g.faces.nbytes + g.organ.nbytes for g in gs)
        return n, mem / 2**20

    nt, mt = tri_stats(tg)
    ns, ms = tri_stats(sg)
    t0 = time.perf_counter()
    pa = [true_plant_area(g, (0.0, 0.0, 0.0), 0.25) for g in tg]
    t_pa = time.perf_counter() - t0
    err = max(abs(p.total / g.plant_area() - 1) for p, g in zip(pa, tg))

    print(f"target params (30):            {t_params * 1e3:8.1f} ms")
    print(f"30 target trees:               {t_targets:8.2f} s  ({t_targets / 30 * 1e3:.0f} ms/tree)")
    print(f"   triangles total {nt.sum():,}  per tree min {nt.min():,} mean {nt.mean():,.0f} "
          f"max {nt.max():,};  mesh memory {mt:.0f} MiB")
    el = np.array([g.foliage_element_area for g in tg])
    print(f"   foliage element area min {el.min():.4f} median {np.median(el):.4f} "
          f"max {el.max():.4f} m^2")
    print(f"{args.n_surrounding} surrounding trees:         {t_sur:8.2f} s  "
          f"({t_sur / max(args.n_surrounding, 1) * 1e3:.0f} ms/tree)")
    print(f"   triangles total {ns.sum():,}  per tree min {ns.min():,} mean {ns.mean():,.0f} "
          f"max {ns.max():,};  mesh memory {ms:.0f} MiB")
    print(f"true plant area, 30 targets at 0.25 m: {t_pa:8.2f} s  (max rel. sum error {err:.1e})")
    print(f"peak RSS: {_peak_rss_mib():.0f} MiB")
    benchresult.record(seed=args.seed, target_params_s=t_params, targets_s=t_targets, target_triangles=int(nt.sum()),
                       surrounding=args.n_surrounding, surrounding_s=t_sur, surrounding_triangles=int(ns.sum()),
                       plant_area_s=t_pa, plant_area_max_rel_error=float(err), peak_rss_mib=_peak_rss_mib())
    return 0


if __name__ == "__main__":
    raise SystemExit(benchresult.run("bench_trees", main))
