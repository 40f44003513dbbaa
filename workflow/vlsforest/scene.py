"""Scene assembly per plot × method (the study's simulation scenes) and HELIOS++ export.

A plot scene (:func:`assemble_scene`) is a SCENE.yaml for :mod:`vlsforest.sim` with

* a ground plane at the plot's ground elevation (median of the TLS ground points) over the
  horizontal extent of the plot's TLS points;
* each target tree's stem as its Poisson mesh (:mod:`vlsforest.stems`) and its crown as the
  method's voxels of the tree's other TLS points;
* every surrounding tree as voxels of the method;

with object ids (:func:`vlsforest.domain.labels.object_ids`) that separate each target's stem (``10·t + 1``) and crown
(``10·t + 2``, t = segmented tree id) from the surrounding trees (``2``) and the ground (``1``),
and materials (reflectance of foliage for voxels, wood for stems, ground for the plane).

:func:`export_helios` writes the same scene as HELIOS++ scene XML with its parts (OBJ, AMAPVox
``.vox``) through :mod:`vlsforest.sim.helios`, the home of the HELIOS++ export (scenes and
surveys).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import yaml

from vlsforest.domain.labels import GROUND_ID, SURROUNDING_ID, object_ids
from vlsforest.errors import ConfigError, InputDataError
from vlsforest.io.voxel_model import VoxelModel

#: default reflectances of scene materials (fractions at the scanner wavelength)
DEFAULT_REFLECTANCE = {"foliage": 0.45, "wood": 0.35, "ground": 0.3}


def crown_points(xyz, tree_id, stem_masks: dict | None = None):
    """Points that voxel models are built from: tree points minus ground and meshed stem points.

    Parameters
    ----------
    xyz : ndarray (n, 3)
        Segmented TLS points of the plot.
    tree_id : ndarray (n,)
        Tree id per point (0 = ground / no tree).
    stem_masks : dict tree id → (ndarray (m, 3))
        Stem points of each target tree (as selected by :mod:`vlsforest.stems`); they are
        removed (exact coordinate match).

    Returns
    -------
    xyz, owner : ndarrays
    """
    from scipy.spatial import cKDTree

    xyz = np.asarray(xyz, dtype=np.float64)
    tid = np.asarray(tree_id, dtype=np.int64)
    keep = tid > 0
    for t, pts in (stem_masks or {}).items():
        pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
        idx = np.flatnonzero(tid == int(t))
        if len(pts) == 0 or len(idx) == 0:
            continue
        d, _ = cKDTree(pts).query(xyz[idx], k=1)
        keep[idx[d < 1e-6]] = False
    if not keep.any():
        raise InputDataError("no tree points left to voxelise (every point is ground or stem)")
    return xyz[keep], tid[keep]


def assemble_scene(out: Path, model: VoxelModel, targets, stems: dict, ground_z: float, extent,
                   reflectance: dict | None = None, method: str = "") -> Path:
    """Write the SCENE.yaml of one plot × method and its voxel parts.

    Parameters
    ----------
    out : path
        SCENE.yaml to write; voxel parts go beside it (``crown_{t}.npz``, ``surrounding.npz``).
    model : VoxelModel
        The method's voxels of the whole plot (``owner`` = segmented tree id).
    targets : DataFrame or list of int
        Target tree ids (column ``tree_id``).
    stems : dict tree id → path
        Stem mesh (OBJ/PLY) of each target; referenced relative to the YAML.
    ground_z : float
        Plane elevation.
    extent : (xmin, ymin, xmax, ymax)
        Plane extent.
    reflectance : dict, optional
        ``foliage``, ``wood``, ``ground`` (default :data:`DEFAULT_REFLECTANCE`).
    method : str
        Method name written as a comment/name.

    Returns
    -------
    Path
        The SCENE.yaml.
    """
    out = Path(out)
    refl = dict(DEFAULT_REFLECTANCE)
    for k, v in (reflectance or {}).items():
        if k not in refl:
            raise ConfigError(f"scene.reflectance: unknown material {k!r} (foliage, wood, ground)")
        if not (isinstance(v, (int, float)) and 0 <= v <= 1):
            raise ConfigError(f"scene.reflectance.{k} must be a fraction in [0, 1], got {v!r}")
        refl[k] = float(v)
    ids = [int(t) for t in (targets["tree_id"] if hasattr(targets, "columns") else targets)]
    if not np.isfinite(ground_z):
        raise InputDataError("ground elevation is not finite")
    ext = [float(v) for v in extent]
    if not (ext[0] < ext[2] and ext[1] < ext[3]):
        raise InputDataError(f"plot extent {ext} is empty")
    parts = [{"id": GROUND_ID, "type": "plane", "z": float(ground_z), "extent": ext,
              "reflectance": refl["ground"], "classification": 2, "name": "ground"}]
    for t in ids:
        sid, cid = object_ids(t)
        if t not in stems:
            raise InputDataError(f"no stem mesh for target tree {t}")
        rel = os.path.relpath(Path(stems[t]).resolve(), out.parent.resolve())
        parts.append({"id": sid, "type": "mesh", "path": rel, "reflectance": refl["wood"],
                      "classification": 4, "name": f"stem_{t}"})
        m = model.owner == t
        if m.any():
            model.subset(m).save(out.parent / f"crown_{t}.npz")
            parts.append({"id": cid, "type": "voxels", "path": f"crown_{t}.npz", "reflectance": refl["foliage"],
                          "classification": 5, "name": f"crown_{t}"})
    others = ~np.isin(model.owner, ids)
    if others.any():
        model.subset(others).save(out.parent / "surrounding.npz")
        parts.append({"id": SURROUNDING_ID, "type": "voxels", "path": "surrounding.npz",
                      "reflectance": refl["foliage"], "classification": 5, "name": "surrounding"})
    doc = {"name": method, "voxel_backend": "auto", "parts": parts}
    from vlsforest.io.atomic import write_text

    return write_text(out, yaml.safe_dump(doc, sort_keys=False))


def export_helios(scene_yaml, out_dir, scene_id: str = "vlsforest_scene") -> Path:
    """Write a SCENE.yaml as a HELIOS++ scene folder: every part type the simulator reads.

    The HELIOS++ export lives in :mod:`vlsforest.sim.helios`; this is its
    :func:`~vlsforest.sim.helios.export_scene` (a survey goes with
    :func:`~vlsforest.sim.helios.export_survey`).

    Parameters
    ----------
    scene_yaml : path
    out_dir : path
        Folder for ``scene.xml`` and its parts (``part_{id}.obj`` / ``part_{id}.vox``); it
        appears whole or not at all (:func:`vlsforest.io.atomic.atomic_dir`).
    scene_id : str
        The XML scene id.

    Returns
    -------
    Path
        ``out_dir/scene.xml``. Part ids are our object ids, so HELIOS++'s ``hitObjectId`` matches
        our ``object_id``.
    """
    from vlsforest.sim.helios import export_scene

    return export_scene(scene_yaml, out_dir, scene_id=scene_id)


__all__ = ["DEFAULT_REFLECTANCE", "assemble_scene", "crown_points", "export_helios"]
