"""``vlsforest experiment``: experiments that test the cause of a finding (:mod:`vlsforest.experiments`).

``vlsforest experiment tls-step --config-json JSON --plot P3 [--steps 0.1 0.017] [--trees N]
[--band M] [--cells 0.1 0.05] -o tls_step.json`` scans a plot's target trees at several TLS angular
steps and writes the filled 0.02 m and 0.25 m cells (and those of the ``--cells`` sizes) and their
fill per step (:func:`vlsforest.experiments.tls_step.run_tls_step`).
``vlsforest experiment recording-detector --config-json JSON --plot P3 [--sensor uls]
--variants-json JSON -o recording_detector.json`` records a plot with the recording physics and
with detector variants and writes the target trees' multiple-return shares
(:func:`vlsforest.experiments.recording_detector.run_recording_detector`).
``vlsforest experiment crown-outline --inputs-json JSON --methods fixed_0.25 … --scenarios als uls
-o crown_outline.json`` splits each method's CPA error on a finished run into the model's own
outline, the part the simulation does not see and the crown base, and its CBH error into the
model's own crown base and the part the simulation sees of it
(:func:`vlsforest.experiments.crown_outline.run_crown_outline`).
``vlsforest experiment shift-room --inputs-json JSON --base scaled --shifted scaled_random_shift
--scenarios als uls -o shift_room.json`` relates each target tree's cube size to what the random
shift changes (:func:`vlsforest.experiments.shift_room.run_shift_room`).
``vlsforest experiment cog-shift --inputs-json JSON --base scaled --shifted scaled_cog_shift
--scenarios als uls -o cog_shift.json`` predicts each target tree's change under the CoG shift from
the cubes its returns lie on, sets it beside the simulated change and splits off what the
shifted model's pulses reach (:func:`vlsforest.experiments.cog_shift.run_cog_shift`).
``vlsforest experiment cog-parts --inputs-json JSON --base scaled --shifted scaled_cog_shift
--scenarios als uls --seeds-json JSON --region-margin 1 -o cog_parts.json`` simulates the CoG
shift's vertical and horizontal parts apart with the run's surveys and seeds
(:func:`vlsforest.experiments.cog_parts.run_cog_parts`).
``vlsforest experiment reseed --inputs-json JSON --method scaled --scenarios als --seeds-json JSON
[--seed-offset 1] --region-margin 1 -o reseed.json`` simulates one method again with each
scenario's seed plus the offset and sets the target trees' metrics beside the run's
(:func:`vlsforest.experiments.reseed.run_reseed`). ``--inputs-json`` names the run's files
(:mod:`vlsforest.experiments.run_outputs`).

Same config and seed give the same bytes.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from vlsforest.commands import declare_outputs
from vlsforest.errors import ConfigError


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``experiment`` sub-command to ``subparsers``."""
    p = subparsers.add_parser("experiment", help="experiments that test the cause of a finding that disagrees")
    sub = p.add_subparsers(dest="experiment", required=True, metavar="EXPERIMENT")
    t = sub.add_parser("tls-step", help="the TLS angular step and the 0.02 m / scaled voxel ratio",
                       description="Scan a plot's target trees at several TLS angular steps (restricted field "
                                   "of view) and count the filled 0.02 m and 0.25 m cells of their returns.")
    t.add_argument("--config-json", default="{}", metavar="JSON",
                   help="workflow config (forest, tls blocks and seed) as JSON, as `vlsforest synth` takes it")
    t.add_argument("--plot", required=True, help="the plot whose target trees are scanned")
    t.add_argument("--steps", type=float, nargs="+", default=[0.1, 0.017], metavar="DEG",
                   help="angular steps in degrees (default: the embedded forest's 0.1 and the study's 0.017)")
    t.add_argument("--trees", type=int, metavar="N", help="only the first N target trees")
    t.add_argument("--band", type=float, metavar="M",
                   help="scan only a horizontal slab of M metres through the middle of each crown")
    t.add_argument("--cells", type=float, nargs="*", default=[], metavar="M",
                   help="further cell sizes (m) to count and give the fill of, e.g. the fixed methods' 0.1 0.05")
    _result_file(t)
    r = sub.add_parser("recording-detector", help="the recordings' detector and their multiple-return share",
                       description="Record a plot again with the recording physics and with detector variants "
                                   "and report the target trees' multiple-return shares by species group.")
    r.add_argument("--config-json", default="{}", metavar="JSON",
                   help="workflow config (forest, recordings blocks and seed) as JSON, as `vlsforest synth` takes it")
    r.add_argument("--plot", required=True, help="the plot recorded")
    r.add_argument("--sensor", choices=("als", "uls"), default="uls", help="the recording (default uls)")
    r.add_argument("--variants-json", required=True, metavar="JSON",
                   help='variant name → recording-physics keys, e.g. {"helios_rule": {"peak_rule": {"physical": 0}}}')
    _result_file(r)
    inputs_help = ("the run's files by plot: targets, reference tree clouds, and per method voxels, tree clouds "
                   "and metrics (vlsforest.experiments.run_outputs)")
    c = sub.add_parser("crown-outline", help="where the voxel models' crown projection area and base errors come from",
                       description="Split each method's CPA error on a finished run into the model's own outline, "
                                   "the part the simulation does not see, and the simulated crown base; and its "
                                   "CBH error into the model's own crown base and the part the simulation sees.")
    c.add_argument("--inputs-json", required=True, metavar="JSON", help=inputs_help)
    c.add_argument("--methods", nargs="+", required=True, metavar="METHOD", help="the voxel methods")
    c.add_argument("--scenarios", nargs="+", required=True, metavar="SCENARIO", help="the scenarios")
    _result_file(c)
    h = sub.add_parser("shift-room", help="the scaled cubes' size and what the random shift changes",
                       description="Relate each target tree's mean cube side in the unshifted scaled model to the "
                                   "change of its metrics under the random shift, over the trees of a finished run.")
    h.add_argument("--inputs-json", required=True, metavar="JSON", help=inputs_help)
    h.add_argument("--base", required=True, metavar="METHOD", help="the unshifted scaled method")
    h.add_argument("--shifted", required=True, metavar="METHOD", help="its randomly shifted variant")
    h.add_argument("--scenarios", nargs="+", required=True, metavar="SCENARIO", help="the scenarios")
    h.add_argument("--metrics", nargs="+", default=["hmean", "multi_return_pct", "cbh", "cpa"], metavar="METRIC",
                   help="metrics whose change is related to the cube size (default: the study's finding's four)")
    _result_file(h)
    g = sub.add_parser("cog-shift", help="what the CoG shift does to the cubes the returns come from",
                       description="Carry each return of the unshifted scaled model's simulation along with the "
                                   "cube it lies on to the CoG-shifted cubes, and set the change of Hmean, height "
                                   "and CPA this predicts beside the simulated change; carry the shifted "
                                   "model's returns back the same way to give the change that comes from what "
                                   "its pulses reach; over the trees of a finished run.")
    g.add_argument("--inputs-json", required=True, metavar="JSON", help=inputs_help)
    g.add_argument("--base", required=True, metavar="METHOD", help="the unshifted scaled method")
    g.add_argument("--shifted", required=True, metavar="METHOD", help="its CoG-shift variant")
    g.add_argument("--scenarios", nargs="+", required=True, metavar="SCENARIO", help="the scenarios")
    g.add_argument("--margin", type=float, default=None, metavar="M",
                   help="a return comes from a cube within this distance (m) of it (default: half the cell)")
    _result_file(g)
    q = sub.add_parser("cog-parts", help="the CoG shift's vertical and horizontal parts, simulated apart",
                       description="Move the unshifted scaled cubes by only the vertical or only the horizontal "
                                   "part of their CoG displacement, simulate each with the run's surveys, seeds "
                                   "and region, and set the target trees' changes beside the whole shift's.")
    _simulation_options(q, inputs_help, "the base method")
    q.add_argument("--base", required=True, metavar="METHOD", help="the unshifted scaled method")
    q.add_argument("--shifted", required=True, metavar="METHOD", help="its CoG-shift variant")
    _result_file(q)
    r = sub.add_parser("reseed", help="the run's own noise: one method simulated again with another seed",
                       description="Simulate one method of a finished run again with the run's surveys and region "
                                   "and each scenario's seed plus an offset, and set the target trees' metrics "
                                   "beside the run's.")
    _simulation_options(r, inputs_help, "the method")
    r.add_argument("--method", required=True, metavar="METHOD", help="the method simulated again")
    r.add_argument("--seed-offset", type=int, default=1, metavar="K",
                   help="added to each scenario's seed (default 1; 0 reproduces the run's metrics)")
    _result_file(r)
    return p


def _simulation_options(parser, inputs_help: str, scene_owner: str) -> None:
    """The options of an experiment that simulates a finished run's plots again
    (:mod:`vlsforest.experiments.resimulate`); ``scene_owner`` names the method whose scene it reads."""
    parser.add_argument("--inputs-json", required=True, metavar="JSON",
                        help=inputs_help + "; each plot also with its site (site.json) and surveys (scenario → "
                                           f"SURVEY.yaml), {scene_owner} with its scene (the folder of its SCENE.yaml)")
    parser.add_argument("--scenarios", nargs="+", required=True, metavar="SCENARIO", help="the scenarios simulated")
    parser.add_argument("--seeds-json", required=True, metavar="JSON",
                        help="scenario → the seed of its simulations in the run")
    parser.add_argument("--region-margin", type=float, required=True, metavar="M",
                        help="the simulation region's margin around the targets (m; the run's "
                             "simulation.region_margin_m)")
    parser.add_argument("--workers", type=int, default=1, metavar="N", help="simulation worker processes (default 1)")


def _result_file(parser) -> None:
    """The ``-o`` option every experiment writes its JSON result to, and the command's run."""
    parser.add_argument("-o", "--output", required=True, type=Path, metavar="JSON", help="result file")
    parser.set_defaults(func=run)
    declare_outputs(parser, output=None)


def _check_plot(cfg: dict, plot: str, seed: int) -> None:
    """Refuse a ``--plot`` that is not a plot of the configured virtual forest (naming the option)."""
    from vlsforest.synth.forest import forest_from_config
    from vlsforest.synth.record import synth_settings

    names = [p.name for p in forest_from_config(synth_settings(cfg)["forest"], seed)]
    if plot not in names:
        raise ConfigError(f"--plot: unknown plot {plot!r} (known: {', '.join(names)})")


def _json_object(text: str, option: str) -> dict:
    try:
        value = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ConfigError(f"{option}: not valid JSON ({exc.msg})") from None
    if not isinstance(value, dict):
        raise ConfigError(f"{option}: must be a JSON object")
    return value


def _log(name):
    return lambda line: print(f"experiment {name}: {line}", file=sys.stderr, flush=True)


def run(args) -> int:
    """Execute ``vlsforest experiment`` with parsed ``args``; return 0."""
    from vlsforest.io.atomic import write_text

    if args.experiment in ("crown-outline", "shift-room", "cog-shift", "cog-parts", "reseed"):
        return _run_on_outputs(args, write_text)
    cfg = _json_object(args.config_json, "--config-json")
    seed = cfg.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ConfigError(f"--config-json: seed must be an integer ≥ 0, got {seed!r}")
    _check_plot(cfg, args.plot, seed)
    if args.experiment == "recording-detector":
        from vlsforest.experiments.recording_detector import run_recording_detector

        variants = _json_object(args.variants_json, "--variants-json")
        res = run_recording_detector(cfg, args.plot, args.sensor, variants, seed=seed,
                                     progress=_log("recording-detector"))
        write_text(args.output, json.dumps(res, indent=1, sort_keys=True) + "\n")
        for v in res["variants"]:
            print(f"vlsforest experiment recording-detector: {v['name']}: conifer {v['conifer']['mean_pct']:.1f} %, "
                  f"broadleaf {v['broadleaf']['mean_pct']:.1f} %")
        return 0
    from vlsforest.experiments.tls_step import check_arguments, run_tls_step

    if args.trees is not None and args.trees < 1:
        raise ConfigError(f"--trees: must be ≥ 1, got {args.trees}")
    check_arguments(args.steps, args.band, args.cells, names=("--steps", "--band", "--cells"))
    res = run_tls_step(cfg, args.plot, args.steps, seed=seed, trees=args.trees, band_m=args.band,
                       cells_m=args.cells, progress=_log("tls-step"))
    write_text(args.output, json.dumps(res, indent=1, sort_keys=True) + "\n")
    for s in res["steps"]:
        print(f"vlsforest experiment tls-step: {s['step_deg']:g}°: {s['cells_fine']} / {s['cells_coarse']} cells, "
              f"ratio {s['ratio']:.1f}")
    return 0


def _run_on_outputs(args, write_text) -> int:
    """The experiments that take a finished run's files apart (``crown-outline``, ``shift-room``,
    ``cog-shift``, ``cog-parts``, ``reseed``)."""
    manifest = _json_object(args.inputs_json, "--inputs-json")
    if args.experiment == "reseed":
        from vlsforest.commands import check_workers
        from vlsforest.experiments.reseed import run_reseed

        check_workers(args.workers)
        res = run_reseed(manifest, args.method, args.scenarios, _json_object(args.seeds_json, "--seeds-json"),
                         args.region_margin, tmp_dir=args.output.parent, seed_offset=args.seed_offset,
                         workers=args.workers, progress=_log("reseed"))
        write_text(args.output, json.dumps(res, indent=1, sort_keys=True) + "\n")
        for sc, per in res["summary"].items():
            for k, v in per.items():
                print(f"vlsforest experiment reseed: {sc} {k}: reseeded − run {v['mean']:+.3f} "
                      f"(se {v['se']:.3f}, {v['n']} trees)")
        return 0
    if args.experiment == "cog-parts":
        from vlsforest.commands import check_workers
        from vlsforest.experiments.cog_parts import run_cog_parts

        check_workers(args.workers)
        res = run_cog_parts(manifest, args.base, args.shifted, args.scenarios,
                            _json_object(args.seeds_json, "--seeds-json"), args.region_margin,
                            tmp_dir=args.output.parent, workers=args.workers, progress=_log("cog-parts"))
        write_text(args.output, json.dumps(res, indent=1, sort_keys=True) + "\n")
        for sc, per in res["summary"].items():
            for k, v in per.items():
                print(f"vlsforest experiment cog-parts: {sc} {k}: whole {v['whole']['mean']:+.3f} = vertical "
                      f"{v['vertical']['mean']:+.3f} + horizontal {v['horizontal']['mean']:+.3f} + interaction "
                      f"{v['interaction']['mean']:+.3f}")
        return 0
    if args.experiment == "crown-outline":
        from vlsforest.experiments.crown_outline import run_crown_outline

        res = run_crown_outline(manifest, args.methods, args.scenarios, progress=_log("crown-outline"))
        write_text(args.output, json.dumps(res, indent=1, sort_keys=True) + "\n")
        for m, per in res["summary"].items():
            for sc, v in per.items():
                print(f"vlsforest experiment crown-outline: {m} {sc}: CPA error {v['error']['mean']:+.2f} m² = "
                      + " ".join(f"{k} {v[k]['mean']:+.2f}" for k in ("outline", "unseen", "base")))
        return 0
    if args.experiment == "cog-shift":
        from vlsforest.experiments.cog_shift import run_cog_shift

        res = run_cog_shift(manifest, args.base, args.shifted, args.scenarios, margin_m=args.margin,
                            progress=_log("cog-shift"))
        write_text(args.output, json.dumps(res, indent=1, sort_keys=True) + "\n")
        for sc, per in res["summary"].items():
            for k, v in per.items():
                pred = f"predicted {v['predicted']['mean']:+.3f}, " if "predicted" in v else ""
                print(f"vlsforest experiment cog-shift: {sc} {k}: {pred}simulated {v['simulated']['mean']:+.3f}")
        return 0
    from vlsforest.experiments.shift_room import run_shift_room

    res = run_shift_room(manifest, args.base, args.shifted, args.scenarios, args.metrics, progress=_log("shift-room"))
    write_text(args.output, json.dumps(res, indent=1, sort_keys=True) + "\n")
    for sc, per in res["summary"].items():
        for k, v in per.items():
            print(f"vlsforest experiment shift-room: {sc} {k}: change {v['change']['mean']:+.3f}, "
                  f"r = {v['fit']['r']:+.2f} with the cube side")
    return 0
