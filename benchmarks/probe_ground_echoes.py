"""Probe: the ground observables from all ground echoes vs single-return ground echoes only.

Reads a case that ``bench_diagnose.py`` has run (its quick view and "real" recording under
``--workdir``) and prints the mean residual (real − simulated, in SD units of the residual as
given) of ``ground_sd_nadir``, ``ground_sd_growth`` (``ground_sd_local`` until session 37),
``ground_dz_lines`` and ``ground_share_pct`` for each assignment,
once with every ground echo and once with the ground echoes of single-return pulses only; also
the real trees' mean of the first three. Session 25 (README, "Diagnosis"), seed 0's ellipse:

    python benchmarks/bench_diagnose.py --seeds 0 --cases elliptical_footprint --real-quality 5 \\
        --sim-quality 5 --workdir /tmp/diag
    python benchmarks/probe_ground_echoes.py --workdir /tmp/diag --seed 0 --case elliptical_footprint \\
        --assign '{"none": {}, "truth": {"elliptical_footprint": {"major_mrad": 1.6, "minor_mrad": 0.5}},
                   "circle": {"beam_divergence": {"scale": 3.039}}}'

Six traced simulations (≈ 5 min on 2 cores at 61 sub-rays).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "workflow"))

GROUND = ("ground_sd_nadir", "ground_sd_growth", "ground_dz_lines", "ground_share_pct")


def main(argv=None) -> int:
    from bench_diagnose import add_case_arguments, case_setup
    from vlsforest.diagnose import core
    from vlsforest.diagnose.features import FEATURES

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_case_arguments(ap)
    ap.add_argument("--assign", required=True, help="JSON: label → candidate assignment")
    a = ap.parse_args(argv)
    assigns = json.loads(a.assign)
    orig = core.tree_features
    single = {"on": False}

    def features(arrays, labels, trees, columns=None):
        if single["on"]:  # ground echoes of pulses with more than one return are not ground here
            arrays = dict(arrays)
            cls = np.array(arrays["classification"])
            cls[(cls == 2) & (np.asarray(arrays["number_of_returns"]) > 1)] = 0
            arrays["classification"] = cls
        return orig(arrays, labels, trees, columns)

    core.tree_features = features
    for on in (False, True):
        single["on"] = on
        study = core._Study(case_setup(a), lambda m: print(m, file=sys.stderr))
        sd = np.nanstd(study.residual({}), axis=0, ddof=1)
        print("single-return ground echoes only" if on else "all ground echoes")
        for label, assign in assigns.items():
            m = np.nanmean(study.residual(assign), axis=0) / sd
            print(f"  {label:10s}", {f: round(float(m[FEATURES.index(f)]), 2) for f in GROUND})
        print("  real mean", {f: round(float(study.real[f].mean()), 4) for f in GROUND[:3]})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
