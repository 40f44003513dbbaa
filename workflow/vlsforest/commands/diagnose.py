"""``vlsforest diagnose --real DIR --sim-config FILE --scenario als|uls -o OUT.json`` — physics diagnosis."""

from __future__ import annotations

import json
import sys
from pathlib import Path


def register(sub) -> None:
    """Add the ``diagnose`` sub-command."""
    p = sub.add_parser(
        "diagnose", help="locate a sim-vs-real mismatch, name the missing physics, fit it, check held-out trees",
        description="Compare per-tree observables of a real recording with simulations of the voxel scenes, "
                    "locate where they differ (strata, bootstrap CIs, BH correction), rank the physics "
                    "candidates by the share of the mismatch their signature explains, fit the winner on "
                    "training trees and accept it only if held-out trees improve significantly; then look for "
                    "a second effect. Writes the JSON report (keys significant_mismatch, mismatches, effects, "
                    "accepted, verdict, …).")
    p.add_argument("--real", required=True, metavar="DIR",
                   help="folder with the real recordings, DIR/<plot>/<recording>.laz (e.g. results/forest/plots)")
    p.add_argument("--sim-config", required=True, metavar="FILE",
                   help="YAML naming per plot the scene, survey, segmentation folder and extraction radius")
    p.add_argument("--scenario", required=True, choices=("als", "uls"))
    p.add_argument("-o", "--output", required=True, metavar="OUT.json")
    p.add_argument("--figure", default=None, metavar="PNG", help="also draw the residuals before/after")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=run)


def run(args) -> int:
    """Execute ``vlsforest diagnose``."""
    from vlsforest.diagnose import diagnose, load_setup

    setup = load_setup(args.sim_config, real_dir=args.real, scenario=args.scenario)
    rep = diagnose(setup, log=(lambda m: None) if args.quiet else None)
    out = Path(args.output)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(rep, indent=1, sort_keys=True) + "\n")
    if args.figure:
        from vlsforest.diagnose.figure import plot_diagnosis

        plot_diagnosis(rep, args.figure)
    print(f"diagnose: {rep['verdict']} → {out}", file=sys.stderr)
    return 0
