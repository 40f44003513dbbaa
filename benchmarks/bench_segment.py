"""Benchmark: segmentation of one plot of a recorded virtual forest (all TLS scans).

Target (issue tracker): ≤ 5 min per plot on 2 cores for the default forest (8 scans at 0.1°,
~6 M points). Times reading, segmenting and writing (``segmented.laz``, ``trees.csv``,
``trees/{id}.laz``, ``dtm.npz``) with :func:`vlsforest.segment.segment_files`, then, when the
forest's ``truth/`` folder is present, prints the accuracy against it: target stems found (F1,
matching within 0.5 m; a false positive is a found stem that matches no true stem and stands
within 5 m of a target), mean per-tree point IoU of the targets, DBH and stem-base errors of
all matched stems.

Usage::

    python benchmarks/bench_segment.py [FOREST_DIR] [--plot P5] [--out DIR] [--set KEY=VALUE ...]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

from vlsforest.segment import SegmentConfig, match_stems, segment_files

import benchresult

TARGET_S = 300.0


def _accuracy(forest: Path, plot: str, scans, res) -> None:
    truth_csv = forest / "truth" / "trees.csv"
    if not truth_csv.is_file():
        print("no truth folder: accuracy not measured")
        return
    lab = np.concatenate([np.load(forest / "truth" / plot / "tls" / f"{p.stem}_labels.npz")["tree_id"] for p in scans])
    truth = pd.read_csv(truth_csv)
    truth = truth[truth["plot"] == plot].reset_index(drop=True)
    targets = truth[truth["target"]].reset_index(drop=True)
    trees = res.trees
    txy = trees[["x", "y"]].to_numpy()
    pairs = match_stems(txy, targets[["x", "y"]].to_numpy(), 0.5)
    all_pairs = match_stems(txy, truth[["x", "y"]].to_numpy(), 0.5)
    unmatched = np.setdiff1d(np.arange(len(trees)), [f for f, _ in all_pairs])
    fp = 0
    if len(unmatched):
        d = np.hypot(txy[unmatched, 0, None] - targets["x"].to_numpy()[None],
                     txy[unmatched, 1, None] - targets["y"].to_numpy()[None])
        fp = int((d.min(axis=1) < 5.0).sum())
    tp = len(pairs)
    f1 = 2 * tp / (2 * tp + fp + len(targets) - tp) if len(targets) else float("nan")
    ext = json.loads((forest / "plots" / plot / "plot.json").read_text())["extent"]
    inside = truth["x"].between(ext[0], ext[2]) & truth["y"].between(ext[1], ext[3])
    n_in = int(inside.sum())
    found_in = sum(1 for _, t in all_pairs if inside[t])
    print(f"stems: {len(trees)} found, {len(all_pairs)} match a true stem; "
          f"{found_in} of {n_in} true stems inside the plot found")
    print(f"targets: {tp} of {len(targets)} found, {fp} false positives near them, F1 = {f1:.3f}")
    for f, t in pairs:
        T = lab == targets["tree_id"][t]
        P = res.tree_id == trees["tree_id"][f]
        iou = (T & P).sum() / (T | P).sum()
        print(f"  target {targets['tree_id'][t]} ({targets['species'][t]}): IoU {iou:.3f}, "
              f"DBH {trees['dbh'][f]:.3f} vs {targets['dbh'][t]:.3f} m, "
              f"height {trees['height'][f]:.1f} vs {targets['height'][t]:.1f} m, "
              f"{int((T & P).sum())} of {int(T.sum())} points")
    if pairs:
        ious = [((lab == targets["tree_id"][t]) & (res.tree_id == trees["tree_id"][f])).sum()
                / ((lab == targets["tree_id"][t]) | (res.tree_id == trees["tree_id"][f])).sum() for f, t in pairs]
        print(f"mean target IoU: {np.mean(ious):.3f}")
    if all_pairs:
        dbh = np.array([trees["dbh"][f] - truth["dbh"][t] for f, t in all_pairs])
        dz = np.array([trees["z"][f] - truth["z_ground"][t] for f, t in all_pairs])
        print(f"DBH error of {len(dbh)} matched stems: median |e| {np.median(np.abs(dbh)) * 100:.2f} cm, "
              f"median e {np.median(dbh) * 100:+.2f} cm; stem base z: median |e| {np.median(np.abs(dz)) * 100:.2f} cm")
    g = res.classification == 2
    print(f"ground: recall {(g & (lab == 0)).sum() / max((lab == 0).sum(), 1):.4f}, "
          f"precision {(g & (lab == 0)).sum() / max(g.sum(), 1):.4f}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("forest", nargs="?", default="/tmp/lead/default_forest3", type=Path)
    ap.add_argument("--plot", default="P5")
    ap.add_argument("--out", type=Path, default=None, help="output folder (default: a temporary one)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a segmentation setting other than its default (repeatable), e.g. edge_power=2")
    args = ap.parse_args(argv)
    settings = {}
    for kv in args.set:
        key, _, val = kv.partition("=")
        settings[key] = json.loads(val)
    tls = args.forest / "plots" / args.plot / "tls"
    scans = sorted(tls.glob("scan_*.laz"), key=lambda p: int(p.stem.split("_")[1]))
    if not scans:
        print(f"no scans under {tls}")
        return 1
    with tempfile.TemporaryDirectory() as tmp:
        out = args.out or Path(tmp) / "seg"
        t0 = time.perf_counter()
        res = segment_files(scans, out, SegmentConfig.from_dict(settings))
        total = time.perf_counter() - t0
        i = res.info
        print(f"plot {args.plot}: {len(scans)} scans, {i['n_points']} points, {i['n_voxels']} voxels, "
              f"{i['n_edges']} edges, {len(res.trees)} trees")
        print(f"time: read {i['t_read_s']:.1f} s, ground {i['t_ground_s']:.1f} s, seeds {i['t_seeds_s']:.1f} s, "
              f"growth {i['t_growth_s']:.1f} s, write {i['t_write_s']:.1f} s; total {total:.1f} s "
              f"(target ≤ {TARGET_S:.0f} s: {'OK' if total <= TARGET_S else 'TOO SLOW'})")
        print(f"stem bridges {i['n_bridges']}, unreached voxels {i['unreached']}, attached {i['attached']}")
        _accuracy(args.forest, args.plot, scans, res)
        benchresult.record(plot=args.plot, scans=len(scans), points=i["n_points"], trees=len(res.trees),
                           seconds_total=total, target_s=TARGET_S, settings=settings,
                           **{k: v for k, v in i.items() if k.startswith("t_")})
    return 0


if __name__ == "__main__":
    raise SystemExit(benchresult.run("bench_segment", main))
