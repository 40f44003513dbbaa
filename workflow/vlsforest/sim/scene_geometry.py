"""The parts of a scene: their materials and geometry (bounded ground planes, triangle meshes and
voxel sets).

Each record names the scene part it belongs to (its index in
:attr:`vlsforest.sim.scene.Scene.parts`) and holds the arrays the tracing structures are built
from (:mod:`vlsforest.sim.tracing`). :class:`SceneGeometry` keeps the records of one scene
and answers what the whole geometry is: its bounds, its numbers of cubes and triangles.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from vlsforest.domain.cubes import cube_triangles

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


#: the two triangles of a plane's rectangle, over the corners of :meth:`PlaneGeometry.corners`
PLANE_FACES = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int32)


@dataclass
class PlaneGeometry:
    """A horizontal rectangle at height ``z`` over ``extent = (xmin, ymin, xmax, ymax)``.

    Attributes
    ----------
    part : int
        Index of its scene part.
    z : float
        Height.
    extent : tuple of float
        ``(xmin, ymin, xmax, ymax)``.
    """

    part: int
    z: float
    extent: tuple

    def corners(self) -> np.ndarray:
        """The rectangle's four corners, (4, 3), counter-clockwise from (xmin, ymin)."""
        x0, y0, x1, y1 = self.extent
        return np.array([[x0, y0, self.z], [x1, y0, self.z], [x1, y1, self.z], [x0, y1, self.z]])

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounds (lo, hi)."""
        return (np.array([self.extent[0], self.extent[1], self.z]),
                np.array([self.extent[2], self.extent[3], self.z]))

    def fields(self) -> dict:
        """``z`` and ``extent`` (see :meth:`vlsforest.sim.scene.Scene.part_geometries`)."""
        return {"z": self.z, "extent": self.extent}


@dataclass
class MeshGeometry:
    """A triangle mesh.

    Attributes
    ----------
    part : int
        Index of its scene part.
    vertices : ndarray of float64, shape (n, 3)
        Vertex coordinates.
    faces : ndarray of int32, shape (m, 3)
        Vertex indices per triangle.
    labels : ndarray of uint8, shape (m,), optional
        One label per face (e.g. a tree's organ); None: no labels.
    """

    part: int
    vertices: np.ndarray
    faces: np.ndarray
    labels: np.ndarray | None = None

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounds (lo, hi) of the vertices."""
        return self.vertices.min(axis=0), self.vertices.max(axis=0)

    def fields(self) -> dict:
        """``vertices`` and ``faces`` (see :meth:`vlsforest.sim.scene.Scene.part_geometries`)."""
        return {"vertices": self.vertices, "faces": self.faces}


@dataclass
class VoxelGeometry:
    """Opaque cubes on the lattice ``origin + ijk·size``.

    Attributes
    ----------
    part : int
        Index of its scene part.
    ijk : ndarray of int64, shape (n, 3)
        Cell indices.
    origin : ndarray, shape (3,)
        Lattice origin (corner of cell 0, 0, 0).
    size : float
        Cell size.
    half : ndarray, shape (n,), optional
        Per-cell cube half size (0: no cube); None: full cells.
    centre : ndarray, shape (n, 3), optional
        Per-cell cube centre; None: centred in their cells.
    """

    part: int
    ijk: np.ndarray
    origin: np.ndarray
    size: float
    half: np.ndarray | None = None
    centre: np.ndarray | None = None

    @property
    def n_cubes(self) -> int:
        """Number of cubes the set puts into the scene (scaled cubes of half size 0: none)."""
        return len(self.ijk) if self.half is None else int(np.count_nonzero(self.half > 0))

    @property
    def lattice_key(self) -> tuple:
        """Voxel sets with equal keys share a lattice (same size, congruent origin)."""
        frac = np.round(np.mod(self.origin / self.size, 1.0), 9) % 1.0
        return (round(self.size, 12), tuple(frac))

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounds (lo, hi) of the cells."""
        return (self.origin + self.ijk.min(axis=0) * self.size,
                self.origin + (self.ijk.max(axis=0) + 1) * self.size)

    def triangle_chunks(self, shift, chunk: int = 1 << 16):
        """The cubes as triangles (8 vertices and 12 faces per cube), ``chunk`` cubes at a time.

        Parameters
        ----------
        shift : array_like, shape (3,)
            Subtracted from the vertices (the origin of the frame they are wanted in).
        chunk : int
            Cubes per piece: one piece at a time is in memory besides what the caller keeps.

        Yields
        ------
        vertices : ndarray of float32, shape (8 k, 3)
        faces : ndarray of int32, shape (12 k, 3)
            Indices into the vertices of the whole set (a piece's first cube is cube ``a`` of
            the set, its vertices start at ``8 a``).
        """
        if self.half is None:
            rows = np.arange(len(self.ijk))
        else:
            rows = np.flatnonzero(self.half > 0)
        for a in range(0, len(rows), chunk):
            r = rows[a:a + chunk]
            if self.half is None or self.centre is None:  # full cells, or scaled cubes centred in theirs
                centre = self.origin + (self.ijk[r] + 0.5) * self.size
            else:
                centre = self.centre[r]
            half = np.full(len(centre), 0.5 * self.size) if self.half is None else self.half[r]
            verts, faces = cube_triangles(centre, half, first=a)
            yield (verts - shift).astype(np.float32), faces.astype(np.int32)

    def fields(self) -> dict:
        """``ijk``, ``origin``, ``size``, ``half``, ``centre`` (see
        :meth:`vlsforest.sim.scene.Scene.part_geometries`)."""
        return {"ijk": self.ijk, "origin": self.origin, "size": self.size, "half": self.half,
                "centre": self.centre}


class SceneGeometry:
    """The geometry records of one scene, by kind, in the order they were added.

    Attributes
    ----------
    planes : list of PlaneGeometry
    meshes : list of MeshGeometry
    voxels : list of VoxelGeometry
    """

    def __init__(self):
        self.planes: list[PlaneGeometry] = []
        self.meshes: list[MeshGeometry] = []
        self.voxels: list[VoxelGeometry] = []
        self._bounds = None

    def add(self, record: PlaneGeometry | MeshGeometry | VoxelGeometry) -> None:
        """Add one record to the list of its kind."""
        kinds = {PlaneGeometry: self.planes, MeshGeometry: self.meshes, VoxelGeometry: self.voxels}
        kinds[type(record)].append(record)
        self._bounds = None

    def records(self) -> list:
        """Every record: planes, meshes, then voxel sets."""
        return [*self.planes, *self.meshes, *self.voxels]

    def copy(self) -> "SceneGeometry":
        """A copy with its own lists of the same records (adding to one leaves the other)."""
        other = SceneGeometry()
        other.planes, other.meshes, other.voxels = list(self.planes), list(self.meshes), list(self.voxels)
        other._bounds = self._bounds
        return other

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounds (lo, hi) of all records (inf, −inf without any)."""
        if self._bounds is None:
            lo = np.full(3, np.inf)
            hi = np.full(3, -np.inf)
            for r in self.records():
                r_lo, r_hi = r.bounds()
                lo = np.minimum(lo, r_lo)
                hi = np.maximum(hi, r_hi)
            self._bounds = lo, hi
        return self._bounds[0].copy(), self._bounds[1].copy()

    @property
    def n_cubes(self) -> int:
        """Number of cubes of all voxel sets."""
        return int(sum(v.n_cubes for v in self.voxels))

    @property
    def n_triangles(self) -> int:
        """Number of mesh triangles."""
        return int(sum(len(m.faces) for m in self.meshes))

    @property
    def max_voxel_size(self) -> float:
        """Side of the largest voxel cell (m; 0 without voxels)."""
        return float(max((v.size for v in self.voxels), default=0.0))

    @property
    def has_labels(self) -> bool:
        """Whether any mesh carries per-face labels."""
        return any(m.labels is not None for m in self.meshes)
