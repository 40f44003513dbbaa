"""Benchmark: what the inter-echo observables of the diagnosis see, real vs voxel simulation.

On one forest seed of the campaign (``bench_diagnose.py`` must have built its quick view and its
null "real" ULS recording first), the per-tree percentiles of the inter-echo distances (3-D
distance between consecutive echoes of one pulse within a tree) of the "real" ULS and of the
diagnosis' simulations of the voxel reconstruction at several detection windows. It shows why
``interecho_floor`` (the 1st percentile) separates a dead-zone change from the reconstruction's
error: the reconstruction moves the 10th percentile and the median, the window moves the floor.

    python benchmarks/bench_interecho_floor.py --workdir /tmp/s21/diag --seed 2 --real-quality 5 --sim-quality 5

Prints, per cloud, the mean and SD over trees of each percentile. About 3 min on 2 cores.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

QUANTILES = (0.1, 1, 5, 10, 50)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/vlsforest-bench-diagnose"))
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--real-quality", type=int, default=5)
    ap.add_argument("--sim-quality", type=int, default=5)
    ap.add_argument("--windows", type=float, nargs="+", default=[1.5, 1.42, 1.0])
    a = ap.parse_args(argv)
    from vlsforest.diagnose import core, load_setup
    from vlsforest.diagnose.features import _interecho, _pulse_key
    from vlsforest.extract import _ColumnIndex

    wd = a.workdir / f"seed{a.seed}"
    real = wd / ("null" + ("" if a.real_quality == 4 else f"_q{a.real_quality}")) / "forest" / "plots"
    cfg = wd / "sim.yaml"
    if not (real / "Q1" / "uls.laz").is_file() or not cfg.is_file():
        raise SystemExit(f"{real}: run bench_diagnose.py --seeds {a.seed} --cases null "
                         f"--real-quality {a.real_quality} first")
    setup = load_setup(cfg, real_dir=real)
    captured = {}  # the arrays of the last cloud whose observables were computed
    features = core._PlotSim._features

    def capture(self, arrays):
        captured["arrays"] = arrays
        return features(self, arrays)

    core._PlotSim._features = capture
    ps = core._PlotSim(setup.plots[0], 0, setup.workers, lambda m: None, a.sim_quality, None)
    real_arrays = captured["arrays"]  # the "real" ULS, read once by the diagnosis itself

    def per_tree(arrays):
        lab = ps._label(arrays, _ColumnIndex(arrays["xyz"][:, :2]))
        rows = []
        for tid in ps.trees.tree_id.astype(int):
            idx = np.flatnonzero(lab == tid)
            ie = _interecho(arrays["xyz"][idx], _pulse_key(arrays, idx), np.asarray(arrays["return_number"][idx]))
            if len(ie) >= 10:
                rows.append(np.percentile(ie, QUANTILES))
        r = np.array(rows)
        return "  ".join(f"p{q:g} {m:.3f} ± {s:.3f}" for q, m, s in zip(QUANTILES, r.mean(0), r.std(0))) + f"  ({len(r)} trees)"

    print(f"seed {a.seed}, real ULS at quality {a.real_quality}, simulation at {a.sim_quality} (m, mean ± SD over trees)")
    print(f"{'real':>18s}  {per_tree(real_arrays)}", flush=True)
    for w in a.windows:
        ps.features({"waveform_window": {"window_ns": w}})
        print(f"{f'voxels, {w:g} ns':>18s}  {per_tree(captured['arrays'])}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
