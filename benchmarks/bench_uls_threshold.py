"""Experiment: a ULS detection threshold in the "real" recording vs the real Bretten ALS-vs-ULS signs.

The real Bretten trees (1,016 with both sensors) have ULS heights ≈ 0.2 m above ALS, a lower
CBH and a *smaller* CPA; the virtual forest reproduces the first two signs but not the CPA one
(README, "How the virtual forest compares"). This records the quick forest's ALS and ULS once
with the default recording physics, keeping every sub-ray hit, then re-detects the ULS with
several energy thresholds (and optionally windows) without tracing again, and prints per
setting the mean ULS − ALS height, CBH and CPA over the trees seen by both (truth labels, ≥ 50
points) and the ULS multiple-return share per species.

    python benchmarks/bench_uls_threshold.py --thresholds 0 1000 5000 10000 20000 40000

About 2 min on 2 cores.
"""

from __future__ import annotations

import argparse
import copy
import sys
from pathlib import Path

import numpy as np
import pandas as pd

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--thresholds", type=float, nargs="+", default=[0, 1000, 5000, 10000, 20000, 40000])
    ap.add_argument("--windows-ns", type=float, nargs="+", default=[0.0],
                    help="ULS window sizes to try (0: the preset's)")
    ap.add_argument("--als-thresholds", type=float, nargs="*", default=[],
                    help="also re-detect the ALS with these thresholds")
    ap.add_argument("--als-base", type=float, default=None,
                    help="ALS threshold of the ULS − ALS comparison (default: as recorded)")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)

    from conftest import QUICK_SYNTH
    from vlsforest.metrics import tree_metrics
    from vlsforest.sim import redetect, survey_from_dict, trace_hits
    from vlsforest.synth import record as R
    from vlsforest.synth.forest import forest_from_config, generate_plot_trees, truth_table

    st = R.synth_settings(QUICK_SYNTH)
    plot = forest_from_config(st["forest"], a.seed)[0]
    geoms = generate_plot_trees(plot)
    trees = truth_table([plot], geoms).set_index("tree_id")
    phys = R.validate_recording_physics(R.DEFAULT_RECORDING_PHYSICS)
    base = R.plot_scene(plot, geoms, "tls", phys.get("tls", {}))
    store = {}
    for sensor in ("als", "uls"):
        scene = R.restyle_for(base, sensor, phys[sensor])
        runs = []
        for sv in R.airborne_survey(plot, sensor, st["recordings"][sensor], phys[sensor], a.seed):
            runs.append((sv, *trace_hits(scene, survey_from_dict(sv), region=R._recording_region(plot))))
        store[sensor] = (scene.part_table(), runs)

    def metrics(sensor, overrides):
        parts, runs = store[sensor]
        pts = []
        for r, (sv, pulses, hits) in enumerate(runs):
            sv = copy.deepcopy(sv)
            sv.setdefault("overrides", {}).update(overrides)
            p = redetect(parts, pulses, hits, survey_from_dict(sv)).points
            p["point_source_id"] = p["point_source_id"].astype(np.int64) + 100 * r
            pts.append(p)
        P = {k: np.concatenate([q[k] for q in pts]) for k in pts[0]}
        tid = P["object_id"] // 10  # tree parts: object id 10·tree_id + organ group
        rows = {}
        for t in np.unique(tid[tid > 0]):
            m = tid == t
            if m.sum() >= 50:
                attrs = {k: P[k][m] for k in ("return_number", "number_of_returns", "gps_time", "point_source_id")}
                rows[t] = tree_metrics(P["xyz"][m], ground_z=trees.loc[t, "z_ground"], **attrs)
        return pd.DataFrame(rows).T

    species = trees["species"]
    print("real Bretten targets (Weiser et al. 2021): multiple returns ALS broadleaf 55.9 %, conifer"
          " 73.4 %; ULS 28.1 %, 33.1 %")
    als = metrics("als", {})
    share = als.groupby(species.loc[als.index].values)["multi_return_pct"].mean().round(1).to_dict()
    print(f"ALS multiple returns by species: {share}")
    for thr in a.als_thresholds:
        m = metrics("als", {"min_energy": thr})
        share = m.groupby(species.loc[m.index].values)["multi_return_pct"].mean().round(1).to_dict()
        print(f"ALS threshold {thr:8.0f}: multiple returns {share}", flush=True)
    if a.als_base is not None:
        als = metrics("als", {"min_energy": a.als_base})
        print(f"ULS − ALS below against the ALS re-detected with threshold {a.als_base:g}")
    for thr in a.thresholds:
        for win in a.windows_ns:
            ov = {"min_energy": thr}
            if win > 0:
                ov["window_size_ns"] = win
            uls = metrics("uls", ov)
            common = als.index.intersection(uls.index)
            d = uls.loc[common] - als.loc[common]
            share = uls.groupby(species.loc[uls.index].values)["multi_return_pct"].mean().round(1).to_dict()
            print(f"threshold {thr:8.0f}, window {win or 'preset'}: {len(common)} trees; ULS − ALS height "
                  f"{d['height'].mean():+.2f} m, CBH {d['cbh'].mean():+.2f} m, CPA {d['cpa'].mean():+.2f} m²; "
                  f"ULS multiple returns {share}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
