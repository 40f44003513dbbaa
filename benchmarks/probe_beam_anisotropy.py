"""Probe: does the offset of ULS echoes from the TLS points show the beam's aspect ratio?

An echo lies on the beam's centre ray at the range of whatever the footprint hit, so it sits off
the hit surface by up to the footprint's half-width, and an elliptical footprint (major axis along
the scan, i.e. across the flight line) displaces echoes more across-track than along-track. Per
tree this probe measures, for every first-return echo labelled to the tree, the horizontal vector
to the nearest TLS point of that tree, split into its across-track and along-track components
(the flight direction of each flight line from its echoes' positions against GPS time), and takes
``mean |across| − mean |along|`` in cm — overall and in three scan-angle strata (< 8°, 8–18°,
≥ 18°) — and beside it the all-echo ground roughness ``ground_sd_all`` (cm;
:func:`ground_sd_all`), the observable the diagnosis' aspect fit rested on until session 37, and
``ground_sd_growth``, the one it rests on since. It prints the mean residual (real − simulated), its SD across trees and the t-value for
each beam assignment, with the quick forest's ULS recorded with the ellipse 1.6 × 0.5 mrad
(aspect 3.2; ``bench_diagnose.py``'s ``elliptical_footprint`` case at 61 "real" sub-rays):

    python benchmarks/probe_beam_anisotropy.py --workdir /tmp/diag --seed 0
    python benchmarks/probe_beam_anisotropy.py --workdir /tmp/diag --seed 0 --truth-scene
    python benchmarks/probe_beam_anisotropy.py --workdir /tmp/diag --seed 0 --method fixed_0.05

The first simulates the voxel reconstruction (the diagnosis' view, four traces at 61 sub-rays,
≈ 4 min on 2 cores after the quick workflow and the recording, ≈ 4 min more the first time), the
second the true leaves (two traces, ≈ 2 min), the third the quick workflow's 0.05 m voxels
(built first if missing): on the true leaves the observable separates the
hidden ellipse from the circle of its solid angle; on the voxels the reconstruction adds a bias
and a gain of its own (README, "Diagnosis", session 29).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "workflow"))

#: the scan-angle strata (degrees of |scan angle|) besides all first returns
STRATA = {"all": (0.0, 90.0), "nadir": (0.0, 8.0), "mid": (8.0, 18.0), "off": (18.0, 90.0)}
#: assignments simulated: the study's beam, the hidden ellipse, the circle of its solid angle,
#: the ellipse of that solid angle at aspect 6
ASSIGN = {
    "as given": {},
    "hidden ellipse 1.6 × 0.5 (aspect 3.2)": {"elliptical_footprint": {"major_mrad": 1.6, "minor_mrad": 0.5}},
    "circle of its solid angle (× 3.04)": {"beam_divergence": {"scale": 3.04}},
    "same solid angle, aspect 6": {"elliptical_footprint": {"major_mrad": float(np.sqrt(0.8 * 6)),
                                                            "minor_mrad": float(np.sqrt(0.8 / 6))}},
}


def flight_directions(arrays: dict) -> dict:
    """Unit horizontal flight direction per flight line (point source id) with ≥ 100 echoes,
    from the least-squares slope of x and y against GPS time."""
    sid = np.asarray(arrays["point_source_id"])
    t = np.asarray(arrays["gps_time"], np.float64)
    xy = arrays["xyz"][:, :2]
    out = {}
    for s in np.unique(sid):
        m = sid == s
        if m.sum() < 100:
            continue
        tt = t[m] - t[m].mean()
        v = np.array([np.dot(tt, xy[m, 0]), np.dot(tt, xy[m, 1])]) / np.dot(tt, tt)
        if np.linalg.norm(v) > 0:
            out[int(s)] = v / np.linalg.norm(v)
    return out


def offset_anisotropy(arrays: dict, labels: np.ndarray, kd: dict) -> pd.DataFrame:
    """Per tree, ``mean |across| − mean |along|`` (cm) of its first returns' offsets from the
    nearest TLS point, per stratum of :data:`STRATA` (NaN with < 20 echoes)."""
    dirs = flight_directions(arrays)
    sid = np.asarray(arrays["point_source_id"])
    first = np.asarray(arrays["return_number"]) == 1
    ang = np.abs(np.asarray(arrays["scan_angle"], np.float64))
    rows = {}
    for tid, (tree, pts) in kd.items():
        m = (labels == tid) & first
        if m.sum() < 20:
            continue
        p = arrays["xyz"][m]
        _, j = tree.query(p)
        d = p[:, :2] - pts[j, :2]
        al = np.array([dirs.get(int(s), (np.nan, np.nan)) for s in sid[m]])
        along = np.abs(d[:, 0] * al[:, 0] + d[:, 1] * al[:, 1])
        across = np.abs(d[:, 1] * al[:, 0] - d[:, 0] * al[:, 1])
        row = {}
        for name, (lo, hi) in STRATA.items():
            sel = (ang[m] >= lo) & (ang[m] < hi) & np.isfinite(along)
            row[name] = 100.0 * (across[sel].mean() - along[sel].mean()) if sel.sum() >= 20 else np.nan
        rows[tid] = row
    return pd.DataFrame.from_dict(rows, orient="index")


def ground_sd_all(arrays: dict, trees) -> "pd.Series":
    """Per tree, the SD (cm) of all ground echoes under its crown (radius + the features'
    ``GROUND_PAD_M``) about per-1 m-cell, per-flight-line planes: the diagnosis' observable
    ``ground_sd_local`` until session 37, which split it by scan angle."""
    from vlsforest.diagnose.features import GROUND_PAD_M, _ground_stats

    g = np.asarray(arrays["classification"]) == 2
    xyz, line = arrays["xyz"][g], np.asarray(arrays["point_source_id"])[g]
    out = {}
    for _, t in trees.iterrows():
        m = np.hypot(xyz[:, 0] - t.x, xyz[:, 1] - t.y) <= t.crown_radius + GROUND_PAD_M
        out[int(t.tree_id)] = 100.0 * _ground_stats(xyz[m], line[m])[0]
    return pd.Series(out, dtype=float)


def probe_arguments(doc: str, argv=None):
    """The probes' arguments (``--workdir``, ``--seed``, ``--truth-scene``, ``--method``), parsed."""
    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    ap.add_argument("--workdir", type=Path, required=True)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--truth-scene", action="store_true", help="simulate the true leaves instead of the voxels")
    ap.add_argument("--method", default="scaled",
                    help="the voxel method of the quick workflow whose scene is simulated (default scaled)")
    return ap.parse_args(argv)


def probe_setup(a):
    """The diagnosis set-up of the probes and the beam assignments to simulate: the quick
    workflow's view of seed ``a.seed`` (the ``a.method`` scene built first if missing, or the
    true leaves with ``a.truth_scene``) against its ULS recorded with the hidden ellipse at 61
    sub-rays."""
    import bench_diagnose as bd

    from vlsforest.diagnose import load_setup
    from vlsforest.sim import Scene

    bd.BASE["uls"]["beam_sample_quality"] = 5
    wd = bd._quick_view(a.seed, a.workdir)
    res = wd / "results" / "Q1"
    if not (res / a.method / "scene" / "scene.yaml").is_file():
        from wfrun import QUICK, snakemake_cli

        proc = snakemake_cli(f"results/Q1/{a.method}/scene", "--cores", 2, "--configfile", QUICK,
                             "--config", f"seed={a.seed}", cwd=wd, timeout=3600)
        if proc.returncode != 0:
            raise SystemExit(proc.stderr[-3000:])
    cfg = a.workdir / f"seed{a.seed}" / "probe_sim.yaml"
    cfg.write_text(yaml.safe_dump({"scenario": "uls", "seed": 0, "folds": 3, "beam_sample_quality": 5, "plots": {"Q1": {
        "scene": str(res / a.method / "scene" / "scene.yaml"), "survey": str(res / "surveys" / "uls.yaml"),
        "segment": str(res / "segment"), "radius": 0.3, "margin": 5}}}))
    forest = bd._record(a.seed, "elliptical_footprint", a.workdir)
    setup = load_setup(cfg, real_dir=forest / "plots")
    assign = ASSIGN
    if a.truth_scene:
        truth = bd._truth_scene(a.seed)
        Scene.from_yaml = classmethod(lambda cls, path, voxel_transform=None: truth)
        assign = {k: v for k, v in ASSIGN.items() if "hidden" in k or "circle" in k}
    return setup, assign


def main(argv=None) -> int:
    from scipy.spatial import cKDTree

    from vlsforest.diagnose import core
    from vlsforest.diagnose.features import cloud_arrays
    from vlsforest.io.las import read_las

    a = probe_arguments(__doc__, argv)
    setup, assign = probe_setup(a)
    kd: dict = {}
    got: list = []
    orig = core.tree_features

    def features(arrays, labels, trees, columns=None):
        f = orig(arrays, labels, trees, columns)
        if kd:
            an = offset_anisotropy(arrays, labels, kd)
            an["ground_sd_all"] = ground_sd_all(arrays, trees).reindex(an.index)
            an["ground_sd_growth"] = f["ground_sd_growth"].reindex(an.index)
            got.append(an)
        return f

    core.tree_features = features
    study = core._Study(setup, lambda m: print(m, file=sys.stderr))
    plot = study.plots[0]
    kd.update({tid: (cKDTree(pts), pts) for tid, pts in plot.tree_points.items()})
    plot._features(cloud_arrays(read_las(plot.p.real)))
    real = got.pop()
    cols = (*STRATA, "ground_sd_all", "ground_sd_growth")
    print(f"seed {a.seed}, {'true leaves' if a.truth_scene else 'voxels: ' + a.method}; "
          f"real: {', '.join(f'{k} {real[k].mean():+.3f}' for k in cols)} (cm; the growth: ln of a ratio)")
    print("assignment | " + " | ".join(f"{k}: sim, residual mean ± SD (t)" for k in cols))
    for label, asg in assign.items():
        study.sim(asg)
        sim = got.pop()
        cells = []
        for k in cols:
            r = (real[k] - sim[k]).dropna()
            cells.append(f"{sim[k].mean():+.3f}, {r.mean():+.3f} ± {r.std(ddof=1):.3f} "
                         f"({r.mean() / r.std(ddof=1) * np.sqrt(len(r)):+.1f})")
        print(f"{label} | " + " | ".join(cells), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
