"""``vlsforest voxels``: the voxel model of one method for one plot.

``vlsforest voxels CROWNS.npz --method-json '{"kind": "fixed", "voxel_size": 0.25}' -o voxels.npz
[--pad pad.vox --targets targets.csv] [--groups-json …] [--default-group broadleaf] [--seed N]
[--vox OUT.vox]`` builds the cubes (see :mod:`vlsforest.voxels`) from the crown points written by
``vlsforest scene crowns``; scaled kinds need the plot's PAD grid and the targets table (species
per tree → leaf angle distribution and PADmax). ``--vox`` also writes an AMAPVox ``.vox``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from vlsforest.commands import NPZ, declare_outputs


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``voxels`` sub-command."""
    from vlsforest.domain.species import DEFAULT_GROUP

    p = subparsers.add_parser("voxels", help="voxel model of one method (fixed / PAD-scaled cubes)",
                              description=__doc__.split("\n\n")[1])
    p.add_argument("crowns", type=Path, help="crowns.npz (xyz, owner)")
    p.add_argument("--method-json", required=True, help="the method's config entry as JSON (with 'kind')")
    p.add_argument("--method", default="method", help="method name (for messages)")
    p.add_argument("--pad", type=Path, default=None, help="the plot's PAD grid (.vox from vlsforest pad)")
    p.add_argument("--min-pulses", type=int, default=5, help="PAD cells crossed by fewer shots are flagged")
    p.add_argument("--targets", type=Path, default=None, help="targets.csv (species per target tree)")
    p.add_argument("--groups-json", default=None,
                   help='species groups, e.g. {"broadleaf": {"lad": "planophile", "pad_max": 5}, …}')
    p.add_argument("--default-group", default=DEFAULT_GROUP,
                   help=f"species group of non-target trees (default {DEFAULT_GROUP})")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--vox", type=Path, default=None, help="also write the model as AMAPVox .vox")
    p.add_argument("-o", "--output", required=True, type=Path, help="voxels.npz")
    p.set_defaults(func=run)
    declare_outputs(p, output=NPZ, vox=(".vox",))
    return p


def run(args) -> int:
    """Execute ``vlsforest voxels``."""
    from vlsforest.errors import ConfigError
    from vlsforest.io.voxel_model import load_crowns
    from vlsforest.voxels import ModelInputs, PadGrid, build_model

    try:
        method = json.loads(args.method_json)
    except json.JSONDecodeError as exc:
        raise ConfigError(f"--method-json: {exc}") from None
    xyz, owner = load_crowns(args.crowns)
    species_of = {}
    if args.targets is not None:
        from vlsforest.io.csvfile import read_csv_table

        t = read_csv_table(args.targets, "targets table", ("group",), ids=("tree_id",))
        species_of = dict(zip(t.tree_id.tolist(), t.group.astype(str)))
    pad = PadGrid.from_vox(args.pad, args.min_pulses) if args.pad is not None else None
    if args.groups_json:
        try:
            groups = json.loads(args.groups_json)
        except json.JSONDecodeError as exc:
            raise ConfigError(f"--groups-json: {exc}") from None
        if method.get("kind") == "scaled":
            method = {**method, "groups": groups}
    model = build_model(method, ModelInputs(xyz, owner, species_of, pad, args.seed, args.default_group),
                        args.method)
    model.save(args.output)
    if args.vox is not None:
        from vlsforest.io.vox import write_vox
        from vlsforest.io.voxel_model import model_vox

        write_vox(args.vox, model_vox(model, None if model.half is None else 1.0))
    print(f"voxels {args.method}: {model.n_voxels} cubes, side {model.sides().min():.4f}–{model.sides().max():.4f} m")
    return 0
