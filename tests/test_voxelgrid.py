"""Tests of the sparse voxel-grid DDA tracer against a brute-force slab test over all cubes."""

from __future__ import annotations

import numpy as np
import pytest

from vlsforest.errors import ConfigError, InputDataError
from vlsforest.sim._voxelgrid import VoxelGrid


# ------------------------------------------------------------------------------------------
# brute force reference: closed slab test of every ray against every cube (numpy)
# ------------------------------------------------------------------------------------------
def _pair_hits(o, d, lo, hi, tmax=None):
    """t (m, n) of each ray-cube pair (inf: miss) and the entry face, same semantics as the grid.

    Hit: the closed box meets the ray for some t in [0, tmax], except when it is only touched at
    t = 0 by a ray moving away (t_far == 0). Inside / on the surface: t = 0, face = axis of largest
    |dir|, opposite sign.
    """
    o = o[:, None, :]
    d = d[:, None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        a = (lo[None] - o) / d
        b = (hi[None] - o) / d
    near = np.minimum(a, b)
    far = np.maximum(a, b)
    par = d == 0.0
    inside = (o >= lo[None]) & (o <= hi[None])
    near = np.where(par, np.where(inside, -np.inf, np.inf), near)
    far = np.where(par, np.where(inside, np.inf, -np.inf), far)
    tn = near.max(axis=2)
    tf = far.min(axis=2)
    hit = (tn <= tf) & (tf > 0.0)
    t = np.where(hit, np.maximum(tn, 0.0), np.inf)
    if tmax is not None:
        t = np.where(t <= tmax[:, None], t, np.inf)
    ax = near.argmax(axis=2)  # first axis of the largest near value
    dd = np.broadcast_to(d, near.shape)
    s_entry = np.take_along_axis(dd, ax[..., None], axis=2)[..., 0]
    big = np.abs(dd).argmax(axis=2)
    s_big = np.take_along_axis(dd, big[..., None], axis=2)[..., 0]
    face = np.where(tn > 0.0, -np.sign(s_entry) * (ax + 1), -np.sign(s_big) * (big + 1))
    face = np.where(np.isfinite(t), face, 0).astype(np.int8)
    return t, face


def _brute(o, d, lo, hi, tmax=None):
    t, face = _pair_hits(o, d, lo, hi, tmax)
    j = t.argmin(axis=1)
    rows = np.arange(len(o))
    tb = t[rows, j]
    return tb, np.where(np.isfinite(tb), j, -1), face[rows, j], t, face


def _check(grid, o, d, lo, hi, parts, tmax=None, generic=True):
    """Compare grid.trace with brute force; cube arrays are indexed like grid.source_index."""
    t, part, face, vox = grid.trace(o, d, tmax)
    tb, jb, fb, tall, fall = _brute(o, d, lo, hi, tmax)
    hit = np.isfinite(tb)
    np.testing.assert_array_equal(np.isfinite(t), hit)
    np.testing.assert_allclose(t[hit], tb[hit], rtol=1e-9, atol=1e-9)
    assert np.all(vox[~hit] == -1) and np.all(part[~hit] == -1) and np.all(face[~hit] == 0)
    src = grid.source_index[vox[hit]]
    rows = np.flatnonzero(hit)
    # the reported cube is a genuine hit at the reported t, with the reported face
    np.testing.assert_allclose(tall[rows, src], t[hit], rtol=1e-9, atol=1e-9)
    np.testing.assert_array_equal(face[hit], fall[rows, src])
    np.testing.assert_array_equal(part[hit], parts[src])
    if generic:  # no ties in t: the very same cube
        np.testing.assert_array_equal(src, jb[hit])
        np.testing.assert_array_equal(face[hit], fb[hit])
    return hit


def _random_cells(rng, n_cells, box_lo, box_hi, frac):
    ijk = np.stack(np.meshgrid(*[np.arange(a, b) for a, b in zip(box_lo, box_hi)],
                               indexing="ij"), axis=-1).reshape(-1, 3)
    sel = rng.random(len(ijk)) < frac
    ijk = ijk[sel]
    return ijk[rng.permutation(len(ijk))[:n_cells]]


def _rays(rng, lo, hi, m):
    """Mixed rays: from outside towards the box, from inside, axis-parallel, one zero component,
    non-unit directions."""
    size = hi - lo
    c = 0.5 * (lo + hi)
    out = []
    # from outside, aimed at random points of the box
    u = rng.normal(size=(m, 3))
    o = c + u / np.linalg.norm(u, axis=1, keepdims=True) * (1.5 * size.max())
    tgt = lo + rng.random((m, 3)) * size
    out.append((o, (tgt - o) * rng.uniform(0.2, 3.0, (m, 1))))
    # from inside, random directions
    o = lo + rng.random((m, 3)) * size
    out.append((o, rng.normal(size=(m, 3))))
    # axis-parallel (both signs), from outside and inside
    o = lo - 0.3 * size + rng.random((m, 3)) * 1.6 * size
    d = np.zeros((m, 3))
    ax = rng.integers(0, 3, m)
    d[np.arange(m), ax] = rng.choice([-1.0, 1.0], m) * rng.uniform(0.5, 2.0, m)
    out.append((o, d))
    # one zero component
    d = rng.normal(size=(m, 3))
    d[np.arange(m), rng.integers(0, 3, m)] = 0.0
    o = lo - 0.3 * size + rng.random((m, 3)) * 1.6 * size
    out.append((o, d))
    return np.concatenate([a for a, _ in out]), np.concatenate([b for _, b in out])


def _lattice_rays(grid_lo_idx, grid_hi_idx, origin, h, rng, m):
    """Rays through exact lattice corners/edges/face centres with small-integer directions
    (all values dyadic so that ties are exact in both frames)."""
    dirs = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)
                     if (i, j, k) != (0, 0, 0)] + [(1, 2, 0), (2, -1, 1), (0, 1, -2), (2, 2, 1)],
                    dtype=np.float64)
    d = dirs[rng.integers(0, len(dirs), m)]
    lo = np.asarray(grid_lo_idx) - 2
    hi = np.asarray(grid_hi_idx) + 2
    corner = rng.integers(lo, hi + 1, (m, 3)).astype(np.float64)
    corner += rng.integers(0, 2, (m, 3)) * 0.5  # corners, edge midpoints, face centres
    return origin + corner * h, d


# ------------------------------------------------------------------------------------------
# full cells
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("block_bits", [2, 3])
def test_full_cells_match_brute_force(block_bits):
    rng = np.random.default_rng(1)
    h = 0.37
    origin = np.array([0.31, -1.7, 2.05])
    ijk = _random_cells(rng, 400, (-9, -3, -20), (7, 13, -5), 0.15)
    parts = rng.integers(0, 5, len(ijk)).astype(np.int32)
    g = VoxelGrid.build(ijk, origin, h, part=parts, block_bits=block_bits,
                        keep_source_index=True)
    assert g.n_voxels == len(ijk) and g.n_duplicates == 0
    lo = origin + ijk * h
    hi = lo + h
    blo, bhi = g.bounds
    np.testing.assert_allclose(blo, origin + ijk.min(0) * h)
    np.testing.assert_allclose(bhi, origin + (ijk.max(0) + 1) * h)
    o, d = _rays(rng, blo, bhi, 1000)
    hit = _check(g, o, d, lo, hi, parts)
    assert 0.3 < hit.mean() < 0.95  # the test exercises both hits and misses
    np.testing.assert_array_equal(g.voxel_ijk(np.arange(g.n_voxels)), ijk[g.source_index])


def test_sparse_clusters_skip_empty_blocks():
    """Two small clusters far apart with many empty blocks between them."""
    rng = np.random.default_rng(2)
    a = _random_cells(rng, 150, (-60, -60, -60), (-50, -50, -50), 0.3)
    b = _random_cells(rng, 150, (40, 30, 45), (52, 41, 55), 0.3)
    ijk = np.concatenate([a, b])
    g = VoxelGrid.build(ijk, (0.0, 0.0, 0.0), 0.1, part=7, keep_source_index=True)
    assert g.n_blocks < 20
    lo = ijk * 0.1
    hi = lo + 0.1
    parts = np.full(len(ijk), 7, np.int32)
    blo, bhi = g.bounds
    o, d = _rays(rng, blo, bhi, 500)
    # plus rays from one cluster to the other
    o2 = lo[rng.integers(0, 150, 500)] + 0.05 + rng.normal(0, 0.3, (500, 3))
    d2 = hi[150 + rng.integers(0, 150, 500)] - o2
    _check(g, np.concatenate([o, o2]), np.concatenate([d, d2]), lo, hi, parts)


def test_runs_of_empty_blocks_and_sub_blocks_are_marched_exactly():
    """Long runs of empty blocks next to occupied ones (Chebyshev radius 0) and runs of empty
    4x4x4 sub-blocks inside an occupied block, which the DDA marches through on boundary
    parameters alone: the hits must still be those of brute force, ties included."""
    rng = np.random.default_rng(11)
    h = 0.25
    origin = np.array([1.0, -3.0, 0.5])
    n = 48  # three 16-cell blocks per axis
    ii, jj = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    floor = np.stack([ii.ravel(), jj.ravel(), np.zeros(n * n, np.int64)], axis=1)  # z-block 0
    jw, kw = np.meshgrid(np.arange(n), np.arange(16, 32), indexing="ij")
    # a wall in the last cell column of x-block 2, z-block 1: blocks (0|1, y, 1) are empty with
    # radius 0 (the floor lies next to them) and in block (2, y, 1) the first three sub-blocks
    # along x are empty
    wall = np.stack([np.full(jw.size, n - 1), jw.ravel(), kw.ravel()], axis=1)
    extra = _random_cells(rng, 40, (0, 0, 33), (n, n, n), 0.05)
    ijk = np.unique(np.concatenate([floor, wall, extra]), axis=0)
    g = VoxelGrid.build(ijk, origin, h, part=1, block_bits=4, keep_source_index=True)
    assert g.block_bits == 4 and g._coarse.min() == -1
    lo = origin + ijk * h
    hi = lo + h
    parts = np.ones(len(ijk), np.int32)
    m = 1500
    # along +x through z-block 1 (straight, slightly tilted, and with exact lattice ties)
    o = origin + np.column_stack([np.full(m, -3.0), rng.uniform(0, n, m), rng.uniform(16, 32, m)]) * h
    d = np.column_stack([np.ones(m), rng.normal(0, 0.05, m), rng.normal(0, 0.05, m)])
    d[: m // 3, 1:] = 0.0
    ot = origin + np.column_stack([np.full(m, -3.0), rng.integers(0, n + 1, m) * 0.5,
                                   16 + rng.integers(0, 33, m) * 0.5]) * h
    dt = np.array([(1.0, 0.0, 0.0), (2.0, 1.0, 0.0), (2.0, 0.0, 1.0), (4.0, 1.0, -1.0),
                   (1.0, 1.0, 1.0)])[rng.integers(0, 5, m)]
    hit = _check(g, np.concatenate([o, ot]), np.concatenate([d, dt]), lo, hi, parts, generic=False)
    assert hit.mean() > 0.5
    # and from above, down through the empty blocks onto the floor or the wall
    o, d = _lattice_rays((0, 0, 0), (n, n, n), origin, h, rng, 3000)
    _check(g, o, d, lo, hi, parts, generic=False)


@pytest.mark.parametrize("block_bits", [2, 3])
def test_full_cells_exact_edges_and_corners(block_bits):
    rng = np.random.default_rng(3)
    h = 0.5
    origin = np.array([-1.5, 2.0, 0.25])
    ijk = _random_cells(rng, 300, (-6, -2, -4), (5, 9, 6), 0.35)
    g = VoxelGrid.build(ijk, origin, h, part=3, block_bits=block_bits,
                        keep_source_index=True)
    lo = origin + ijk * h
    hi = lo + h
    parts = np.full(len(ijk), 3, np.int32)
    o, d = _lattice_rays(ijk.min(0), ijk.max(0) + 1, origin, h, rng, 3000)
    hit = _check(g, o, d, lo, hi, parts, generic=False)
    assert hit.mean() > 0.2
    # rays along the outer faces/edges of the grid box and through its corners
    blo, bhi = g.bounds
    corners = np.array([[x, y, z] for x in (blo[0], bhi[0]) for y in (blo[1], bhi[1])
                        for z in (blo[2], bhi[2])])
    o = np.repeat(corners, 3, axis=0)
    d = np.tile(np.eye(3), (8, 1)) * np.where(o == np.tile(blo, (24, 1)), 1.0, -1.0)
    _check(g, o, d, lo, hi, parts, generic=False)


def test_single_cell_grazing_rays():
    """Rays along a face, along an edge, through a corner, and starting on the surface."""
    g = VoxelGrid.build([[0, 0, 0]], (0.0, 0.0, 0.0), 1.0)
    o = np.array([
        [-1.0, 0.0, 0.5],   # along the y=0 face, +x
        [-1.0, 1.0, 1.0],   # along the top-back edge, +x
        [-1.0, -1.0, -1.0],  # through two corners, diagonal
        [2.0, -1.0, 0.5],   # diagonal in z=0.5 through the edge x=1,y=0
        [0.5, 0.5, 1.0],    # on the top face, moving away: no hit
        [0.5, 0.5, 1.0],    # on the top face, moving in: t = 0
        [0.5, 0.5, 0.5],    # inside: t = 0, face of the largest |d| axis
        [1.0, 0.5, 0.5],    # on the +x face moving along it (in the face plane)
        [-1.0, 0.0, 0.5],   # touches the edge x=0, y=1 only (line y = x + 1)
        [-1.001, 0.0, 0.5],  # just misses it
    ])
    d = np.array([
        [1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 1.0], [-1.0, 1.0, 0.0],
        [0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [0.2, -0.9, 0.3], [0.0, 1.0, 0.0],
        [1.0, 1.0, 0.0], [1.0, 1.0, 0.0],
    ])
    t, part, face, vox = g.trace(o, d)
    expect_t = [1.0, 1.0, 1.0, 1.0, np.inf, 0.0, 0.0, 0.0, 1.0, np.inf]
    expect_f = [-1, -1, -1, 1, 0, 3, 2, -2, -1, 0]
    np.testing.assert_allclose(t, expect_t)
    np.testing.assert_array_equal(face, expect_f)
    np.testing.assert_array_equal(part, np.where(np.isfinite(expect_t), 0, -1))


def test_nadir_rays_hit_top_faces():
    rng = np.random.default_rng(4)
    h = 0.02
    ijk = _random_cells(rng, 3000, (0, 0, 0), (60, 60, 40), 0.05)
    origin = np.array([100.0, -50.0, 5.0])
    g = VoxelGrid.build(ijk, origin, h)
    xy = rng.random((4000, 2)) * 60 * h
    o = np.column_stack([origin[0] + xy[:, 0], origin[1] + xy[:, 1], np.full(4000, 80.0)])
    d = np.tile([0.0, 0.0, -1.0], (4000, 1))
    t, part, face, vox = g.trace(o, d)
    hit = np.isfinite(t)
    assert hit.mean() > 0.5
    assert np.all(face[hit] == 3)
    # t = height of the origin above the top of the highest filled cell in that column
    col = np.floor(xy / h).astype(int)
    top = np.full((60, 60), -1)
    np.maximum.at(top, (ijk[:, 0], ijk[:, 1]), ijk[:, 2])
    ktop = top[col[:, 0], col[:, 1]]
    np.testing.assert_array_equal(hit, ktop >= 0)
    np.testing.assert_allclose(t[hit], 80.0 - (origin[2] + (ktop[hit] + 1) * h), atol=1e-9)
    np.testing.assert_array_equal(g.voxel_ijk(vox[hit])[:, 2], ktop[hit])


def test_serial_argument_chooses_the_kernel(monkeypatch):
    # the kernel follows the call's argument, not module state: a forked worker asks for the
    # single-threaded one; both give the same hits
    from vlsforest.sim import _voxelgrid

    rng = np.random.default_rng(5)
    h = 0.1
    ijk = _random_cells(rng, 500, (0, 0, 0), (20, 20, 20), 0.2)
    g = VoxelGrid.build(ijk, np.zeros(3), h)
    o, d = _rays(rng, *g.bounds, 500)
    used = []
    for name in ("_trace_kernel", "_trace_kernel_serial"):
        kernel = getattr(_voxelgrid, name)
        monkeypatch.setattr(_voxelgrid, name, lambda *a, _k=kernel, _n=name: (used.append(_n), _k(*a))[1])
    serial = g.trace(o, d, serial=True)
    parallel = g.trace(o, d, serial=False)
    assert used == ["_trace_kernel_serial", "_trace_kernel"]
    assert np.isfinite(serial[0]).any()
    for a, b in zip(serial, parallel):
        np.testing.assert_array_equal(a, b)


def test_tmax_is_honoured():
    rng = np.random.default_rng(5)
    h = 0.25
    origin = np.array([0.1, 0.2, 0.3])
    ijk = _random_cells(rng, 300, (0, 0, 0), (12, 12, 12), 0.25)
    g = VoxelGrid.build(ijk, origin, h, keep_source_index=True)
    lo = origin + ijk * h
    hi = lo + h
    blo, bhi = g.bounds
    o, d = _rays(rng, blo, bhi, 400)
    t_free, *_ = g.trace(o, d)
    tmax = np.where(rng.random(len(o)) < 0.5, t_free * rng.uniform(0.5, 1.5, len(o)),
                    rng.uniform(0, 3, len(o)))
    tmax = np.where(np.isfinite(tmax), tmax, 2.0)
    hit = _check(g, o, d, lo, hi, np.zeros(len(ijk), np.int32), tmax=tmax)
    t, *_ = g.trace(o, d, tmax)
    assert np.all(t[hit] <= tmax[hit])
    fin = np.isfinite(t_free)
    assert np.all(np.isfinite(t[fin]) == (t_free[fin] <= tmax[fin]))
    # tmax exactly at the hit: accepted (closed interval)
    t_eq, _, _, v_eq = g.trace(o[fin], d[fin], t_free[fin])
    np.testing.assert_array_equal(t_eq, t_free[fin])
    assert np.all(v_eq >= 0)


def test_duplicates_keep_first_in_full_mode():
    ijk = np.array([[0, 0, 0], [1, 0, 0], [0, 0, 0], [1, 0, 0], [2, 0, 0]])
    g = VoxelGrid.build(ijk, (0, 0, 0), 1.0, part=[10, 11, 12, 13, 14], keep_source_index=True)
    assert g.n_voxels == 3 and g.n_duplicates == 2
    assert sorted(g.source_index.tolist()) == [0, 1, 4]
    t, part, face, vox = g.trace([[0.5, 0.5, 5.0], [1.5, 0.5, 5.0], [2.5, 0.5, 5.0]],
                                 [[0, 0, -1.0]] * 3)
    np.testing.assert_array_equal(part, [10, 11, 14])
    np.testing.assert_allclose(t, [4.0, 4.0, 4.0])


# ------------------------------------------------------------------------------------------
# scaled / shifted cubes
# ------------------------------------------------------------------------------------------
def _scaled_cubes(rng, ijk, h, origin, dyadic=True):
    n = len(ijk)
    if dyadic:  # exactly representable in float32 and float64
        a = rng.integers(1, 33, n)
        half = a * h / 64
        b = rng.integers(-(32 - a)[:, None], (32 - a)[:, None] + 1, (n, 3))
        off = b * h / 64
    else:
        half = rng.uniform(0.05, 0.5, n) * h
        off = (rng.uniform(-1, 1, (n, 3)) * (0.5 * h - half[:, None])) * 0.999999
    centre = origin + (ijk + 0.5) * h + off
    return half, centre


@pytest.mark.parametrize("dyadic", [True, False])
def test_scaled_cubes_match_brute_force(dyadic):
    rng = np.random.default_rng(6)
    h = 0.5 if dyadic else 0.37
    origin = np.array([-1.5, 2.0, 0.25]) if dyadic else np.array([0.3, -2.2, 7.1])
    ijk = _random_cells(rng, 500, (-8, -5, -3), (6, 9, 12), 0.3)
    half, centre = _scaled_cubes(rng, ijk, h, origin, dyadic)
    half[::23] = 0.0  # dropped
    parts = rng.integers(0, 300, len(ijk)).astype(np.int32)  # > 256 ids: int32 codes
    g = VoxelGrid.build(ijk, origin, h, part=parts, half_size=half, centre=centre,
                        block_bits=2, keep_source_index=True)
    keep = half > 0
    assert g.scaled and g.n_voxels == keep.sum()
    assert np.all(half[g.source_index] > 0)
    lo = centre - half[:, None]
    hi = centre + half[:, None]
    lo[~keep] = 1e9  # dropped cubes are never hit: move them out of reach in the brute force
    hi[~keep] = 1e9
    blo, bhi = g.bounds
    o, d = _rays(rng, blo, bhi, 800)
    if dyadic:
        o2, d2 = _lattice_rays(ijk.min(0), ijk.max(0) + 1, origin, h, rng, 2000)
        o, d = np.concatenate([o, o2]), np.concatenate([d, d2])
        hit = _check(g, o, d, lo, hi, parts, generic=False)
        # generic rays (first part) must agree on the very cube
        _check(g, o[:3200], d[:3200], lo, hi, parts, generic=True)
    else:
        t, *_ = g.trace(o, d)
        tb, *_ = _brute(o, d, lo, hi)
        hit = np.isfinite(tb)
        np.testing.assert_array_equal(np.isfinite(t), hit)  # float32 storage: t to ~1e-7 h
        np.testing.assert_allclose(t[hit], tb[hit], rtol=0, atol=1e-6)
    assert 0.2 < hit.mean() < 0.95


def test_from_centres_scaled_and_full():
    rng = np.random.default_rng(7)
    h = 0.1
    ijk = _random_cells(rng, 200, (-5, -5, -5), (5, 5, 5), 0.3)
    half, centre = _scaled_cubes(rng, ijk, h, np.zeros(3), dyadic=False)
    g = VoxelGrid.from_centres(centre, h, half_size=half, part=4, keep_source_index=True)
    np.testing.assert_array_equal(g.voxel_ijk(np.arange(g.n_voxels)), ijk[g.source_index])
    lo = centre - half[:, None]
    hi = centre + half[:, None]
    blo, bhi = g.bounds
    o, d = _rays(rng, blo, bhi, 300)
    t, part, face, vox = g.trace(o, d)
    tb, jb, fb, *_ = _brute(o, d, lo, hi)
    np.testing.assert_allclose(t, tb, rtol=0, atol=1e-7)
    hit = np.isfinite(tb)
    np.testing.assert_array_equal(g.source_index[vox[hit]], jb[hit])
    assert np.all(part[hit] == 4)
    # full cells from centres with a lattice origin; centres may be slightly noisy
    origin = np.array([0.05, -0.02, 1.0])
    c = origin + (ijk + 0.5) * h + rng.uniform(-0.05, 0.05, ijk.shape) * h
    g2 = VoxelGrid.from_centres(c, h, origin=origin, keep_source_index=True)
    np.testing.assert_array_equal(g2.voxel_ijk(np.arange(g2.n_voxels)), ijk[g2.source_index])
    assert not g2.scaled


def test_zero_size_cube_is_dropped():
    # three cubes in a column; the top one has half size 0
    ijk = np.array([[0, 0, 2], [0, 0, 1], [0, 0, 0]])
    g = VoxelGrid.build(ijk, (0, 0, 0), 1.0, part=[1, 2, 3], half_size=[0.0, 0.25, 0.5])
    assert g.n_voxels == 2
    t, part, face, vox = g.trace([[0.5, 0.5, 10.0]], [[0.0, 0.0, -1.0]])
    assert part[0] == 2 and face[0] == 3
    assert t[0] == pytest.approx(10.0 - 1.75)
    with pytest.raises(InputDataError):
        VoxelGrid.build([[0, 0, 0]], (0, 0, 0), 1.0, half_size=0.0)  # nothing left


def test_cubes_outside_their_cell_are_rejected():
    h = 1.0
    with pytest.raises(InputDataError, match="inside its cell"):
        VoxelGrid.build([[0, 0, 0]], (0, 0, 0), h, half_size=0.3, centre=[[0.5, 0.5, 0.75]])
    with pytest.raises(InputDataError, match="half size"):
        VoxelGrid.build([[0, 0, 0]], (0, 0, 0), h, half_size=0.6)
    with pytest.raises(InputDataError, match="inside the cell"):
        VoxelGrid.from_centres([[0.5, 0.5, 0.25]], h, half_size=0.3)
    with pytest.raises(InputDataError, match="lattice"):
        VoxelGrid.from_centres([[0.0, 0.5, 0.5]], h)  # a cell corner, not a centre
    # just inside (within the tolerance) is accepted
    g = VoxelGrid.build([[0, 0, 0]], (0, 0, 0), h, half_size=0.25, centre=[[0.5, 0.5, 0.75]])
    assert g.n_voxels == 1


def test_scaled_duplicates_and_bad_inputs_raise():
    with pytest.raises(InputDataError, match="share a cell"):
        VoxelGrid.build([[0, 0, 0], [0, 0, 0]], (0, 0, 0), 1.0, half_size=0.2)
    with pytest.raises(ConfigError, match="cell_size"):
        VoxelGrid.build([[0, 0, 0]], (0, 0, 0), 0.0)
    with pytest.raises(ConfigError, match="origin"):
        VoxelGrid.build([[0, 0, 0]], (0, 0), 1.0)
    with pytest.raises(InputDataError, match="ijk"):
        VoxelGrid.build([[0.5, 0, 0]], (0, 0, 0), 1.0)
    with pytest.raises(InputDataError, match="too large"):
        VoxelGrid.build([[0, 0, 0], [10**6, 10**6, 10**6]], (0, 0, 0), 1.0)
    g = VoxelGrid.build([[0, 0, 0]], (0, 0, 0), 1.0)
    with pytest.raises(InputDataError, match="zero-length"):
        g.trace([[0, 0, 5.0]], [[0, 0, 0.0]])
    with pytest.raises(InputDataError):
        g.trace([[0, 0, np.nan]], [[0, 0, 1.0]])


# ------------------------------------------------------------------------------------------
# memory
# ------------------------------------------------------------------------------------------
def test_memory_per_voxel_for_2m_voxels():
    """2 M voxels at 25 % occupancy of a 200³ box (sparse blocks, B = 8).

    Bound: an occupied 8³ block costs 64 B of mask + 16 B of rank prefixes + 8 B of base = 88 B;
    at occupancy p per cell that is 88 / (512 p) B per voxel = 0.69 B at p = 0.25, plus the
    coarse array (4 B per 512 cells). One part id for all costs nothing per voxel, ≤ 256 ids
    one byte. A dense int32 per-cell index table would cost 16 B per voxel here.
    """
    rng = np.random.default_rng(8)
    n_side = 200
    sel = np.flatnonzero(rng.random(n_side**3) < 0.25)
    ijk = np.column_stack(np.unravel_index(sel, (n_side,) * 3)).astype(np.int32) - 77
    n = len(ijk)
    assert 1.9e6 < n < 2.1e6
    g = VoxelGrid.build(ijk, (0.0, 0.0, 0.0), 0.02)
    assert g.block_bits == 3 and g.n_voxels == n
    assert g.nbytes / n < 0.75
    g2 = VoxelGrid.build(ijk, (0.0, 0.0, 0.0), 0.02, part=(sel % 3).astype(np.int32))
    assert (g2.nbytes - g.nbytes) / n == pytest.approx(1.0, rel=1e-4)  # uint8 part codes
    # structure is correct: voxel -> cell round trip on a sample
    v = rng.integers(0, n, 2000)
    ijk_v = g.voxel_ijk(v)
    occupied = np.zeros((n_side,) * 3, bool)
    occupied[tuple((ijk + 77).T)] = True
    assert occupied[tuple((ijk_v + 77).T)].all()
    assert np.unique(g.voxel_ijk(np.arange(0, n, 997)), axis=0).shape[0] == len(range(0, n, 997))
