"""``vlsforest synth CONFIG.yaml -o DIR`` — build and record the embedded virtual Bretten forest."""

from __future__ import annotations

from pathlib import Path

from vlsforest.commands import FOLDER, check_workers, declare_outputs
from vlsforest.errors import ConfigError
from vlsforest.io.yamlfile import read_yaml


def register(sub) -> None:
    """Add the ``synth`` sub-command."""
    p = sub.add_parser("synth", help="build and record the virtual Bretten forest (TLS, ALS, ULS, truth)",
                       description="Build the seeded virtual forest of CONFIG.yaml (its forest/tls/recordings "
                                   "blocks; defaults otherwise) and record it: TLS scans with scanner positions, "
                                   "'real' ALS and ULS with the recording physics, and the truth files.")
    p.add_argument("config", nargs="?", default=None,
                   help="workflow config YAML (forest:, tls:, recordings:, seed: are used)")
    p.add_argument("--config-json", default=None, help="the same settings as a JSON object (workflow use)")
    p.add_argument("-o", "--output", required=True, help="output folder")
    p.add_argument("--seed", type=int, default=None, help="master seed (default: the config's seed, else 0)")
    p.add_argument("--recording-physics", default=None, help="recording physics YAML (default: built in)")
    p.add_argument("--plots", default=None, help="comma-separated plot names (default: all)")
    p.add_argument("--part", action="store_true",
                   help="write only the --plots' own folders (plots/<plot>/, truth/<plot>/), not the forest's "
                        "truth/trees.csv and settings: one workflow job per plot; `vlsforest collect truth` "
                        "writes those afterwards (the same bytes as one call for all plots)")
    p.add_argument("--workers", type=int, default=None,
                   help="CPUs to use, ≥ 1 (default: one plot at a time, its simulations on all CPUs)")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=run)
    declare_outputs(p, output=FOLDER)


def run(args) -> int:
    """Execute ``vlsforest synth``."""
    from vlsforest.synth.record import load_recording_physics, synthesize

    if (args.config is None) == (args.config_json is None):
        raise ConfigError("give either CONFIG.yaml or --config-json")
    if args.config_json is not None:
        import json

        try:
            cfg = json.loads(args.config_json)
        except json.JSONDecodeError as exc:
            raise ConfigError(f"--config-json is not valid JSON: {exc}") from None
        where = "--config-json"
    else:
        path = Path(args.config)
        cfg = read_yaml(path, "config", empty={})
        where = str(path)
    if not isinstance(cfg, dict):
        raise ConfigError(f"{where}: the config must be a mapping")
    check_workers(args.workers)
    seed = args.seed if args.seed is not None else int(cfg.get("seed", 0))
    physics = load_recording_physics(args.recording_physics) if args.recording_physics else None
    plots = [p.strip() for p in args.plots.split(",") if p.strip()] if args.plots else None
    synthesize(cfg, args.output, seed=seed, physics=physics, plots=plots, workers=args.workers, quiet=args.quiet,
               part=args.part)
    return 0
