"""``vlsforest experiment``: experiments that test the cause of a finding (:mod:`vlsforest.experiments`).

``vlsforest experiment tls-step --config-json JSON --plot P3 [--steps 0.1 0.017] [--trees N]
[--band M] -o tls_step.json`` scans a plot's target trees at several TLS angular steps and writes the
filled 0.02 m and 0.25 m cells per step (:func:`vlsforest.experiments.tls_step.run_tls_step`).
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
    t.add_argument("-o", "--output", required=True, type=Path, metavar="JSON", help="result file")
    t.set_defaults(func=run)
    declare_outputs(t, output=None)
    return p


def run(args) -> int:
    """Execute ``vlsforest experiment`` with parsed ``args``; return 0."""
    from vlsforest.experiments.tls_step import run_tls_step
    from vlsforest.io.atomic import write_text

    try:
        cfg = json.loads(args.config_json)
    except json.JSONDecodeError as exc:
        raise ConfigError(f"--config-json: not valid JSON ({exc.msg})") from None
    if not isinstance(cfg, dict):
        raise ConfigError("--config-json: must be a JSON object")
    if args.trees is not None and args.trees < 1:
        raise ConfigError(f"--trees: must be ≥ 1, got {args.trees}")
    seed = cfg.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ConfigError(f"--config-json: seed must be an integer ≥ 0, got {seed!r}")
    res = run_tls_step(cfg, args.plot, args.steps, seed=seed, trees=args.trees, band_m=args.band,
                       progress=lambda line: print(f"experiment tls-step: {line}", file=sys.stderr, flush=True))
    write_text(args.output, json.dumps(res, indent=1, sort_keys=True) + "\n")
    for s in res["steps"]:
        print(f"vlsforest experiment tls-step: {s['step_deg']:g}°: {s['cells_fine']} / {s['cells_coarse']} cells, "
              f"ratio {s['ratio']:.1f}")
    return 0
