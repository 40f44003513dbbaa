"""Sparse voxel grid with a numba 3-D DDA ray tracer (scene voxels that do not fit Embree).

The study's 0.02 m voxel forests hold tens of millions of filled cells; expanding each cube to
12 triangles for Embree does not fit in memory (simulator.md §14). :class:`VoxelGrid` stores the
cubes of ONE lattice as a two-level sparse occupancy structure and traces rays through it with an
Amanatides–Woo digital differential analyser (DDA), compiled with numba. Meshes and the ground are
traced by embreex; the caller keeps the nearer of the two hits.

Structure
---------
* Lattice: cell size ``h``, lattice origin ``origin``; cell ``(i, j, k)`` spans
  ``origin + [i, i+1) * h`` (and likewise in y, z). Indices are stored relative to their minimum.
* Coarse level: a dense ``int32`` array over blocks of ``B = 2**block_bits`` cells per axis. An
  occupied block holds its block id (>= 0); an empty block holds ``-D``, ``D`` the Chebyshev
  distance in blocks (capped at 33) to the nearest occupied block, so the DDA jumps over the whole
  empty cube of blocks within ``D - 1`` in one step. ``block_bits`` is chosen automatically as the
  smallest of 3, 4, 5 (B = 8, 16, 32) whose coarse array has at most 2**24 entries (64 MiB):
  a 10 m × 10 m × 20 m crown at 0.02 m (500 × 500 × 1000 cells) gets B = 8 (0.5 M entries,
  2 MiB); a 100 m × 100 m × 45 m plot at 0.02 m (5000 × 5000 × 2250 cells) would need 110 M
  entries (440 MiB) at B = 8 and gets B = 16 (13.8 M entries, 55 MiB).
* Fine level: per occupied block a ``B**3``-bit occupancy mask, one ``uint64`` word per 4×4×4
  sub-block (an all-zero word is skipped like an empty block), per word the number of set bits
  before it in the block (``uint16``), and per block the number of voxels in all earlier blocks
  (``int64``). A voxel's index into the per-voxel arrays is
  ``base[block] + prefix[word] + popcount(word bits below the cell)``: no per-cell table.
  Cost per occupied block: 88 bytes at B = 8, 648 bytes at B = 16.
* Per voxel: a part id (stored as a code into a small table of distinct ids: 0 bytes when one id
  is given for all, 1 byte for ≤ 256 distinct ids, else 4 bytes) and, for *scaled/shifted* cubes,
  ``float32`` (dx, dy, dz, half) in cell units, the offset of the cube centre from the cell centre
  and the half size (16 bytes).
* Build: four sequential numba passes over the input (mark blocks, set bits, rank, scatter
  per-voxel data); no sort and no temporary larger than one byte per input row. Repeated cells
  are found from the bits already set.

Hit semantics
-------------
* Rays are ``origin + t * dir`` with ``t ≥ 0``; ``t`` is the ray parameter, in units of
  ``|dir|`` (metres when ``dir`` is a unit vector).
* Cubes are closed boxes. A cube is hit when the ray meets it for some ``t`` in ``[0, tmax]``,
  except a ray that only touches the cube at its origin and moves away (``t_far == 0``), which
  does not hit it (no self-hit of a ray started on a surface). Grazing hits (along a face, through
  an edge or corner) count: the traversal visits every cell whose closed box the ray touches.
* The hit ``face`` is the outward normal of the face the ray entered through, ±1/±2/±3 for
  ±x/±y/±z (the first of x, y, z when it enters through an edge or corner). A ray that starts
  inside (or on the surface of) a cube and moves into it hits it at ``t = 0`` with the face of the
  axis of largest ``|dir|`` component, opposite in sign to that component.
* Traversal: a cell-level Amanatides–Woo DDA in cell units (``p = (o - lo) / h``,
  ``d = dir / h``, the same ``t``). Every boundary parameter is computed from its integer cell
  boundary by one formula (never accumulated), so edge and corner crossings are exact ties; at a
  tie all tied axes step together and the cells that only touch the ray at that edge/corner are
  tested too. A ray lying in a cell boundary plane (zero direction component) is walked on both
  sides. Empty blocks/sub-blocks are left in one step (jump to the exit cell of the empty box).
  Runs of empty blocks of Chebyshev radius 0 (next to an occupied block), and runs of empty
  sub-blocks inside one block, are followed on block/sub-block boundary parameters alone and the
  cells settled once, at the end of the run; a run ends at any tie (`_march_blocks`,
  `_march_words`; the same cells are reached, bit for bit).
* In scaled mode the DDA walks cells and slab-tests the cube of each occupied cell. Cubes lie
  inside their cells and cells are visited in order of entry, so the first cube hit is the
  nearest (ties in ``t`` may resolve to either cube).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from vlsforest.errors import ConfigError, InputDataError

__all__ = ["VoxelGrid"]

#: largest coarse array chosen automatically (entries, 4 bytes each).
_AUTO_COARSE_MAX = 1 << 24
#: largest coarse array accepted at all (1 GiB).
_HARD_COARSE_MAX = 1 << 28
#: largest Chebyshev distance (in blocks) recorded in empty coarse entries for space skipping.
_EMPTY_RADIUS_MAX = 32
#: relative tolerance (of the cell size) for "the cube lies inside its cell".
_INSIDE_TOL = 1e-6
#: full-cell centres given to :meth:`VoxelGrid.from_centres` must lie this close (in cells)
#: to a cell centre of the lattice.
_CENTRE_TOL = 0.1

_U1 = np.uint64(1)
_M1 = np.uint64(0x5555555555555555)
_M2 = np.uint64(0x3333333333333333)
_M4 = np.uint64(0x0F0F0F0F0F0F0F0F)
_H01 = np.uint64(0x0101010101010101)


# --------------------------------------------------------------------------------------------
# numba kernels: bits
# --------------------------------------------------------------------------------------------
@njit(cache=True, inline="always")
def _popcount(x):
    x = x - ((x >> _U1) & _M1)
    x = (x & _M2) + ((x >> np.uint64(2)) & _M2)
    x = (x + (x >> np.uint64(4))) & _M4
    return np.int64((x * _H01) >> np.uint64(56))


@njit(cache=True, inline="always")
def _bit_index(i, j, k, bs):
    """Bit of cell (i, j, k) in its block: word = 4x4x4 sub-block, bit = cell in the sub-block."""
    m = (1 << bs) - 1
    i &= m
    j &= m
    k &= m
    sb = bs - 2
    word = ((k >> 2) << (2 * sb)) | ((j >> 2) << sb) | (i >> 2)
    return (word << 6) | ((k & 3) << 4) | ((j & 3) << 2) | (i & 3)


# --------------------------------------------------------------------------------------------
# numba kernels: build (sequential passes over the voxels, no Python loops)
# --------------------------------------------------------------------------------------------
@njit(cache=True)
def _mark_blocks(ijk, mins, bs, nbx, nby, coarse):
    for r in range(ijk.shape[0]):
        i = np.int64(ijk[r, 0]) - mins[0]
        j = np.int64(ijk[r, 1]) - mins[1]
        k = np.int64(ijk[r, 2]) - mins[2]
        coarse[((k >> bs) * nby + (j >> bs)) * nbx + (i >> bs)] = 0


@njit(cache=True)
def _number_blocks(coarse):
    nb = 0
    for q in range(coarse.shape[0]):
        if coarse[q] >= 0:
            coarse[q] = nb
            nb += 1
    return nb


@njit(cache=True)
def _empty_radius(coarse, nbx, nby, nbz, kmax):
    """Mark each empty block with -D, D = Chebyshev distance (in blocks, capped at kmax + 1) to
    the nearest occupied block, so that the cube of blocks within D - 1 of it is empty."""
    big = kmax + 1
    n = coarse.shape[0]
    f = np.empty(n, np.int32)
    for q in range(n):
        f[q] = 0 if coarse[q] >= 0 else big
    # x: exact 1-D distance (two passes)
    for z in range(nbz):
        for y in range(nby):
            row = (z * nby + y) * nbx
            for x in range(1, nbx):
                if f[row + x - 1] + 1 < f[row + x]:
                    f[row + x] = f[row + x - 1] + 1
            for x in range(nbx - 2, -1, -1):
                if f[row + x + 1] + 1 < f[row + x]:
                    f[row + x] = f[row + x + 1] + 1
    # y and z: g(y) = min over y' of max(f(y'), |y - y'|), scanning outwards while useful
    line = np.empty(max(nby, nbz), np.int32)
    for axis in range(2):
        nl = nby if axis == 0 else nbz
        stride = nbx if axis == 0 else nbx * nby
        n_other = nbz if axis == 0 else nby
        for o in range(n_other):
            for x in range(nbx):
                start = (o * nby * nbx + x) if axis == 0 else (o * nbx + x)
                for a in range(nl):
                    line[a] = f[start + a * stride]
                for a in range(nl):
                    best = line[a]
                    s = 1
                    while s < best:
                        if a - s >= 0 and max(line[a - s], s) < best:
                            best = max(line[a - s], s)
                        if a + s < nl and max(line[a + s], s) < best:
                            best = max(line[a + s], s)
                        s += 1
                    f[start + a * stride] = best
    for q in range(n):
        if coarse[q] < 0:
            coarse[q] = -min(f[q], big)


@njit(cache=True)
def _set_bits(ijk, mins, bs, nbx, nby, wpb, coarse, masks, keep):
    ndup = 0
    for r in range(ijk.shape[0]):
        i = np.int64(ijk[r, 0]) - mins[0]
        j = np.int64(ijk[r, 1]) - mins[1]
        k = np.int64(ijk[r, 2]) - mins[2]
        bid = np.int64(coarse[((k >> bs) * nby + (j >> bs)) * nbx + (i >> bs)])
        idx = _bit_index(i, j, k, bs)
        w = bid * wpb + (idx >> 6)
        bit = _U1 << np.uint64(idx & 63)
        if masks[w] & bit:
            keep[r] = 0
            ndup += 1
        else:
            masks[w] |= bit
            keep[r] = 1
    return ndup


@njit(cache=True)
def _ranks(masks, wpb, prefix, base):
    total = 0
    for b in range(base.shape[0]):
        base[b] = total
        run = 0
        for w in range(wpb):
            prefix[b * wpb + w] = run
            run += _popcount(masks[b * wpb + w])
        total += run
    return total


@njit(cache=True)
def _scatter(ijk, mins, bs, nbx, nby, wpb, coarse, masks, prefix, base, keep,
             code_in, code_out, cube_in, cube_out, src_out):
    for r in range(ijk.shape[0]):
        if keep[r] == 0:
            continue
        i = np.int64(ijk[r, 0]) - mins[0]
        j = np.int64(ijk[r, 1]) - mins[1]
        k = np.int64(ijk[r, 2]) - mins[2]
        bid = np.int64(coarse[((k >> bs) * nby + (j >> bs)) * nbx + (i >> bs)])
        idx = _bit_index(i, j, k, bs)
        w = bid * wpb + (idx >> 6)
        below = masks[w] & ((_U1 << np.uint64(idx & 63)) - _U1)
        v = base[bid] + np.int64(prefix[w]) + _popcount(below)
        if code_out.shape[0] > 0:
            code_out[v] = code_in[r]
        if cube_out.shape[0] > 0:
            for a in range(4):
                cube_out[v, a] = cube_in[r, a]
        if src_out.shape[0] > 0:
            src_out[v] = r


@njit(cache=True)
def _centres_to_cells(centres, origin, h, half, tol, centre_tol, ijk, off):
    """Cells of cube centres; offsets in cell units. Returns the first bad row or -1."""
    scaled = half.shape[0] > 0
    for r in range(centres.shape[0]):
        for a in range(3):
            u = (centres[r, a] - origin[a]) / h
            c = np.floor(u)
            ijk[r, a] = np.int64(c)
            o = u - c - 0.5
            if scaled:
                if abs(o) + half[r] / h > 0.5 + tol:
                    return r
                off[r, a] = o
            elif abs(o) > centre_tol:
                return r
    return -1


@njit(cache=True)
def _voxel_ijk(vox, base, prefix, masks, wpb, bs, block_of, nbx, nby, mins, out):
    nblk = base.shape[0]
    total = base[nblk - 1] + np.int64(prefix[(nblk - 1) * wpb + wpb - 1]) + _popcount(
        masks[(nblk - 1) * wpb + wpb - 1])
    for q in range(vox.shape[0]):
        v = vox[q]
        if v < 0 or v >= total:
            return q
        b = np.searchsorted(base, v, side="right") - 1
        r = v - base[b]
        w = wpb - 1
        for ww in range(wpb):
            if np.int64(prefix[b * wpb + ww]) + _popcount(masks[b * wpb + ww]) > r:
                w = ww
                break
        r -= np.int64(prefix[b * wpb + w])
        word = masks[b * wpb + w]
        bit = 0
        for bb in range(64):
            if (word >> np.uint64(bb)) & _U1:
                if r == 0:
                    bit = bb
                    break
                r -= 1
        key = np.int64(block_of[b])
        bx = key % nbx
        by = (key // nbx) % nby
        bz = key // (nbx * nby)
        sb = bs - 2
        sm = (1 << sb) - 1
        out[q, 0] = (bx << bs) + ((w & sm) << 2) + (bit & 3) + mins[0]
        out[q, 1] = (by << bs) + (((w >> sb) & sm) << 2) + ((bit >> 2) & 3) + mins[1]
        out[q, 2] = (bz << bs) + ((w >> (2 * sb)) << 2) + (bit >> 4) + mins[2]
    return -1


@njit(cache=True)
def _block_keys(coarse, nblk):
    out = np.empty(nblk, np.int64)
    for q in range(coarse.shape[0]):
        if coarse[q] >= 0:
            out[coarse[q]] = q
    return out


# --------------------------------------------------------------------------------------------
# numba kernels: tracing (all in cell units: p = (o - lo) / h, d = dir / h, same t)
# --------------------------------------------------------------------------------------------
# The small helpers are inlined in numba's IR (inline="always"); the large steps (_slab,
# _cube_hit, _probe, _march_blocks, _march_words, _walk) are functions of their own: inlined,
# they would make one body that numba compiles several times more slowly
# (benchmarks/bench_compile.py), for the same hits at about the same speed.
@njit(cache=True, inline="always")
def _next_t(c, p, d, iv):
    """Ray parameter at which the ray leaves cell ``c`` along one axis (inf if parallel).

    ``iv = 1 / d``; every DDA boundary parameter is computed by this one formula, so equal
    boundaries give bit-identical parameters (exact ties at edges and corners).
    """
    if d > 0.0:
        return (c + 1.0 - p) * iv
    if d < 0.0:
        return (c - p) * iv
    return np.inf


@njit(cache=True, inline="always")
def _settle(c, p, d, iv, t, clo, chi):
    """First cell (in walking order) within [clo, chi] whose exit parameter is >= t."""
    if c < clo:
        c = clo
    if c > chi:
        c = chi
    if d > 0.0:
        while c < chi and (c + 1.0 - p) * iv < t:
            c += 1
        while c > clo and (c - p) * iv >= t:
            c -= 1
    elif d < 0.0:
        while c > clo and (c - p) * iv < t:
            c -= 1
        while c < chi and (c + 1.0 - p) * iv >= t:
            c += 1
    return c


@njit(cache=True, inline="always")
def _estimate(p, d, t):
    q = p + t * d
    if d > 0.0:
        return np.int64(np.floor(q))
    return np.int64(np.ceil(q)) - 1


@njit(cache=True)
def _slab(px, py, pz, dx, dy, dz, ivx, ivy, ivz, lox, loy, loz, hix, hiy, hiz):
    """Closed ray-box test (``iv = 1/d``). Returns (t, face); t = inf for a miss."""
    tn = -np.inf
    tf = np.inf
    ax = 0
    sgn = 0.0
    if dx == 0.0:
        if px < lox or px > hix:
            return np.inf, 0
    else:
        a = (lox - px) * ivx
        b = (hix - px) * ivx
        if a > b:
            a, b = b, a
        if a > tn:
            tn = a
            ax = 1
            sgn = dx
        if b < tf:
            tf = b
    if dy == 0.0:
        if py < loy or py > hiy:
            return np.inf, 0
    else:
        a = (loy - py) * ivy
        b = (hiy - py) * ivy
        if a > b:
            a, b = b, a
        if a > tn:
            tn = a
            ax = 2
            sgn = dy
        if b < tf:
            tf = b
    if dz == 0.0:
        if pz < loz or pz > hiz:
            return np.inf, 0
    else:
        a = (loz - pz) * ivz
        b = (hiz - pz) * ivz
        if a > b:
            a, b = b, a
        if a > tn:
            tn = a
            ax = 3
            sgn = dz
        if b < tf:
            tf = b
    if tn > tf or tf <= 0.0:
        return np.inf, 0
    if tn > 0.0:
        return tn, (-ax if sgn > 0.0 else ax)
    ax = 1
    sgn = dx
    if abs(dy) > abs(sgn):
        ax = 2
        sgn = dy
    if abs(dz) > abs(sgn):
        ax = 3
        sgn = dz
    return 0.0, (-ax if sgn > 0.0 else ax)


@njit(cache=True)
def _cube_hit(v, cx, cy, cz, px, py, pz, dx, dy, dz, ivx, ivy, ivz, tmax, cubes):
    """Slab test of voxel ``v`` in cell (cx, cy, cz). Returns (t, face, voxel or -1)."""
    if cubes.shape[0] > 0:
        hf = np.float64(cubes[v, 3])
        ox = cx + 0.5 + np.float64(cubes[v, 0])
        oy = cy + 0.5 + np.float64(cubes[v, 1])
        oz = cz + 0.5 + np.float64(cubes[v, 2])
        t, f = _slab(px, py, pz, dx, dy, dz, ivx, ivy, ivz,
                     ox - hf, oy - hf, oz - hf, ox + hf, oy + hf, oz + hf)
    else:
        t, f = _slab(px, py, pz, dx, dy, dz, ivx, ivy, ivz, cx + 0.0, cy + 0.0, cz + 0.0,
                     cx + 1.0, cy + 1.0, cz + 1.0)
    if t < np.inf and t <= tmax:
        return t, f, v
    return np.inf, 0, np.int64(-1)


@njit(cache=True)
def _probe(bid, cx, cy, cz, px, py, pz, dx, dy, dz, ivx, ivy, ivz, tmax, bs, wpb,
           masks, prefix, base, cubes):
    """Test cell (cx, cy, cz) of block ``bid``. Returns (t, face, voxel or -1)."""
    idx = _bit_index(cx, cy, cz, bs)
    w = bid * wpb + (idx >> 6)
    sh = np.uint64(idx & 63)
    word = masks[w]
    if ((word >> sh) & _U1) == 0:
        return np.inf, 0, np.int64(-1)
    v = base[bid] + np.int64(prefix[w]) + _popcount(word & ((_U1 << sh) - _U1))
    return _cube_hit(v, cx, cy, cz, px, py, pz, dx, dy, dz, ivx, ivy, ivz, tmax, cubes)


@njit(cache=True, inline="always")
def _exit_cell(c, d, lo, hi, n):
    """Cell along one axis through which the ray leaves the box [lo, hi] (clipped to the grid).

    ``c`` is the current cell, returned unchanged for an axis the ray is parallel to.
    """
    if d > 0.0:
        return min(hi, n - 1)
    if d < 0.0:
        return max(lo, 0)
    return c


@njit(cache=True)
def _march_blocks(px, py, pz, dx, dy, dz, ivx, ivy, ivz, sx, sy, sz, cx, cy, cz, bx, by, bz,
                  tend, nx, ny, nz, bs, nbx, nby, coarse):
    """Follow the ray through consecutive empty blocks of Chebyshev radius 0.

    Starting in empty block (bx, by, bz), step to the next block while the ray leaves the
    current one through exactly one face (no tie of block-boundary parameters) into a block
    that is again empty with radius 0. Returns the last such block and whether the walk goes
    on (False: the ray ends, ``te > tend``, or leaves the grid on the way).

    The cell-level walk reaches the same cells: in each of these blocks it would jump to the
    block's exit cell and step across. Its only extra work there is probing the cells that
    touch the ray where a cell boundary inside the block ties with the exit: those lie in the
    current or the next block, both empty, so the probes find nothing. The boundary
    parameters are computed by :func:`_next_t` from the same exit cells, so they are
    bit-identical to the ones the cell-level jump computes, and the jump out of the last
    block (settled from the cells before the run, which are not past the ray's cells at
    the exit) lands where the block-by-block jumps would have.
    """
    while True:
        lx = _exit_cell(cx, dx, bx << bs, ((bx + 1) << bs) - 1, nx)
        ly = _exit_cell(cy, dy, by << bs, ((by + 1) << bs) - 1, ny)
        lz = _exit_cell(cz, dz, bz << bs, ((bz + 1) << bs) - 1, nz)
        tex = _next_t(lx, px, dx, ivx)
        tey = _next_t(ly, py, dy, ivy)
        tez = _next_t(lz, pz, dz, ivz)
        te = min(tex, min(tey, tez))
        if te > tend:
            return bx, by, bz, False
        qx = bx
        qy = by
        qz = bz
        if tex == te:
            if tey == te or tez == te:
                return bx, by, bz, True
            q = lx + sx
            if q < 0 or q >= nx:
                return bx, by, bz, False
            qx = q >> bs
        elif tey == te:
            if tez == te:
                return bx, by, bz, True
            q = ly + sy
            if q < 0 or q >= ny:
                return bx, by, bz, False
            qy = q >> bs
        else:
            q = lz + sz
            if q < 0 or q >= nz:
                return bx, by, bz, False
            qz = q >> bs
        if coarse[(qz * nby + qy) * nbx + qx] != -1:
            return bx, by, bz, True
        bx = qx
        by = qy
        bz = qz


@njit(cache=True)
def _march_words(px, py, pz, dx, dy, dz, ivx, ivy, ivz, sx, sy, sz, cx, cy, cz, tend,
                 nx, ny, nz, bs, bid, wpb, masks):
    """Follow the ray through consecutive empty 4x4x4 sub-blocks of occupied block ``bid``.

    Starts in the (empty) sub-block of cell (cx, cy, cz); the same as :func:`_march_blocks`
    one level down, without leaving the block. Returns the last empty sub-block of the run
    (in sub-block units, i.e. cell >> 2) and whether the walk goes on.
    """
    ux = cx >> 2
    uy = cy >> 2
    uz = cz >> 2
    sb = bs - 2
    sm = (1 << sb) - 1
    while True:
        lx = _exit_cell(cx, dx, ux << 2, (ux << 2) + 3, nx)
        ly = _exit_cell(cy, dy, uy << 2, (uy << 2) + 3, ny)
        lz = _exit_cell(cz, dz, uz << 2, (uz << 2) + 3, nz)
        tex = _next_t(lx, px, dx, ivx)
        tey = _next_t(ly, py, dy, ivy)
        tez = _next_t(lz, pz, dz, ivz)
        te = min(tex, min(tey, tez))
        if te > tend:
            return ux, uy, uz, False
        qx = ux
        qy = uy
        qz = uz
        if tex == te:
            if tey == te or tez == te:
                return ux, uy, uz, True
            q = lx + sx
            if q < 0 or q >= nx:
                return ux, uy, uz, False
            if (q >> bs) != (lx >> bs):
                return ux, uy, uz, True
            qx = q >> 2
        elif tey == te:
            if tez == te:
                return ux, uy, uz, True
            q = ly + sy
            if q < 0 or q >= ny:
                return ux, uy, uz, False
            if (q >> bs) != (ly >> bs):
                return ux, uy, uz, True
            qy = q >> 2
        else:
            q = lz + sz
            if q < 0 or q >= nz:
                return ux, uy, uz, False
            if (q >> bs) != (lz >> bs):
                return ux, uy, uz, True
            qz = q >> 2
        if masks[bid * wpb + (((qz & sm) << (2 * sb)) | ((qy & sm) << sb) | (qx & sm))] != 0:
            return ux, uy, uz, True
        ux = qx
        uy = qy
        uz = qz


@njit(cache=True)
def _walk(px, py, pz, dx, dy, dz, ivx, ivy, ivz, cx, cy, cz, tend, tmax, nx, ny, nz,
          bs, nbx, nby, wpb, coarse, masks, prefix, base, cubes):
    """DDA from the settled start cell. Returns (t, face, voxel); voxel -1 for a miss."""
    sx = 1 if dx > 0.0 else -1
    sy = 1 if dy > 0.0 else -1
    sz = 1 if dz > 0.0 else -1
    tmx = _next_t(cx, px, dx, ivx)
    tmy = _next_t(cy, py, dy, ivy)
    tmz = _next_t(cz, pz, dz, ivz)
    while True:
        bx = cx >> bs
        by = cy >> bs
        bz = cz >> bs
        bid = np.int64(coarse[(bz * nby + by) * nbx + bx])
        if bid < 0:
            # empty block: the cube of blocks within Chebyshev radius r around it is empty
            r = -bid - 1
            if r == 0:
                # a run of single empty blocks (radius 0) left through one face each: march
                # block to block on block-boundary parameters alone; the cells are settled
                # below only in the last block of the run (see _march_blocks)
                bx, by, bz, go = _march_blocks(px, py, pz, dx, dy, dz, ivx, ivy, ivz,
                                               sx, sy, sz, cx, cy, cz, bx, by, bz,
                                               tend, nx, ny, nz, bs, nbx, nby, coarse)
                if not go:
                    return np.inf, 0, np.int64(-1)
            xlo = (bx - r) << bs
            xhi = ((bx + r + 1) << bs) - 1
            ylo = (by - r) << bs
            yhi = ((by + r + 1) << bs) - 1
            zlo = (bz - r) << bs
            zhi = ((bz + r + 1) << bs) - 1
            empty = True
        else:
            idx = _bit_index(cx, cy, cz, bs)
            w = bid * wpb + (idx >> 6)
            word = masks[w]
            if word == 0:
                # empty 4x4x4 sub-block; a run of them inside this block is marched through
                # like a run of empty blocks (see _march_words)
                ux, uy, uz, go = _march_words(px, py, pz, dx, dy, dz, ivx, ivy, ivz,
                                              sx, sy, sz, cx, cy, cz, tend, nx, ny, nz,
                                              bs, bid, wpb, masks)
                if not go:
                    return np.inf, 0, np.int64(-1)
                xlo = ux << 2
                xhi = xlo + 3
                ylo = uy << 2
                yhi = ylo + 3
                zlo = uz << 2
                zhi = zlo + 3
                empty = True
            else:
                empty = False
                sh = np.uint64(idx & 63)
                if (word >> sh) & _U1:
                    v = base[bid] + np.int64(prefix[w]) + _popcount(word & ((_U1 << sh) - _U1))
                    t, f, v = _cube_hit(v, cx, cy, cz, px, py, pz, dx, dy, dz, ivx, ivy, ivz,
                                        tmax, cubes)
                    if v >= 0:
                        return t, f, v
        if empty:
            # jump to the cell in which the ray leaves the empty box [lo, hi]
            lx = _exit_cell(cx, dx, xlo, xhi, nx)
            ly = _exit_cell(cy, dy, ylo, yhi, ny)
            lz = _exit_cell(cz, dz, zlo, zhi, nz)
            te = min(_next_t(lx, px, dx, ivx),
                     min(_next_t(ly, py, dy, ivy), _next_t(lz, pz, dz, ivz)))
            if te > tend:
                return np.inf, 0, np.int64(-1)
            if dx > 0.0:
                cx = _settle(_estimate(px, dx, te), px, dx, ivx, te, cx, lx)
            elif dx < 0.0:
                cx = _settle(_estimate(px, dx, te), px, dx, ivx, te, lx, cx)
            if dy > 0.0:
                cy = _settle(_estimate(py, dy, te), py, dy, ivy, te, cy, ly)
            elif dy < 0.0:
                cy = _settle(_estimate(py, dy, te), py, dy, ivy, te, ly, cy)
            if dz > 0.0:
                cz = _settle(_estimate(pz, dz, te), pz, dz, ivz, te, cz, lz)
            elif dz < 0.0:
                cz = _settle(_estimate(pz, dz, te), pz, dz, ivz, te, lz, cz)
            tmx = _next_t(cx, px, dx, ivx)
            tmy = _next_t(cy, py, dy, ivy)
            tmz = _next_t(cz, pz, dz, ivz)
        tn = min(tmx, min(tmy, tmz))
        if tn > tend:
            return np.inf, 0, np.int64(-1)
        s = 0
        if tmx == tn:
            s |= 1
        if tmy == tn:
            s |= 2
        if tmz == tn:
            s |= 4
        if s != 1 and s != 2 and s != 4:
            # the ray passes exactly through an edge or corner: the cells that touch it there
            for m in range(1, 7):
                if (m & s) != m or m == s:
                    continue
                qx = cx + sx if (m & 1) else cx
                qy = cy + sy if (m & 2) else cy
                qz = cz + sz if (m & 4) else cz
                if qx < 0 or qx >= nx or qy < 0 or qy >= ny or qz < 0 or qz >= nz:
                    continue
                b2 = np.int64(coarse[((qz >> bs) * nby + (qy >> bs)) * nbx + (qx >> bs)])
                if b2 < 0:
                    continue
                t, f, v = _probe(b2, qx, qy, qz, px, py, pz, dx, dy, dz, ivx, ivy, ivz, tmax,
                                 bs, wpb, masks, prefix, base, cubes)
                if v >= 0:
                    return t, f, v
        if s & 1:
            cx += sx
            if cx < 0 or cx >= nx:
                return np.inf, 0, np.int64(-1)
            tmx = _next_t(cx, px, dx, ivx)
        if s & 2:
            cy += sy
            if cy < 0 or cy >= ny:
                return np.inf, 0, np.int64(-1)
            tmy = _next_t(cy, py, dy, ivy)
        if s & 4:
            cz += sz
            if cz < 0 or cz >= nz:
                return np.inf, 0, np.int64(-1)
            tmz = _next_t(cz, pz, dz, ivz)


@njit(cache=True, inline="always")
def _clip(p, d, n, t0, t1):
    if d == 0.0:
        if p < 0.0 or p > n:
            return np.inf, -np.inf
        return t0, t1
    iv = 1.0 / d
    a = (0.0 - p) * iv
    b = (n - p) * iv
    if a > b:
        a, b = b, a
    return max(t0, a), min(t1, b)


@njit(cache=True, inline="always")
def _start_options(p, d, iv, t0, n):
    """Start cell(s) along one axis: two when the ray lies in a cell boundary plane."""
    if d != 0.0:
        return _settle(_estimate(p, d, t0), p, d, iv, t0, 0, n - 1), np.int64(-1), 1
    c = np.int64(np.floor(p))
    if c >= n:
        return c - 1, np.int64(-1), 1
    if p == c and c >= 1:
        return c, c - 1, 2
    return c, np.int64(-1), 1


@njit(cache=True)
def _trace_one(px, py, pz, dx, dy, dz, tmax, nx, ny, nz, bs, nbx, nby, wpb,
               coarse, masks, prefix, base, cubes):
    t0, t1 = _clip(px, dx, nx, 0.0, tmax)
    t0, t1 = _clip(py, dy, ny, t0, t1)
    t0, t1 = _clip(pz, dz, nz, t0, t1)
    if not t0 <= t1:
        return np.inf, 0, np.int64(-1)
    ivx = 1.0 / dx if dx != 0.0 else np.inf
    ivy = 1.0 / dy if dy != 0.0 else np.inf
    ivz = 1.0 / dz if dz != 0.0 else np.inf
    ax0, ax1, nvx = _start_options(px, dx, ivx, t0, nx)
    ay0, ay1, nvy = _start_options(py, dy, ivy, t0, ny)
    az0, az1, nvz = _start_options(pz, dz, ivz, t0, nz)
    bt = np.inf
    bf = 0
    bv = np.int64(-1)
    for ix in range(nvx):
        for iy in range(nvy):
            for iz in range(nvz):
                t, f, v = _walk(px, py, pz, dx, dy, dz, ivx, ivy, ivz,
                                ax0 if ix == 0 else ax1, ay0 if iy == 0 else ay1,
                                az0 if iz == 0 else az1, t1, tmax, nx, ny, nz,
                                bs, nbx, nby, wpb, coarse, masks, prefix, base, cubes)
                if v >= 0 and t < bt:
                    bt = t
                    bf = f
                    bv = v
    return bt, bf, bv


@njit(parallel=True, cache=True, fastmath=False)
def _trace_kernel(origins, dirs, tmax, lo, h, nx, ny, nz, bs, nbx, nby, wpb,
                  coarse, masks, prefix, base, cubes, out_t, out_face, out_vox):
    m = origins.shape[0]
    has_tmax = tmax.shape[0] > 0
    for r in prange(m):
        px = (origins[r, 0] - lo[0]) / h
        py = (origins[r, 1] - lo[1]) / h
        pz = (origins[r, 2] - lo[2]) / h
        dx = dirs[r, 0] / h
        dy = dirs[r, 1] / h
        dz = dirs[r, 2] / h
        tm = tmax[r] if has_tmax else np.inf
        t, f, v = _trace_one(px, py, pz, dx, dy, dz, tm, nx, ny, nz, bs, nbx, nby, wpb,
                             coarse, masks, prefix, base, cubes)
        out_t[r] = t
        out_face[r] = f
        out_vox[r] = v


@njit(cache=True, fastmath=False)
def _trace_kernel_serial(origins, dirs, tmax, lo, h, nx, ny, nz, bs, nbx, nby, wpb,
                         coarse, masks, prefix, base, cubes, out_t, out_face, out_vox):
    """Single-threaded twin of :func:`_trace_kernel` (for forked worker processes)."""
    m = origins.shape[0]
    has_tmax = tmax.shape[0] > 0
    for r in range(m):
        px = (origins[r, 0] - lo[0]) / h
        py = (origins[r, 1] - lo[1]) / h
        pz = (origins[r, 2] - lo[2]) / h
        dx = dirs[r, 0] / h
        dy = dirs[r, 1] / h
        dz = dirs[r, 2] / h
        tm = tmax[r] if has_tmax else np.inf
        t, f, v = _trace_one(px, py, pz, dx, dy, dz, tm, nx, ny, nz, bs, nbx, nby, wpb,
                             coarse, masks, prefix, base, cubes)
        out_t[r] = t
        out_face[r] = f
        out_vox[r] = v


# --------------------------------------------------------------------------------------------
# public class
# --------------------------------------------------------------------------------------------
def _as_int_array(a, name):
    a = np.asarray(a)
    if a.dtype.kind not in "iu":
        raise InputDataError(f"{name}: integer cell indices expected, got dtype {a.dtype}")
    if a.dtype not in (np.int32, np.int64):
        a = a.astype(np.int64)
    return np.ascontiguousarray(a)


def _vector3(v, name):
    try:
        a = np.asarray(v, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{name}: three finite numbers expected ({exc})") from None
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ConfigError(f"{name}: three finite numbers expected, got {v!r}")
    return a


def _cell_size(h):
    try:
        h = float(h)
    except (TypeError, ValueError):
        raise ConfigError(f"cell_size: a positive number expected, got {h!r}") from None
    if not (np.isfinite(h) and h > 0.0):
        raise ConfigError(f"cell_size: a positive finite number expected, got {h!r}")
    return h


class VoxelGrid:
    """Sparse occupancy grid of axis-aligned cubes on one lattice, traced with a 3-D DDA.

    Build with :meth:`build` (integer cell indices) or :meth:`from_centres` (cube centres); see
    the module docstring for the structure and the exact hit semantics.

    Attributes
    ----------
    n_voxels : int
        Number of cubes held (after dropping zero-size cubes and duplicates).
    cell_size : float
        Lattice cell size ``h`` (m).
    origin : ndarray, shape (3,)
        Lattice origin: cell (i, j, k) spans ``origin + [i, i+1) * h`` etc.
    scaled : bool
        True when the cubes carry their own centre and half size (scaled/shifted mode).
    block_bits : int
        Log2 of the block edge in cells.
    n_duplicates : int
        Input cells dropped as repeats of an earlier row (full-cell mode only).
    source_index : ndarray of int64 or None
        Input row of every voxel (``build(..., keep_source_index=True)`` only).
    """

    def __init__(self):  # use build() / from_centres()
        raise TypeError("use VoxelGrid.build() or VoxelGrid.from_centres()")

    # ---------------------------------------------------------------- construction
    @classmethod
    def build(cls, ijk, origin, cell_size, part=0, half_size=None, centre=None, *,
              block_bits=None, keep_source_index=False) -> "VoxelGrid":
        """Build the grid from integer cell indices.

        Parameters
        ----------
        ijk : array_like of int, shape (n, 3)
            Cell indices on the lattice (any sign, any offset; int32 input is not copied).
        origin : array_like, shape (3,)
            Lattice origin (m).
        cell_size : float
            Cell size ``h`` (m), > 0.
        part : int or array_like of int, shape (n,)
            Scene-part id returned for hits on each cube (one id for all, or one per row).
        half_size : None, float or array_like, shape (n,)
            None: full cells (fixed-size voxels). Otherwise scaled mode: per-cube half size (m),
            ``0 <= half <= h/2``; cubes of half size 0 are dropped.
        centre : None or array_like, shape (n, 3)
            Scaled mode only: cube centres (m, world frame); None centres each cube in its cell.
            Each cube must lie inside its cell (tolerance ``1e-6 h``).
        block_bits : int, optional
            Block edge ``2**block_bits`` cells (2..5); default chosen automatically.
        keep_source_index : bool
            Store :attr:`source_index` (8 bytes per voxel).

        Returns
        -------
        VoxelGrid

        Raises
        ------
        ConfigError
            Bad ``cell_size``, ``origin`` or ``block_bits``; ``centre`` without ``half_size``.
        InputDataError
            Bad array shapes or values, no voxels, a cube outside its cell, repeated cells in
            scaled mode, or an index range too large for the coarse array.

        Notes
        -----
        Repeated cells: in full-cell mode the first row wins (its part id is kept) and the
        number of dropped rows is :attr:`n_duplicates`; in scaled mode they are an error.
        """
        h = _cell_size(cell_size)
        org = _vector3(origin, "origin")
        ijk = _as_int_array(ijk, "ijk")
        if ijk.ndim != 2 or ijk.shape[1] != 3:
            raise InputDataError(f"ijk: shape (n, 3) expected, got {ijk.shape}")
        n = ijk.shape[0]
        cube = None
        if half_size is None:
            if centre is not None:
                raise ConfigError("centre: given without half_size (full cells are centred)")
        else:
            half = np.broadcast_to(np.asarray(half_size, dtype=np.float64), (n,))
            if not np.all(np.isfinite(half)) or np.any(half < 0.0):
                raise InputDataError("half_size: finite values >= 0 expected")
            if np.any(half > 0.5 * h * (1.0 + _INSIDE_TOL)):
                r = int(np.argmax(half > 0.5 * h * (1.0 + _INSIDE_TOL)))
                raise InputDataError(
                    f"half_size: cube {r} has half size {half[r]!r} > cell_size/2 = {0.5 * h!r}")
            cube = np.zeros((n, 4), dtype=np.float32)
            cube[:, 3] = np.minimum(half / h, 0.5)
            if centre is not None:
                c = np.asarray(centre, dtype=np.float64)
                if c.shape != (n, 3) or not np.all(np.isfinite(c)):
                    raise InputDataError(f"centre: finite array of shape ({n}, 3) expected")
                off = (c - org) / h - (ijk.astype(np.float64) + 0.5)
                bad = np.abs(off) + (half / h)[:, None] > 0.5 + _INSIDE_TOL
                if np.any(bad):
                    r = int(np.argmax(bad.any(axis=1)))
                    raise InputDataError(
                        f"centre: cube {r} (centre {c[r].tolist()}, half size {half[r]!r}) "
                        f"does not lie inside its cell {ijk[r].tolist()}")
                lim = (0.5 - cube[:, 3:4]).astype(np.float64)
                cube[:, :3] = np.clip(off, -lim, lim)
        return cls._assemble(ijk, org, h, part, cube, half_size is not None, block_bits,
                             keep_source_index)

    @classmethod
    def from_centres(cls, centres, cell_size, origin=None, part=0, half_size=None, *,
                     block_bits=None, keep_source_index=False) -> "VoxelGrid":
        """Build the grid from cube centres.

        Parameters
        ----------
        centres : array_like, shape (n, 3)
            Cube centres (m).
        cell_size : float
            Lattice cell size ``h`` (m).
        origin : array_like, shape (3,), optional
            Lattice origin; default (0, 0, 0), i.e. cell corners at integer multiples of ``h``.
        part : int or array_like of int, shape (n,)
            Scene-part id(s).
        half_size : None, float or array_like, shape (n,)
            None: full cells; each centre must lie within ``0.1 h`` of a cell centre of the
            lattice (otherwise the origin or cell size is wrong). Otherwise the cube of that
            half size centred at the given centre must lie inside the cell containing the
            centre (tolerance ``1e-6 h``); half size 0 drops the cube.
        block_bits, keep_source_index
            As in :meth:`build` (``source_index`` refers to rows of ``centres``).

        Returns
        -------
        VoxelGrid
        """
        h = _cell_size(cell_size)
        org = np.zeros(3) if origin is None else _vector3(origin, "origin")
        c = np.ascontiguousarray(np.asarray(centres, dtype=np.float64))
        if c.ndim != 2 or c.shape[1] != 3:
            raise InputDataError(f"centres: shape (n, 3) expected, got {c.shape}")
        if not np.all(np.isfinite(c)):
            raise InputDataError("centres: non-finite coordinates")
        n = c.shape[0]
        if half_size is None:
            half = np.zeros(0)
        else:
            half = np.ascontiguousarray(
                np.broadcast_to(np.asarray(half_size, dtype=np.float64), (n,)))
            if not np.all(np.isfinite(half)) or np.any(half < 0.0):
                raise InputDataError("half_size: finite values >= 0 expected")
        ijk = np.empty((n, 3), dtype=np.int64)
        off = np.empty((n if half_size is not None else 0, 3), dtype=np.float64)
        bad = _centres_to_cells(c, org, h, half, _INSIDE_TOL, _CENTRE_TOL, ijk, off)
        if bad >= 0:
            if half_size is None:
                raise InputDataError(
                    f"centres: centre {bad} {c[bad].tolist()} is not within {_CENTRE_TOL} cells "
                    f"of a cell centre of the lattice (origin {org.tolist()}, cell_size {h})")
            raise InputDataError(
                f"centres: cube {bad} (centre {c[bad].tolist()}, half size {half[bad]!r}) does "
                f"not lie inside the cell of cell_size {h} that contains its centre")
        cube = None
        if half_size is not None:
            cube = np.empty((n, 4), dtype=np.float32)
            cube[:, 3] = np.minimum(half / h, 0.5)
            lim = (0.5 - cube[:, 3:4]).astype(np.float64)
            cube[:, :3] = np.clip(off, -lim, lim)
            del off
        return cls._assemble(ijk, org, h, part, cube, half_size is not None, block_bits,
                             keep_source_index)

    @classmethod
    def _assemble(cls, ijk, org, h, part, cube, scaled, block_bits, keep_source_index):
        n_in = ijk.shape[0]
        part_arr = np.asarray(part)
        if part_arr.ndim == 0:
            if part_arr.dtype.kind not in "iu":
                raise InputDataError(f"part: integer id expected, got {part!r}")
            table = np.array([int(part_arr)], dtype=np.int32)
            code_in = np.zeros(0, dtype=np.uint8)
        else:
            if part_arr.shape != (n_in,) or part_arr.dtype.kind not in "iu":
                raise InputDataError(f"part: integer array of shape ({n_in},) expected")
            table, code_in = np.unique(part_arr, return_inverse=True)
            if table.size and (table.min() < np.iinfo(np.int32).min
                               or table.max() > np.iinfo(np.int32).max):
                raise InputDataError("part: ids must fit in int32")
            table = table.astype(np.int32)
            code_in = code_in.astype(np.uint8 if table.size <= 256 else np.int32)
        src_rows = None
        if scaled:
            keep_rows = cube[:, 3] > 0.0
            if not np.all(keep_rows):  # zero-size cubes are dropped, never traced
                src_rows = np.flatnonzero(keep_rows)
                ijk = ijk[src_rows]
                cube = cube[src_rows]
                if code_in.size:
                    code_in = code_in[src_rows]
        else:
            cube = np.zeros((0, 4), dtype=np.float32)
        n = ijk.shape[0]
        if n == 0:
            raise InputDataError("no voxels to build a grid from (empty input or all half sizes 0)")
        mins = ijk.min(axis=0).astype(np.int64)
        maxs = ijk.max(axis=0).astype(np.int64)
        dims = maxs - mins + 1
        if block_bits is None:
            for bs in (3, 4, 5):
                nb = -(-dims // (1 << bs))
                if int(np.prod(nb)) <= _AUTO_COARSE_MAX:
                    break
        else:
            if block_bits not in (2, 3, 4, 5):
                raise ConfigError(f"block_bits: 2, 3, 4 or 5 expected, got {block_bits!r}")
            bs = int(block_bits)
        nb = -(-dims // (1 << bs))
        if int(np.prod(nb.astype(np.float64))) > _HARD_COARSE_MAX:
            raise InputDataError(
                f"ijk: the cells span {dims.tolist()} cells, too large for one grid "
                f"(split the scene or use a coarser lattice)")
        nbx, nby, nbz = (int(x) for x in nb)
        wpb = max(1, (1 << (3 * bs)) // 64)
        coarse = np.full(nbx * nby * nbz, -1, dtype=np.int32)
        _mark_blocks(ijk, mins, bs, nbx, nby, coarse)
        nblk = _number_blocks(coarse)
        _empty_radius(coarse, nbx, nby, nbz, _EMPTY_RADIUS_MAX)
        masks = np.zeros(nblk * wpb, dtype=np.uint64)
        keep = np.empty(n, dtype=np.uint8)
        ndup = int(_set_bits(ijk, mins, bs, nbx, nby, wpb, coarse, masks, keep))
        if ndup and scaled:
            r = int(np.argmin(keep))
            raise InputDataError(
                f"ijk: {ndup} cubes share a cell with an earlier cube (first: row {r}, cell "
                f"{ijk[r].tolist()}); scaled mode allows one cube per cell")
        prefix = np.empty(nblk * wpb, dtype=np.uint16)
        base = np.empty(nblk, dtype=np.int64)
        nvox = int(_ranks(masks, wpb, prefix, base))
        code_out = np.empty(nvox if code_in.size else 0, dtype=code_in.dtype)
        cube_out = np.empty((nvox if scaled else 0, 4), dtype=np.float32)
        src_out = np.empty(nvox if keep_source_index else 0, dtype=np.int64)
        if code_out.size or cube_out.size or src_out.size:
            _scatter(ijk, mins, bs, nbx, nby, wpb, coarse, masks, prefix, base, keep,
                     code_in, code_out, cube, cube_out, src_out)
        if src_rows is not None and src_out.size:
            src_out = src_rows[src_out]

        self = object.__new__(cls)
        self.cell_size = h
        self.origin = org
        self.scaled = bool(scaled)
        self.block_bits = bs
        self.n_voxels = nvox
        self.n_duplicates = ndup
        self.source_index = src_out if keep_source_index else None
        self._mins = mins
        self._dims = dims
        self._nb = (nbx, nby, nbz)
        self._wpb = wpb
        self._coarse = coarse
        self._masks = masks
        self._prefix = prefix
        self._base = base
        self._cubes = cube_out
        self._part_table = table
        self._part_code = code_out
        return self

    # ---------------------------------------------------------------- properties
    @property
    def nbytes(self) -> int:
        """Bytes held by the structure (coarse array, masks, ranks, per-voxel data)."""
        arrays = (self._coarse, self._masks, self._prefix, self._base, self._cubes,
                  self._part_table, self._part_code)
        total = sum(a.nbytes for a in arrays)
        if self.source_index is not None:
            total += self.source_index.nbytes
        return int(total)

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi): the axis-aligned box of all cells that hold a voxel (m)."""
        lo = self.origin + self._mins * self.cell_size
        hi = self.origin + (self._mins + self._dims) * self.cell_size
        return lo, hi

    @property
    def n_blocks(self) -> int:
        """Number of occupied blocks."""
        return int(self._base.shape[0])

    def __repr__(self) -> str:
        return (f"VoxelGrid(n_voxels={self.n_voxels}, cell_size={self.cell_size}, "
                f"scaled={self.scaled}, blocks={self.n_blocks}x{1 << self.block_bits}^3, "
                f"nbytes={self.nbytes})")

    # ---------------------------------------------------------------- queries
    def voxel_ijk(self, voxel) -> np.ndarray:
        """Global cell indices (m, 3) int64 of voxel indices as returned by :meth:`trace`."""
        v = np.ascontiguousarray(np.asarray(voxel, dtype=np.int64).reshape(-1))
        out = np.empty((v.shape[0], 3), dtype=np.int64)
        keys = _block_keys(self._coarse, self.n_blocks)
        bad = _voxel_ijk(v, self._base, self._prefix, self._masks, self._wpb, self.block_bits,
                         keys, self._nb[0], self._nb[1], self._mins, out)
        if bad >= 0:
            raise InputDataError(f"voxel: index {v[bad]} out of range [0, {self.n_voxels})")
        return out

    def voxel_parts(self, voxel) -> np.ndarray:
        """Part ids (int32) of voxel indices."""
        v = np.asarray(voxel, dtype=np.int64)
        if self._part_code.size:
            return self._part_table[self._part_code[v]]
        if np.any((v < 0) | (v >= self.n_voxels)):
            raise InputDataError(f"voxel: index out of range [0, {self.n_voxels})")
        return np.full(v.shape, self._part_table[0], dtype=np.int32)

    def trace(self, origins, dirs, tmax=None, serial: bool = False):
        """First hit of each ray ``origins + t * dirs``, ``0 <= t <= tmax``.

        Parameters
        ----------
        origins, dirs : array_like, shape (m, 3)
            Ray origins (m) and directions (need not be unit, must be non-zero).
        tmax : None or array_like, shape (m,)
            Largest ray parameter accepted (inf when None).
        serial : bool, optional
            True: trace with the single-threaded kernel (in a forked worker process, where
            numba's workqueue threading layer must not run, or when one CPU is asked for);
            False: with the parallel kernel.

        Returns
        -------
        t : ndarray of float64, shape (m,)
            Ray parameter of the hit, in units of ``|dirs|`` (metres for unit directions);
            inf for no hit.
        part : ndarray of int32
            Part id of the hit cube, -1 for no hit.
        face : ndarray of int8
            Outward normal of the entered face, ±1/±2/±3 for ±x/±y/±z; 0 for no hit.
        voxel : ndarray of int64
            Index of the hit voxel (see :meth:`voxel_ijk`, :attr:`source_index`), -1 for none.
        """
        o = np.ascontiguousarray(np.asarray(origins, dtype=np.float64))
        d = np.ascontiguousarray(np.asarray(dirs, dtype=np.float64))
        if o.ndim != 2 or o.shape[1] != 3 or d.shape != o.shape:
            raise InputDataError(
                f"origins, dirs: two arrays of shape (m, 3) expected, got {o.shape}, {d.shape}")
        if not (np.all(np.isfinite(o)) and np.all(np.isfinite(d))):
            raise InputDataError("origins, dirs: non-finite values")
        if np.any(np.all(d == 0.0, axis=1)):
            raise InputDataError("dirs: zero-length direction")
        m = o.shape[0]
        if tmax is None:
            tm = np.zeros(0)
        else:
            tm = np.ascontiguousarray(
                np.broadcast_to(np.asarray(tmax, dtype=np.float64), (m,)))
            if np.any(np.isnan(tm)):
                raise InputDataError("tmax: NaN values")
        out_t = np.empty(m, dtype=np.float64)
        out_face = np.empty(m, dtype=np.int8)
        out_vox = np.empty(m, dtype=np.int64)
        lo = self.origin + self._mins * self.cell_size
        nx, ny, nz = (int(x) for x in self._dims)
        kernel = _trace_kernel_serial if serial else _trace_kernel
        kernel(o, d, tm, lo, self.cell_size, nx, ny, nz, self.block_bits,
               self._nb[0], self._nb[1], self._wpb, self._coarse, self._masks,
               self._prefix, self._base, self._cubes, out_t, out_face, out_vox)
        hit = out_vox >= 0
        out_part = np.full(m, -1, dtype=np.int32)
        if self._part_code.size:
            out_part[hit] = self._part_table[self._part_code[out_vox[hit]]]
        else:
            out_part[hit] = self._part_table[0]
        return out_t, out_part, out_face, out_vox
