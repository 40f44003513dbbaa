"""Benchmark: the two label look-ups made faster in session 35, against their former algorithms.

1. Tree labels of a recording (``vlsforest.extract._TreeLabeller``, which the diagnosis runs on
   every simulated cloud and ``extract reference`` on every real one): the cell shortcuts against
   the former per-tree nearest-point queries of every point in a tree's box (re-implemented here
   as the reference). Both must give the same labels.
2. Face labels of Embree hits (``Scene.trace_local(with_labels=True)``, the virtual forest's
   recordings): the flat table against the former one pass per geometry, on the hits of one
   block of sub-rays over a scene of many labelled meshes. Both must give the same labels.

    python benchmarks/bench_labels.py [--study /path/to/study --plot P3]

With ``--study`` (a workflow directory after ``snakemake`` on the default config), part 1 uses
that plot's segmented trees and its "real" ULS recording, as the diagnosis does; without it, a
synthetic stand. CPU seconds of this process (``resource.getrusage``), best of ``--repeat`` runs.
"""

from __future__ import annotations

import argparse
import resource
import sys
from pathlib import Path

import numpy as np


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _best(fn, repeat: int):
    best, out = np.inf, None
    for _ in range(repeat):
        c = _cpu()
        out = fn()
        best = min(best, _cpu() - c)
    return best, out


def _labels_by_queries(trees: list, xyz: np.ndarray, eligible: np.ndarray, radius: float, columns) -> np.ndarray:
    """The former labeller (session 34): every eligible point in a tree's box, gathered through
    the column index, is queried against the tree's KD-tree."""
    label = np.zeros(len(xyz), dtype=np.int64)
    best = np.full(len(xyz), np.inf)
    for tid, tlo, thi, kd, _ in trees:
        near = columns.box(tlo[0], tlo[1], thi[0], thi[1])
        p = xyz[near]
        inside = eligible[near]
        for k in range(3):
            inside &= (p[:, k] >= tlo[k]) & (p[:, k] <= thi[k])
        cand = near[inside]
        if len(cand) == 0:
            continue
        d, _ = kd.query(xyz[cand], k=1, distance_upper_bound=radius)
        better = (d <= radius) & (d < best[cand])
        label[cand[better]] = tid
        best[cand[better]] = d[better]
    return label


def _synthetic_stand(seed: int = 0):
    """60 trees on a 40 m × 40 m plot (TLS points on crown shells) and a 3 M-point recording (80 %
    of it scattered 0.15 m about the crowns' points)."""
    rng = np.random.default_rng(seed)
    trees = {}
    for t in range(1, 61):
        c = rng.uniform([0, 0, 12], [40, 40, 20])
        n = 60000
        u = rng.normal(size=(n, 3))
        u /= np.linalg.norm(u, axis=1)[:, None]
        trees[t] = c + u * rng.uniform(0.6, 1.0, (n, 1)) * np.array([3.0, 3.0, 6.0])
    # returns mostly in the crowns (near the TLS points, as a recording's), the rest anywhere
    shell = np.concatenate(list(trees.values()))
    pick = shell[rng.integers(0, len(shell), 2_400_000)] + rng.normal(0, 0.15, (2_400_000, 3))
    xyz = np.concatenate([pick, rng.uniform([0, 0, 0], [40, 40, 28], (600_000, 3))])
    cls = np.where(xyz[:, 2] < 0.5, 2, 5).astype(np.uint8)
    return trees, xyz, cls


def bench_tree_labels(a) -> None:
    from vlsforest.extract import _ColumnIndex, _TreeLabeller
    from vlsforest.io.las import PointCloud, read_las

    if a.study:
        import pandas as pd

        seg = a.study / "results" / a.plot / "segment"
        stems = pd.read_csv(seg / "trees.csv")
        trees = {int(t): read_las(seg / "trees" / f"{int(t)}.laz").xyz for t in stems.tree_id
                 if (seg / "trees" / f"{int(t)}.laz").is_file()}
        cloud = read_las(a.study / "results" / "forest" / "plots" / a.plot / "uls.laz")
        xyz, cls = cloud.xyz, np.asarray(cloud.attrs["classification"])
        what = f"{a.plot} of {a.study}: {len(trees)} segmented trees, 'real' ULS"
    else:
        trees, xyz, cls = _synthetic_stand()
        what = "synthetic stand: 60 trees"
    radius = 0.3
    c = _cpu()
    lab = _TreeLabeller(trees, radius)
    build = _cpu() - c
    cloud = PointCloud(xyz, {"classification": cls})
    columns = _ColumnIndex(xyz[:, :2])
    eligible = ~np.isin(cls, [2, 7, 18])
    t_new, new = _best(lambda: lab(cloud, columns=columns), a.repeat)
    t_old, old = _best(lambda: _labels_by_queries(lab.trees, xyz, eligible, radius, columns), a.repeat)
    same = np.array_equal(new, old)
    print(f"tree labels, {what}, {len(xyz):,} points ({(new > 0).sum():,} on a tree), radius {radius} m")
    print(f"  per-tree queries of every box point: {t_old:.2f} CPU-s")
    print(f"  cell shortcuts + queries of the rest: {t_new:.2f} CPU-s  (× {t_old / t_new:.2f} faster; "
          f"grids built once: {build:.2f} CPU-s)")
    print(f"  identical labels: {same}")
    if not same:
        raise SystemExit("bench_labels: the labels differ")


def bench_face_labels(a) -> None:
    from vlsforest.sim.scene import Scene, _hit_labels

    rng = np.random.default_rng(1)
    sc = Scene()
    sc.add_plane(1, 0.0, [-60, -60, 60, 60])
    n_meshes, n_faces = 150, 20000  # a plot's trees: one labelled mesh each
    for m in range(n_meshes):
        c = rng.uniform([-40, -40, 5], [40, 40, 25])
        v = c + rng.normal(0, 2.0, (3 * n_faces, 3))
        sc.add_mesh(2 + m, v, np.arange(3 * n_faces).reshape(-1, 3),
                    face_labels=rng.integers(1, 3, n_faces))
    n = 750_000  # one block: 20,000 pulses × 37 sub-rays
    o = np.column_stack([rng.uniform(-40, 40, (n, 2)), np.full(n, 60.0)])
    d = np.tile([0.0, 0.0, -1.0], (n, 1))
    sc.prepare()
    res = sc._embree.run((o - sc.shift).astype(np.float32), d.astype(np.float32), output=1)
    gid, prim = res["geomID"], res["primID"]
    offsets, flat = sc._embree_labels
    per_geometry = [m.labels for m in sc._meshes] + [None]  # Embree's geometries: the meshes, then the plane

    def old():
        label = np.zeros(n, dtype=np.uint8)
        hit = gid >= 0
        hidx = np.flatnonzero(hit)
        g, p = gid[hit], prim[hit]
        for k, lab in enumerate(per_geometry):
            if lab is not None:
                sel = g == k
                label[hidx[sel]] = lab[p[sel]]
        return label

    def new():
        label = np.zeros(n, dtype=np.uint8)
        _hit_labels(gid, prim, offsets, flat, label)
        return label

    new()  # compile / load the kernel
    t_old, a_old = _best(old, a.repeat)
    t_new, a_new = _best(new, a.repeat)
    same = np.array_equal(a_old, a_new)
    print(f"face labels of {n:,} sub-ray hits over {n_meshes} labelled meshes and a plane "
          f"({(gid < len(per_geometry) - 1).sum():,} on a mesh)")
    print(f"  one pass per geometry: {t_old * 1e3:.1f} ms; flat table, one pass: {t_new * 1e3:.1f} ms "
          f"(× {t_old / max(t_new, 1e-9):.0f} faster)")
    print(f"  identical labels: {same}")
    if not same:
        raise SystemExit("bench_labels: the face labels differ")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--study", type=Path, default=None, help="workflow directory with results/ (default config)")
    ap.add_argument("--plot", default="P3")
    ap.add_argument("--repeat", type=int, default=2)
    a = ap.parse_args(argv)
    if a.study and not (a.study / "results" / a.plot / "segment" / "trees.csv").is_file():
        print(f"bench_labels: {a.study}/results/{a.plot}/segment/trees.csv not found", file=sys.stderr)
        return 2
    bench_tree_labels(a)
    bench_face_labels(a)
    return 0


if __name__ == "__main__":
    sys.exit(main())
