"""Probe: does the ground in open cells show the beam's aspect ratio, free of the voxel model?

The ellipse's aspect fit rested on the all-echo ground roughness (``ground_sd_local`` until
session 37; here ``ground_sd_all``; README, "Diagnosis", sessions 26–29), which the voxel
reconstruction biases: ground echoes under a crown share their pulse with vegetation, and the
waveform's peaks merge. On bare, flat ground the beam's shape
still acts (the footprint's range spread at oblique incidence shifts and widens the echo), so
the ground observables computed only in *open* cells — 1 m cells where no return of the whole
recording (any flight line) is above ground — might see the aspect without the mixing. Per tree
(the ground column under its crown + 2 m, as the diagnosis' ground observables) this probe
computes that roughness and ``ground_dz_lines`` from the open cells' ground echoes only, and
beside them the diagnosis' own ground observables, for the quick forest's ULS recorded with the
hidden ellipse 1.6 × 0.5 mrad (aspect 3.2; ``bench_diagnose.py``'s ``elliptical_footprint`` case
at 61 sub-rays) and simulations of the tool's view with several beams. It prints the simulated
mean over trees and the t-value of the residual real − simulated across trees:

    python benchmarks/probe_open_ground.py --workdir /tmp/diag --seed 0
    python benchmarks/probe_open_ground.py --workdir /tmp/diag --seed 0 --truth-scene

(the first simulates the voxel reconstruction, four traces at 61 sub-rays, ≈ 4 min on 2 cores
after the quick workflow and the recording; the second the true leaves, two traces).

    python benchmarks/probe_open_ground.py --plane

prints the physics behind the idea on a bare plane (the miniVUX at 70 m, 61 sub-rays, ≈ 30 s):
the mean ground height per 10° of scan angle for the hidden ellipse and the circle of its solid
angle.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "workflow"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

#: the columns printed: the open-cell observables and the diagnosis' own ground observables
COLS = ("open_sd", "open_dz", "open_n", "ground_sd_all", "ground_dz_lines", "ground_sd_single", "ground_dz_single")


def open_ground(arrays: dict, trees: pd.DataFrame, cell: float = 1.0, pad: float = 2.0) -> pd.DataFrame:
    """Per tree: (SD about local planes, median offset between lines) in cm of the ground echoes
    in open cells (no non-ground return of any line in the cell) under the crown + ``pad``, and
    their number."""
    from vlsforest.diagnose.features import _ground_stats

    xyz = arrays["xyz"]
    ground = np.asarray(arrays["classification"]) == 2
    ij = np.floor(xyz[:, :2] / cell).astype(np.int64)
    lo = ij.min(axis=0)
    k = ij - lo
    span = k.max(axis=0) + 1
    code = k[:, 0] * span[1] + k[:, 1]
    veg = np.zeros(int(span[0] * span[1]), bool)
    veg[code[~ground]] = True
    openg = ground & ~veg[code]
    g = xyz[openg]
    line = np.asarray(arrays["point_source_id"])[openg]
    rows = {}
    for t in trees.itertuples():
        d = np.hypot(g[:, 0] - t.x, g[:, 1] - t.y) <= t.crown_radius + pad
        sd, dz = _ground_stats(g[d], line[d])
        rows[int(t.tree_id)] = {"open_sd": 100.0 * sd, "open_dz": 100.0 * dz, "open_n": float(d.sum())}
    return pd.DataFrame.from_dict(rows, orient="index")


def plane_heights() -> None:
    """Mean height (mm) of the echoes from a horizontal plane per 10° of off-nadir angle, for the
    ellipse 1.6 × 0.5 mrad (FWHM) and the circle of its solid angle."""
    from vlsforest.sim import Scene, simulate
    from vlsforest.sim.scanner import fwhm_to_1e2
    from vlsforest.sim.survey import survey_from_dict

    sc = Scene()
    sc.add_plane(1, 0.0, [-300, -300, 300, 300])
    major, minor = fwhm_to_1e2(1.6), fwhm_to_1e2(0.5)
    circle = float(np.sqrt(major * minor))
    bins = np.arange(0, 75, 10)
    for name, div in (("ellipse 1.6 × 0.5", [major, minor]), ("circle of its solid angle", [circle, circle])):
        sv = survey_from_dict({"scanner": "riegl_minivux1uav", "seed": 0, "overrides": {
            "prf_hz": 20000, "scan_freq_hz": 50, "scan_angle_deg": 70.0, "range_min_m": 0.0,
            "beam_divergence_mrad": div, "beam_sample_quality": 5},
            "platform": {"speed_mps": 5.0, "legs": [{"start": [0, -5, 70.0], "end": [0, 5, 70.0], "active": True}]}})
        r = simulate(sc, sv, workers=2)
        p = np.searchsorted(r.pulses["slot"], r.points["pulse"])
        ang = np.degrees(np.arccos(np.clip(-r.pulses["direction"][p, 2], -1, 1)))
        idx = np.digitize(ang, bins)
        z = r.points["xyz"][:, 2]
        print(f"{name}: mean height (mm) per 10° from nadir: "
              + ", ".join(f"{1000 * z[idx == i].mean():.1f}" for i in range(1, len(bins)) if (idx == i).any()))


def main(argv=None) -> int:
    if "--plane" in (sys.argv[1:] if argv is None else argv):
        plane_heights()
        return 0
    from probe_beam_anisotropy import ground_sd_all, probe_arguments, probe_setup

    from vlsforest.diagnose import core
    from vlsforest.diagnose.features import cloud_arrays
    from vlsforest.io.las import read_las

    a = probe_arguments(__doc__, argv)
    setup, assign = probe_setup(a)
    got: list = []
    orig = core.tree_features

    def features(arrays, labels, trees, columns=None):
        f = orig(arrays, labels, trees, columns)
        og = open_ground(arrays, trees)
        og["ground_sd_all"] = ground_sd_all(arrays, trees).reindex(og.index)
        for c in ("ground_dz_lines", "ground_sd_single", "ground_dz_single"):
            og[c] = 100.0 * f[c].reindex(og.index)
        got.append(og)
        return f

    core.tree_features = features
    study = core._Study(setup, lambda m: print(m, file=sys.stderr))
    plot = study.plots[0]
    plot._features(cloud_arrays(read_las(plot.p.real)))
    real = got.pop()
    print(f"seed {a.seed}, {'true leaves' if a.truth_scene else 'voxels: ' + a.method}; "
          f"real: {', '.join(f'{k} {real[k].mean():.3f}' for k in COLS)} (cm; open_n: echoes)")
    print("assignment | " + " | ".join(f"{k}: sim (t)" for k in COLS))
    for label, asg in assign.items():
        study.sim(asg)
        sim = got.pop()
        cells = []
        for k in COLS:
            r = (real[k] - sim[k]).dropna()
            t = r.mean() / r.std(ddof=1) * np.sqrt(len(r)) if len(r) > 2 and r.std(ddof=1) > 0 else np.nan
            cells.append(f"{sim[k].mean():.3f} ({t:+.1f}, n {len(r)})")
        print(f"{label} | " + " | ".join(cells), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
