"""``vlsforest detect HITS.npz SURVEY.yaml -o OUT.laz`` — re-run detection without tracing."""

from __future__ import annotations

import sys

from vlsforest.commands import LAS, PULSES, declare_outputs


def register(sub) -> None:
    """Add the ``detect`` sub-command."""
    p = sub.add_parser("detect", help="re-run waveform detection on stored sub-ray hits",
                       description="Re-run energy, waveform, peak detection and noise on the sub-ray hits "
                                   "saved by 'vlsforest simulate --hits', with the detection settings of "
                                   "SURVEY.yaml (window, bins, threshold, noise, max returns).")
    p.add_argument("hits", help="hits file written by 'vlsforest simulate --hits'")
    p.add_argument("survey", help="SURVEY.yaml (its beam geometry must match the one traced)")
    p.add_argument("-o", "--output", required=True, help="output LAS/LAZ")
    p.add_argument("--seed", type=int, default=None, help="noise seed")
    p.add_argument("--pulses", default=None, help="also write the per-pulse table (.npz or .csv)")
    p.set_defaults(func=run)
    declare_outputs(p, output=LAS, pulses=PULSES)


def run(args) -> int:
    """Execute ``vlsforest detect``."""
    from vlsforest.sim import load_hits, load_survey, redetect, write_points, write_pulses

    parts, pulses, hits, block, beam = load_hits(args.hits)
    survey = load_survey(args.survey)
    res = redetect(parts, pulses, hits, survey, seed=args.seed, block_slots=block, beam=beam)
    write_points(args.output, res)
    if args.pulses:
        write_pulses(args.pulses, res)
    print(f"detect: {res.timings['n_pulses']} pulses, {res.timings['n_points']} points → {args.output}",
          file=sys.stderr)
    return 0
