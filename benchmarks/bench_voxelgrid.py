"""Benchmark of the sparse voxel-grid tracer (a script, not a test).

Builds a synthetic ellipsoidal crown (10 m × 10 m × 20 m, base at 5 m) of random-occupancy cells
(denser towards the crown surface) at 0.02 m (~20 M voxels) and at 0.05 m (~2 M voxels), and
traces ULS-like rays from 70 m above ground, 0–60° off nadir, aimed at the crown. Prints build
time, structure size, process peak RSS and trace rate on 2 threads.

Run: ``python benchmarks/bench_voxelgrid.py [--rays 2000000] [--threads 2]``
"""

from __future__ import annotations

import argparse
import resource
import sys
import time

import numba
import numpy as np

from vlsforest.sim._voxelgrid import VoxelGrid

import benchresult

CROWN_HALF = np.array([5.0, 5.0, 10.0])  # semi-axes (m)
CROWN_CENTRE = np.array([0.0, 0.0, 15.0])
FLIGHT_Z = 70.0


def peak_rss_gb() -> float:
    """Peak resident set size of this process (GB; ru_maxrss is in KiB on Linux)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e9


def crown_cells(h: float, p0: float, p1: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Cells of an ellipsoidal crown, occupied with probability ``p0 + p1 * r**4`` (r: normalised
    radius), generated layer by layer into a growing int32 array (no big float temporaries)."""
    rng = np.random.default_rng(seed)
    origin = CROWN_CENTRE - CROWN_HALF  # lattice origin at the crown's box corner
    n_cells = np.round(2 * CROWN_HALF / h).astype(int)
    x = (np.arange(n_cells[0]) + 0.5) * h - CROWN_HALF[0]
    y = (np.arange(n_cells[1]) + 0.5) * h - CROWN_HALF[1]
    rxy2 = (x[:, None] / CROWN_HALF[0]) ** 2 + (y[None, :] / CROWN_HALF[1]) ** 2
    out = np.empty((1 << 20, 3), dtype=np.int32)
    n = 0
    for k in range(n_cells[2]):
        z = (k + 0.5) * h - CROWN_HALF[2]
        r2 = rxy2 + (z / CROWN_HALF[2]) ** 2
        p = np.where(r2 <= 1.0, p0 + p1 * r2 * r2, 0.0)
        i, j = np.nonzero(rng.random(r2.shape) < p)
        m = len(i)
        if n + m > len(out):
            out = np.resize(out, (max(2 * len(out), n + m), 3))
        out[n:n + m, 0] = i
        out[n:n + m, 1] = j
        out[n:n + m, 2] = k
        n += m
    return out[:n].copy(), origin


def uls_rays(m: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Rays from FLIGHT_Z, 0–60° off nadir, aimed at random points of the crown's mid plane."""
    rng = np.random.default_rng(seed)
    tgt = np.column_stack([rng.uniform(-CROWN_HALF[0], CROWN_HALF[0], m),
                           rng.uniform(-CROWN_HALF[1], CROWN_HALF[1], m),
                           np.full(m, CROWN_CENTRE[2])])
    theta = np.deg2rad(rng.uniform(0.0, 60.0, m))
    phi = rng.uniform(0.0, 2 * np.pi, m)
    d = np.column_stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), -np.cos(theta)])
    o = tgt - d * ((FLIGHT_Z - CROWN_CENTRE[2]) / np.cos(theta))[:, None]
    return o, d


def scan_rays(m: int, seed: int, n_lines: int = 50, n_per_line: int = 400):
    """Scan-ordered rays: per scanner position (70 m above ground, 0–60° off nadir, random
    azimuth, looking at the crown centre) a raster of ``n_lines`` scan lines of ``n_per_line``
    pulses covering ±5 m at the crown; consecutive rays are neighbours, as in a real scan."""
    rng = np.random.default_rng(seed)
    per = n_lines * n_per_line
    o_all, d_all = [], []
    for _ in range(-(-m // per)):
        theta = np.deg2rad(rng.uniform(0.0, 60.0))
        phi = rng.uniform(0.0, 2 * np.pi)
        axis = np.array([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), -np.cos(theta)])
        dist = (FLIGHT_Z - CROWN_CENTRE[2]) / np.cos(theta)
        u = np.cross(axis, [0.0, 0.0, 1.0])
        u /= np.linalg.norm(u)
        v = np.cross(axis, u)
        a, b = np.meshgrid(np.linspace(-5, 5, n_per_line) / dist, np.linspace(-5, 5, n_lines) / dist)
        d = axis + a.reshape(-1, 1) * u + b.reshape(-1, 1) * v
        d_all.append(d / np.linalg.norm(d, axis=1, keepdims=True))
        o_all.append(np.repeat((CROWN_CENTRE - axis * dist)[None], per, axis=0))
    return np.concatenate(o_all)[:m], np.concatenate(d_all)[:m]


def run_case(label: str, h: float, p0: float, p1: float, n_rays: int) -> None:
    print(f"--- {label}: cell size {h} m")
    t0 = time.perf_counter()
    ijk, origin = crown_cells(h, p0, p1, seed=1)
    t_gen = time.perf_counter() - t0
    print(f"  generated {len(ijk):,} cells in {t_gen:.1f} s (input int32 array "
          f"{ijk.nbytes / 1e6:.0f} MB)")
    t0 = time.perf_counter()
    grid = VoxelGrid.build(ijk, origin, h)
    t_build = time.perf_counter() - t0
    lo, hi = grid.bounds
    print(f"  build: {t_build:.2f} s  ({len(ijk) / t_build / 1e6:.1f} M voxels/s)")
    print(f"  n_voxels {grid.n_voxels:,}; blocks {grid.n_blocks:,} of {1 << grid.block_bits}^3 "
          f"cells; coarse {np.prod(grid._nb):,} entries; bounds {lo.round(3)} .. {hi.round(3)}")
    print(f"  nbytes {grid.nbytes / 1e6:.1f} MB = {grid.nbytes / grid.n_voxels:.2f} B/voxel")
    del ijk
    for label, (o, d) in (("random order", uls_rays(n_rays, seed=2)),
                          ("scan order", scan_rays(n_rays, seed=3))):
        grid.trace(o[:1000], d[:1000])  # warm-up (compilation is cached on disk)
        best = np.inf
        for _ in range(3):
            t0 = time.perf_counter()
            t, part, face, vox = grid.trace(o, d)
            best = min(best, time.perf_counter() - t0)
        hit = np.isfinite(t)
        print(f"  trace, {label}: {n_rays:,} ULS rays (0-60 deg off nadir, from {FLIGHT_Z} m, "
              f"aimed at the crown) in {best:.3f} s = {n_rays / best / 1e6:.2f} M rays/s on "
              f"{numba.get_num_threads()} threads; hit fraction {hit.mean():.3f}; "
              f"faces +z {np.mean(face[hit] == 3):.2f}")
    print(f"  process peak RSS so far: {peak_rss_gb():.2f} GB")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rays", type=int, default=2_000_000)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    numba.set_num_threads(min(args.threads, numba.config.NUMBA_NUM_THREADS))
    # warm the numba cache on a tiny grid so that compilation is not timed
    VoxelGrid.build(np.zeros((1, 3), np.int32), (0, 0, 0), 1.0).trace([[0.5, 0.5, 2]], [[0, 0, -1]])
    print(f"numba threads: {numba.get_num_threads()}, peak RSS at start {peak_rss_gb():.2f} GB")
    run_case("20 M-voxel crown", 0.02, 0.04, 0.26, args.rays)
    rss20 = peak_rss_gb()
    print(f"peak RSS <= 4 GB for the 20 M-voxel crown (build + trace): "
          f"{'yes' if rss20 <= 4.0 else 'no'} ({rss20:.2f} GB)")
    run_case("2 M-voxel crown", 0.05, 0.06, 0.42, args.rays)
    benchresult.record(rays=args.rays, threads=numba.get_num_threads(), peak_rss_20m_gb=rss20,
                       peak_rss_gb=peak_rss_gb())
    return 0


if __name__ == "__main__":
    sys.exit(benchresult.run("bench_voxelgrid", main))
