"""Benchmark: per-tree metrics for 30 trees × 7 model variants × 2 scenarios (420 tree clouds).

Target (issue tracker): all 420 tree clouds in ≤ 60 s. The clouds are synthetic but of
realistic size and shape (2–20 k points: stem, ellipsoidal crown, some ground and understorey
returns, pulses with 1–4 returns); the voxel variants are quantised to their voxel size so
that degenerate (collinear/duplicate) slices occur as in simulated clouds. Each variant ×
scenario is one labelled cloud of 30 trees processed by :func:`vlsforest.metrics.cloud_metrics`,
as the workflow does. Generation is not timed.

Usage::

    python benchmarks/bench_metrics.py [--seed 0] [--trees 30] [--cbh-convention paper]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from vlsforest.io.las import PointCloud
from vlsforest.metrics import cloud_metrics

import benchresult

TARGET_S = 60.0
#: model variants: (name, quantisation step of the voxel model or None)
VARIANTS = (
    ("fixed_0.25", 0.25),
    ("fixed_0.10", 0.10),
    ("fixed_0.05", 0.05),
    ("fixed_0.02", 0.02),
    ("scaled", 0.05),
    ("scaled_shift", None),
    ("scaled_cog", None),
)
SCENARIOS = ("ALS", "ULS")


def _tree(rng: np.random.Generator, n: int, quant: float | None, x0: float, y0: float) -> np.ndarray:
    height = rng.uniform(15.0, 35.0)
    cbh = rng.uniform(0.2, 0.6) * height
    n_stem, n_ground = n // 8, n // 25
    n_crown = n - n_stem - n_ground
    t = rng.uniform(0, 2 * np.pi, n_stem)
    r_stem = rng.uniform(0.1, 0.3)
    stem = np.column_stack([r_stem * np.cos(t), r_stem * np.sin(t), rng.uniform(0, cbh, n_stem)])
    # crown: points inside a cone-ish envelope, denser towards the surface
    zc = cbh + (height - cbh) * rng.beta(2.0, 1.6, n_crown)
    rmax = rng.uniform(1.5, 4.5)
    rad = rmax * np.clip((height - zc) / (height - cbh), 0, 1) ** 0.8 * np.sqrt(rng.uniform(0.3, 1.0, n_crown))
    a = rng.uniform(0, 2 * np.pi, n_crown)
    crown = np.column_stack([rad * np.cos(a), rad * np.sin(a), zc])
    # ground returns near the stem foot (as kept by a tree extraction around the TLS stem)
    ground = np.column_stack([rng.uniform(-0.5, 0.5, (n_ground, 2)), rng.normal(0, 0.03, n_ground)])
    pts = np.concatenate([stem, crown, ground])
    if quant:
        pts = np.round(pts / quant) * quant
    return pts + np.array([x0, y0, 0.0])


def make_cloud(rng: np.random.Generator, n_trees: int, quant: float | None) -> PointCloud:
    """A labelled cloud of ``n_trees`` synthetic trees in UTM-like coordinates."""
    parts, ids = [], []
    for t in range(n_trees):
        n = int(rng.integers(2000, 20001))
        parts.append(_tree(rng, n, quant, 481_000.0 + 12.0 * t, 3_812_000.0))
        ids.append(np.full(n, t + 1, dtype=np.int32))
    xyz = np.concatenate(parts)
    n = len(xyz)
    # pulses of 1–4 returns; a tree keeps a random subset of each pulse's returns
    nor = rng.integers(1, 5, n).astype(np.uint8)
    rn = np.minimum(rng.integers(1, 5, n), nor).astype(np.uint8)
    gps = 1e5 + np.cumsum(rng.integers(0, 2, n)) * 1e-5
    attrs = {
        "tree_id": np.concatenate(ids),
        "gps_time": gps,
        "number_of_returns": nor,
        "return_number": rn,
        "point_source_id": np.ones(n, np.uint16),
    }
    return PointCloud(xyz, attrs)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--trees", type=int, default=30)
    ap.add_argument("--cbh-convention", default="paper", choices=("paper", "authors"))
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)

    clouds = []
    for scen in SCENARIOS:
        for name, quant in VARIANTS:
            clouds.append((f"{scen}/{name}", make_cloud(rng, args.trees, quant)))
    n_clouds = len(clouds) * args.trees
    n_points = sum(len(c) for _, c in clouds)

    total = 0.0
    for label, cloud in clouds:
        t0 = time.perf_counter()
        df = cloud_metrics(cloud, "tree_id", cbh_convention=args.cbh_convention, source=label)
        dt = time.perf_counter() - t0
        total += dt
        assert len(df) == args.trees and np.isfinite(df["height"]).all()
        print(f"{label:22s} {len(cloud):9d} points  {dt:7.3f} s  median CBH {df['cbh'].median():6.2f} m")
    print(
        f"total: {n_clouds} tree clouds, {n_points} points, {total:.2f} s "
        f"(cbh {args.cbh_convention}); target {TARGET_S:.0f} s; ratio {total / TARGET_S:.3f}"
    )
    benchresult.record(tree_clouds=n_clouds, points=n_points, seconds_total=total, target_s=TARGET_S,
                       cbh_convention=args.cbh_convention)
    return 0 if total <= TARGET_S else 1


if __name__ == "__main__":
    raise SystemExit(benchresult.run("bench_metrics", main))
