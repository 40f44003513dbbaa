"""The scene file (SCENE.yaml): its format and its reader.

SCENE.yaml::

    parts:
      - {id: 1, type: plane, z: 241.6, extent: [xmin, ymin, xmax, ymax], reflectance: 0.3}
      - {id: 2, type: mesh, path: stem.obj, reflectance: 0.3}              # OBJ or PLY
      - {id: 3, type: vox, path: crown.vox, mode: fixed}                   # AMAPVox .vox
      - {id: 4, type: vox, path: crown.vox, mode: scaled, pad_max: 8, alpha: 0.5,
         random_shift: true, seed: 1}
      - {id: 5, type: voxels, path: centres.csv, size: 0.25}               # x,y,z[,size]
      - {id: 7, type: voxels, path: crown.npz}                             # vlsforest.io.voxel_model.VoxelModel
      - {id: 6, type: voxels, points: tls.laz, size: 0.02, min_points: 1}  # voxelise points

Every part has an integer object ``id`` (written per return as ``object_id``) and a material:
``reflectance`` (fraction at the scanner wavelength, default 0.5), ``specularity`` (Phong ks,
default 0 = Lambertian), ``shininess`` (Phong exponent, default 10), and a LAS
``classification`` (default 2 for planes, 1 otherwise). Paths are relative to the YAML file.

Voxel placement follows HELIOS++: a ``.vox`` cell (i, j, k) is centred at
``min_corner + (ijk + 0.5)·res``. In ``scaled`` mode the cube's half size is
``res/2 · (PAD/pad_max)^alpha`` with PAD from ``pad_column`` (default ``PadBVTotal``);
``pad_max`` comes from the part, else from the file header (``#max_pad``), else it is an
error. Deliberate differences from HELIOS++ v1.0: PAD is clipped to ``pad_max`` first so a
cube never outgrows its cell (HELIOS++ lets it, quirk 9), voxels with PAD 0 or NaN carry no
cube, and ``random_shift`` moves each cube by ``U(−1, 1)·(res/2 − half)`` per axis with the
part's own seed.

Voxel back-ends (top-level ``voxel_backend``, :mod:`vlsforest.sim.routing`): Embree, with 12
triangles per cube, or a sparse two-level grid walked by a 3-D DDA (no triangles, so tens of
millions of voxels fit in memory); ``embree`` and ``grid`` send every voxel set to one of them.
``auto`` (default) decides per voxel lattice (the voxel sets of one cell size and congruent
origin, counted together; :func:`~vlsforest.sim.routing.embree_pays`): with the number of rays
to trace known (:meth:`vlsforest.sim.scene.Scene.plan_for_rays`; the simulator estimates it from
the survey), a lattice goes to Embree when the time Embree saves on those rays exceeds its build
time by a margin, and never with more than :data:`~vlsforest.sim.routing.EMBREE_VOXEL_MAX`
cubes; without it, a lattice goes to Embree up to
:data:`~vlsforest.sim.routing.EMBREE_VOXEL_LIMIT` cubes. The two back ends give the same hits up
to rays that graze a cube's edge or corner.

Embree's robust traversal (top-level ``embree_robust``, default true): off, leaf-level scenes
trace ≈ 16 % faster and many more rays that meet a shared edge or vertex slip through the surface
(:mod:`vlsforest.sim._embree`).

The reader is what :meth:`vlsforest.sim.scene.Scene.from_yaml` and
:meth:`~vlsforest.sim.scene.Scene.from_dict` call.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from vlsforest.domain.cubes import scaled_cubes
from vlsforest.errors import ConfigError, InputDataError
from vlsforest.io.csvfile import read_csv_table
from vlsforest.io.voxel_model import VoxelModel
from vlsforest.sim.scene_geometry import Material

#: the keys of each part type besides :data:`COMMON_KEYS`
PART_KEYS = {
    "plane": {"z", "extent"},
    "mesh": {"path"},
    "vox": {"path", "mode", "pad_max", "alpha", "random_shift", "seed", "pad_column"},
    "voxels": {"path", "points", "size", "min_points"},  # path: CSV (needs size) or .npz model
}
#: the keys every part may have
COMMON_KEYS = {"id", "type", "reflectance", "specularity", "shininess", "classification", "name"}
#: the top-level keys
TOP_KEYS = {"parts", "voxel_backend", "embree_robust", "name"}


def load_scene(path, scene_type, voxel_transform=None):
    """Read a SCENE.yaml.

    Parameters
    ----------
    path : path
        The file; part paths are relative to its folder.
    scene_type : type
        :class:`vlsforest.sim.scene.Scene` (or a subclass) to build.
    voxel_transform : callable, optional
        Maps each voxel model read from an ``.npz`` part to the model that is added instead.

    Returns
    -------
    Scene
    """
    from vlsforest.io.yamlfile import read_yaml

    path = Path(path)
    return build_scene(read_yaml(path, "scene", mapping=False), scene_type, base_dir=path.parent,
                       source=str(path), voxel_transform=voxel_transform)


def build_scene(cfg: dict, scene_type, base_dir=".", source: str = "scene", voxel_transform=None):
    """A scene from a parsed SCENE.yaml mapping (arguments as in :func:`load_scene`; ``source``
    names the mapping in error messages)."""
    if not isinstance(cfg, dict) or "parts" not in cfg:
        raise ConfigError(f"{source}: needs a top-level 'parts:' list")
    extra = set(cfg) - TOP_KEYS
    if extra:
        raise ConfigError(f"{source}: unknown top-level key(s) {sorted(extra)}")
    parts = cfg["parts"]
    if not isinstance(parts, list) or not parts:
        raise ConfigError(f"{source}: 'parts' must be a non-empty list")
    scene = scene_type(voxel_backend=cfg.get("voxel_backend", "auto"), embree_robust=cfg.get("embree_robust"))
    base = Path(base_dir)
    for n, p in enumerate(parts):
        _add_part(scene, p, base, f"{source}: parts[{n}]", voxel_transform)
    return scene


def targets_region(site, margin_m: float, max_voxel_size: float) -> tuple[list[float], float]:
    """The simulation region around a scene's target trees.

    Parameters
    ----------
    site : str or Path
        A ``site.json`` (``vlsforest scene targets``) with the targets' ``targets_extent``
        ``[xmin, ymin, xmax, ymax]`` of their TLS points.
    margin_m : float
        Margin around the extent (m). A target's voxels reach one cell diagonal beyond its
        points, so a narrower margin is widened to ``√2 · max_voxel_size``.
    max_voxel_size : float
        The scene's largest voxel cell (m; 0 without voxels).

    Returns
    -------
    region : list of 4 floats
        ``[xmin, ymin, xmax, ymax]`` widened by the margin.
    margin : float
        The margin used.

    Raises
    ------
    InputDataError
        When the file has no ``targets_extent``.
    """
    import json

    src = Path(site)
    try:
        ext = [float(v) for v in json.loads(src.read_text())["targets_extent"]]
        if len(ext) != 4:
            raise ValueError(f"{len(ext)} values, 4 needed")
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputDataError(f"{src}: no 'targets_extent' to take the region from ({exc})") from None
    m = max(float(margin_m), math.sqrt(2.0) * float(max_voxel_size))
    return [ext[0] - m, ext[1] - m, ext[2] + m, ext[3] + m], m


def voxelise_points(xyz, size: float, min_points: int = 1) -> np.ndarray:
    """Cells of the global lattice (origins at multiples of ``size``) holding ≥ ``min_points`` points."""
    if not (np.isfinite(size) and size > 0):
        raise ConfigError(f"voxel size must be > 0, got {size!r}")
    ijk = np.floor(np.asarray(xyz, dtype=np.float64) / size).astype(np.int64)
    cells, counts = np.unique(ijk, axis=0, return_counts=True)
    return cells[counts >= min_points]


# ---------------------------------------------------------------------- parts
def _num(d: dict, key: str, where: str, default=None, positive=False, integer=False):
    if key not in d:
        if default is None:
            raise ConfigError(f"{where}.{key} is required")
        return default
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
        raise ConfigError(f"{where}.{key} must be a finite number, got {v!r}")
    if integer and int(v) != v:
        raise ConfigError(f"{where}.{key} must be an integer, got {v!r}")
    if positive and v <= 0:
        raise ConfigError(f"{where}.{key} must be > 0, got {v!r}")
    return int(v) if integer else float(v)


class _Part:
    """One part mapping, checked for its keys, with its common fields read."""

    def __init__(self, p, base: Path, where: str):
        if not isinstance(p, dict):
            raise ConfigError(f"{where} must be a mapping")
        kind = p.get("type")
        if kind not in PART_KEYS:
            raise ConfigError(f"{where}.type must be one of {sorted(PART_KEYS)}, got {kind!r}")
        unknown = set(p) - COMMON_KEYS - PART_KEYS[kind]
        if unknown:
            raise ConfigError(f"{where}: unknown key(s) {sorted(unknown)} for a {kind} part")
        self.p, self.base, self.where, self.kind = p, base, where, kind
        self.oid = self.num("id", integer=True)
        refl = self.num("reflectance", default=0.5)
        if not 0 <= refl <= 1:
            raise ConfigError(f"{where}.reflectance must be a fraction in [0, 1], got {refl!r}")
        ks = self.num("specularity", default=0.0)
        if not 0 <= ks <= 1:
            raise ConfigError(f"{where}.specularity must be in [0, 1], got {ks!r}")
        self.material = Material(refl, ks, self.num("shininess", default=10.0))
        self.cls = self.num("classification", default=2 if kind == "plane" else 1, integer=True)
        self.name = str(p.get("name", ""))

    def num(self, key, **kw):
        return _num(self.p, key, self.where, **kw)

    def path(self, key: str) -> Path:
        if key not in self.p or not isinstance(self.p[key], str):
            raise ConfigError(f"{self.where}.{key} must be a file path")
        q = Path(self.p[key])
        return q if q.is_absolute() else self.base / q

    def add_voxels(self, scene, ijk, origin, size, half=None, centre=None) -> None:
        scene.add_voxels(self.oid, ijk, origin, size, half, centre, self.material, self.cls, self.name)


def _add_part(scene, p, base: Path, where: str, voxel_transform=None) -> None:
    part = _Part(p, base, where)
    {"plane": _add_plane, "mesh": _add_mesh, "vox": _add_vox, "voxels": _add_voxels}[part.kind](
        scene, part, voxel_transform)


def _add_plane(scene, part: _Part, voxel_transform) -> None:
    p = part.p
    if "extent" not in p or not isinstance(p["extent"], (list, tuple)) or len(p["extent"]) != 4:
        raise ConfigError(f"{part.where}.extent must be [xmin, ymin, xmax, ymax]")
    scene.add_plane(part.oid, part.num("z"), p["extent"], part.material, part.cls, part.name)


def _add_mesh(scene, part: _Part, voxel_transform) -> None:
    from vlsforest.io.mesh import read_mesh

    mesh = read_mesh(part.path("path"))
    scene.add_mesh(part.oid, mesh.vertices, mesh.faces, part.material, part.cls, part.name)


def _add_vox(scene, part: _Part, voxel_transform) -> None:
    from vlsforest.io.vox import read_vox

    p, where = part.p, part.where
    vox = read_vox(part.path("path"))
    mode = p.get("mode", "fixed")
    if mode not in ("fixed", "scaled"):
        raise ConfigError(f"{where}.mode must be 'fixed' or 'scaled', got {mode!r}")
    half = centre = None
    ijk = vox.ijk.astype(np.int64)
    if mode == "scaled":
        pad_max = p.get("pad_max", vox.max_pad)
        if pad_max is None:
            raise ConfigError(f"{where}.pad_max is required: the .vox header has no #max_pad")
        pad_max = _num({"pad_max": pad_max}, "pad_max", where, positive=True)
        alpha = part.num("alpha", default=0.5, positive=True)
        col = p.get("pad_column", "PadBVTotal")
        if col not in vox.columns:
            raise InputDataError(f"{part.path('path')}: no column {col!r} for scaled voxels")
        half_all = scaled_cubes(ijk, vox.column(col), pad_max, vox.res, alpha)
        keep = half_all > 0
        ijk, half = ijk[keep], half_all[keep]
        centre = vox.min_corner + (ijk + 0.5) * vox.res
        if p.get("random_shift", False):
            rng = np.random.default_rng(part.num("seed", default=0, integer=True))
            centre = centre + rng.uniform(-1.0, 1.0, size=centre.shape) * (0.5 * vox.res - half)[:, None]
        if len(ijk) == 0:
            raise InputDataError(f"{part.path('path')}: every voxel has PAD 0 or NaN — nothing to scale")
    part.add_voxels(scene, ijk, vox.min_corner, vox.res, half, centre)


def _add_voxels(scene, part: _Part, voxel_transform) -> None:
    p = part.p
    if ("path" in p) == ("points" in p):
        raise ConfigError(f"{part.where}: give exactly one of 'path' (voxel centres CSV or model .npz) or 'points'")
    if "path" in p and str(p["path"]).lower().endswith(".npz"):
        model = VoxelModel.load(part.path("path"))
        if model.n_voxels == 0:
            raise InputDataError(f"{part.path('path')}: voxel model holds no voxels")
        if voxel_transform is not None:
            model = voxel_transform(model)
        half = None if model.half is None else model.half
        part.add_voxels(scene, model.ijk, np.zeros(3), model.size, half, None if half is None else model.centres())
        return
    size = part.num("size", positive=True)
    if "points" in p:
        ijk = voxelise_points(_read_points(part.path("points")), size,
                              part.num("min_points", default=1, integer=True, positive=True))
        part.add_voxels(scene, ijk, np.zeros(3), size)
        return
    path = part.path("path")
    cen, sizes = _read_centres(path)
    ijk = np.floor(cen / size).astype(np.int64)
    if sizes is None:
        off = cen - (ijk + 0.5) * size
        if np.abs(off).max() > 1e-6 * max(1.0, size) + 1e-6:
            raise InputDataError(f"{path}: voxel centres are not on the {size} m lattice "
                                 "(cell origins at integer multiples of the size)")
        part.add_voxels(scene, ijk, np.zeros(3), size)
    else:
        if (sizes > size * (1 + 1e-9)).any() or (sizes < 0).any():
            raise InputDataError(f"{path}: a cube size is negative or exceeds the cell size {size}")
        keep = sizes > 0
        part.add_voxels(scene, ijk[keep], np.zeros(3), size, sizes[keep] / 2.0, cen[keep])


# ---------------------------------------------------------------------- files
def _read_points(path: Path) -> np.ndarray:
    if path.suffix.lower() in (".las", ".laz"):
        from vlsforest.io.las import read_las

        return read_las(path).xyz
    cen, _ = _read_centres(path, "points file")
    return cen


def _read_centres(path: Path, what: str = "voxel centres file"):
    df = read_csv_table(path, what)
    cols = {c.strip().lower(): c for c in df.columns}
    if not {"x", "y", "z"} <= set(cols):
        raise InputDataError(f"{path}: needs columns x, y, z (and optionally size)")
    xyz = df[[cols["x"], cols["y"], cols["z"]]].to_numpy(dtype=np.float64)
    if len(xyz) == 0:
        raise InputDataError(f"{path}: no rows")
    if not np.isfinite(xyz).all():
        raise InputDataError(f"{path}: NaN or infinite coordinates")
    sizes = df[cols["size"]].to_numpy(dtype=np.float64) if "size" in cols else None
    if sizes is not None and not np.isfinite(sizes).all():
        raise InputDataError(f"{path}: NaN sizes")
    return xyz, sizes
