"""Embree scenes (vlsforest.sim._embree): the numpy upload of triangle buffers and robust mode."""

from __future__ import annotations

import numpy as np
import pytest

from vlsforest.domain.cubes import cube_triangles
from vlsforest.errors import ConfigError
from vlsforest.sim import _embree
from vlsforest.sim.scene import Scene


@pytest.fixture
def embreex_upload(monkeypatch):
    """Force the fallback: embreex's own TriangleMesh copies the buffers."""
    monkeypatch.setattr(_embree, "_api", False)


def _soup(n=20000, seed=0):
    rng = np.random.default_rng(seed)
    c = rng.uniform(-5, 5, (n, 3))
    v = (c[:, None, :] + rng.normal(0, 0.2, (n, 3, 3))).reshape(-1, 3).astype(np.float32)
    f = np.arange(3 * n, dtype=np.int32).reshape(-1, 3)
    return v, f


def _rays(m=200000, seed=1):
    rng = np.random.default_rng(seed)
    o = rng.uniform(-6, 6, (m, 3)).astype(np.float32)
    o[:, 2] = 20
    d = np.column_stack([rng.normal(0, 0.3, m), rng.normal(0, 0.3, m), -np.ones(m)])
    return o, (d / np.linalg.norm(d, axis=1)[:, None]).astype(np.float32)


def _trace(robust, *meshes):
    sc = _embree.new_scene(robust)
    for v, f in meshes:
        _embree.add_triangles(sc, v, f)
    o, d = _rays()
    return sc.run(o, d, output=1)


@pytest.mark.parametrize("robust", [False, True])
def test_numpy_upload_gives_embreex_hits_bit_for_bit(robust, monkeypatch):
    assert _embree.fast_upload_available()  # embreex is pinned: the fast path must be in use
    meshes = [_soup(seed=0), _soup(5000, seed=3)]
    fast = _trace(robust, *meshes)
    monkeypatch.setattr(_embree, "_api", False)
    slow = _trace(robust, *meshes)
    assert (fast["geomID"] >= 0).sum() > 10000  # the rays do hit the soup
    assert set(np.unique(fast["geomID"])) == {-1, 0, 1}  # geometry ids in order of the calls
    for key in ("tfar", "geomID", "primID", "Ng", "u", "v"):
        np.testing.assert_array_equal(fast[key], slow[key], err_msg=key)


def _flags(embree_scene):
    lib = _embree._load()
    return lib.rtcGetSceneFlags(_embree._scene_handle(embree_scene))


@pytest.mark.parametrize("robust", [False, True])
def test_scene_sets_embree_robust_flag(robust):
    sc = Scene(embree_robust=robust)
    sc.add_mesh(1, np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float), np.array([[0, 1, 2]]))
    sc.prepare()
    assert _flags(sc.tracer.embree) == (4 if robust else 0)
    t, part, _ = sc.trace(np.array([[0.25, 0.25, 3.0]]), np.array([[0.0, 0.0, -1.0]]))
    assert t[0] == pytest.approx(3.0) and part[0] == 0


def test_embree_robust_defaults_on_and_is_read_from_the_scene_file():
    assert Scene().embree_robust is True
    cfg = {"parts": [{"id": 1, "type": "plane", "z": 0.0, "extent": [0, 0, 1, 1]}]}
    assert Scene.from_dict(cfg).embree_robust is True
    assert Scene.from_dict({**cfg, "embree_robust": False}).embree_robust is False
    with pytest.raises(ConfigError, match="embree_robust must be true or false"):
        Scene.from_dict({**cfg, "embree_robust": "yes"})


def _icosphere(levels=4, radius=0.15):
    t = (1 + 5 ** 0.5) / 2
    v = [np.array(p, float) for p in [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t),
                                      (0, 1, t), (0, -1, -t), (0, 1, -t), (t, 0, -1), (t, 0, 1),
                                      (-t, 0, -1), (-t, 0, 1)]]
    v = [p / np.linalg.norm(p) for p in v]
    f = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4),
         (11, 10, 2), (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9),
         (4, 9, 5), (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    for _ in range(levels):
        cache, nf = {}, []

        def mid(a, b):
            k = (min(a, b), max(a, b))
            if k not in cache:
                m = v[a] + v[b]
                v.append(m / np.linalg.norm(m))
                cache[k] = len(v) - 1
            return cache[k]

        for a, b, c in f:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            nf += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        f = nf
    return (np.array(v) * radius).astype(np.float32), np.array(f, np.int32)


def test_rays_aimed_at_edges_and_vertices_of_a_closed_mesh():
    """Why robust mode is the default: of rays aimed exactly at shared vertices and edges of a
    closed surface, plain mode lets many times more slip through to the far side."""
    v, f = _icosphere()
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    targets = np.concatenate([v] + [(w * v[e[:, 0]] + (1 - w) * v[e[:, 1]]).astype(np.float32)
                                    for w in (0.5, 0.25)])
    targets = np.repeat(targets, 4, axis=0)
    rng = np.random.default_rng(2)
    d = rng.normal(size=targets.shape)
    d /= np.linalg.norm(d, axis=1)[:, None]
    normal = targets / np.linalg.norm(targets, axis=1)[:, None]
    cos = -(d * normal).sum(axis=1)
    d[cos < 0] *= -1  # every ray comes in from outside
    keep = np.abs(cos) > 0.2  # not grazing
    d, targets = d[keep].astype(np.float32), targets[keep]
    o = (targets - 30.0 * d).astype(np.float32)
    assert len(o) > 100000
    slipped = {}
    for robust in (True, False):
        sc = _embree.new_scene(robust)
        _embree.add_triangles(sc, v, f)
        res = sc.run(o, d, output=1)
        assert (res["geomID"] >= 0).all()  # the sphere is hit, at the near or the far side
        # the ray stops at the aimed-at point at the latest (earlier where that point is where
        # it leaves the polyhedron again); later means it slipped through the near side
        slipped[robust] = int((res["tfar"] > 30.0 + 2e-3).sum())
    assert slipped[True] < 0.005 * len(o)  # robust mode: a few rays in a thousand at most
    assert slipped[False] > 10 * max(slipped[True], 1)  # without it: many more


def test_scene_handle_check_rejects_a_wrong_layout(monkeypatch):
    """If the handle read from the embreex object is not a scene, the fast path is not used."""
    monkeypatch.setattr(_embree, "_api", None)
    monkeypatch.setattr(_embree, "_scene_handle", lambda scene: 0)
    assert not _embree.fast_upload_available()
    # the fallback still builds a working scene
    v, f = _soup(100)
    sc = _embree.new_scene(False)
    _embree.add_triangles(sc, v, f)
    o, d = _rays(1000)
    assert (sc.run(o, d, output=1)["geomID"] >= 0).any()


def test_voxel_cubes_go_to_embree_in_pieces_with_the_same_bits(monkeypatch):
    """Cube triangles written piece by piece into Embree's buffers give the BVH (and hits) of
    the whole lattice's triangles copied by embreex; half size 0 drops a scaled cube."""
    from vlsforest.sim.scene_geometry import VoxelGeometry

    rng = np.random.default_rng(4)
    ijk = np.unique(rng.integers(0, 60, (90000, 3)), axis=0)
    half = rng.uniform(0.0, 0.05, len(ijk))
    half[::7] = 0.0

    def build():
        sc = Scene(voxel_backend="embree")
        sc.add_voxels(1, ijk, [1.0, 2.0, 3.0], 0.1)
        sc.add_voxels(2, ijk[:5000] + [0, 0, 70], [1.0, 2.0, 3.0], 0.1, half=half[:5000])
        return sc

    sc = build()
    lo, hi = sc.bounds()
    o = np.column_stack([rng.uniform(lo[0], hi[0], 100000), rng.uniform(lo[1], hi[1], 100000),
                         np.full(100000, hi[2] + 1.0)])
    d = np.column_stack([rng.normal(0, 0.2, 100000), rng.normal(0, 0.2, 100000), -np.ones(100000)])
    d /= np.linalg.norm(d, axis=1)[:, None]
    new = sc.trace(o, d)
    assert (new[1] == 1).sum() > 5000 and (new[1] == 0).sum() > 5000  # both parts hit
    chunks = []
    real = VoxelGeometry.triangle_chunks
    monkeypatch.setattr(VoxelGeometry, "triangle_chunks",
                        lambda v, shift: chunks.append(1) or real(v, shift, chunk=4096))
    np.testing.assert_array_equal(build().trace(o, d)[0], new[0])
    assert len(chunks) == 2
    # the reference: the whole lattice's triangles at once, copied by embreex
    monkeypatch.setattr(_embree, "_api", False)

    def whole(v, shift):
        keep = np.ones(len(v.ijk), bool) if v.half is None else v.half > 0
        centre = v.origin + (v.ijk[keep] + 0.5) * v.size
        h = np.full(len(centre), 0.5 * v.size) if v.half is None else v.half[keep]
        verts, faces = cube_triangles(centre, h)
        return [((verts - shift).astype(np.float32), faces.astype(np.int32))]

    monkeypatch.setattr(VoxelGeometry, "triangle_chunks", whole)
    for a, b in zip(build().trace(o, d), new):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("pieces", [[], [(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32))]])
def test_empty_chunked_mesh_is_an_empty_geometry_keeping_later_ids(pieces):
    """No pieces (or empty ones) still add one geometry, so a later mesh keeps its id (1)."""
    sc = _embree.new_scene(False)
    _embree.add_triangle_chunks(sc, 0, 0, iter(pieces))
    v, f = _soup(seed=0)
    _embree.add_triangles(sc, v, f)
    o, d = _rays(20000)
    hits = sc.run(o, d, output=1)
    assert set(np.unique(hits["geomID"])) == {-1, 1}
