"""``vlsforest metrics``: per-tree metrics (Table 4) of a labelled LAS/LAZ file as CSV.

``vlsforest metrics IN.laz --tree-id FIELD [--ground-z Z] -o OUT.csv`` writes one row per tree
(column ``tree_id`` then :data:`vlsforest.metrics.METRIC_COLUMNS`), sorted by tree id, floats
with six decimals and ``NaN`` for undefined values, so that the same input gives the same bytes.
"""

from __future__ import annotations

import argparse
import math
import sys
import warnings
from pathlib import Path

import numpy as np

from vlsforest.commands import CSV, declare_outputs
from vlsforest.errors import ConfigError, InputDataError
from vlsforest.io.atomic import write_csv


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``metrics`` sub-command to ``subparsers``."""
    p = subparsers.add_parser(
        "metrics",
        help="per-tree metrics (height, percentiles, densities, CBH, CPA …) as CSV",
        description=(
            "Compute the per-tree metrics of Weiser et al. (2021), Table 4, for every labelled "
            "tree of a LAS/LAZ file. Points whose tree id is NaN or ≥ 1e300 belong to no tree."
        ),
    )
    p.add_argument("input", type=Path, help="input LAS/LAZ file")
    p.add_argument("--tree-id", required=True, metavar="FIELD", help="point attribute holding the tree id")
    p.add_argument(
        "--ground-z", type=float, default=0.0, metavar="Z", help="terrain height subtracted from z (default 0)"
    )
    p.add_argument("--ground-table", type=Path, default=None, metavar="CSV",
                   help="per-tree terrain height: a CSV with the tree id column (--ground-key) and z")
    p.add_argument("--ground-key", default="tree_id", help="tree id column of --ground-table (default tree_id)")
    p.add_argument("-o", "--output", required=True, type=Path, metavar="OUT.csv", help="output CSV")
    add_metric_options(p)
    p.set_defaults(func=run)
    declare_outputs(p, output=CSV)
    return p


def add_metric_options(p: argparse.ArgumentParser) -> None:
    """Add the metric definitions' options (``--multi-return``, ``--cbh-convention``) to ``p``."""
    from vlsforest.metrics import CBH_CONVENTIONS, MULTI_RETURN_MODES

    p.add_argument(
        "--multi-return",
        choices=MULTI_RETURN_MODES,
        default="pulse",
        help="definition of multi_return_pct (default: pulse)",
    )
    p.add_argument(
        "--cbh-convention",
        choices=CBH_CONVENTIONS,
        default="paper",
        help="crown base height definition: the paper's text or the authors' script (default: paper)",
    )


def ground_table(path: Path, key: str, what: str = "ground table") -> dict:
    """Per-tree terrain heights ``{tree id: z}`` from a CSV with columns ``key`` and ``z``
    (``what`` names the file in errors)."""
    from vlsforest.io.csvfile import read_height_table

    gt = read_height_table(path, what, ids=(key,))
    return {int(k): float(z) for k, z in zip(gt[key], gt["z"])}


def write_metrics(cloud, tree_field: str, ground, output: Path, *, source: str, multi_return: str = "pulse",
                  cbh_convention: str = "paper", prog: str = "vlsforest metrics"):
    """Compute the per-tree metrics of ``cloud`` and write them to ``output`` (fixed format).

    ``ground`` is a terrain height or ``{tree id: z}``; with a mapping every tree it names gets a
    row (NaN metrics where it has no point). Warnings of the metrics go to stderr once each,
    prefixed with ``prog``. Returns the table.
    """
    from vlsforest.metrics import FLOAT_FORMAT, cloud_metrics

    if tree_field not in cloud.attrs:
        raise InputDataError(f"{source}: no tree-id field {tree_field!r} (fields: {', '.join(sorted(cloud.attrs))})")
    tree_ids = sorted(ground) if isinstance(ground, dict) else None
    if tree_ids and not np.isin(cloud.attrs[tree_field], tree_ids).any():
        raise InputDataError(f"{source}: none of the trees {', '.join(map(str, tree_ids))} has a point in "
                             f"{tree_field!r}")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        df = cloud_metrics(
            cloud,
            tree_field,
            ground_z=ground,
            tree_ids=tree_ids,
            multi_return=multi_return,
            cbh_convention=cbh_convention,
            source=source,
        )
    seen = set()
    for w in caught:
        if not issubclass(w.category, UserWarning):
            continue
        msg = str(w.message)
        if msg not in seen:
            seen.add(msg)
            print(f"{prog}: warning: {msg}", file=sys.stderr)
    if df.empty:
        print(f"{prog}: warning: {source}: no point has a tree id in {tree_field!r}", file=sys.stderr)
    write_csv(Path(output), df, index=False, float_format=FLOAT_FORMAT, na_rep="NaN", lineterminator="\n")
    return df


def run(args) -> int:
    """Execute ``vlsforest metrics`` with parsed ``args``; return 0."""
    from vlsforest.io.las import read_las

    if not math.isfinite(args.ground_z):
        raise ConfigError(f"--ground-z: must be finite, got {args.ground_z}")
    ground = args.ground_z
    if args.ground_table is not None:
        ground = ground_table(args.ground_table, args.ground_key)
    cloud = read_las(args.input, allow_empty=args.ground_table is not None)
    df = write_metrics(cloud, args.tree_id, ground, args.output, source=str(args.input),
                       multi_return=args.multi_return, cbh_convention=args.cbh_convention)
    print(f"vlsforest metrics: {len(df)} trees -> {args.output}")
    return 0
