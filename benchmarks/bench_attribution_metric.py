"""Benchmark: the attribution's explained fraction in the diagonal vs a covariance-whitened metric.

Offline re-ranking of the diagnosis campaign's cases (``bench_diagnose.py`` work folder; the
diagnosis itself has the whitened metric as the option ``metric: whitened``, this compares both
metrics on stored recordings without full runs): for one forest seed the candidates'
signatures are simulated once on that seed's quick view, then each case's "real" recording
gives a residual, and every candidate's explained fraction is computed

* as the diagnosis does (weights 1 / across-tree variance per observable: a diagonal metric), and
* in the metric of the across-tree residual covariance (observables standardised, correlation
  shrunk towards the identity with the Ledoit–Wolf intensity), where strongly correlated
  observables — e.g. the seven views of the return structure — count once, not seven times.

Prints per case the chance level and the five candidates with the largest whitened fraction as
``(name, diagonal EV, whitened EV, whitened amplitude in signature steps)``.

    python benchmarks/bench_attribution_metric.py --workdir /tmp/camp 0 w2:trajectory_noise w:null

Each case argument is ``ROOT:CASE`` with the case's recording in
``WORKDIR/ROOT/seed{SEED}/CASE/forest`` and the seed's view (``sim.yaml``) in
``WORKDIR/w/seed{SEED}``. Uses the diagnosis internals; a study's first case costs the signature
simulations (≈ 2–3 min on 2 cores), each further case only reads its recording.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/vlsforest-bench-diagnose"))
    ap.add_argument("seed", type=int)
    ap.add_argument("cases", nargs="+", help="ROOT:CASE")
    a = ap.parse_args(argv)
    from vlsforest.diagnose import core, library as lib, stats as st

    cfg = a.workdir / "w" / f"seed{a.seed}" / "sim.yaml"
    S0 = sigs = None
    for rc in a.cases:
        root, case = rc.split(":")
        setup = core.load_setup(cfg, real_dir=a.workdir / root / f"seed{a.seed}" / case / "forest" / "plots")
        if sigs is None:
            study = core._Study(setup, lambda m: None)
            S0 = study.sim({})
            D0 = study.residual({})
            _, sigs, _ = core._attribute(study, {}, lib.select(None), D0, st.weights(D0))
        else:
            real = core._Study(setup, lambda m: None).real
            D0 = (real - S0.reindex(real.index)).to_numpy(float)
        w = st.weights(D0)
        rbar = np.nanmean(D0, 0)
        ok = np.isfinite(rbar) & (w > 0)  # the observables both metrics use (chance level's m)
        sd, R, lam = st.shrunk_correlation(D0)
        rows = []
        for name, J in sigs.items():
            ev = st.project(rbar, J, w)[1]
            aw, evw, _ = st.project_whitened(rbar, J, w, sd, R)
            rows.append((name, round(max(ev, 0.0), 3), round(evw, 3), round(aw, 2)))
        rows.sort(key=lambda x: -x[2])
        print(json.dumps({"seed": a.seed, "case": rc, "shrinkage": round(lam, 2),
                          "chance": round(st.chance_ev(int(ok.sum()), len(rows)), 3),
                          "top (name, ev_diagonal, ev_whitened, amplitude)": rows[:5]}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
