"""``vlsforest stems``: stem points and trimmed Poisson stem mesh of one tree.

``vlsforest stems TREE.laz --scans SCANS.csv --base X Y Z [--dbh D] [--depth 8] -o OUTDIR`` reads
one tree's TLS points (``point_source_id`` = scan id) and the scanner positions, and writes

* ``OUTDIR/stem.ply`` and ``OUTDIR/stem.obj``: the trimmed screened-Poisson stem mesh;
* ``OUTDIR/stem_points.laz``: the tree points selected as stem points, with all their input
  attributes and an extra dimension ``tree_point_index`` (uint32, the point's index in
  ``TREE.laz``), so that the crown points are exactly the others;
* ``OUTDIR/stem.json``: counts, height ranges, crown base estimate, mesh size, mean radius,
  timings (see :func:`vlsforest.stems.build_stem`).

Plot mode (the workflow's ``stems`` rule): ``vlsforest stems --segment DIR --targets targets.csv
--scans SCANS.csv [--config-json JSON] -o OUTDIR`` does the same for every row of
``targets.csv`` (columns ``tree_id, x, y, z`` and optionally ``dbh``; ``z`` is the stem base),
reading ``DIR/trees/{tree_id}.laz`` and writing ``OUTDIR/{tree_id}/…``. ``--config-json`` is the
``stems`` config block, e.g. ``{"depth": 8}``; its keys: :data:`CONFIG_KEYS`.

The mesh and point files are byte-identical for the same inputs; ``stem.json`` differs only in
its timings.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from vlsforest.commands import FOLDER, declare_outputs
from vlsforest.errors import ConfigError, InputDataError

#: keys of the ``stems`` config block: the depth, :func:`vlsforest.stems.trace_stem` and
#: :func:`vlsforest.stems.stem_mesh` settings
TRACE_KEYS = ("slice_height", "tolerance", "max_gap", "min_radius", "min_slice_points", "min_coverage")
MESH_KEYS = ("voxel", "k", "density_quantile", "max_extent", "min_component_faces")
CONFIG_KEYS = ("depth",) + TRACE_KEYS + MESH_KEYS


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``stems`` sub-command to ``subparsers``."""
    p = subparsers.add_parser(
        "stems",
        help="stem points and trimmed screened-Poisson stem mesh of one tree",
        description=(
            "Select the stem surface points of one tree (stem below the crown and the visible stem "
            "in the crown) by slice-wise circle fits from the stem base, and mesh them by screened "
            "Poisson reconstruction (pymeshlab), trimmed to the points."
        ),
    )
    p.add_argument("input", type=Path, nargs="?", help="the tree's TLS points (LAS/LAZ, point_source_id = scan id)")
    p.add_argument("--segment", type=Path, metavar="DIR", help="plot mode: segmentation folder (trees/{tree_id}.laz)")
    p.add_argument("--targets", type=Path, metavar="targets.csv", help="plot mode: targets (tree_id, x, y, z[, dbh])")
    p.add_argument("--config-json", default=None, metavar="JSON", help='stems settings, e.g. {"depth": 8}')
    p.add_argument("--scans", required=True, type=Path, metavar="SCANS.csv", help="scan positions (scan_id, x, y, z)")
    p.add_argument("--base", type=float, nargs=3, metavar=("X", "Y", "Z"), help="tree mode: stem base (ground z)")
    p.add_argument("--dbh", type=float, default=None, metavar="D", help="diameter at breast height (m), optional")
    p.add_argument("--depth", type=int, default=None, help="Poisson octree depth (default 8, as in the study; overrides the config)")
    p.add_argument(
        "--max-extent", type=float, default=None, metavar="M",
        help="trim the mesh where it is farther than M from the stem points (default 0.09 m; overrides the config)",
    )
    p.add_argument("-o", "--output", required=True, type=Path, metavar="OUTDIR", help="output folder")
    p.set_defaults(func=run)
    declare_outputs(p, output=FOLDER)
    return p


def _json_ready(obj):
    if isinstance(obj, dict):
        return {k: _json_ready(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_ready(v) for v in obj]
    if isinstance(obj, (np.floating, float)):
        v = float(obj)
        return v if math.isfinite(v) else None
    if isinstance(obj, np.integer):
        return int(obj)
    return obj


def _settings(args) -> dict:
    """Merge ``--config-json`` and the explicit options into one checked settings dict."""
    cfg = {}
    if args.config_json:
        try:
            cfg = json.loads(args.config_json)
        except json.JSONDecodeError as exc:
            raise ConfigError(f"--config-json: not valid JSON ({exc})") from None
        if cfg is None:
            cfg = {}
        if not isinstance(cfg, dict):
            raise ConfigError("--config-json: must be a JSON object (the stems config block)")
        unknown = sorted(set(cfg) - set(CONFIG_KEYS))
        if unknown:
            raise ConfigError(f"stems.{unknown[0]}: unknown setting (known: {', '.join(CONFIG_KEYS)})")
    if args.depth is not None:
        cfg["depth"] = args.depth
    if args.max_extent is not None:
        cfg["max_extent"] = args.max_extent
    depth = cfg.get("depth", 8)
    if isinstance(depth, bool) or not isinstance(depth, int) or not 4 <= depth <= 12:
        raise ConfigError(f"stems.depth (--depth): must be an integer in 4..12, got {depth!r}")
    cfg["depth"] = depth
    for key in TRACE_KEYS + MESH_KEYS:
        if key in cfg:
            v = cfg[key]
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ConfigError(f"stems.{key}: must be a non-negative number, got {v!r}")
    if "max_extent" in cfg and not cfg["max_extent"] > 0:
        raise ConfigError(f"stems.max_extent (--max-extent): must be a positive number, got {cfg['max_extent']}")
    return cfg


def _one_tree(path: Path, scans_path: Path, scanners: dict, base, dbh, cfg: dict, out: Path) -> dict:
    """Stem of one tree file into ``out``; returns the summary written to ``stem.json``."""
    from vlsforest.io.atomic import make_folder, write_text
    from vlsforest.io.las import read_las, write_las
    from vlsforest.io.mesh import write_mesh
    from vlsforest.stems import build_stem

    t0 = time.perf_counter()
    cloud = read_las(path, require=("point_source_id",))
    t_read = time.perf_counter() - t0
    result = build_stem(
        cloud, scanners, base, dbh=dbh, depth=cfg["depth"], source=str(path),
        trace_options={k: cfg[k] for k in TRACE_KEYS if k in cfg},
        mesh_options={k: cfg[k] for k in MESH_KEYS if k in cfg},
    )
    t1 = time.perf_counter()
    make_folder(out)
    write_mesh(out / "stem.ply", result.mesh)
    write_mesh(out / "stem.obj", result.mesh)
    idx = np.flatnonzero(result.mask).astype(np.uint32)
    write_las(out / "stem_points.laz", cloud.subset(result.mask), extra={"tree_point_index": idx})
    t_write = time.perf_counter() - t1
    summary = dict(result.summary)
    timings = {k: summary.pop(k) for k in [k for k in summary if k.startswith("time_")]}
    timings.update({"time_read_s": t_read, "time_write_s": t_write, "time_total_s": time.perf_counter() - t0})
    # stem.json holds results only (same inputs → same bytes); timings go to the log
    summary.update({"input": str(path), "scans": str(scans_path), "settings": {k: cfg[k] for k in sorted(cfg)}})
    print(f"vlsforest stems: {path}: " + ", ".join(f"{k[5:-2]} {v:.2f} s" for k, v in timings.items()),
          file=sys.stderr)
    write_text(out / "stem.json", json.dumps(_json_ready(summary), indent=2, sort_keys=True) + "\n")
    return summary


def run(args) -> int:
    """Execute ``vlsforest stems`` with parsed ``args``; return 0."""
    from vlsforest.stems import read_scanner_positions

    cfg = _settings(args)
    if args.dbh is not None and not (math.isfinite(args.dbh) and args.dbh > 0):
        raise ConfigError(f"--dbh: must be a positive number, got {args.dbh}")
    plot_mode = args.segment is not None or args.targets is not None
    if plot_mode:
        if args.input is not None or args.base is not None or args.dbh is not None:
            raise ConfigError("input/--base/--dbh: give either a tree file with --base, or --segment with --targets")
        if args.segment is None or args.targets is None:
            raise ConfigError("--segment/--targets: plot mode needs both")
        return _run_plot(args, cfg, read_scanner_positions(args.scans))
    if args.input is None or args.base is None:
        raise ConfigError("input/--base: give a tree file and --base X Y Z (or --segment and --targets)")
    if not all(math.isfinite(v) for v in args.base):
        raise ConfigError(f"--base: must be three finite numbers, got {args.base}")
    scanners = read_scanner_positions(args.scans)
    summary = _one_tree(args.input, args.scans, scanners, args.base, args.dbh, cfg, Path(args.output))
    print(
        f"vlsforest stems: {summary['n_stem_points']} stem points, mesh {summary['mesh_vertices']} vertices / "
        f"{summary['mesh_faces']} faces -> {args.output}"
    )
    return 0


def _run_plot(args, cfg: dict, scanners: dict) -> int:
    import pandas as pd

    from vlsforest.io.csvfile import read_csv_table

    path = Path(args.targets)
    targets = read_csv_table(path, "targets table", ids=("tree_id",), numbers=("x", "y", "z"))
    if targets.empty:
        raise InputDataError(f"{path}: no targets listed")
    ids = targets["tree_id"].to_numpy()
    base = targets[["x", "y", "z"]].to_numpy()
    dbh = np.full(len(ids), np.nan)  # an optional DBH guides the stem fit; an empty cell leaves it to the points
    if "dbh" in targets.columns:
        dbh = pd.to_numeric(targets["dbh"], errors="coerce").to_numpy(np.float64)
        if np.any(np.isnan(dbh) & targets["dbh"].notna().to_numpy()):
            raise InputDataError(f"{path}: targets table has values in column 'dbh' that are not numbers")
    out = Path(args.output)
    for tid, b, d in zip(ids, base, dbh):
        d = float(d) if math.isfinite(d) and d > 0 else None
        s = _one_tree(Path(args.segment) / "trees" / f"{tid}.laz", args.scans, scanners, b, d, cfg, out / str(tid))
        print(
            f"vlsforest stems: tree {tid}: {s['n_stem_points']} stem points, mesh {s['mesh_vertices']} vertices / "
            f"{s['mesh_faces']} faces"
        )
    return 0
