"""Probe: which observables set a candidate's fitted value, and how far each is from the truth.

Reads a case that ``bench_diagnose.py`` has run (its quick view and "real" recording under
``--workdir``), fits ``--candidate`` from ``--base`` exactly as a diagnosis stage does
(``core._fit``: the signature's information weights, the grid, the crossing votes) and prints
every vote — the observable, where its mean residual crosses zero along the grid, its share of
the weight — beside the observable's mean residual when the simulation is told the truth
(``--truth``, in SD units of the residual at ``--base``): a voter whose told-the-truth residual
is far from 0 is pulled by the reconstruction's own error. Session 26, seed 1's ellipse:

    python benchmarks/bench_diagnose.py --seeds 1 --cases elliptical_footprint --real-quality 5 \\
        --sim-quality 5 --workdir /tmp/diag
    python benchmarks/probe_fit_votes.py --workdir /tmp/diag --seed 1 --case elliptical_footprint \\
        --candidate elliptical_footprint --base '{"beam_divergence": {"scale": 3.0424837088067482}}' \\
        --truth '{"elliptical_footprint": {"major_mrad": 1.6, "minor_mrad": 0.5}}'

Eight traced simulations for the ellipse (≈ 7 min on 2 cores at 61 sub-rays).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "workflow"))


def main(argv=None) -> int:
    from bench_diagnose import add_case_arguments, case_setup
    from vlsforest.diagnose import core
    from vlsforest.diagnose import library as lib
    from vlsforest.diagnose import stats as st
    from vlsforest.diagnose.features import FEATURES

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_case_arguments(ap)
    ap.add_argument("--candidate", required=True)
    ap.add_argument("--base", default="{}", help="JSON: the assignment the stage starts from")
    ap.add_argument("--truth", required=True, help="JSON: the hidden assignment (the oracle)")
    ap.add_argument("--sim-quality", type=int, default=5)
    a = ap.parse_args(argv)
    setup = case_setup(a)
    setup.beam_sample_quality = a.sim_quality
    study = core._Study(setup, lambda m: print(m, file=sys.stderr))
    base, truth = json.loads(a.base), json.loads(a.truth)
    cand = lib.CANDIDATES[a.candidate]
    w = st.weights(study.residual({}))  # as the diagnosis: from the residual as given
    study.pin(base)
    D = study.residual(base)
    _, sigs, _ = core._attribute(study, base, [cand], D, w)  # its signature, as the stage makes it
    wfit = w * st.information_weights(sigs[cand.name], D)
    rng = np.random.default_rng(setup.seed)
    folds = np.arange(len(D)) % setup.folds
    allv, _, ci, info = core._fit(study, base, cand, wfit, folds, setup.grid, rng)
    votes = info["votes"]
    sd = np.nanstd(D, axis=0, ddof=1)
    told = np.nanmean(study.residual(truth), axis=0) / sd
    print(f"{cand.name} from {base}: {allv} (CI of {cand.params[0].name}: {ci})")
    for par, r in info["rests_on"].items():
        print(f"{par} rests on {r['observable']} ({100 * r['weight_share']:.1f} % of the weight); "
              f"{r['without_it']:.4g} without it")
    for par, v in votes.items():
        print(f"votes on {par}:")
        for f, x in v.items():
            j = FEATURES.index(f)
            print(f"  {f:22s} crossing {x['crossing']:8.3f}  weight {x['weight_share']:6.3f}  "
                  f"told the truth {told[j]:+6.2f} SD")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
