"""Scenes for the simulator: parts with their materials, geometry and the nearest hits of rays.

A :class:`Scene` is a list of :class:`ScenePart` (object id, kind, :class:`Material`, LAS class)
with the geometry of each: bounded ground planes, triangle meshes and opaque voxel sets. It is
built from a scene file (:meth:`Scene.from_yaml`; the format: :mod:`vlsforest.sim.scene_file`)
or by its ``add_*`` methods, and traces rays to their nearest hit (:meth:`Scene.trace`).

The work is shared out:

- :mod:`vlsforest.sim.scene_file` — the SCENE.yaml format and its reader;
- :mod:`vlsforest.sim.scene_geometry` — the geometry records of the parts (:attr:`Scene.geometry`);
- :mod:`vlsforest.sim.routing` — which voxel sets Embree traces and which a voxel grid;
- :mod:`vlsforest.sim.tracing` — the Embree scene, the voxel grids and the ray queries
  (:attr:`Scene.tracer`).
"""

from __future__ import annotations

import numpy as np

from vlsforest.errors import ConfigError, InputDataError
from vlsforest.sim._voxelgrid import VoxelGrid
from vlsforest.sim.scene_file import build_scene, load_scene
from vlsforest.sim.scene_geometry import (
    Material,
    MeshGeometry,
    PlaneGeometry,
    SceneGeometry,
    ScenePart,
    VoxelGeometry,
)
from vlsforest.sim.tracing import Tracer


class Scene:
    """A scene built from parts; traces rays to their nearest hit.

    Build with :meth:`from_yaml`, :meth:`from_dict` or the ``add_*`` methods; then call
    :meth:`trace`. The Embree BVH is built lazily, per process (a pickled scene leaves it
    behind).

    Parameters
    ----------
    voxel_backend : {"auto", "embree", "grid"}
        Where the voxel sets are traced (:mod:`vlsforest.sim.routing`).
    embree_robust : bool, optional
        Embree's robust traversal (:mod:`vlsforest.sim._embree`); None: on.

    Attributes
    ----------
    parts : list of ScenePart
        The parts, in the order they were added.
    geometry : vlsforest.sim.scene_geometry.SceneGeometry
        Their geometry records (each names its part's index in :attr:`parts`).
    tracer : vlsforest.sim.tracing.Tracer
        The tracing structures of the geometry and the ray queries.
    """

    def __init__(self, voxel_backend: str = "auto", embree_robust: bool | None = None):
        self.parts: list[ScenePart] = []
        self.geometry = SceneGeometry()
        self.tracer = Tracer(self.geometry, voxel_backend, embree_robust)

    @property
    def voxel_backend(self) -> str:
        """Where the voxel sets are traced: ``auto``, ``embree`` or ``grid``."""
        return self.tracer.voxel_backend

    @property
    def embree_robust(self) -> bool:
        """Whether Embree's robust traversal is on (see :mod:`vlsforest.sim._embree`)."""
        return self.tracer.embree_robust

    # ------------------------------------------------------------------ building
    def _add(self, object_id, kind, material, classification, name, record) -> None:
        if any(p.object_id == object_id for p in self.parts):
            raise ConfigError(f"parts: object id {object_id} is used twice")
        self.parts.append(ScenePart(int(object_id), kind, material or Material(), int(classification), name))
        self.geometry.add(record)
        self.tracer.reset()

    def add_plane(self, object_id: int, z: float, extent, material: Material | None = None,
                  classification: int = 2, name: str = "") -> None:
        """Add a horizontal plane at height ``z`` bounded by ``extent = (xmin, ymin, xmax, ymax)``."""
        ext = tuple(float(v) for v in extent)
        if len(ext) != 4 or not (ext[0] < ext[2] and ext[1] < ext[3]) or not np.isfinite(ext).all():
            raise ConfigError(f"plane {object_id}: extent must be [xmin, ymin, xmax, ymax] with min < max")
        if not np.isfinite(z):
            raise ConfigError(f"plane {object_id}: z must be finite")
        self._add(object_id, "plane", material, classification, name,
                  PlaneGeometry(len(self.parts), float(z), ext))

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
            if (lab.shape != (len(f),) or lab.dtype.kind not in "iu"
                    or (len(lab) and (lab.min() < 0 or lab.max() > 255))):
                raise InputDataError(f"mesh part {object_id}: face_labels must be one integer 0–255 per face")
            lab = lab.astype(np.uint8)
        self._add(object_id, "mesh", material, classification, name,
                  MeshGeometry(len(self.parts), v, f.astype(np.int32), lab))

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
        self._add(object_id, "voxels", material, classification, name,
                  VoxelGeometry(len(self.parts), ijk, np.asarray(origin, dtype=np.float64), float(size),
                                None if half is None else np.asarray(half, dtype=np.float64),
                                None if centre is None else np.asarray(centre, dtype=np.float64)))

    @classmethod
    def from_yaml(cls, path, voxel_transform=None) -> "Scene":
        """Load a SCENE.yaml (its format: :mod:`vlsforest.sim.scene_file`).

        ``voxel_transform`` (optional) maps each voxel model read from an ``.npz`` part to the
        model that is added instead (e.g. a correction of the reconstruction).
        """
        return load_scene(path, cls, voxel_transform=voxel_transform)

    @classmethod
    def from_dict(cls, cfg: dict, base_dir=".", source: str = "scene", voxel_transform=None) -> "Scene":
        """Build a scene from a parsed SCENE.yaml mapping (``voxel_transform``: see :meth:`from_yaml`)."""
        return build_scene(cfg, cls, base_dir=base_dir, source=source, voxel_transform=voxel_transform)

    def restyled(self, materials: dict) -> "Scene":
        """A copy with other materials, sharing geometry, voxel grids and the Embree BVH.

        Parts added to either later, or :meth:`plan_for_rays` on either, leave the other as it is.

        Parameters
        ----------
        materials : dict
            Object id → :class:`Material` for the parts to change (others keep theirs).

        Returns
        -------
        Scene
            Of the class of this scene (a subclass gives its own class); its ``__init__`` is not
            called, so it holds the attributes of :class:`Scene` only.
        """
        unknown = set(materials) - {p.object_id for p in self.parts}
        if unknown:
            raise ConfigError(f"restyled: no part with object id(s) {sorted(unknown)}")
        self.prepare()
        other = type(self).__new__(type(self))
        other.parts = [ScenePart(p.object_id, p.kind, materials.get(p.object_id, p.material), p.classification,
                                 p.name) for p in self.parts]
        other.geometry = self.geometry.copy()
        other.tracer = self.tracer.shared_copy(other.geometry)
        return other

    # ------------------------------------------------------------------ geometry
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounds (lo, hi) of the whole scene."""
        return self.geometry.bounds()

    def footprint(self) -> tuple[tuple, float]:
        """Horizontal extent and ground elevation to plan surveys over.

        The first ground plane's extent and height; without a plane, the scene's bounds and
        their lowest z.
        """
        if self.geometry.planes:
            p = self.geometry.planes[0]
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
        fields = {r.part: r.fields() for r in self.geometry.records()}
        return [{"part": part, "kind": part.kind, **fields[i]} for i, part in enumerate(self.parts)]

    def part_table(self) -> dict:
        """Per part: ``object_id``, ``classification``, ``reflectance``, ``specularity``,
        ``shininess`` arrays — the part table :func:`vlsforest.sim.redetect` takes."""
        return {"object_id": np.array([p.object_id for p in self.parts], np.int32),
                "classification": np.array([p.classification for p in self.parts], np.uint8),
                "reflectance": np.array([p.material.reflectance for p in self.parts]),
                "specularity": np.array([p.material.specularity for p in self.parts]),
                "shininess": np.array([p.material.shininess for p in self.parts])}

    @property
    def n_voxels(self) -> int:
        """Number of cubes in the scene."""
        return self.geometry.n_cubes

    @property
    def max_voxel_size(self) -> float:
        """Side of the largest voxel cell in the scene (m; 0 without voxels)."""
        return self.geometry.max_voxel_size

    @property
    def n_triangles(self) -> int:
        """Number of mesh triangles in the scene."""
        return self.geometry.n_triangles

    @property
    def has_labels(self) -> bool:
        """Whether any mesh part carries per-face labels."""
        return self.geometry.has_labels

    # ------------------------------------------------------------------ tracing
    @property
    def grids(self) -> list[VoxelGrid]:
        """The voxel grids, one per lattice (voxel parts sharing a lattice are merged)."""
        return self.tracer.grids

    def plan_for_rays(self, n_rays: float) -> None:
        """Route the voxel lattices (``voxel_backend="auto"``) for about ``n_rays`` rays.

        Without a plan, ``auto`` sends a lattice of up to
        :data:`~vlsforest.sim.routing.EMBREE_VOXEL_LIMIT` cubes to Embree; with one, a lattice
        goes to Embree when its build costs less than the time it saves over the grid on
        ``n_rays`` rays (see :data:`~vlsforest.sim.routing.EMBREE_VOXEL_MAX`). Both backends give
        the same hits up to rays that graze a cube edge or corner. Structures already built for
        another routing are dropped and rebuilt on the next trace. No effect with a fixed backend.

        Parameters
        ----------
        n_rays : float
            Expected number of rays (sub-rays) to trace.
        """
        self.tracer.plan_for_rays(n_rays)

    @property
    def needs_ray_estimate(self) -> bool:
        """Whether :meth:`plan_for_rays` can change the routing (``auto`` with voxel sets)."""
        return self.tracer.needs_ray_estimate

    @property
    def has_grids(self) -> bool:
        """Whether any voxel set is traced in a voxel grid (from the routing; builds nothing)."""
        return self.tracer.has_grids

    @property
    def uses_embree(self) -> bool:
        """Whether anything is traced with Embree: a mesh or plane, or a voxel set that the routing
        (:func:`vlsforest.sim.routing.route_voxels`: the scene's ``voxel_backend`` and, under
        ``auto``, the cubes of its lattice and the rays planned by :meth:`plan_for_rays`) gives to
        Embree."""
        return self.tracer.uses_embree

    @property
    def shift(self) -> np.ndarray:
        """World position of the origin of the float32 coordinates Embree works in."""
        return self.tracer.shift

    def prepare(self) -> None:
        """Build the voxel grids and the Embree BVH now (else lazily at the first trace).

        The simulator calls it before forking its workers, which then share the structures
        copy-on-write instead of each building its own.
        """
        self.tracer.prepare()

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
        return self.tracer.trace(origins, dirs, with_labels, serial)

    def trace_local(self, o32, d32, with_labels: bool = False, world=None, serial: bool = False):
        """:meth:`trace` for float32 rays already in the Embree frame (world − :attr:`shift`).

        Saves the conversions when the caller builds its rays in float32 (the simulator does).
        ``world`` optionally passes the same rays in float64 world coordinates for the voxel
        grids (otherwise rebuilt from the float32 ones); ``serial`` as in :meth:`trace`.
        """
        return self.tracer.trace_local(o32, d32, with_labels, world, serial)

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
        return self.tracer.cast_embree(o32, d32)
