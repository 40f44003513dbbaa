"""Scenes for the simulator: triangle meshes (Embree), opaque voxel sets (sparse grid DDA) and
bounded ground planes.

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

Voxel back-ends (top-level ``voxel_backend``): ``auto`` (default) gives voxel sets of up to
300 000 cubes to Embree as 12 triangles per cube (fastest for small models) and traces
larger ones with a sparse two-level grid and a 3-D DDA (no triangles, so tens of millions of
voxels fit in memory); ``embree`` and ``grid`` force one back-end. Both give the same hits.

Embree's robust traversal (top-level ``embree_robust``, default true): off, leaf-level scenes
trace ≈ 16 % faster and many more rays that meet a shared edge or vertex slip through the surface
(:mod:`vlsforest.sim._embree`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numba
import numpy as np

from vlsforest.domain.cubes import cube_triangles, scaled_cubes
from vlsforest.errors import ConfigError, InputDataError, VlsforestError
from vlsforest.io.voxel_model import VoxelModel
from vlsforest.sim import _embree
from vlsforest.sim._voxelgrid import VoxelGrid
from vlsforest.sim.waveform import hit_cos32

_PART_KEYS = {
    "plane": {"z", "extent"},
    "mesh": {"path"},
    "vox": {"path", "mode", "pad_max", "alpha", "random_shift", "seed", "pad_column"},
    "voxels": {"path", "points", "size", "min_points"},  # path: CSV (needs size) or .npz model
}
_COMMON_KEYS = {"id", "type", "reflectance", "specularity", "shininess", "classification", "name"}


@dataclass(frozen=True)
class Material:
    """Surface material of a scene part.

    Attributes
    ----------
    reflectance : float
        Reflectance at the scanner wavelength, fraction 0–1.
    specularity : float
        Phong specular share ks (0 = Lambertian).
    shininess : float
        Phong exponent.
    """

    reflectance: float = 0.5
    specularity: float = 0.0
    shininess: float = 10.0


@dataclass
class ScenePart:
    """One part of a scene: its object id, kind, material and LAS class."""

    object_id: int
    kind: str
    material: Material = field(default_factory=Material)
    classification: int = 1
    name: str = ""


@dataclass
class _Plane:
    part: int
    z: float
    extent: tuple


@dataclass
class _Mesh:
    part: int
    vertices: np.ndarray
    faces: np.ndarray
    labels: np.ndarray | None = None


@dataclass
class _VoxelSet:
    part: int
    ijk: np.ndarray
    origin: np.ndarray
    size: float
    half: np.ndarray | None = None
    centre: np.ndarray | None = None


class Scene:
    """A scene built from parts; traces rays to their nearest hit.

    Build with :meth:`from_yaml`, :meth:`from_dict` or the ``add_*`` methods; then call
    :meth:`trace`. The Embree BVH is built lazily, per process.
    """

    #: with ``voxel_backend="auto"``, the voxel sets of a lattice go to Embree as 12 triangles
    #: per cube when the lattice holds up to this many cubes in all, else all of them to one
    #: sparse grid. Embree pays ≈ 6 µs per cube to build and then traces faster; the grid
    #: builds in ≈ 0.5 µs per cube, and one grid per lattice beats Embree plus a grid for the
    #: same crowns (``benchmarks/bench_embree_build.py``, ``benchmarks/bench_sim.py``).
    EMBREE_VOXEL_LIMIT = 300_000
    #: when the number of rays to trace is known (:meth:`plan_for_rays`; the simulator estimates
    #: it from the survey before tracing), ``auto`` weighs instead the Embree build (≈ 6 µs per
    #: cube, ``benchmarks/bench_embree_build.py``) against what Embree saves per ray over the
    #: grid (≈ 0.16 µs at 0.25 m cells, more in finer lattices, where the grid walks more cells:
    #: ≈ 0.16 µs · (0.25 m / h)^0.6), with a margin of 1.25 for the build, and never sends more
    #: than :attr:`EMBREE_VOXEL_MAX` cubes of one lattice to Embree (≈ 1 kB each, built piece by
    #: piece, :func:`_cube_triangle_chunks`): a dense airborne flight traces fine crowns faster
    #: in Embree, a sparse one in the grid (``benchmarks/bench_sim.py``).
    EMBREE_VOXEL_MAX = 4_000_000
    _EMBREE_BUILD_S_PER_CUBE = 6e-6
    _EMBREE_SAVES_S_PER_RAY = 0.16e-6
    _EMBREE_BUILD_MARGIN = 1.25

    def __init__(self, voxel_backend: str = "auto", embree_robust: bool | None = None):
        if voxel_backend not in ("auto", "embree", "grid"):
            raise ConfigError(f"voxel_backend must be 'auto', 'embree' or 'grid', got {voxel_backend!r}")
        if embree_robust is None:
            embree_robust = _embree.ROBUST_DEFAULT
        if not isinstance(embree_robust, (bool, np.bool_)):
            raise ConfigError(f"embree_robust must be true or false, got {embree_robust!r}")
        self.voxel_backend = voxel_backend
        #: Embree's robust traversal (see :mod:`vlsforest.sim._embree`)
        self.embree_robust = bool(embree_robust)
        self.parts: list[ScenePart] = []
        self._planes: list[_Plane] = []
        self._meshes: list[_Mesh] = []
        self._voxelsets: list[_VoxelSet] = []
        self._grids: list[VoxelGrid] | None = None
        self._embree_routing: list[bool] | None = None
        self._expected_rays: float | None = None
        self._embree = None
        self._embree_parts = None
        self._shift = None
        self._bounds = None

    # ------------------------------------------------------------------ building
    def _add_part(self, object_id, kind, material, classification, name) -> int:
        if any(p.object_id == object_id for p in self.parts):
            raise ConfigError(f"parts: object id {object_id} is used twice")
        self.parts.append(ScenePart(int(object_id), kind, material or Material(), int(classification), name))
        self._grids = None
        self._embree_routing = None
        self._embree = None
        self._bounds = None
        return len(self.parts) - 1

    def add_plane(self, object_id: int, z: float, extent, material: Material | None = None,
                  classification: int = 2, name: str = "") -> None:
        """Add a horizontal plane at height ``z`` bounded by ``extent = (xmin, ymin, xmax, ymax)``."""
        ext = tuple(float(v) for v in extent)
        if len(ext) != 4 or not (ext[0] < ext[2] and ext[1] < ext[3]) or not np.isfinite(ext).all():
            raise ConfigError(f"plane {object_id}: extent must be [xmin, ymin, xmax, ymax] with min < max")
        if not np.isfinite(z):
            raise ConfigError(f"plane {object_id}: z must be finite")
        idx = self._add_part(object_id, "plane", material, classification, name)
        self._planes.append(_Plane(idx, float(z), ext))

    def add_mesh(self, object_id: int, vertices, faces, material: Material | None = None,
                 classification: int = 1, name: str = "", face_labels=None) -> None:
        """Add a triangle mesh (vertices (n, 3) float, faces (m, 3) int).

        ``face_labels`` (optional, one small non-negative integer per face, e.g. the organ of a
        tree) is written per return as the extra dimension ``label`` (hits on other parts: 0).
        """
        v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
        f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
        if len(f) == 0:
            raise InputDataError(f"mesh part {object_id}: the mesh has no faces")
        if not np.isfinite(v).all():
            raise InputDataError(f"mesh part {object_id}: NaN or infinite vertices")
        if f.min() < 0 or f.max() >= len(v):
            raise InputDataError(f"mesh part {object_id}: face index out of range")
        lab = None
        if face_labels is not None:
            lab = np.asarray(face_labels)
            if lab.shape != (len(f),) or lab.dtype.kind not in "iu" or (len(lab) and (lab.min() < 0 or lab.max() > 255)):
                raise InputDataError(f"mesh part {object_id}: face_labels must be one integer 0–255 per face")
            lab = lab.astype(np.uint8)
        idx = self._add_part(object_id, "mesh", material, classification, name)
        self._meshes.append(_Mesh(idx, v, f.astype(np.int32), lab))

    def add_voxels(self, object_id: int, ijk, origin, size: float, half=None, centre=None,
                   material: Material | None = None, classification: int = 1, name: str = "") -> None:
        """Add opaque cubes on the lattice ``origin + ijk·size``.

        Parameters
        ----------
        ijk : ndarray, shape (n, 3)
            Integer cell indices.
        origin : array_like, shape (3,)
            Lattice origin (corner of cell 0, 0, 0).
        size : float
            Cell size.
        half, centre : ndarray, optional
            Per-voxel cube half size (n,) and centre (n, 3); omitted: full cells.
        """
        if not (np.isfinite(size) and size > 0):
            raise ConfigError(f"voxel part {object_id}: voxel size must be > 0, got {size!r}")
        ijk = np.asarray(ijk, dtype=np.int64).reshape(-1, 3)
        if len(ijk) == 0:
            raise InputDataError(f"voxel part {object_id}: no voxels")
        idx = self._add_part(object_id, "voxels", material, classification, name)
        self._voxelsets.append(_VoxelSet(idx, ijk, np.asarray(origin, dtype=np.float64), float(size),
                                         None if half is None else np.asarray(half, dtype=np.float64),
                                         None if centre is None else np.asarray(centre, dtype=np.float64)))

    @classmethod
    def from_yaml(cls, path, voxel_transform=None) -> "Scene":
        """Load a SCENE.yaml (see the module docstring).

        ``voxel_transform`` (optional) maps each voxel model read from an ``.npz`` part to the
        model that is added instead (e.g. a correction of the reconstruction).
        """
        path = Path(path)
        return cls.from_dict(_load_yaml(path, "scene"), base_dir=path.parent, source=str(path),
                             voxel_transform=voxel_transform)

    @classmethod
    def from_dict(cls, cfg: dict, base_dir=".", source: str = "scene", voxel_transform=None) -> "Scene":
        """Build a scene from a parsed SCENE.yaml mapping (``voxel_transform``: see :meth:`from_yaml`)."""
        if not isinstance(cfg, dict) or "parts" not in cfg:
            raise ConfigError(f"{source}: needs a top-level 'parts:' list")
        extra = set(cfg) - {"parts", "voxel_backend", "embree_robust", "name"}
        if extra:
            raise ConfigError(f"{source}: unknown top-level key(s) {sorted(extra)}")
        parts = cfg["parts"]
        if not isinstance(parts, list) or not parts:
            raise ConfigError(f"{source}: 'parts' must be a non-empty list")
        scene = cls(voxel_backend=cfg.get("voxel_backend", "auto"), embree_robust=cfg.get("embree_robust"))
        base = Path(base_dir)
        for n, p in enumerate(parts):
            _add_part_from_dict(scene, p, base, f"{source}: parts[{n}]", voxel_transform)
        return scene

    # ------------------------------------------------------------------ geometry
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounds (lo, hi) of the whole scene."""
        if self._bounds is None:
            self._bounds = self._compute_bounds()
        return self._bounds[0].copy(), self._bounds[1].copy()

    def _compute_bounds(self):
        lo = np.full(3, np.inf)
        hi = np.full(3, -np.inf)
        for p in self._planes:
            lo = np.minimum(lo, [p.extent[0], p.extent[1], p.z])
            hi = np.maximum(hi, [p.extent[2], p.extent[3], p.z])
        for m in self._meshes:
            lo = np.minimum(lo, m.vertices.min(axis=0))
            hi = np.maximum(hi, m.vertices.max(axis=0))
        for v in self._voxelsets:
            lo = np.minimum(lo, v.origin + v.ijk.min(axis=0) * v.size)
            hi = np.maximum(hi, v.origin + (v.ijk.max(axis=0) + 1) * v.size)
        return lo, hi

    def footprint(self) -> tuple[tuple, float]:
        """Horizontal extent and ground elevation to plan surveys over.

        The first ground plane's extent and height; without a plane, the scene's bounds and
        their lowest z.
        """
        if self._planes:
            p = self._planes[0]
            return p.extent, p.z
        lo, hi = self.bounds()
        return (lo[0], lo[1], hi[0], hi[1]), lo[2]

    def part_geometries(self) -> list[dict]:
        """The geometry of every part, in part order (what an exporter needs).

        Returns
        -------
        list of dict
            Each with ``part`` (the :class:`ScenePart`) and ``kind``, and by kind: ``plane``
            ``z``, ``extent``; ``mesh`` ``vertices``, ``faces``; ``voxels`` ``ijk``,
            ``origin``, ``size``, ``half`` (None: full cells) and ``centre`` (None: centred in
            their cells).
        """
        out = [None] * len(self.parts)
        for p in self._planes:
            out[p.part] = {"z": p.z, "extent": p.extent}
        for m in self._meshes:
            out[m.part] = {"vertices": m.vertices, "faces": m.faces}
        for v in self._voxelsets:
            out[v.part] = {"ijk": v.ijk, "origin": v.origin, "size": v.size, "half": v.half, "centre": v.centre}
        return [{"part": part, "kind": part.kind, **geom} for part, geom in zip(self.parts, out)]

    def part_table(self) -> dict:
        """Per part: ``object_id``, ``classification``, ``reflectance``, ``specularity``,
        ``shininess`` arrays — the part table :func:`vlsforest.sim.redetect` takes."""
        return {"object_id": np.array([p.object_id for p in self.parts], np.int32),
                "classification": np.array([p.classification for p in self.parts], np.uint8),
                "reflectance": np.array([p.material.reflectance for p in self.parts]),
                "specularity": np.array([p.material.specularity for p in self.parts]),
                "shininess": np.array([p.material.shininess for p in self.parts])}

    @property
    def grids(self) -> list[VoxelGrid]:
        """The voxel grids, one per lattice (voxel parts sharing a lattice are merged)."""
        if self._grids is None:
            self._grids = _build_grids([s for s, e in zip(self._voxelsets, self._routing()) if not e])
        return self._grids

    def _routing(self) -> list[bool]:
        """Per voxel set (in :attr:`_voxelsets` order): whether it goes to Embree.

        Computed once per scene state (adding a part resets it): :attr:`uses_embree` asks on
        every trace call.
        """
        if self._embree_routing is None:
            if self.voxel_backend == "auto":
                keys = [_lattice_key(s) for s in self._voxelsets]
                cubes: dict[tuple, int] = {}
                for k, s in zip(keys, self._voxelsets):
                    cubes[k] = cubes.get(k, 0) + len(s.ijk)
                self._embree_routing = [self._embree_pays(cubes[k], k[0]) for k in keys]
            else:
                self._embree_routing = [self.voxel_backend == "embree"] * len(self._voxelsets)
        return self._embree_routing

    def _embree_pays(self, n_cubes: int, size: float) -> bool:
        """``auto`` routing of one lattice of ``n_cubes`` cubes of side ``size``."""
        if self._expected_rays is None:
            return n_cubes <= self.EMBREE_VOXEL_LIMIT
        if n_cubes > self.EMBREE_VOXEL_MAX:
            return False
        saves = self._expected_rays * self._EMBREE_SAVES_S_PER_RAY * (0.25 / size) ** 0.6
        return saves > self._EMBREE_BUILD_MARGIN * self._EMBREE_BUILD_S_PER_CUBE * n_cubes

    def plan_for_rays(self, n_rays: float) -> None:
        """Route the voxel lattices (``voxel_backend="auto"``) for about ``n_rays`` rays.

        Without a plan, ``auto`` sends a lattice of up to :attr:`EMBREE_VOXEL_LIMIT` cubes to
        Embree; with one, a lattice goes to Embree when its build costs less than the time it saves
        over the grid on ``n_rays`` rays (see :attr:`EMBREE_VOXEL_MAX`). Both backends give the
        same hits up to rays that graze a cube edge or corner. Structures already built for another
        routing are dropped and rebuilt on the next trace. No effect with a fixed backend.

        Parameters
        ----------
        n_rays : float
            Expected number of rays (sub-rays) to trace.
        """
        if self.voxel_backend != "auto":
            return
        n = float(n_rays)
        if not np.isfinite(n) or n < 0:
            raise ConfigError(f"plan_for_rays: expected number of rays must be finite and >= 0, got {n_rays!r}")
        before = self._routing()
        self._expected_rays = n
        self._embree_routing = None
        if self._routing() != before:
            self._grids = None
            self._embree = None
            self._embree_parts = None

    @property
    def n_voxels(self) -> int:
        """Number of cubes in the scene."""
        return int(sum(_n_cubes(s) for s in self._voxelsets))

    @property
    def max_voxel_size(self) -> float:
        """Side of the largest voxel cell in the scene (m; 0 without voxels)."""
        return float(max((s.size for s in self._voxelsets), default=0.0))

    @property
    def n_triangles(self) -> int:
        """Number of mesh triangles in the scene."""
        return int(sum(len(m.faces) for m in self._meshes))

    def _build_embree(self):
        lo, hi = self.bounds()
        self._shift = np.where(np.isfinite(lo + hi), 0.5 * (lo + hi), 0.0)
        sc = _embree.new_scene(self.embree_robust)
        parts = []
        labels = []
        for m in self._meshes:
            _embree.add_triangles(sc, (m.vertices - self._shift).astype(np.float32), m.faces)
            parts.append(m.part)
            labels.append(m.labels)
        for p in self._planes:  # Embree is called anyway: two triangles beat a numpy pass
            x0, y0, x1, y1 = p.extent
            v = np.array([[x0, y0, p.z], [x1, y0, p.z], [x1, y1, p.z], [x0, y1, p.z]]) - self._shift
            _embree.add_triangles(sc, v.astype(np.float32), np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int32))
            parts.append(p.part)
            labels.append(None)
        for v, in_embree in zip(self._voxelsets, self._routing()):
            if in_embree:
                n = _n_cubes(v)
                if n:
                    _embree.add_triangle_chunks(sc, 8 * n, 12 * n, _cube_triangle_chunks(v, self._shift))
                    parts.append(v.part)
                    labels.append(None)
        self._embree = sc
        self._embree_parts = np.asarray(parts, dtype=np.int32)
        self._embree_labels = _label_table(labels)

    @property
    def has_labels(self) -> bool:
        """Whether any mesh part carries per-face labels."""
        return any(m.labels is not None for m in self._meshes)

    def restyled(self, materials: dict) -> "Scene":
        """A copy with other materials, sharing geometry, voxel grids and the Embree BVH.

        Parameters
        ----------
        materials : dict
            Object id → :class:`Material` for the parts to change (others keep theirs).
        """
        unknown = set(materials) - {p.object_id for p in self.parts}
        if unknown:
            raise ConfigError(f"restyled: no part with object id(s) {sorted(unknown)}")
        self.prepare()
        other = Scene.__new__(Scene)  # not copy.copy: __getstate__ would drop the BVH
        other.__dict__.update(self.__dict__)
        other.parts = [ScenePart(p.object_id, p.kind, materials.get(p.object_id, p.material), p.classification,
                                 p.name) for p in self.parts]
        return other

    def prepare(self) -> None:
        """Build the voxel grids and the Embree BVH now (else lazily at the first trace).

        The simulator calls it before forking its workers, which then share the structures
        copy-on-write instead of each building its own.
        """
        self.grids
        if self._embree is None and self.uses_embree:
            self._build_embree()
            # Embree commits the BVH lazily: force it with one ray
            self._embree.run(np.zeros((1, 3), np.float32), np.array([[0, 0, 1]], np.float32))

    def trace(self, origins, dirs, with_labels: bool = False, serial: bool = False):
        """Nearest hit of each ray.

        Parameters
        ----------
        origins, dirs : ndarray, shape (n, 3)
            Ray origins (world coordinates, float64) and unit directions.
        with_labels : bool
            Also return the face label of each hit (0 where none).
        serial : bool, optional
            Trace the voxel grids without numba threads (see :meth:`VoxelGrid.trace`).

        Returns
        -------
        t : ndarray (n,)
            Range to the hit (inf: none).
        part : ndarray of int32 (n,)
            Index into :attr:`parts` (−1: none).
        cos_inc : ndarray (n,)
            |cos| of the incidence angle between ray and surface normal.
        label : ndarray of uint8 (n,)
            Only with ``with_labels``.
        """
        o = np.ascontiguousarray(origins, dtype=np.float64)
        d = np.ascontiguousarray(dirs, dtype=np.float64)
        if self.uses_embree:
            self.prepare()
            return self.trace_local((o - self._shift).astype(np.float32), d.astype(np.float32), with_labels,
                                    world=(o, d))
        n = len(o)
        t = np.full(n, np.inf)
        part = np.full(n, -1, dtype=np.int32)
        cos_inc = np.zeros(n)
        label = np.zeros(n, dtype=np.uint8) if with_labels else None
        for p in self._planes:  # analytic, float64 (scenes without meshes)
            dz = d[:, 2]
            with np.errstate(divide="ignore", invalid="ignore"):
                tp = (p.z - o[:, 2]) / dz
            ok = np.isfinite(tp) & (tp > 0) & (tp < t)
            if ok.any():
                x = o[ok, 0] + tp[ok] * d[ok, 0]
                y = o[ok, 1] + tp[ok] * d[ok, 1]
                inside = (x >= p.extent[0]) & (x <= p.extent[2]) & (y >= p.extent[1]) & (y <= p.extent[3])
                idx = np.flatnonzero(ok)[inside]
                t[idx] = tp[idx]
                part[idx] = p.part
                cos_inc[idx] = np.abs(dz[idx])
                if with_labels:
                    label[idx] = 0
        self._trace_grids(o, d, t, part, cos_inc, label, serial)
        if with_labels:
            return t, part, cos_inc, label
        return t, part, cos_inc

    @property
    def has_grids(self) -> bool:
        """Whether any voxel set is traced in a voxel grid (from the routing; builds nothing)."""
        return not all(self._routing())

    @property
    def needs_ray_estimate(self) -> bool:
        """Whether :meth:`plan_for_rays` can change the routing (``auto`` with voxel sets)."""
        return self.voxel_backend == "auto" and bool(self._voxelsets)

    @property
    def uses_embree(self) -> bool:
        """Whether meshes (and planes, and small voxel sets) are traced with Embree."""
        return bool(self._meshes) or any(self._routing())

    @property
    def shift(self) -> np.ndarray:
        """World position of the origin of the float32 coordinates Embree works in."""
        self.prepare()
        return self._shift.copy()

    def trace_local(self, o32, d32, with_labels: bool = False, world=None, serial: bool = False):
        """:meth:`trace` for float32 rays already in the Embree frame (world − :attr:`shift`).

        Saves the conversions when the caller builds its rays in float32 (the simulator does).
        ``world`` optionally passes the same rays in float64 world coordinates for the voxel
        grids (otherwise rebuilt from the float32 ones); ``serial`` as in :meth:`trace`.
        """
        self.prepare()
        res = self._embree.run(o32, d32, output=1)
        gid = res["geomID"]
        n = len(gid)
        t = np.empty(n)
        part = np.empty(n, dtype=np.int32)
        cos_inc = np.empty(n)
        _embree_hits(res["tfar"], gid, res["Ng"], d32, self._embree_parts, t, part, cos_inc)
        label = np.zeros(n, dtype=np.uint8) if with_labels else None
        if with_labels:
            offsets, flat = self._embree_labels
            _hit_labels(gid, res["primID"], offsets, flat, label)
        if self.grids:
            o, d = world if world is not None else (o32.astype(np.float64) + self._shift, d32.astype(np.float64))
            self._trace_grids(o, d, t, part, cos_inc, label, serial)
        if with_labels:
            return t, part, cos_inc, label
        return t, part, cos_inc

    def cast_embree(self, o32, d32):
        """Embree's raw answer for float32 rays in its frame, for scenes without voxel grids.

        Returns
        -------
        tfar : ndarray of float32
            Hit distance (inf or undefined where ``geom`` < 0).
        geom : ndarray of int32
            Embree geometry id (−1: no hit).
        ng : ndarray of float32, shape (n, 3)
            Geometric normal of the hit triangle.
        parts : ndarray of int32
            Scene part (index into :attr:`parts`) of each Embree geometry.
        """
        self.prepare()
        if self.grids:
            raise VlsforestError("cast_embree: the scene has voxel grids; use trace_local")
        res = self._embree.run(o32, d32, output=1)
        return res["tfar"], res["geomID"], res["Ng"], self._embree_parts

    def _trace_grids(self, o, d, t, part, cos_inc, label, serial=False):
        """Update nearest hits (in place) with the voxel grids."""
        for g in self.grids:
            tg, pg, face, _ = g.trace(o, d, t.copy(), serial=serial)
            better = (pg >= 0) & (tg < t)
            if better.any():
                t[better] = tg[better]
                part[better] = pg[better]
                if label is not None:
                    label[better] = 0
                axis = np.abs(face[better].astype(np.int64)) - 1
                cos_inc[better] = np.abs(d[better, axis])

    def __getstate__(self):  # the Embree scene cannot be pickled; rebuilt lazily after unpickling
        state = self.__dict__.copy()
        state["_embree"] = None
        state["_embree_parts"] = None
        state["_embree_labels"] = None
        return state


# ---------------------------------------------------------------------- helpers
def _label_table(labels: list) -> tuple[np.ndarray, np.ndarray]:
    """Per-face labels of the Embree geometries as one flat table.

    Returns ``(offsets, flat)``: geometry ``g``'s face ``p`` has label ``flat[offsets[g] + p]``;
    ``offsets[g]`` is −1 for a geometry without labels (its hits keep label 0).
    """
    offsets = np.full(len(labels), -1, dtype=np.int64)
    chunks = []
    start = 0
    for g, lab in enumerate(labels):
        if lab is not None:
            offsets[g] = start
            chunks.append(np.asarray(lab, dtype=np.uint8))
            start += len(lab)
    flat = np.concatenate(chunks) if chunks else np.zeros(0, dtype=np.uint8)
    return offsets, flat


@numba.njit(cache=True)
def _hit_labels(gid, prim, offsets, flat, label):
    """Label of each hit from :func:`_label_table` (in place; rays without a hit or on a geometry
    without labels keep theirs), one pass instead of one pass per geometry."""
    for i in range(gid.shape[0]):
        g = gid[i]
        if g >= 0:
            o = offsets[g]
            if o >= 0:
                label[i] = flat[o + prim[i]]


@numba.njit(cache=True)
def _embree_hits(tfar, gid, ng, d, parts, t, part, cos_inc):
    """Embree's answer as range (inf: no hit), scene part (−1: none) and |cos| of the incidence
    angle (0: none; float32 arithmetic on Embree's geometric normal), in one pass."""
    for i in range(gid.shape[0]):
        g = gid[i]
        t[i] = np.inf
        part[i] = -1
        cos_inc[i] = 0.0
        if g >= 0:
            t[i] = np.float64(tfar[i])
            part[i] = parts[g]
            cos_inc[i] = hit_cos32(ng, d, i)


def _load_yaml(path: Path, what: str):
    from vlsforest.io.yamlfile import read_yaml

    return read_yaml(path, what, mapping=False)


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


def _add_part_from_dict(scene: Scene, p, base: Path, where: str, voxel_transform=None) -> None:
    if not isinstance(p, dict):
        raise ConfigError(f"{where} must be a mapping")
    kind = p.get("type")
    if kind not in _PART_KEYS:
        raise ConfigError(f"{where}.type must be one of {sorted(_PART_KEYS)}, got {kind!r}")
    unknown = set(p) - _COMMON_KEYS - _PART_KEYS[kind]
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {sorted(unknown)} for a {kind} part")
    oid = _num(p, "id", where, integer=True)
    refl = _num(p, "reflectance", where, default=0.5)
    if not 0 <= refl <= 1:
        raise ConfigError(f"{where}.reflectance must be a fraction in [0, 1], got {refl!r}")
    ks = _num(p, "specularity", where, default=0.0)
    if not 0 <= ks <= 1:
        raise ConfigError(f"{where}.specularity must be in [0, 1], got {ks!r}")
    mat = Material(refl, ks, _num(p, "shininess", where, default=10.0))
    cls_ = _num(p, "classification", where, default=2 if kind == "plane" else 1, integer=True)
    name = str(p.get("name", ""))

    def path_of(key):
        if key not in p or not isinstance(p[key], str):
            raise ConfigError(f"{where}.{key} must be a file path")
        q = Path(p[key])
        return q if q.is_absolute() else base / q

    if kind == "plane":
        if "extent" not in p or not isinstance(p["extent"], (list, tuple)) or len(p["extent"]) != 4:
            raise ConfigError(f"{where}.extent must be [xmin, ymin, xmax, ymax]")
        scene.add_plane(oid, _num(p, "z", where), p["extent"], mat, cls_, name)
    elif kind == "mesh":
        from vlsforest.io.mesh import read_mesh

        mesh = read_mesh(path_of("path"))
        scene.add_mesh(oid, mesh.vertices, mesh.faces, mat, cls_, name)
    elif kind == "vox":
        from vlsforest.io.vox import read_vox

        vox = read_vox(path_of("path"))
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
            alpha = _num(p, "alpha", where, default=0.5, positive=True)
            col = p.get("pad_column", "PadBVTotal")
            if col not in vox.columns:
                raise InputDataError(f"{path_of('path')}: no column {col!r} for scaled voxels")
            half_all = scaled_cubes(ijk, vox.column(col), pad_max, vox.res, alpha)
            keep = half_all > 0
            ijk, half = ijk[keep], half_all[keep]
            centre = vox.min_corner + (ijk + 0.5) * vox.res
            if p.get("random_shift", False):
                rng = np.random.default_rng(_num(p, "seed", where, default=0, integer=True))
                centre = centre + rng.uniform(-1.0, 1.0, size=centre.shape) * (0.5 * vox.res - half)[:, None]
            if len(ijk) == 0:
                raise InputDataError(f"{path_of('path')}: every voxel has PAD 0 or NaN — nothing to scale")
        scene.add_voxels(oid, ijk, vox.min_corner, vox.res, half, centre, mat, cls_, name)
    else:  # voxels
        if ("path" in p) == ("points" in p):
            raise ConfigError(f"{where}: give exactly one of 'path' (voxel centres CSV or model .npz) or 'points'")
        if "path" in p and str(p["path"]).lower().endswith(".npz"):
            model = VoxelModel.load(path_of("path"))
            if model.n_voxels == 0:
                raise InputDataError(f"{path_of('path')}: voxel model holds no voxels")
            if voxel_transform is not None:
                model = voxel_transform(model)
            half = None if model.half is None else model.half
            scene.add_voxels(oid, model.ijk, np.zeros(3), model.size, half,
                             None if half is None else model.centres(), mat, cls_, name)
            return
        size = _num(p, "size", where, positive=True)
        if "points" in p:
            ijk = voxelise_points(_read_points(path_of("points")), size,
                                  _num(p, "min_points", where, default=1, integer=True, positive=True))
            scene.add_voxels(oid, ijk, np.zeros(3), size, material=mat, classification=cls_, name=name)
        else:
            cen, sizes = _read_centres(path_of("path"))
            ijk = np.floor(cen / size).astype(np.int64)
            if sizes is None:
                off = cen - (ijk + 0.5) * size
                if np.abs(off).max() > 1e-6 * max(1.0, size) + 1e-6:
                    raise InputDataError(f"{path_of('path')}: voxel centres are not on the {size} m lattice "
                                         "(cell origins at integer multiples of the size)")
                scene.add_voxels(oid, ijk, np.zeros(3), size, material=mat, classification=cls_, name=name)
            else:
                if (sizes > size * (1 + 1e-9)).any() or (sizes < 0).any():
                    raise InputDataError(f"{path_of('path')}: a cube size is negative or exceeds the cell size {size}")
                keep = sizes > 0
                scene.add_voxels(oid, ijk[keep], np.zeros(3), size, sizes[keep] / 2.0, cen[keep], mat, cls_, name)


def voxelise_points(xyz, size: float, min_points: int = 1) -> np.ndarray:
    """Cells of the global lattice (origins at multiples of ``size``) holding ≥ ``min_points`` points."""
    if not (np.isfinite(size) and size > 0):
        raise ConfigError(f"voxel size must be > 0, got {size!r}")
    ijk = np.floor(np.asarray(xyz, dtype=np.float64) / size).astype(np.int64)
    cells, counts = np.unique(ijk, axis=0, return_counts=True)
    return cells[counts >= min_points]


def _read_points(path: Path) -> np.ndarray:
    if path.suffix.lower() in (".las", ".laz"):
        from vlsforest.io.las import read_las

        return read_las(path).xyz
    cen, _ = _read_centres(path)
    return cen


def _read_centres(path: Path):
    import pandas as pd

    if not path.is_file():
        raise InputDataError(f"{path}: no such file")
    try:
        df = pd.read_csv(path)
    except Exception as exc:
        raise InputDataError(f"{path}: not a readable CSV ({exc})") from None
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


# the unit cube's corners and triangles under the names tests of the Embree backend read


def _n_cubes(v: _VoxelSet) -> int:
    """Number of cubes a voxel set puts into the scene (scaled cubes of half size 0: none)."""
    return len(v.ijk) if v.half is None else int(np.count_nonzero(v.half > 0))


def _cube_triangle_chunks(v: _VoxelSet, shift, chunk: int = 1 << 16):
    """The cubes of a voxel set as triangles (8 vertices and 12 faces per cube), in pieces of
    ``chunk`` cubes, shifted to the Embree frame and in float32: one piece at a time in memory
    besides Embree's own buffers. Yields ``(vertices, faces)``; faces index the whole set's
    vertices."""
    if v.half is None:
        rows = np.arange(len(v.ijk))
    else:
        rows = np.flatnonzero(v.half > 0)
    for a in range(0, len(rows), chunk):
        r = rows[a:a + chunk]
        if v.half is None or v.centre is None:  # full cells, or scaled cubes centred in theirs
            centre = v.origin + (v.ijk[r] + 0.5) * v.size
        else:
            centre = v.centre[r]
        half = np.full(len(centre), 0.5 * v.size) if v.half is None else v.half[r]
        verts, faces = cube_triangles(centre, half, first=a)
        yield (verts - shift).astype(np.float32), faces.astype(np.int32)


def _lattice_key(s: _VoxelSet) -> tuple:
    """Voxel sets with equal keys share a lattice (same size, congruent origin)."""
    frac = np.round(np.mod(s.origin / s.size, 1.0), 9) % 1.0
    return (round(s.size, 12), tuple(frac))


def _build_grids(sets: list[_VoxelSet]) -> list[VoxelGrid]:
    """Merge voxel sets that share a lattice (same size, congruent origin) into one grid each."""
    groups: dict[tuple, list[_VoxelSet]] = {}
    for s in sets:
        groups.setdefault(_lattice_key(s), []).append(s)
    grids = []
    for group in groups.values():
        size = group[0].size
        origin = group[0].origin
        ijks, parts, halves, centres = [], [], [], []
        scaled = any(s.half is not None for s in group)
        for s in group:
            shift = np.round((s.origin - origin) / size).astype(np.int64)
            ijk = s.ijk + shift
            ijks.append(ijk)
            parts.append(np.full(len(ijk), s.part, dtype=np.int32))
            if scaled:
                if s.half is None:
                    halves.append(np.full(len(ijk), size / 2.0))
                    centres.append(origin + (ijk + 0.5) * size)
                else:
                    halves.append(s.half)
                    centres.append(s.centre)
        grids.append(VoxelGrid.build(np.concatenate(ijks), origin, size, part=np.concatenate(parts),
                                     half_size=np.concatenate(halves) if scaled else None,
                                     centre=np.concatenate(centres) if scaled else None))
    return grids
