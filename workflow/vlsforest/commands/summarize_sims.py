"""``vlsforest summarize-sims SIM.laz … -o OUT.csv`` — one row of counts per simulated cloud."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def register(sub) -> None:
    """Add the ``summarize-sims`` sub-command."""
    p = sub.add_parser("summarize-sims", help="summarise simulated clouds (points, pulses, returns)",
                       description="One CSV row per simulated cloud results/{plot}/{method}/{scenario}/sim.laz: "
                                   "points, pulses with returns, share of multi-return pulses, points per object.")
    p.add_argument("clouds", nargs="+", help="simulated LAS/LAZ files")
    p.add_argument("-o", "--output", required=True, help="CSV to write")
    p.set_defaults(func=run)


def summarize(path) -> dict:
    """Counts of one simulated cloud."""
    from vlsforest.io.las import read_las

    path = Path(path)
    c = read_las(path, require=("gps_time", "number_of_returns", "point_source_id"), allow_empty=True)
    a = c.attrs
    key = np.stack([a["point_source_id"].astype(np.float64), a["gps_time"]], axis=1) if len(c) else np.zeros((0, 2))
    pulses, first = np.unique(key, axis=0, return_index=True)
    nret = a["number_of_returns"][first] if len(c) else np.zeros(0)
    parts = path.parts
    row = dict(plot=parts[-4] if len(parts) >= 4 else "", method=parts[-3] if len(parts) >= 3 else "",
               scenario=parts[-2] if len(parts) >= 2 else "", n_points=len(c), n_pulses_with_returns=len(pulses),
               multi_return_pct=float(100.0 * np.mean(nret > 1)) if len(nret) else float("nan"))
    if "object_id" in a:
        ids, counts = np.unique(a["object_id"], return_counts=True)
        row["points_per_object"] = ";".join(f"{i}:{n}" for i, n in zip(ids, counts))
    return row


def run(args) -> int:
    """Execute ``vlsforest summarize-sims``."""
    import pandas as pd

    df = pd.DataFrame([summarize(p) for p in args.clouds])
    out = Path(args.output)
    out.parent.mkdir(parents=True, exist_ok=True)
    df.to_csv(out, index=False, float_format="%.6g")
    return 0
