"""Benchmark of the stem stage: time per plot and mesh accuracy on a recorded virtual forest.

For every plot of a forest written by ``vlsforest synth`` (default preset: 6 plots, 5 targets,
8 TLS scans per plot), each target tree's TLS cloud is taken from the truth labels (all points
of the tree, all organs: a stand-in for the segmentation stage, not timed), then the stem stage
runs as ``vlsforest stems`` does (:func:`vlsforest.stems.build_stem` at depth 8 and writing the
PLY, OBJ, stem points LAZ) and is timed. Target (issue tracker): ≤ 5 min per plot on 2 cores.

Accuracy, per tree, from the truth (which the stage never reads):

* selection: precision (share of the selected points that are stem points by the organ labels)
  and recall of the stem points below the true crown base;
* crown base estimate and fitted DBH against the true CBH and DBH;
* mesh: mean / 95th percentile distance of 20,000 points sampled on the mesh to the true stem
  surface (target mean ≤ 2 cm), and the largest distance of those samples to the nearest stem
  point (target ≤ 10 cm).

Usage::

    python benchmarks/bench_stems.py FOREST [--plots P1 P2 ...] [--depth 8]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from vlsforest.io.las import PointCloud, read_las, write_las
from vlsforest.io.mesh import TriangleMesh, read_mesh, write_mesh
from vlsforest.stems import build_stem, read_scanner_positions
from vlsforest.synth.trees import ORGAN_STEM

import benchresult

TARGET_PLOT_S = 300.0
TARGET_MEAN_M = 0.02
TARGET_EXTENT_M = 0.10


def _sample(mesh: TriangleMesh, n: int, rng) -> np.ndarray:
    a = mesh.face_areas()
    f = rng.choice(len(a), n, p=a / a.sum())
    u, v = rng.random(n), rng.random(n)
    s = u + v > 1
    u[s], v[s] = 1 - u[s], 1 - v[s]
    t = mesh.vertices[mesh.faces[f]]
    return t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])


def _dist(points: np.ndarray, mesh: TriangleMesh) -> np.ndarray:
    import open3d as o3d

    origin = np.floor(mesh.vertices.min(axis=0))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor((mesh.vertices - origin).astype(np.float32)),
        o3d.core.Tensor(mesh.faces.astype(np.uint32)),
    )
    return scene.compute_distance(o3d.core.Tensor((points - origin).astype(np.float32))).numpy().astype(float)


def bench_plot(forest: Path, plot: str, depth: int, out: Path) -> list[dict]:
    """Run the stem stage for every target of ``plot``; one dict of figures per tree."""
    tls = forest / "plots" / plot / "tls"
    scans = read_scanner_positions(tls / "scans.csv")
    clouds, tids, organs = [], [], []
    for sid in sorted(scans):
        clouds.append(read_las(tls / f"scan_{sid}.laz"))
        lab = np.load(forest / "truth" / plot / "tls" / f"scan_{sid}_labels.npz")
        tids.append(lab["tree_id"])
        organs.append(lab["organ"])
    cloud = PointCloud.concat(clouds)
    tid, organ = np.concatenate(tids), np.concatenate(organs)
    trees = pd.read_csv(forest / "truth" / "trees.csv")
    trees = trees[(trees["plot"] == plot) & trees["target"].astype(bool)]
    rng = np.random.default_rng(0)
    rows = []
    for t in trees.itertuples():
        m = tid == t.tree_id
        tree, org = cloud.subset(m), organ[m]
        t0 = time.perf_counter()
        res = build_stem(tree, scans, (t.x, t.y, t.z_ground), dbh=t.dbh, depth=depth, source=f"{plot}/{t.tree_id}")
        d = out / plot / str(t.tree_id)
        write_mesh(d / "stem.ply", res.mesh)
        write_mesh(d / "stem.obj", res.mesh)
        write_las(d / "stem_points.laz", tree.subset(res.mask))
        elapsed = time.perf_counter() - t0
        sel = res.mask
        is_stem = org == ORGAN_STEM
        below = (tree.xyz[:, 2] - t.z_ground) < t.cbh
        true = read_mesh(forest / "truth" / plot / "stems" / f"{t.tree_id}.ply")
        s = _sample(res.mesh, 20_000, rng)
        dist = _dist(s, true)
        ext, _ = cKDTree(tree.xyz[sel]).query(s)
        S = res.summary
        rows.append(
            {
                "plot": plot,
                "tree_id": t.tree_id,
                "species": t.species,
                "n_points": len(tree),
                "n_stem": int(sel.sum()),
                "precision": float(is_stem[sel].mean()),
                "recall_below_cbh": float(sel[is_stem & below].mean()) if (is_stem & below).any() else np.nan,
                "cbh_true": t.cbh,
                "cbh_est": S["crown_base_height"],
                "dbh_true": t.dbh,
                "dbh_fit": S["dbh_fitted"],
                "stem_top_m": S["stem_height_range"][1],
                "vertices": S["mesh_vertices"],
                "faces": S["mesh_faces"],
                "mean_dist_cm": 100 * dist.mean(),
                "p95_dist_cm": 100 * np.quantile(dist, 0.95),
                "max_extent_cm": 100 * ext.max(),
                "select_s": S["time_select_s"],
                "mesh_s": S["time_mesh_s"],
                "total_s": elapsed,
            }
        )
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("forest", type=Path, help="a forest folder written by vlsforest synth")
    ap.add_argument("--plots", nargs="*", help="plots to run (default: all under plots/)")
    ap.add_argument("--depth", type=int, default=8)
    args = ap.parse_args(argv)
    plots = args.plots or sorted(p.name for p in (args.forest / "plots").iterdir() if p.is_dir())
    pd.set_option("display.width", 250)
    pd.set_option("display.max_columns", 30)
    all_rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for plot in plots:
            rows = bench_plot(args.forest, plot, args.depth, Path(tmp))
            all_rows += rows
            plot_s = sum(r["total_s"] for r in rows)
            print(f"{plot}: {len(rows)} targets, stem stage {plot_s:.1f} s (target ≤ {TARGET_PLOT_S:.0f} s)", flush=True)
    df = pd.DataFrame(all_rows)
    print(df.round(3).to_string(index=False))
    per_plot = df.groupby("plot")["total_s"].sum()
    print()
    print(f"time per plot: max {per_plot.max():.1f} s, mean {per_plot.mean():.1f} s (target ≤ {TARGET_PLOT_S:.0f} s)")
    print(
        f"mesh→truth mean distance: mean {df.mean_dist_cm.mean():.2f} cm, worst tree {df.mean_dist_cm.max():.2f} cm "
        f"(target ≤ {100 * TARGET_MEAN_M:.0f} cm)"
    )
    print(f"mesh beyond stem points: worst {df.max_extent_cm.max():.1f} cm (target ≤ {100 * TARGET_EXTENT_M:.0f} cm)")
    print(
        f"selection precision: min {df.precision.min():.4f}, recall below CBH: min {df.recall_below_cbh.min():.4f}; "
        f"|CBH est − true| median {np.nanmedian(np.abs(df.cbh_est - df.cbh_true)):.2f} m, "
        f"|DBH fit − true| max {np.nanmax(np.abs(df.dbh_fit - df.dbh_true)) * 100:.1f} cm"
    )
    ok = (
        per_plot.max() <= TARGET_PLOT_S
        and df.mean_dist_cm.max() <= 100 * TARGET_MEAN_M
        and df.max_extent_cm.max() <= 100 * TARGET_EXTENT_M
    )
    print("targets met" if ok else "TARGETS MISSED")
    benchresult.record(depth=args.depth, per_plot_s=per_plot.to_dict(), trees=df.to_dict("records"),
                       targets_met=bool(ok))
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(benchresult.run("bench_stems", main))
