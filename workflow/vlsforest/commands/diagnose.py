"""``vlsforest diagnose --real DIR --sim-config FILE --scenario NAME -o OUT.json`` — physics diagnosis."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from vlsforest.commands import JSON, PNG, YAML, check_workers, declare_outputs
from vlsforest.io.atomic import write_text


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
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--sim-config", metavar="FILE",
                     help="YAML naming per plot the scene, survey, segmentation folder and extraction radius")
    src.add_argument("--sim-config-json", metavar="JSON", help="the same as one JSON string (the workflow's way)")
    p.add_argument("--write-sim-config", metavar="FILE", default=None,
                   help="also write the set-up as YAML (to rerun with --sim-config)")
    p.add_argument("--scenario", required=True, metavar="NAME",
                   help="the scenario's name (a key of the config's scenarios): labels the report and names the "
                        "recording, DIR/<plot>/<NAME>.laz, unless the sim-config names one; the platform and "
                        "scanner are those of the plots' surveys")
    p.add_argument("-o", "--output", required=True, metavar="OUT.json")
    p.add_argument("--figure", default=None, metavar="PNG", help="also draw the residuals before/after")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="worker processes of the diagnosis' ray traces (default: the set-up's workers, else 2; "
                        "1 traces in this process, without moving the hits between processes; the results do "
                        "not depend on it)")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=run)
    declare_outputs(p, output=JSON, figure=PNG, write_sim_config=YAML)


def run(args) -> int:
    """Execute ``vlsforest diagnose``."""
    from vlsforest.diagnose import diagnose, load_setup

    if args.sim_config_json is not None:
        from vlsforest.errors import ConfigError

        try:
            source = json.loads(args.sim_config_json)
        except json.JSONDecodeError as exc:
            raise ConfigError(f"--sim-config-json: not valid JSON ({exc})") from None
    else:
        source = args.sim_config
    setup = load_setup(source, real_dir=args.real, scenario=args.scenario)
    if args.workers is not None:
        check_workers(args.workers)
        setup.workers = args.workers
    if args.write_sim_config:
        import yaml

        d = json.loads(args.sim_config_json) if args.sim_config_json is not None else \
            yaml.safe_load(Path(args.sim_config).read_text())
        write_text(args.write_sim_config, yaml.safe_dump(d, sort_keys=True))
    out = Path(args.output)
    # traces a later stage reads back wait beside the output, in a folder deleted at the end
    # (diagnose makes the output's folder, or says clearly why it cannot)
    rep = diagnose(setup, log=(lambda m: None) if args.quiet else None, work_dir=out.parent)
    write_text(out, json.dumps(rep, indent=1, sort_keys=True) + "\n")
    if args.figure:
        from vlsforest.diagnose.figure import plot_diagnosis

        plot_diagnosis(rep, args.figure)
    print(f"diagnose: {rep['verdict']} → {out}", file=sys.stderr)
    return 0
