"""Embree scenes for :mod:`vlsforest.sim.tracing`: scene flags and a fast geometry upload.

embreex (the project's Embree binding) creates scenes with Embree's *robust* flag on and copies
triangle buffers into Embree element by element through Python indexing, about 15 µs per cube
of 8 vertices and 12 triangles, which made a voxel lattice of 2 M cubes take 30 s to load. Here
the buffers are allocated by Embree (``rtcSetNewGeometryBuffer``, as embreex does) and filled
with one numpy assignment each, through the C API of the same ``libembree4`` that embreex loads.
The scene and the BVH are the very ones embreex would build: the same buffers, the same
geometry ids (attached in the same order), bit-identical hits (``tests/test_sim_embree.py``).

The scene handle is read from the ``EmbreeScene`` object (its first field, right after the
Python object header, in embreex 4.x). Before the fast path is used, the handle is checked: the
scene flags Embree reports for it must be the ones the scene was created with, for one robust
and one plain scene. If that check fails (another embreex layout, no ``libembree4`` beside
embreex), every upload goes through embreex's own ``TriangleMesh`` instead: slower, same result.

Robust mode
-----------
``RTC_SCENE_FLAG_ROBUST`` makes Embree avoid optimisations that lower arithmetic accuracy, so
that fewer rays slip through a closed surface where they meet a shared edge or vertex. The
simulator keeps it on by default (:data:`ROBUST_DEFAULT`, as embreex does): rays aimed exactly
at the vertices and edges of a closed icosphere slip through to its far side far more often
without it (``tests/test_sim_embree.py``), and leaf-level recordings then move points by
centimetres; without it tracing is faster. ``Scene(embree_robust=False)`` (scene file key ``embree_robust: false``)
trades that accuracy for the time, e.g. for survey planning.
"""

from __future__ import annotations

import ctypes
import glob
import os

import numpy as np

#: Embree's robust traversal is on unless a scene turns it off (see the module docstring).
ROBUST_DEFAULT = True

_GEOMETRY_TYPE_TRIANGLE = 0
_BUFFER_TYPE_INDEX = 0
_BUFFER_TYPE_VERTEX = 1
_FORMAT_UINT3 = 0x5003
_FORMAT_FLOAT3 = 0x9003
_SCENE_FLAG_ROBUST = 1 << 2

_api = None  # the ctypes library once checked, False when the fast path is unavailable


def new_scene(robust: bool):
    """A new, empty embreex scene with Embree's robust flag on or off."""
    from embreex import rtcore_scene

    return rtcore_scene.EmbreeScene(robust=bool(robust))


def _scene_handle(scene) -> int:
    """Embree's ``RTCScene`` of an embreex ``EmbreeScene`` (its first C field)."""
    return ctypes.c_void_p.from_address(id(scene) + object.__basicsize__).value or 0


def _load():
    """The checked ``libembree4`` of embreex, or None when the fast path cannot be used."""
    global _api
    if _api is not None:
        return _api or None
    _api = False
    try:
        import embreex

        found = sorted(glob.glob(os.path.join(os.path.dirname(embreex.__file__), os.pardir,
                                              "embreex.libs", "libembree4*.so*")))
        if not found:
            return None
        lib = ctypes.CDLL(found[0])
        vp = ctypes.c_void_p
        lib.rtcGetSceneFlags.restype = ctypes.c_int
        lib.rtcGetSceneFlags.argtypes = [vp]
        lib.rtcGetSceneDevice.restype = vp
        lib.rtcGetSceneDevice.argtypes = [vp]
        lib.rtcReleaseDevice.argtypes = [vp]
        lib.rtcNewGeometry.restype = vp
        lib.rtcNewGeometry.argtypes = [vp, ctypes.c_int]
        lib.rtcSetNewGeometryBuffer.restype = vp
        lib.rtcSetNewGeometryBuffer.argtypes = [vp, ctypes.c_int, ctypes.c_uint, ctypes.c_int,
                                                ctypes.c_size_t, ctypes.c_size_t]
        lib.rtcCommitGeometry.argtypes = [vp]
        lib.rtcAttachGeometry.restype = ctypes.c_uint
        lib.rtcAttachGeometry.argtypes = [vp, vp]
        lib.rtcReleaseGeometry.argtypes = [vp]
        for robust in (True, False):
            sc = new_scene(robust)
            h = _scene_handle(sc)
            want = _SCENE_FLAG_ROBUST if robust else 0
            if not h or lib.rtcGetSceneFlags(h) != want:
                return None
    except (ImportError, OSError, AttributeError, ValueError):
        return None
    _api = lib
    return lib


def fast_upload_available() -> bool:
    """Whether triangle buffers are filled by numpy (else by embreex's ``TriangleMesh``)."""
    return _load() is not None


def add_triangle_chunks(scene, n_vertices: int, n_faces: int, chunks) -> None:
    """Attach one triangle mesh given in pieces, written straight into Embree's buffers.

    Parameters
    ----------
    scene : embreex.rtcore_scene.EmbreeScene
        Scene made by :func:`new_scene`, not yet traced.
    n_vertices, n_faces : int
        Sizes of the whole mesh.
    chunks : iterable of (ndarray, ndarray)
        Consecutive pieces ``(vertices (k, 3) float32, faces (m, 3) int)``; faces index the
        whole mesh's vertices. Only one piece at a time is held besides Embree's buffers (a
        voxel lattice of millions of cubes needs no temporary copy of all its triangles).
    """
    lib = _load()
    if lib is None or n_vertices == 0 or n_faces == 0:
        from embreex.mesh_construction import TriangleMesh

        parts = list(chunks)  # an empty mesh (or no pieces) is still one geometry: ids stay in order
        v = [np.asarray(c[0], np.float32).reshape(-1, 3) for c in parts] or [np.zeros((0, 3), np.float32)]
        f = [np.asarray(c[1]).reshape(-1, 3) for c in parts] or [np.zeros((0, 3), np.int32)]
        TriangleMesh(scene, np.concatenate(v), np.concatenate(f).astype(np.int32))
        return
    h = _scene_handle(scene)
    dev = lib.rtcGetSceneDevice(h)
    geom = lib.rtcNewGeometry(dev, _GEOMETRY_TYPE_TRIANGLE)
    try:
        pv = lib.rtcSetNewGeometryBuffer(geom, _BUFFER_TYPE_VERTEX, 0, _FORMAT_FLOAT3, 16, n_vertices)
        pi = lib.rtcSetNewGeometryBuffer(geom, _BUFFER_TYPE_INDEX, 0, _FORMAT_UINT3, 12, n_faces)
        if not pv or not pi:
            raise MemoryError(f"Embree could not allocate buffers for {n_faces:,} triangles")
        vb = np.ctypeslib.as_array((ctypes.c_float * (4 * n_vertices)).from_address(pv)).reshape(-1, 4)
        ib = np.ctypeslib.as_array((ctypes.c_uint32 * (3 * n_faces)).from_address(pi)).reshape(-1, 3)
        a = b = 0
        for v, f in chunks:
            vb[a:a + len(v), :3] = v
            vb[a:a + len(v), 3] = 0.0
            ib[b:b + len(f)] = f
            a += len(v)
            b += len(f)
        if a != n_vertices or b != n_faces:
            raise ValueError(f"add_triangle_chunks: {a} vertices and {b} faces given, "
                             f"{n_vertices} and {n_faces} announced")
        lib.rtcCommitGeometry(geom)
        lib.rtcAttachGeometry(h, geom)
    finally:
        lib.rtcReleaseGeometry(geom)
        lib.rtcReleaseDevice(dev)


def add_triangles(scene, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Attach a triangle mesh to an embreex scene (geometry ids in order of the calls).

    Parameters
    ----------
    scene : embreex.rtcore_scene.EmbreeScene
        Scene made by :func:`new_scene`, not yet traced (committed).
    vertices : ndarray, shape (n, 3)
        Vertex coordinates (converted to float32).
    faces : ndarray of int, shape (m, 3)
        Vertex indices of each triangle (0 ≤ index < n).
    """
    v = np.ascontiguousarray(vertices, dtype=np.float32).reshape(-1, 3)
    f = np.ascontiguousarray(faces, dtype=np.int32).reshape(-1, 3)
    add_triangle_chunks(scene, len(v), len(f), [(v, f)])
