"""``vlsforest demo -o DIR/scene.yaml`` — write the embedded demo scene."""

from __future__ import annotations

import json
from pathlib import Path

from vlsforest.commands import YAML, declare_outputs
from vlsforest.errors import ConfigError


def register(sub) -> None:
    """Add the ``demo`` sub-command."""
    p = sub.add_parser("demo", help="write the embedded demo scene (one tree on a ground plane)",
                       description="Write the embedded, seeded demo scene: a voxel crown, a stem mesh and a "
                                   "ground plane, with its scene.yaml.")
    p.add_argument("-o", "--output", required=True, help="scene.yaml to write (parts are written beside it)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--voxel-size", type=float, default=None, help="crown voxel size in m (default 0.25)")
    p.add_argument("--plot-json", default=None, help="plot config block as JSON (workflow use)")
    p.add_argument("--method-json", default=None, help="method config block as JSON (workflow use)")
    p.set_defaults(func=run)
    declare_outputs(p, output=YAML)


def _json(text, what):
    if text is None:
        return {}
    try:
        val = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ConfigError(f"--{what}-json is not valid JSON: {exc}") from None
    if not isinstance(val, dict):
        raise ConfigError(f"--{what}-json must be a JSON object")
    return val


def run(args) -> int:
    """Execute ``vlsforest demo``."""
    from vlsforest.demo import write_demo

    plot = _json(args.plot_json, "plot")
    method = _json(args.method_json, "method")
    size = args.voxel_size if args.voxel_size is not None else float(method.get("voxel_size", 0.25))
    out = Path(args.output)
    write_demo(out.parent, seed=args.seed, voxel_size=size, ground_z=float(plot.get("ground_z", 0.0)),
               half_extent=float(plot.get("half_extent_m", 20.0)), name=out.name)
    return 0
