"""``vlsforest scene``: plot scenes for the simulator, per plot × method.

Sub-commands (the workflow runs them in this order):

``targets SEGMENT_DIR --plot-json plot.json -o targets.csv``
    pair the field list of target trees (``plot.json``: ``targets`` with x, y, species, tree_id)
    with the segmented trees; also writes ``site.json`` beside it (ground elevation = median of
    the TLS ground points, extent = the TLS points' horizontal bounding box).
``crowns SEGMENT_DIR --stems STEMS_DIR --targets targets.csv -o crowns.npz``
    the TLS points that voxel models are built from (tree points minus ground and the targets'
    meshed stem points) with their tree ids.
``build --voxels voxels.npz --targets targets.csv --site site.json --stems STEMS_DIR -o DIR/scene.yaml``
    the SCENE.yaml (ground plane, stem meshes, voxel crowns; see :mod:`vlsforest.scene`).
``helios SCENE.yaml -o DIR [--survey SURVEY.yaml]``
    the same scene as HELIOS++ scene XML with OBJ / ``.vox`` parts; with ``--survey`` also the
    survey (``survey.xml``, ``scanner.xml``, ``platform.xml``) in the same folder, so that
    ``cd DIR && helios survey.xml`` runs what ``vlsforest simulate SCENE.yaml SURVEY.yaml`` runs
    (:mod:`vlsforest.sim.helios`). A setting HELIOS++ cannot run is an error unless
    ``--allow-approximations``, which writes the documented downgrade and warns.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from vlsforest.commands import CSV, FOLDER, NPZ, YAML, declare_outputs


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``scene`` sub-command."""
    p = subparsers.add_parser("scene", help="plot scenes per method (targets, crown points, SCENE.yaml, HELIOS++ XML)",
                              description="Build the simulation scene of a plot for one voxel method.")
    sub = p.add_subparsers(dest="what", metavar="{targets,crowns,build,helios}")
    sub.required = True
    t = sub.add_parser("targets", help="match field targets to segmented trees; ground and extent")
    t.add_argument("segment", type=Path, help="segmentation folder (trees.csv, segmented.laz)")
    t.add_argument("--plot-json", required=True, type=Path, help="plot description with 'targets'")
    t.add_argument("--max-dist", type=float, default=1.0, help="largest stem-position mismatch (m)")
    t.add_argument("-o", "--output", required=True, type=Path, help="targets.csv (site.json beside it)")
    declare_outputs(t, output=CSV)
    c = sub.add_parser("crowns", help="TLS points to voxelise, with tree ids")
    c.add_argument("segment", type=Path)
    c.add_argument("--stems", required=True, type=Path, help="stems folder ({tree_id}/stem_points.laz)")
    c.add_argument("--targets", required=True, type=Path)
    c.add_argument("-o", "--output", required=True, type=Path, help="crowns.npz")
    declare_outputs(c, output=NPZ)
    b = sub.add_parser("build", help="write SCENE.yaml for a voxel model")
    b.add_argument("--voxels", required=True, type=Path, help="voxel model .npz (vlsforest voxels)")
    b.add_argument("--targets", required=True, type=Path)
    b.add_argument("--site", required=True, type=Path, help="site.json (ground_z, extent)")
    b.add_argument("--stems", required=True, type=Path, help="stems folder ({tree_id}/stem.obj)")
    b.add_argument("--reflectance-json", default=None, help='e.g. {"foliage": 0.45, "wood": 0.35, "ground": 0.3}')
    b.add_argument("--method", default="", help="method name (recorded in the scene)")
    b.add_argument("--helios", type=Path, default=None, help="also export HELIOS++ scene XML into this folder")
    b.add_argument("-o", "--output", required=True, type=Path, help="SCENE.yaml")
    declare_outputs(b, output=YAML, helios=FOLDER)
    h = sub.add_parser("helios", help="export a SCENE.yaml (and a SURVEY.yaml) as HELIOS++ XML",
                       description="Write a scene as HELIOS++ scene XML with OBJ / .vox parts; with --survey also "
                                   "the survey, scanner and platform XML, run by 'cd OUTPUT && helios survey.xml' "
                                   "(HELIOS++ 1.0.8 and 2.x; 2.x also: 'helios OUTPUT/survey.xml --assets OUTPUT/').")
    h.add_argument("scene", type=Path)
    h.add_argument("--survey", type=Path, default=None,
                   help="SURVEY.yaml to export too (survey.xml, scanner.xml, platform.xml)")
    h.add_argument("--name", default=None, help="the survey's name in HELIOS++ (default: the SURVEY.yaml's stem)")
    h.add_argument("--trajectory-interval", type=float, default=0.0, metavar="S",
                   help="HELIOS++ trajectory output interval in seconds (default 0: none)")
    h.add_argument("--allow-approximations", action="store_true",
                   help="write settings HELIOS++ cannot run (elliptical beam, physical detector, trajectory noise, "
                        "…) as documented approximations, with a warning each, instead of stopping")
    h.add_argument("-o", "--output", required=True, type=Path, help="output folder")
    declare_outputs(h, output=FOLDER)
    p.set_defaults(func=run)
    return p


def _json(path: Path, what):
    from vlsforest.errors import InputDataError

    if not path.is_file():
        raise InputDataError(f"{path}: no such {what}")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise InputDataError(f"{path}: not valid JSON ({exc})") from None


def run(args) -> int:
    """Execute ``vlsforest scene``."""
    import numpy as np

    from vlsforest.errors import ConfigError, InputDataError
    from vlsforest.io.atomic import flush, write_csv, write_text
    from vlsforest.io.csvfile import read_csv_table
    from vlsforest.io.las import read_las

    if args.what == "targets":
        from vlsforest.extract import match_targets

        trees = read_csv_table(args.segment / "trees.csv", "tree table", ids=("tree_id",),
                               numbers=("x", "y", "z"))
        info = _json(args.plot_json, "plot description")
        if not isinstance(info, dict) or not info.get("targets"):
            raise InputDataError(f"{args.plot_json}: needs a non-empty 'targets' list")
        df = match_targets(trees, info["targets"], args.max_dist, source=str(args.segment / "trees.csv"))
        write_csv(args.output, df, index=False, float_format="%.6f")
        seg = read_las(args.segment / "segmented.laz", require=("classification",))
        ground = seg.attrs["classification"] == 2
        if ground.sum() < 3:
            raise InputDataError(f"{args.segment / 'segmented.laz'}: fewer than 3 ground points (class 2)")
        lo, hi = seg.xyz[:, :2].min(axis=0), seg.xyz[:, :2].max(axis=0)
        txy = [read_las(args.segment / "trees" / f"{int(t)}.laz").xyz[:, :2] for t in df.tree_id]
        tlo = np.min([a.min(axis=0) for a in txy], axis=0)
        thi = np.max([a.max(axis=0) for a in txy], axis=0)
        site = {"ground_z": float(np.median(seg.xyz[ground, 2])),
                "extent": [float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])],
                "targets_extent": [float(tlo[0]), float(tlo[1]), float(thi[0]), float(thi[1])],
                "n_targets": int(len(df))}
        write_text(args.output.parent / "site.json", json.dumps(site, indent=1) + "\n")
        print(df.to_string(index=False))
        return 0
    if args.what == "crowns":
        from vlsforest.scene import crown_points
        from vlsforest.io.npz import save_npz

        targets = read_csv_table(args.targets, "targets table", ids=("tree_id",))
        seg = read_las(args.segment / "segmented.laz", require=("tree_id",))
        stems = {}
        for t in targets.tree_id.tolist():
            f = args.stems / str(t) / "stem_points.laz"
            stems[t] = read_las(f, allow_empty=True).xyz
        xyz, owner = crown_points(seg.xyz, seg.attrs["tree_id"], stems)
        save_npz(args.output, {"xyz": xyz, "owner": owner})
        print(f"crowns: {len(xyz)} points of {len(np.unique(owner))} trees")
        return 0
    if args.what == "build":
        from vlsforest.scene import assemble_scene, export_helios
        from vlsforest.io.voxel_model import VoxelModel

        targets = read_csv_table(args.targets, "targets table", ids=("tree_id",))
        site = _json(args.site, "site description")
        model = VoxelModel.load(args.voxels)
        stems = {int(t): args.stems / str(int(t)) / "stem.obj" for t in targets.tree_id}
        refl = None
        if args.reflectance_json:
            try:
                refl = json.loads(args.reflectance_json)
            except json.JSONDecodeError as exc:
                raise ConfigError(f"--reflectance-json: {exc}") from None
        out = assemble_scene(args.output, model, targets, stems, site["ground_z"], site["extent"], refl, args.method)
        if args.helios is not None:
            flush()  # the export reads the scene just written
            export_helios(out, args.helios, scene_id=args.method or "vlsforest")
        print(f"scene: {out} ({model.n_voxels} voxels)")
        return 0
    if args.survey is None:
        if args.allow_approximations or args.name is not None or args.trajectory_interval != 0.0:
            raise ConfigError("--allow-approximations, --name and --trajectory-interval need --survey")
        from vlsforest.scene import export_helios

        print(export_helios(args.scene, args.output))
        return 0
    import sys

    from vlsforest.sim.helios import export_survey

    path, approximations = export_survey(args.scene, args.survey, args.output, name=args.name,
                                         trajectory_interval_s=args.trajectory_interval,
                                         allow_approximations=args.allow_approximations)
    for a in approximations:
        print(f"scene helios: approximation: {a}", file=sys.stderr)
    print(path)
    print(f"run: cd {args.output} && helios {path.name}")
    return 0
