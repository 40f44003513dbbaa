"""``vlsforest segment``: trees of co-registered TLS scans.

``vlsforest segment IN.laz [MORE.laz …] -o DIR`` writes ``DIR/segmented.laz`` (all points with
classification 2 = ground, 7 = noise, 1 = other, and the extra dimension ``tree_id``, 0 = no
tree), ``DIR/trees.csv`` (``tree_id, x, y, z, dbh, height, n_points``), ``DIR/trees/{id}.laz``
and ``DIR/dtm.npz`` (terrain model, see :meth:`vlsforest.segment.Dtm.save`).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from vlsforest.commands import FOLDER, declare_outputs


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``segment`` sub-command to ``subparsers``."""
    from vlsforest.segment import SegmentConfig

    d = SegmentConfig()
    p = subparsers.add_parser(
        "segment",
        help="segment co-registered TLS scans into trees (ground, stems, competitive Dijkstra)",
        description=(
            "Classify ground, find stems in a slice above it (circle fits) and grow trees from "
            "all stems at once by shortest paths over a voxel graph (hidden stretches of stems "
            "bridged). Unreached voxels join the "
            "nearest reached voxel's tree within --attach-dist, else tree id 0."
        ),
    )
    p.add_argument("inputs", nargs="+", type=Path, metavar="IN.laz", help="co-registered scans (LAS/LAZ)")
    p.add_argument("-o", "--output", required=True, type=Path, metavar="DIR", help="output folder")
    p.add_argument("--voxel", type=float, default=d.voxel, help=f"graph voxel size in m (default {d.voxel})")
    p.add_argument("--graph-radius", type=float, default=d.graph_radius,
                   help=f"longest graph edge in m (default {d.graph_radius})")
    p.add_argument("--attach-dist", type=float, default=d.attach_dist,
                   help=f"unreached points join a tree within this distance in m (default {d.attach_dist})")
    p.add_argument("--stem-bridge", type=float, default=d.stem_bridge,
                   help="longest hidden stretch of a stem in m that the growth bridges to its crown, "
                        f"0 = off (default {d.stem_bridge:g})")
    p.add_argument("--ground-tol", type=float, default=d.ground_tol,
                   help=f"ground points lie at most this far above the terrain model (default {d.ground_tol})")
    p.add_argument("--max-deviation", type=float, default=d.max_deviation,
                   help=f"pulse-shape deviation limit when the points carry one (default {d.max_deviation})")
    p.add_argument("--seed", type=int, default=d.seed, help="random seed of the circle fits (default 0)")
    p.add_argument("--no-ground", action="store_true",
                   help="the input holds no ground points (removed beforehand): take a plane under the lowest points as terrain")
    p.add_argument("--no-tree-files", action="store_true", help="do not write DIR/trees/{id}.laz")
    p.add_argument("--config-json", default=None,
                   help="settings as a JSON object (workflow use; keys as SegmentConfig, e.g. graph_radius); "
                        "replaces the options above")
    p.set_defaults(func=run)
    declare_outputs(p, output=FOLDER)
    return p


def run(args) -> int:
    """Execute ``vlsforest segment`` with parsed ``args``; return 0."""
    from vlsforest.segment import SegmentConfig, segment_files

    if args.config_json is not None:
        import json

        from vlsforest.errors import ConfigError

        try:
            d = json.loads(args.config_json)
        except json.JSONDecodeError as exc:
            raise ConfigError(f"--config-json: {exc}") from None
        if not isinstance(d, dict):
            raise ConfigError("--config-json: must be a JSON object (the config's segment block)")
        cfg = SegmentConfig.from_dict(d)
    else:
        cfg = SegmentConfig(
            voxel=args.voxel, graph_radius=args.graph_radius, attach_dist=args.attach_dist,
            stem_bridge=args.stem_bridge,
            ground_tol=args.ground_tol, max_deviation=args.max_deviation, seed=args.seed,
            no_ground=args.no_ground,
        )
    res = segment_files(args.inputs, args.output, cfg, write_trees=not args.no_tree_files, quiet=False)
    info = res.info
    if len(res.trees) == 0:
        print("vlsforest segment: warning: no stems found; every point has tree id 0", file=sys.stderr)
    print(f"vlsforest segment: {info['deviation_filter']}", file=sys.stderr)
    print(
        f"vlsforest segment: {info['n_points']} points, {info['n_ground']} ground, {info['n_noise']} noise, "
        f"{len(res.trees)} trees with {info['n_tree_points']} points "
        f"({info['unreached']} unreached voxels, {info['attached']} attached) -> {args.output}"
    )
    return 0
