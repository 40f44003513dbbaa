"""``vlsforest simulate SCENE.yaml SURVEY.yaml -o OUT.laz`` — run the LiDAR simulator."""

from __future__ import annotations

import sys

from vlsforest.commands import JSON, LAS, NPZ, PULSES, check_workers, declare_outputs


def register(sub) -> None:
    """Add the ``simulate`` sub-command."""
    p = sub.add_parser("simulate", help="simulate a laser scanning survey over a scene",
                       description="Simulate a survey (SURVEY.yaml) over a scene (SCENE.yaml) and write LAS/LAZ.")
    p.add_argument("scene", help="SCENE.yaml")
    p.add_argument("survey", help="SURVEY.yaml")
    p.add_argument("-o", "--output", required=True, help="output LAS/LAZ (LAZ when it ends in .laz)")
    p.add_argument("--seed", type=int, default=None, help="noise seed (default: the survey's seed, else 0)")
    p.add_argument("--pulses", default=None, help="also write the per-pulse table (.npz or .csv)")
    p.add_argument("--hits", default=None, help="also write the sub-ray hits (.npz) for 'vlsforest detect'")
    p.add_argument("--workers", type=int, default=None, help="worker processes, ≥ 1 (default: all CPUs)")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.add_argument("--timing", default=None, help="also write the run's timings and counts as JSON")
    p.add_argument("--region", type=float, nargs=4, default=None, metavar=("XMIN", "YMIN", "XMAX", "YMAX"),
                   help="trace only pulses whose beam reaches this horizontal box (others are emitted, no returns)")
    p.add_argument("--region-from", default=None, metavar="SITE.json",
                   help="region = the 'targets_extent' of a site.json (vlsforest scene targets) widened by --region-margin")
    p.add_argument("--region-margin", type=float, default=1.0,
                   help="margin around the targets (m, default 1: the workflow's simulation.region_margin_m)")
    p.set_defaults(func=run)
    declare_outputs(p, output=LAS, pulses=PULSES, hits=NPZ, timing=JSON)


def run(args) -> int:
    """Execute ``vlsforest simulate``."""
    from vlsforest.io.atomic import write_text
    from vlsforest.sim import (Scene, load_survey, save_hits, simulate, simulate_to_las, write_points,
                               write_pulses)

    if not args.region_margin >= 0:
        from vlsforest.errors import ConfigError

        raise ConfigError(f"--region-margin must be ≥ 0 (m), got {args.region_margin}")
    check_workers(args.workers)
    scene = Scene.from_yaml(args.scene)
    survey = load_survey(args.survey)
    region = args.region
    if args.region_from is not None:
        from vlsforest.sim.scene_file import targets_region

        region, m = targets_region(args.region_from, float(args.region_margin), scene.max_voxel_size)
        if m > args.region_margin:
            # a target's voxels reach one cell diagonal beyond its TLS points (the extent's source):
            # a narrower margin would lose returns of the outermost cells
            print(f"simulate: region margin widened from {args.region_margin:g} to {m:.3f} m (the scene's "
                  f"{scene.max_voxel_size:g} m cells reach that far beyond the targets' points)", file=sys.stderr)
    if args.pulses or args.hits:
        res = simulate(scene, survey, seed=args.seed, workers=args.workers, keep_hits=args.hits is not None,
                       keep_pulses=args.pulses is not None, progress=not args.quiet, region=region)
        write_points(args.output, res)
        if args.pulses:
            write_pulses(args.pulses, res)
        if args.hits:
            save_hits(args.hits, res, scene, survey.scanner)
        t = res.timings
    else:  # the returns go to the file block by block: no pulse table, no joined cloud
        t = simulate_to_las(scene, survey, args.output, seed=args.seed, workers=args.workers,
                            progress=not args.quiet, region=region)
    if args.timing:
        import json

        write_text(args.timing, json.dumps({k: (float(v) if isinstance(v, float) else v)
                                            for k, v in t.items()}, indent=1, sort_keys=True) + "\n")
    if not args.quiet:
        print(f"simulate: {t['n_pulses']} pulses, {t['n_points']} points in {t['total']:.1f} s "
              f"({t['n_pulses'] / max(t['total'], 1e-9):,.0f} pulses/s) → {args.output}", file=sys.stderr)
    return 0
