"""``vlsforest report``: figures of the comparison (PNG) for the Snakemake report.

``vlsforest report figures --metrics tree_metrics.csv --errors errors.csv --voxel-counts
voxel_counts.csv -o FIGDIR [--side-view LABEL=LAS …] [--ground-z Z] [--tree-field F --tree-id ID]
[--tree-cloud PLOT/SOURCE/SCENARIO=LAS …] [--seed N]`` writes the PNGs of :data:`vlsforest.report.figures.FIGURE_FILES` (figure 13 only
with ``--side-view``).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from vlsforest.commands import FOLDER, declare_outputs
from vlsforest.errors import ConfigError


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``report`` sub-command (with its ``figures`` action) to ``subparsers``."""
    p = subparsers.add_parser(
        "report",
        help="figures of the simulated-vs-reference comparison (PNG)",
        description="Report material of the comparison (Weiser et al. 2021, figures 7–13 and voxels vs error).",
    )
    sub = p.add_subparsers(dest="report_action", metavar="<action>")
    sub.required = True
    f = sub.add_parser("figures", help="write every figure as PNG with fixed file names",
                       description="Write the figure PNGs (fixed names) into FIGDIR.")
    f.add_argument("--metrics", required=True, type=Path, metavar="CSV", help="tree_metrics.csv")
    f.add_argument("--errors", required=True, type=Path, metavar="CSV", help="errors.csv of vlsforest stats")
    f.add_argument("--voxel-counts", required=True, type=Path, metavar="CSV", help="voxel_counts.csv")
    f.add_argument("-o", "--output", required=True, type=Path, metavar="FIGDIR", help="output folder")
    f.add_argument("--side-view", action="append", default=[], metavar="LABEL=LAS",
                   help="a simulated tree cloud for figure 13 (repeat, in panel order)")
    f.add_argument("--tree-cloud", action="append", default=[], metavar="PLOT/SOURCE/SCENARIO=LAS",
                   help="a tree cloud (field tree_id) of a method or the reference (repeat): figure 13 shows "
                        "the tree with the most reference points, scaled vs fixed_0.25, from these files")
    f.add_argument("--ground-z", type=float, default=0.0, help="terrain height of the side views (default 0)")
    f.add_argument("--tree-field", default=None, help="attribute selecting the tree in the side-view clouds")
    f.add_argument("--tree-id", type=float, default=None, help="value of --tree-field to keep")
    f.add_argument("--seed", type=int, default=0, help="bootstrap seed of the CI bands (default 0)")
    f.set_defaults(func=run_figures)
    declare_outputs(f, output=FOLDER)
    return p


def _side_views(items: list[str]) -> dict:
    out = {}
    for it in items:
        label, sep, path = it.partition("=")
        if not sep or not label or not path:
            raise ConfigError(f"--side-view: expected LABEL=PATH, got {it!r}")
        if label in out:
            raise ConfigError(f"--side-view: label {label!r} given twice")
        out[label] = Path(path)
    return out


def _tree_clouds(items: list[str]) -> dict:
    """``PLOT/SOURCE/SCENARIO=PATH`` items → {(plot, source, scenario): path}."""
    out = {}
    for it in items:
        key, sep, path = it.partition("=")
        parts = tuple(key.split("/"))
        if not sep or not path or len(parts) != 3 or not all(parts):
            raise ConfigError(f"--tree-cloud: expected PLOT/SOURCE/SCENARIO=PATH, got {it!r}")
        if parts in out:
            raise ConfigError(f"--tree-cloud: {key!r} given twice")
        out[parts] = Path(path)
    return out


def run_figures(args) -> int:
    """Execute ``vlsforest report figures``; return 0."""
    from vlsforest.report.figures import make_figures, side_view_selection
    from vlsforest.stats import load_metrics, load_voxel_counts, read_table

    if not math.isfinite(args.ground_z):
        raise ConfigError(f"--ground-z: must be finite, got {args.ground_z}")
    metrics = load_metrics(args.metrics)
    errors = read_table(args.errors, ("plot", "tree_id", "species", "scenario", "method", "metric", "sim", "ref",
                                      "error", "rel_error"),
                        numeric=("sim", "ref", "error", "rel_error"),
                        str_columns=("plot", "tree_id", "species", "group", "scenario", "method", "metric"))
    vc = load_voxel_counts(args.voxel_counts)
    side = dict(side_views=_side_views(args.side_view) or None, ground_z=args.ground_z, tree_field=args.tree_field,
                tree_id=args.tree_id)
    if args.tree_cloud:
        if side["side_views"]:
            raise ConfigError("--tree-cloud: give either --tree-cloud or --side-view, not both")
        sel = side_view_selection(metrics, _tree_clouds(args.tree_cloud))
        if sel is None:
            print("vlsforest report figures: warning: no simulated tree clouds found for figure 13; skipped",
                  file=sys.stderr)
        else:
            side = dict(side_views=sel["clouds"], ground_z=sel["ground_z"], tree_field=sel["tree_field"],
                        tree_id=sel["tree_id"])
    paths = make_figures(metrics, errors, vc, args.output, seed=args.seed, **side)
    print(f"vlsforest report figures: {len(paths)} figures -> {args.output}")
    return 0
