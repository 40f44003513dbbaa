"""Benchmark of the PAD stage on one recorded plot (default: the largest plot of a forest folder).

    python benchmarks/bench_pad.py FOREST_DIR [--plot P5] [--validate] [--out DIR] [--scans K ...]

Times loading the shots (empty shots rebuilt from the scan pattern), the traversal, both
estimators and the ``.vox`` export, and prints the figures; with ``--validate`` also the
validation against the virtual truth (table and figure written to ``--out``). The target is the
largest default plot in ≤ 10 min on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import benchresult


def _largest_plot(forest: Path) -> str:
    best, area = None, -1.0
    for info in sorted((forest / "plots").glob("*/plot.json")):
        a = float(json.loads(info.read_text())["area_ha"])
        if a > area and (info.parent / "tls").is_dir():
            best, area = info.parent.name, a
    if best is None:
        sys.exit(f"no plot with a tls/ folder under {forest / 'plots'}")
    return best


def main(argv=None) -> int:
    from vlsforest.io.vox import write_vox
    from vlsforest.pad import accumulate, estimate_pad, grid_for_scans, load_tls_scans, pad_to_vox
    from vlsforest.pad_validation import validate_pad

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("forest", type=Path)
    ap.add_argument("--plot")
    ap.add_argument("--validate", action="store_true")
    ap.add_argument("--out", type=Path)
    ap.add_argument("--scans", type=int, nargs="+", help="use only these scan ids")
    a = ap.parse_args(argv)
    plot = a.plot or _largest_plot(a.forest)
    out = a.out or Path(tempfile.mkdtemp(prefix="bench_pad_"))
    out.mkdir(parents=True, exist_ok=True)
    tls = a.forest / "plots" / plot / "tls"
    extent = json.loads((tls.parent / "plot.json").read_text())["extent"]
    t = {}
    t0 = time.perf_counter()
    scans = load_tls_scans(tls, scan_ids=a.scans)
    t["load_s"] = time.perf_counter() - t0
    from vlsforest.commands.pad import low_return_scans

    for msg in low_return_scans(scans):
        print(f"warning: {msg}")
    n_shots = sum(sc.n_shots for sc in scans)
    n_echoes = sum(sc.n_echoes for sc in scans)
    origin, shape = grid_for_scans(scans, 0.25, extent)
    t1 = time.perf_counter()
    acc = accumulate(scans, origin, 0.25, shape)
    t["traverse_s"] = time.perf_counter() - t1
    del scans
    t2 = time.perf_counter()
    res = {}
    for est in ("transmittance", "fpl_unbiased"):
        res[est] = estimate_pad(acc, lad="planophile", pad_max=5.0, estimator=est)
    t["estimate_s"] = time.perf_counter() - t2
    t3 = time.perf_counter()
    vox = pad_to_vox(acc, *res["transmittance"], 5.0)
    write_vox(out / f"{plot}.vox", vox)
    t["vox_s"] = time.perf_counter() - t3
    t["pad_total_s"] = time.perf_counter() - t0
    print(f"plot {plot}: {acc.info['n_scans']} scans, {n_shots:,} shots, {n_echoes:,} echoes")
    print(f"grid {shape[0]}×{shape[1]}×{shape[2]} = {int(np.prod(shape)):,} voxels at 0.25 m, "
          f"{acc.info['crossings']:,} voxel crossings ({acc.info['crossings'] / n_shots:.0f} per shot), "
          f"{acc.info['n_hit_voxels']:,} voxels with plant echoes, {vox.n_voxels:,} rows in the .vox")
    print(f"throughput {acc.info['crossings'] / t['traverse_s'] / 1e6:.1f} M crossings/s")
    for k, v in t.items():
        print(f"{k:>14}: {v:8.1f}")
    if a.validate:
        t4 = time.perf_counter()
        table, _ = validate_pad(acc, a.forest, plot, table_path=out / f"{plot}_validation.csv",
                                figure_path=out / f"{plot}_validation.png")
        print(f"{'validate_s':>14}: {time.perf_counter() - t4:8.1f}")
        with np.printoptions(precision=2):
            import pandas as pd

            with pd.option_context("display.width", 200, "display.max_rows", 200):
                print(table.to_string(index=False, float_format=lambda x: f"{x:.2f}"))
        from vlsforest.pad_validation import median_abs_bias

        capped = median_abs_bias(table, "bias_pct_capped")
        for est, m in median_abs_bias(table).items():
            print(f"median |bias| over species × crown thirds, {est}: {m:.1f} % "
                  f"({capped[est]:.1f} % against the truth capped at PADmax)")
    print(f"outputs in {out}")
    benchresult.record(plot=plot, scans=acc.info["n_scans"], shots=n_shots, echoes=n_echoes,
                       crossings=acc.info["crossings"], **t)
    return 0


if __name__ == "__main__":
    sys.exit(benchresult.run("bench_pad", main))
