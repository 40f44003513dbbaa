"""Nearest hits of rays in a scene's geometry: the acceleration structures and the queries.

Meshes, planes and the voxel sets that :mod:`vlsforest.sim.routing` gives to Embree (12
triangles per cube) go into one Embree scene (:mod:`vlsforest.sim._embree`), in float32
coordinates shifted to the centre of the scene's bounds (:attr:`Tracer.shift`). The other voxel
sets are merged into one sparse grid per lattice (:func:`build_grids`), traced in float64 by a
3-D DDA. A scene with nothing for Embree intersects its planes analytically, in float64. Each ray
keeps the nearest of its hits in all structures.

The structures are built lazily (or by :meth:`Tracer.prepare`), once per routing. The Embree
scene cannot be pickled: a pickled :class:`Tracer` leaves it behind and builds it again when
next asked.
"""

from __future__ import annotations

import numba
import numpy as np

from vlsforest.errors import ConfigError, VlsforestError
from vlsforest.sim import _embree
from vlsforest.sim._voxelgrid import VoxelGrid
from vlsforest.sim.routing import check_backend, check_expected_rays, route_voxels
from vlsforest.sim.scene_geometry import PLANE_FACES, SceneGeometry, VoxelGeometry
from vlsforest.sim.waveform import hit_cos32


class Tracer:
    """The tracing structures of a :class:`~vlsforest.sim.scene_geometry.SceneGeometry`.

    Parameters
    ----------
    geometry : SceneGeometry
        The geometry to trace; call :meth:`reset` after adding to it.
    voxel_backend : {"auto", "embree", "grid"}
        Where the voxel sets are traced (:mod:`vlsforest.sim.routing`).
    embree_robust : bool, optional
        Embree's robust traversal (see :mod:`vlsforest.sim._embree`); None: its default.
    """

    def __init__(self, geometry: SceneGeometry, voxel_backend: str = "auto", embree_robust: bool | None = None):
        check_backend(voxel_backend)
        if embree_robust is None:
            embree_robust = _embree.ROBUST_DEFAULT
        if not isinstance(embree_robust, (bool, np.bool_)):
            raise ConfigError(f"embree_robust must be true or false, got {embree_robust!r}")
        self.geometry = geometry
        self.voxel_backend = voxel_backend
        #: Embree's robust traversal (see :mod:`vlsforest.sim._embree`)
        self.embree_robust = bool(embree_robust)
        self._expected_rays: float | None = None
        self._shift = None
        self.reset()

    # ------------------------------------------------------------------ routing and structures
    def reset(self) -> None:
        """Drop the routing and the built structures (the geometry has changed)."""
        self._routing: list[bool] | None = None
        self._grids: list[VoxelGrid] | None = None
        self._drop_embree()

    def _drop_embree(self) -> None:
        self._embree = None
        self._embree_parts = None
        self._embree_labels = None

    @property
    def routing(self) -> list[bool]:
        """Per voxel set (in ``geometry.voxels`` order): whether Embree traces it.

        Computed once per geometry and plan (:attr:`uses_embree` asks on every trace call).
        """
        if self._routing is None:
            self._routing = route_voxels(self.geometry.voxels, self.voxel_backend, self._expected_rays)
        return self._routing

    def plan_for_rays(self, n_rays: float) -> None:
        """Route the voxel lattices (``voxel_backend="auto"``) for about ``n_rays`` rays.

        See :meth:`vlsforest.sim.scene.Scene.plan_for_rays`. Structures built for another routing
        are dropped.
        """
        if self.voxel_backend != "auto":
            return
        n = check_expected_rays(n_rays)
        before = self.routing
        self._expected_rays = n
        self._routing = None
        if self.routing != before:
            self._grids = None
            self._drop_embree()

    @property
    def needs_ray_estimate(self) -> bool:
        """Whether :meth:`plan_for_rays` can change the routing (``auto`` with voxel sets)."""
        return self.voxel_backend == "auto" and bool(self.geometry.voxels)

    @property
    def has_grids(self) -> bool:
        """Whether any voxel set is traced in a voxel grid (from the routing; builds nothing)."""
        return not all(self.routing)

    @property
    def uses_embree(self) -> bool:
        """Whether meshes (and planes, and the voxel sets routed there) are traced with Embree."""
        return bool(self.geometry.meshes) or any(self.routing)

    @property
    def grids(self) -> list[VoxelGrid]:
        """The voxel grids, one per lattice (voxel sets sharing a lattice are merged)."""
        if self._grids is None:
            self._grids = build_grids([v for v, e in zip(self.geometry.voxels, self.routing) if not e])
        return self._grids

    @property
    def embree(self):
        """The Embree scene (an embreex ``EmbreeScene``; built now if needed; None without one)."""
        self.prepare()
        return self._embree

    @property
    def shift(self) -> np.ndarray:
        """World position of the origin of the float32 coordinates Embree works in."""
        self.prepare()
        return self._shift.copy()

    def prepare(self) -> None:
        """Build the voxel grids and the Embree scene now (else lazily at the first trace)."""
        self.grids
        if self._embree is None and self.uses_embree:
            self._build_embree()
            # Embree commits the BVH lazily: force it with one ray
            self._embree.run(np.zeros((1, 3), np.float32), np.array([[0, 0, 1]], np.float32))

    def _build_embree(self) -> None:
        lo, hi = self.geometry.bounds()
        self._shift = np.where(np.isfinite(lo + hi), 0.5 * (lo + hi), 0.0)
        sc = _embree.new_scene(self.embree_robust)
        parts = []
        labels = []
        for m in self.geometry.meshes:
            _embree.add_triangles(sc, (m.vertices - self._shift).astype(np.float32), m.faces)
            parts.append(m.part)
            labels.append(m.labels)
        for p in self.geometry.planes:  # Embree is called anyway: two triangles beat a numpy pass
            _embree.add_triangles(sc, (p.corners() - self._shift).astype(np.float32), PLANE_FACES)
            parts.append(p.part)
            labels.append(None)
        for v, in_embree in zip(self.geometry.voxels, self.routing):
            if in_embree:
                n = v.n_cubes
                if n:
                    _embree.add_triangle_chunks(sc, 8 * n, 12 * n, v.triangle_chunks(self._shift))
                    parts.append(v.part)
                    labels.append(None)
        self._embree = sc
        self._embree_parts = np.asarray(parts, dtype=np.int32)
        self._embree_labels = _label_table(labels)

    def shared_copy(self, geometry: SceneGeometry) -> "Tracer":
        """A tracer of ``geometry`` (the same records as this one's) sharing the built structures.

        A later :meth:`plan_for_rays` or :meth:`reset` of either changes that one only.
        """
        other = Tracer.__new__(Tracer)  # not copy.copy: __getstate__ would drop the Embree scene
        other.__dict__.update(self.__dict__)
        other.geometry = geometry
        return other

    def __getstate__(self):  # the Embree scene cannot be pickled; rebuilt lazily after unpickling
        state = self.__dict__.copy()
        state["_embree"] = None
        state["_embree_parts"] = None
        state["_embree_labels"] = None
        return state

    # ------------------------------------------------------------------ queries
    def trace(self, origins, dirs, with_labels: bool = False, serial: bool = False):
        """Nearest hit of each ray (see :meth:`vlsforest.sim.scene.Scene.trace`)."""
        o = np.ascontiguousarray(origins, dtype=np.float64)
        d = np.ascontiguousarray(dirs, dtype=np.float64)
        if self.uses_embree:
            self.prepare()
            return self.trace_local((o - self._shift).astype(np.float32), d.astype(np.float32), with_labels,
                                    world=(o, d), serial=serial)
        n = len(o)
        t = np.full(n, np.inf)
        part = np.full(n, -1, dtype=np.int32)
        cos_inc = np.zeros(n)
        label = np.zeros(n, dtype=np.uint8) if with_labels else None
        for p in self.geometry.planes:  # analytic, float64 (scenes without meshes)
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

    def trace_local(self, o32, d32, with_labels: bool = False, world=None, serial: bool = False):
        """:meth:`trace` for float32 rays in the Embree frame (see
        :meth:`vlsforest.sim.scene.Scene.trace_local`)."""
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
        """Embree's raw answer (see :meth:`vlsforest.sim.scene.Scene.cast_embree`)."""
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


def build_grids(voxels: list[VoxelGeometry]) -> list[VoxelGrid]:
    """Merge the voxel sets that share a lattice (same size, congruent origin) into one grid each.

    Parameters
    ----------
    voxels : list of VoxelGeometry
        The voxel sets to trace in grids.

    Returns
    -------
    list of VoxelGrid
        One per lattice, in the order of each lattice's first set; a cube's part is its set's.
    """
    groups: dict[tuple, list[VoxelGeometry]] = {}
    for s in voxels:
        groups.setdefault(s.lattice_key, []).append(s)
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
