"""Benchmark of the virtual Bretten forest: layout of the six plots and the geometry of P5.

Lays out the default forest (:data:`vlsforest.synth.DEFAULT_FOREST`), then generates every tree
of the largest plot, P5 (0.48 ha plus a 10 m margin, 5 target beeches at 150 000 triangles and
the surrounding trees at 40 000), and builds its truth table.  Prints per plot the stand
density and the nominal crown cover (drawn crown projection areas over the laid-out area), then
for the generated plot the measured cover (sum of the geometric CPA, union of the foliage
footprints), tree and triangle counts, mesh memory, times and the peak RSS of the process.

Usage: ``python benchmarks/bench_forest.py [--seed N] [--plot P5]``
"""

from __future__ import annotations

import argparse
import resource
import sys
import time

import numpy as np

from vlsforest.synth import ORGAN_FOLIAGE, DEFAULT_FOREST, forest_from_config, generate_plot_trees, truth_table

import benchresult


def _peak_rss_mib() -> float:
    kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return kb / 1024.0 if sys.platform != "darwin" else kb / 2**20


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--plot", default="P5")
    args = ap.parse_args(argv)

    t0 = time.perf_counter()
    plots = forest_from_config(DEFAULT_FOREST, args.seed)
    t_layout = time.perf_counter() - t0
    print(f"layout of {len(plots)} plots:         {t_layout:8.2f} s  (incl. imports on first use)")
    for p in plots:
        n_t = len(p.target_ids())
        # nominal crown cover: the drawn crown radii (before the crowns' plasticity: neighbour
        # cuts and crown scale) over the laid-out area (plot + margin); the layout draws trees
        # until this reaches forest.canopy_cover
        x0, y0, x1, y1 = p.extent
        area = (x1 - x0 + 2 * p.margin) * (y1 - y0 + 2 * p.margin)
        cover = sum(np.pi * t.params.crown_radius ** 2 for t in p.trees) / area
        print(f"   {p.name}: {p.area_ha():.3f} ha, {n_t} targets, "
              f"{len(p.trees) - n_t} surrounding ({len(p.trees) / area * 1e4:.0f} trees/ha), "
              f"nominal crown projection areas {cover:.2f} × the area, ground plane {p.ground_z():.2f} m")
    plot = {p.name: p for p in plots}[args.plot]
    rss0 = _peak_rss_mib()
    t0 = time.perf_counter()
    geoms = generate_plot_trees(plot)
    t_geom = time.perf_counter() - t0
    t0 = time.perf_counter()
    df = truth_table([plot], geoms)
    t_truth = time.perf_counter() - t0
    ntri = np.array([g.n_triangles for g in geoms.values()])
    tg = df["target"].to_numpy()
    mem = sum(g.vertices.nbytes + g.faces.nbytes + g.organ.nbytes for g in geoms.values())
    print(f"{plot.name} geometry: {len(geoms)} trees ({tg.sum()} targets), "
          f"{ntri.sum():,} triangles (targets {ntri[tg].sum():,}, surrounding {ntri[~tg].sum():,})")
    # the generated crowns: sum of the geometric CPA (truth table) and the union of the foliage
    # footprints on a 0.5 m raster, both over the laid-out area
    x0, y0, x1, y1 = plot.extent
    m = plot.margin
    area = (x1 - x0 + 2 * m) * (y1 - y0 + 2 * m)
    cell = 0.5
    nx, ny = int(np.ceil((x1 - x0 + 2 * m) / cell)), int(np.ceil((y1 - y0 + 2 * m) / cell))
    covered = np.zeros((nx, ny), bool)
    for g in geoms.values():
        xy = g.vertices[g.faces[g.organ == ORGAN_FOLIAGE].ravel(), :2]
        ix = np.floor((xy[:, 0] - (x0 - m)) / cell).astype(int)
        iy = np.floor((xy[:, 1] - (y0 - m)) / cell).astype(int)
        ok = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
        covered[ix[ok], iy[ok]] = True
    print(f"   generated crowns: CPA sum {df['cpa'].sum() / area:.2f} × the area, "
          f"union canopy cover {covered.mean():.2f} (foliage on a {cell} m raster)")
    print(f"   generate_plot_trees: {t_geom:8.2f} s  ({t_geom / len(geoms) * 1e3:.0f} ms/tree)")
    print(f"   truth_table:         {t_truth:8.2f} s")
    print(f"   mesh memory {mem / 2**20:.0f} MiB; peak RSS before {rss0:.0f} MiB, "
          f"after {_peak_rss_mib():.0f} MiB")
    benchresult.record(seed=args.seed, plot=plot.name, layout_s=t_layout, trees=len(geoms), targets=int(tg.sum()),
                       triangles=int(ntri.sum()), generate_s=t_geom, truth_table_s=t_truth,
                       cpa_sum_over_area=float(df["cpa"].sum() / area), union_canopy_cover=float(covered.mean()),
                       mesh_mib=mem / 2**20, peak_rss_mib=_peak_rss_mib())
    return 0


if __name__ == "__main__":
    raise SystemExit(benchresult.run("bench_forest", main))
