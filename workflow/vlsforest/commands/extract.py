"""``vlsforest extract``: target-tree clouds of a recording (reference) or of a simulation.

``vlsforest extract reference CLOUD.laz --segment DIR --targets targets.csv --radius R -o trees.laz``
labels the real ALS/ULS points within R m of a target's TLS points (the study: 0.5 m ALS,
0.3 m ULS; nearest tree wins); ``vlsforest extract sim SIM.laz --targets targets.csv -o trees.laz``
takes a simulated cloud's target points by object id. Both write only the target points, all
returns and attributes kept, with the extra dimension ``tree_id`` = the target's id. With
``--metrics OUT.csv`` they also write the target trees' metrics, as ``vlsforest metrics
trees.laz --tree-id tree_id --ground-table targets.csv --ground-key target_id`` would (the same
bytes, computed from the file just written), in the same process.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from vlsforest.commands import CSV, LAS, declare_outputs
from vlsforest.commands.metrics import add_metric_options


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``extract`` sub-command."""
    p = subparsers.add_parser("extract", help="target-tree clouds of a real recording or a simulation",
                              description=__doc__.split("\n\n")[1])
    sub = p.add_subparsers(dest="what", metavar="{reference,sim}")
    sub.required = True
    r = sub.add_parser("reference", help="label real ALS/ULS points near each target's TLS points")
    r.add_argument("cloud", type=Path, help="real ALS/ULS LAS/LAZ")
    r.add_argument("--segment", required=True, type=Path, help="segmentation folder (trees/{id}.laz)")
    r.add_argument("--targets", required=True, type=Path, help="targets.csv (vlsforest scene targets)")
    r.add_argument("--radius", required=True, type=float, help="extraction radius (m)")
    r.add_argument("--exclude-classes", default="2,7,18", metavar="C,C,…",
                   help="LAS classes never assigned to a tree (default 2,7,18: ground and noise; "
                        "'' keeps every class)")
    r.add_argument("-o", "--output", required=True, type=Path)
    s = sub.add_parser("sim", help="take a simulated cloud's target points by object id")
    s.add_argument("cloud", type=Path, help="simulated LAS/LAZ (with object_id)")
    s.add_argument("--targets", required=True, type=Path, help="targets.csv")
    s.add_argument("-o", "--output", required=True, type=Path)
    for q in (r, s):
        q.add_argument("--metrics", type=Path, default=None, metavar="OUT.csv",
                       help="also write the target trees' metrics (vlsforest metrics; heights above "
                            "each target's ground z of the targets table)")
        add_metric_options(q)
        declare_outputs(q, output=LAS, metrics=CSV)
    p.set_defaults(func=run)
    return p


def _targets(path: Path):
    from vlsforest.errors import InputDataError
    from vlsforest.io.csvfile import read_csv_table

    df = read_csv_table(path, "targets table", ids=("target_id", "tree_id"))
    if len(df) == 0:
        raise InputDataError(f"{path}: targets table has no rows")
    return df


def _classes(text: str) -> tuple:
    from vlsforest.errors import ConfigError

    try:
        out = tuple(int(c) for c in text.replace(" ", "").split(",") if c)
    except ValueError:
        raise ConfigError(f"--exclude-classes: {text!r} is not a comma-separated list of LAS classes") from None
    if any(not 0 <= c <= 255 for c in out):
        raise ConfigError(f"--exclude-classes: LAS classes are 0-255, got {text!r}")
    return out


def run(args) -> int:
    """Execute ``vlsforest extract``."""
    import numpy as np

    from vlsforest.commands.metrics import ground_table, write_metrics
    from vlsforest.errors import InputDataError
    from vlsforest.extract import extract_reference, simulated_targets, target_ids
    from vlsforest.io.atomic import flush
    from vlsforest.io.las import read_las, write_las

    targets = _targets(args.targets)
    ground = ground_table(args.targets, "target_id", "targets table") if args.metrics is not None else None
    cloud = read_las(args.cloud, allow_empty=True, require=("object_id",) if args.what == "sim" else ())
    seg_to_target = dict(zip(targets.tree_id.astype(int), targets.target_id.astype(int)))
    if args.what == "reference":
        pts = {}
        for tid in seg_to_target:
            f = args.segment / "trees" / f"{tid}.laz"
            if not f.is_file():
                raise InputDataError(f"{f}: segmented tree {tid} (a target) is missing")
            pts[tid] = read_las(f).xyz
        excl = _classes(args.exclude_classes)
        lab = extract_reference(pts, cloud, args.radius, exclude_classes=excl)
        if "classification" not in cloud.attrs:
            print("extract reference: no classification in the recording, every point eligible")
        elif excl:
            n_out = int(np.isin(cloud.attrs["classification"], excl).sum())
            print(f"extract reference: {n_out} points of classes {','.join(map(str, excl))} left out")
        else:
            print("extract reference: every class kept (--exclude-classes '')")
        keep = lab > 0
        tree = target_ids(lab[keep], seg_to_target)
    else:
        keep, tree = simulated_targets(cloud, seg_to_target)
    if not keep.any():
        raise InputDataError(f"{args.cloud}: none of the targets has a point in the cloud (target ids "
                             f"{', '.join(str(int(t)) for t in targets.target_id)}; tree ids "
                             f"{', '.join(str(int(t)) for t in targets.tree_id)})")
    write_las(args.output, cloud.subset(keep), extra={"tree_id": tree})
    counts = {int(t): int((tree == t).sum()) for t in targets.target_id}
    print(f"extract {args.what}: {int(keep.sum())} of {len(cloud)} points in {len(counts)} target trees {counts}")
    if args.metrics is not None:  # from the file as written (LAS-quantised), like a later `metrics` run
        flush()  # the metrics read the file just written
        df = write_metrics(read_las(args.output, allow_empty=True), "tree_id", ground, args.metrics,
                           source=str(args.output), multi_return=args.multi_return,
                           cbh_convention=args.cbh_convention, prog="vlsforest extract")
        print(f"extract {args.what}: metrics of {len(df)} trees -> {args.metrics}")
    return 0
