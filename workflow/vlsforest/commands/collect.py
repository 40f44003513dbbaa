"""``vlsforest collect``: gather per-plot workflow outputs into the summary tables.

``collect metrics results/{plot}/{source}/{scenario}/metrics.csv … -o tree_metrics.csv``
    one long table ``plot, tree_id, species, scenario, method, <metrics>`` (``method`` is
    ``reference`` for the real recordings); species from ``results/{plot}/targets.csv``.
``collect voxels results/{plot}/{method}/voxels.npz … -o voxel_counts.csv``
    ``plot, method, n_voxels``.
``collect times results/{plot}/{method}/{scenario}/timing.json … -o sim_times.csv``
    ``plot, method, scenario, seconds, n_pulses, n_points``.
``collect pad results/{plot}/pad/validation.csv … -o pad_validation.csv [--figure F.png]``
    the PAD validation tables of all plots (and their figure).
``collect truth results/forest/truth/{plot} … -o results/forest/truth/trees.csv``
    the virtual forest's truth table of plots recorded one by one (``vlsforest synth --part``),
    with its ``synth_settings.yaml`` and ``recording_physics.yaml`` beside it.

The plot, method and scenario are read from the paths (the workflow's results layout).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from vlsforest.commands import CSV, PNG, declare_outputs
from vlsforest.io.atomic import write_csv
from vlsforest.io.csvfile import read_csv_table


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``collect`` sub-command."""
    p = subparsers.add_parser("collect", help="gather per-plot outputs into summary tables",
                              description="Gather per-plot workflow outputs into the summary tables.")
    p.add_argument("what", choices=("metrics", "voxels", "times", "pad", "truth"))
    p.add_argument("inputs", nargs="+", type=Path)
    p.add_argument("-o", "--output", required=True, type=Path)
    p.add_argument("--figure", type=Path, default=None, help="pad: also draw the validation figure")
    p.set_defaults(func=run)
    declare_outputs(p, output=CSV, figure=PNG)
    return p


def _parts(path: Path, depth: int, what: str):
    from vlsforest.errors import InputDataError

    parts = path.parts
    if len(parts) < depth + 1:
        raise InputDataError(f"{path}: expected results/{{plot}}/…/{path.name} ({what})")
    return parts[-depth - 1:-1]


def run(args) -> int:
    """Execute ``vlsforest collect``."""
    import pandas as pd

    from vlsforest.errors import InputDataError

    rows = []
    if args.what == "truth":
        from vlsforest.synth.record import gather_truth

        names = gather_truth(args.inputs, args.output)
        print(f"collect truth: {len(names)} plots ({', '.join(names)}) -> {args.output}")
        return 0
    if args.what == "metrics":
        frames, species = [], {}
        for f in args.inputs:
            plot, source, scenario = _parts(f, 3, "metrics")
            if plot not in species:
                t = read_csv_table(f.parents[2] / "targets.csv", f"targets table of plot {plot}", ("species",),
                                   ids=("target_id",))
                species[plot] = dict(zip(t.target_id, t.species.astype(str)))
            df = read_csv_table(f, "metrics table", ids=("tree_id",))
            df.insert(0, "method", source)
            df.insert(0, "scenario", scenario)
            df.insert(0, "species", [species[plot].get(i, "unknown") for i in df.tree_id])
            df.insert(0, "plot", plot)
            cols = ["plot", "tree_id", "species", "scenario", "method"]
            frames.append(df[cols + [c for c in df.columns if c not in cols]])
        out = pd.concat(frames, ignore_index=True)
        out = out.sort_values(["plot", "tree_id", "scenario", "method"], kind="stable")
    elif args.what == "voxels":
        from vlsforest.io.voxel_model import VoxelModel

        for f in args.inputs:
            plot, method = _parts(f, 2, "voxel model")
            rows.append({"plot": plot, "method": method, "n_voxels": VoxelModel.load(f).n_voxels})
        out = pd.DataFrame(rows).sort_values(["plot", "method"], kind="stable")
    elif args.what == "pad":
        from vlsforest.pad_validation import plot_validation

        frames = []
        for f in args.inputs:
            frames.append(read_csv_table(f, "PAD validation table"))
        out = pd.concat(frames, ignore_index=True)
        if args.figure is not None:
            plot_validation(out, args.figure)
    else:
        for f in args.inputs:
            plot, method, scenario = _parts(f, 3, "timing")
            try:
                t = json.loads(f.read_text())
            except (OSError, json.JSONDecodeError) as exc:
                raise InputDataError(f"{f}: not a timing JSON ({exc})") from None
            rows.append({"plot": plot, "method": method, "scenario": scenario, "seconds": float(t["total"]),
                         "n_pulses": int(t.get("n_pulses", 0)), "n_points": int(t.get("n_points", 0))})
        out = pd.DataFrame(rows).sort_values(["plot", "method", "scenario"], kind="stable")
    write_csv(args.output, out, index=False, float_format="%.6f", na_rep="NaN", lineterminator="\n")
    print(f"collect {args.what}: {len(out)} rows -> {args.output}")
    return 0
