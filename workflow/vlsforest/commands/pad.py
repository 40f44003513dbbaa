"""``vlsforest pad``: plant area density from multi-scan TLS, as an AMAPVox ``.vox`` file.

``vlsforest pad TLS_DIR -o OUT.vox [--voxel-size 0.25] [--estimator transmittance|fpl_unbiased]
[--lad planophile] [--pad-max 5] [--min-pulses 5] [--extent xmin ymin xmax ymax]
[--keep echoes|sampled|all]`` traverses every shot of every scan of ``TLS_DIR`` (see
:mod:`vlsforest.pad.traverse` for the folder layout) through the global voxel lattice and
writes PAD (``PadBVTotal``, NaN where flagged) with the AMAPVox accumulator columns and a
``flag`` column.

``--validate FOREST_DIR`` also compares both estimators with the virtual truth of a recorded
forest (plot from ``--plot``, default the folder above ``TLS_DIR``) and writes
``--table OUT.csv`` and ``--figure OUT.png`` (default: next to the ``.vox``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from vlsforest.commands import CSV, PNG, declare_outputs
from vlsforest.errors import ConfigError


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``pad`` sub-command to ``subparsers``."""
    from vlsforest.pad import ESTIMATORS, LAD_NAMES

    p = subparsers.add_parser(
        "pad",
        help="plant area density from TLS (AMAPVox-style .vox), optionally validated against truth",
        description=(
            "Traverse every TLS shot (empty shots rebuilt from the scan pattern when the scan's "
            "survey file is present) through a voxel grid and estimate the plant area density."
        ),
    )
    p.add_argument("tls_dir", type=Path, metavar="TLS_DIR", help="folder with scan_{k}.laz, scans.csv, scan_{k}.survey.yaml")
    p.add_argument("-o", "--output", required=True, type=Path, metavar="OUT.vox", help="output .vox file")
    p.add_argument("--voxel-size", type=float, default=0.25, metavar="M", help="voxel edge (default 0.25 m)")
    p.add_argument("--estimator", choices=ESTIMATORS, default="transmittance", help="PAD estimator (default transmittance)")
    p.add_argument("--lad", choices=LAD_NAMES, default="planophile", help="leaf angle distribution (default planophile)")
    p.add_argument("--pad-max", type=float, default=5.0, metavar="PAD", help="PAD cap, m²/m³ (default 5)")
    p.add_argument("--min-pulses", type=int, default=5, metavar="N", help="flag voxels crossed by fewer shots (default 5)")
    p.add_argument("--extent", type=float, nargs=4, metavar=("XMIN", "YMIN", "XMAX", "YMAX"),
                   help="horizontal extent of the grid (default: plot.json above TLS_DIR, else the echoes' bbox)")
    p.add_argument("--keep", choices=("echoes", "sampled", "all"), default="echoes",
                   help="voxels written: with plant echoes (default), crossed by a shot, or all")
    p.add_argument("--mean-leaf-area", type=float, default=0.01, metavar="M2",
                   help="mean leaf area for the finite-leaf free path of the FPL estimator (0: turbid; default 0.01)")
    p.add_argument("--scans", type=int, nargs="+", metavar="K", help="use only these scan ids (default: all)")
    p.add_argument("--blind-radius", type=float, default=0.04, metavar="M",
                   help="an empty shot passing this close to an echo (of any scan) inside its scanner's minimum "
                        "range was blocked there and is left out; 0 keeps all (default 0.04 m)")
    p.add_argument("--validate", type=Path, metavar="FOREST_DIR", help="recorded virtual forest to validate against")
    p.add_argument("--plot", metavar="NAME", help="plot name for --validate (default: the folder above TLS_DIR)")
    p.add_argument("--table", type=Path, metavar="OUT.csv", help="validation table (default OUT_validation.csv)")
    p.add_argument("--figure", type=Path, metavar="OUT.png", help="validation figure (default OUT_validation.png)")
    p.add_argument("--min-shots", type=int, default=20, metavar="N",
                   help="validation: voxels crossed by fewer shots are left out of bias/RMSE (default 20)")
    p.set_defaults(func=run)
    declare_outputs(p, output=(".vox",), table=CSV, figure=PNG)
    return p


def _default_extent(tls_dir: Path):
    info = tls_dir.resolve().parent / "plot.json"
    if not info.is_file():
        return None
    try:
        ext = json.loads(info.read_text())["extent"]
    except (ValueError, KeyError, TypeError):
        return None
    return ext


def low_return_scans(scans, ratio: float = 0.5) -> list[str]:
    """Warnings for scans whose share of shots with an echo is below ``ratio`` × the median share.

    A scanner standing in or next to vegetation closer than its minimum range records those
    shots as empty; their rebuilt empty shots then cross the whole scene and bias PAD low.
    """
    import numpy as np

    share = {sc.scan_id: float(np.count_nonzero(np.diff(sc.shot_ptr))) / sc.n_shots
             for sc in scans if sc.empty_shots and sc.n_shots}
    if len(share) < 2:
        return []
    med = float(np.median(list(share.values())))
    return [f"scan {k}: only {100 * v:.0f} % of its shots returned an echo (median {100 * med:.0f} %); if the "
            "scanner was blinded by nearby vegetation its empty shots bias PAD low (see --scans)"
            for k, v in share.items() if v < ratio * med]


def run(args) -> int:
    """Execute ``vlsforest pad`` with parsed ``args``; return 0."""
    from vlsforest.io.vox import write_vox
    from vlsforest.pad import accumulate, estimate_pad, grid_for_scans, load_tls_scans, pad_to_vox
    from vlsforest.pad_validation import median_abs_bias, validate_pad

    if not args.pad_max > 0:
        raise ConfigError(f"--pad-max: must be > 0, got {args.pad_max}")
    if args.min_pulses < 1:
        raise ConfigError(f"--min-pulses: must be ≥ 1, got {args.min_pulses}")
    if args.min_shots < 1:
        raise ConfigError(f"--min-shots: must be ≥ 1, got {args.min_shots}")
    if args.validate is not None:  # the validation outputs named after -o are checked up front too
        from vlsforest.io.atomic import check_output_path

        stem = args.output.with_suffix("")
        check_output_path(args.table or Path(f"{stem}_validation.csv"), CSV, "--table")
        check_output_path(args.figure or Path(f"{stem}_validation.png"), PNG, "--figure")
    t0 = time.perf_counter()
    scans = load_tls_scans(args.tls_dir, scan_ids=args.scans, blind_radius=args.blind_radius)
    n_blind = sum(sc.blind_shots for sc in scans)
    if n_blind:
        per = ", ".join(f"scan {sc.scan_id}: {sc.blind_shots}" for sc in scans if sc.blind_shots)
        print(f"vlsforest pad: {n_blind} empty shots blocked inside the scanners' minimum range left out ({per})",
              file=sys.stderr)
    for msg in low_return_scans(scans):
        print(f"vlsforest pad: warning: {msg}", file=sys.stderr)
    if not all(sc.empty_shots for sc in scans):
        print("vlsforest pad: warning: some scans have no survey file; their empty shots are unknown, "
              "so PAD is biased high there", file=sys.stderr)
    extent = args.extent if args.extent is not None else _default_extent(args.tls_dir)
    origin, shape = grid_for_scans(scans, args.voxel_size, extent)
    acc = accumulate(scans, origin, args.voxel_size, shape, mean_leaf_area=args.mean_leaf_area)
    n_shots = acc.n_shots
    del scans
    pad, flags = estimate_pad(acc, lad=args.lad, pad_max=args.pad_max, estimator=args.estimator,
                              min_pulses=args.min_pulses)
    vox = pad_to_vox(acc, pad, flags, args.pad_max, lad=args.lad, keep=args.keep, estimator=args.estimator)
    write_vox(args.output, vox)
    print(f"vlsforest pad: {n_shots} shots, grid {shape[0]}×{shape[1]}×{shape[2]}, {vox.n_voxels} voxels "
          f"-> {args.output} ({time.perf_counter() - t0:.1f} s)")
    if args.validate is not None:
        plot = args.plot or args.tls_dir.resolve().parent.name
        stem = args.output.with_suffix("")
        table_path = args.table or Path(f"{stem}_validation.csv")
        figure_path = args.figure or Path(f"{stem}_validation.png")
        table, _ = validate_pad(acc, args.validate, plot, min_pulses=args.min_pulses, min_shots=args.min_shots,
                                table_path=table_path, figure_path=figure_path)
        allb = table[table["height_band"] == "crown"]
        for _, r in allb.iterrows():
            print(f"vlsforest pad: {plot} {r['species']} {r['estimator']}: crown bias {r['bias_pct']:+.1f} % "
                  f"(capped truth {r['bias_pct_capped']:+.1f} %), "
                  f"RMSE {r['rmse']:.2f} m²/m³ ({int(r['n_voxels'])} voxels ≥ {args.min_shots} shots)")
        capped = median_abs_bias(table, "bias_pct_capped")
        for est, m in median_abs_bias(table).items():
            print(f"vlsforest pad: {plot} {est}: median |bias| over species × crown thirds {m:.1f} % "
                  f"({capped[est]:.1f} % against the truth capped at PADmax)")
        print(f"vlsforest pad: validation -> {table_path}, {figure_path}")
    return 0
