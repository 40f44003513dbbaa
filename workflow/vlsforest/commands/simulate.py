"""``vlsforest simulate SCENE.yaml SURVEY.yaml -o OUT.laz`` — run the LiDAR simulator."""

from __future__ import annotations

import sys


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
    p.add_argument("--workers", type=int, default=None, help="worker processes (default: all CPUs)")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=run)


def run(args) -> int:
    """Execute ``vlsforest simulate``."""
    from vlsforest.sim import Scene, load_survey, save_hits, simulate, write_points, write_pulses

    scene = Scene.from_yaml(args.scene)
    survey = load_survey(args.survey)
    res = simulate(scene, survey, seed=args.seed, workers=args.workers, keep_hits=args.hits is not None,
                   keep_pulses=args.pulses is not None, progress=not args.quiet)
    write_points(args.output, res)
    if args.pulses:
        write_pulses(args.pulses, res)
    if args.hits:
        save_hits(args.hits, res, scene)
    t = res.timings
    if not args.quiet:
        print(f"simulate: {t['n_pulses']} pulses, {t['n_points']} points in {t['total']:.1f} s "
              f"({t['n_pulses'] / max(t['total'], 1e-9):,.0f} pulses/s) → {args.output}", file=sys.stderr)
    return 0
