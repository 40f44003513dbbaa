"""Pulse generation: the emitted pulses of a range of slots, in the world frame.

A pulse slot is a tick of the scanner's PRF on the trajectory (:mod:`vlsforest.sim.trajectory`);
its deflector (:mod:`vlsforest.sim.deflector`) says whether it is emitted and where its beam
points in the body frame, and the trajectory's attitude turns that into the world frame.

One compiled pass builds the pulses slot by slot, either every emitted pulse (:func:`emit`) or
only those whose beam cone can meet a box (:func:`emit_toward`, the pulses the simulator
traces: most slots of a ULS survey over a plot are either not emitted or aimed away from the
scene, and their frames are never built). Both call the deflector's per-slot functions, so a
pulse has the same bits either way. With trajectory noise the beam is traced along the
perturbed trajectory and georeferenced from the nominal one (:attr:`PulseBatch.geo_origin`).

Pulses are computed from the global slot index alone, so the result is the same however a slot
range is split into calls.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numba
import numpy as np

from vlsforest.sim.beam import cone_meets_box, cones_meet_box
from vlsforest.sim.deflector import (CONIC, TLS, DeflectorPattern, across_track_frame, conic_frame, deflect_pattern,
                                     node_frame, sweep)
from vlsforest.sim.trajectory import Trajectory, rotate

__all__ = ["PulseBatch", "emit", "emit_toward"]

# what the compiled pass builds the frames of
_EVERY, _TOWARD, _NONE = 0, 1, 2


@dataclass
class PulseBatch:
    """Emitted pulses of a slot range (arrays of length m).

    Attributes
    ----------
    slot : ndarray of int64
        Global slot index.
    gps_time : ndarray of float64
        Emission time, s.
    origin : ndarray, shape (m, 3)
        Beam origin, world frame.
    direction : ndarray, shape (m, 3)
        Unit beam direction, world frame.
    scan_dir : ndarray, shape (m, 3)
        Unit vector ⟂ ``direction``: the way the beam sweeps (tls: increasing elevation).
    scan_angle_deg : ndarray of float64
        Signed across-track deflection from nadir (tls: elevation in the head frame).
    source_id : ndarray of uint16
        Flight line / scan position number, from 1.
    geo_origin, geo_direction, geo_scan_dir : ndarray, shape (m, 3), or None
        With trajectory noise: the geometry the system *believes* (the nominal trajectory), from
        which the returns are georeferenced, while ``origin``/``direction`` are where the beam
        really went. None without trajectory noise (both are the same).
    """

    slot: np.ndarray
    gps_time: np.ndarray
    origin: np.ndarray
    direction: np.ndarray
    scan_dir: np.ndarray
    scan_angle_deg: np.ndarray
    source_id: np.ndarray
    geo_origin: np.ndarray | None = None
    geo_direction: np.ndarray | None = None
    geo_scan_dir: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.slot)

    def _fields(self):
        return _BATCH_FIELDS + (_GEO_FIELDS if self.geo_origin is not None else ())

    def subset(self, index) -> "PulseBatch":
        """Return the pulses selected by a boolean mask, an index array or a slice."""
        return PulseBatch(**{k: getattr(self, k)[index] for k in self._fields()})

    def georeferenced(self) -> "PulseBatch":
        """The batch as the system records it: origin and directions of the nominal trajectory
        (``self`` without trajectory noise). Returns are placed along these, so a trajectory
        error moves the points the way a GNSS/INS error does."""
        if self.geo_origin is None:
            return self
        return PulseBatch(slot=self.slot, gps_time=self.gps_time, origin=self.geo_origin,
                          direction=self.geo_direction, scan_dir=self.geo_scan_dir,
                          scan_angle_deg=self.scan_angle_deg, source_id=self.source_id)

    @staticmethod
    def empty() -> "PulseBatch":
        """A batch without pulses."""
        return PulseBatch(
            slot=np.zeros(0, np.int64),
            gps_time=np.zeros(0),
            origin=np.zeros((0, 3)),
            direction=np.zeros((0, 3)),
            scan_dir=np.zeros((0, 3)),
            scan_angle_deg=np.zeros(0),
            source_id=np.zeros(0, np.uint16),
        )

    @staticmethod
    def concat(batches: Sequence["PulseBatch"]) -> "PulseBatch":
        """Concatenate batches in the given order."""
        batches = list(batches)
        if not batches:
            return PulseBatch.empty()
        fields = _BATCH_FIELDS
        if any(b.geo_origin is not None for b in batches):
            batches = [b if b.geo_origin is not None else
                       PulseBatch(**{k: getattr(b, k) for k in _BATCH_FIELDS}, geo_origin=b.origin,
                                  geo_direction=b.direction, geo_scan_dir=b.scan_dir) for b in batches]
            fields = _BATCH_FIELDS + _GEO_FIELDS
        return PulseBatch(**{k: np.concatenate([getattr(b, k) for b in batches]) for k in fields})


_BATCH_FIELDS = ("slot", "gps_time", "origin", "direction", "scan_dir", "scan_angle_deg", "source_id")
_GEO_FIELDS = ("geo_origin", "geo_direction", "geo_scan_dir")


def _check_range(trajectory: Trajectory, start, stop) -> tuple[int, int]:
    start, stop = int(start), int(stop)
    if not 0 <= start <= stop <= trajectory.n_slots:
        raise ValueError(f"slot range [{start}, {stop}) outside [0, {trajectory.n_slots})")
    return start, stop


def _run(trajectory: Trajectory, pattern: DeflectorPattern, start, stop, mode, lo, hi, tan_off):
    return _emit(start, stop, trajectory.offsets, trajectory.t0, trajectory.p0, trajectory.vel, trajectory.rot, mode,
                 lo, hi, float(tan_off), *pattern.args())


def emit(trajectory: Trajectory, pattern: DeflectorPattern, start: int, stop: int) -> PulseBatch:
    """The emitted pulses of the slots ``[start, stop)``.

    Parameters
    ----------
    trajectory : Trajectory
        The platform's motion.
    pattern : DeflectorPattern
        The scanner's deflector.
    start, stop : int
        Slot range within ``[0, trajectory.n_slots]``.

    Returns
    -------
    PulseBatch
        With ``geo_*`` fields when the trajectory has noise.
    """
    start, stop = _check_range(trajectory, start, stop)
    if start == stop:
        return PulseBatch.empty()
    none = np.zeros(3)
    slot, _, seg, t, origin, direction, scan_dir, angle = _run(trajectory, pattern, start, stop, _EVERY, none, none,
                                                               0.0)
    source_id = trajectory.source_id[seg]
    if trajectory.noise is None:
        return PulseBatch(slot=slot, gps_time=t, origin=origin, direction=direction, scan_dir=scan_dir,
                          scan_angle_deg=angle, source_id=source_id)
    # traced along the perturbed geometry, georeferenced from the nominal one
    _, d_body, s_body, _ = deflect_pattern(pattern, slot - trajectory.offsets[seg])
    shift, rot = trajectory.perturbed(seg, t)
    return PulseBatch(slot=slot, gps_time=t, origin=origin + shift, direction=rotate(rot, d_body),
                      scan_dir=rotate(rot, s_body), scan_angle_deg=angle, source_id=source_id, geo_origin=origin,
                      geo_direction=direction, geo_scan_dir=scan_dir)


def emit_toward(trajectory: Trajectory, pattern: DeflectorPattern, start: int, stop: int, lo, hi, tan_off: float):
    """The emitted slots of ``[start, stop)`` and the pulses among them whose beam cone can
    meet a box.

    Gives what :func:`emit` followed by the cone test :func:`vlsforest.sim.beam.cone_meets_box`
    give; without trajectory noise in the compiled pass, which builds the pulse frame only for
    the pulses that can pass.

    Parameters
    ----------
    trajectory : Trajectory
        The platform's motion.
    pattern : DeflectorPattern
        The scanner's deflector.
    start, stop : int
        Slot range.
    lo, hi : array_like, shape (3,)
        The box; with a non-finite corner no pulse passes.
    tan_off : float
        Tangent of the cone's half angle.

    Returns
    -------
    slot : ndarray of int64
        Every emitted slot of the range.
    live : ndarray of int64
        Index into ``slot`` of the pulses that pass.
    batch : PulseBatch
        Those pulses.
    """
    lo = np.asarray(lo, np.float64)
    hi = np.asarray(hi, np.float64)
    start, stop = _check_range(trajectory, start, stop)
    if trajectory.noise is not None or start == stop:
        batch = emit(trajectory, pattern, start, stop)
        live = np.flatnonzero(cones_meet_box(batch.origin, batch.direction, lo, hi, float(tan_off)))
        return batch.slot, live, batch.subset(live)
    mode = _TOWARD if np.isfinite(lo).all() and np.isfinite(hi).all() else _NONE
    slot, live, seg, t, origin, direction, scan_dir, angle = _run(trajectory, pattern, start, stop, mode, lo, hi,
                                                                  tan_off)
    return slot, live, PulseBatch(slot=slot[live], gps_time=t, origin=origin, direction=direction, scan_dir=scan_dir,
                                  scan_angle_deg=angle, source_id=trajectory.source_id[seg])


# --------------------------------------------------------------------------- compiled pass


@numba.njit(cache=True, inline="always")
def _may_meet(k, seg, r, p0, vel, rot, prf, lo, hi, tan_off):
    """A cheap necessary condition of the cone test for an across-track beam at ``r`` radians.

    The beam direction is taken from float32 sine and cosine (error < 1e-6) and tested
    against the ball around the padded box (the exact test's box, padded as it pads it), with
    a margin that covers the direction error over the distance involved: when this returns
    False the exact test fails too, so its costlier float64 trigonometry can be skipped.
    """
    dt = k / prf
    o0 = p0[seg, 0] + dt * vel[seg, 0]
    o1 = p0[seg, 1] + dt * vel[seg, 1]
    o2 = p0[seg, 2] + dt * vel[seg, 2]
    r32 = np.float32(r)
    sa = np.float64(np.sin(r32))
    ca = np.float64(np.cos(r32))
    d0 = rot[0, 0, seg] * sa - rot[0, 2, seg] * ca
    d1 = rot[1, 0, seg] * sa - rot[1, 2, seg] * ca
    d2 = rot[2, 0, seg] * sa - rot[2, 2, seg] * ca
    h0, h1, h2 = 0.5 * (hi[0] - lo[0]), 0.5 * (hi[1] - lo[1]), 0.5 * (hi[2] - lo[2])
    v0, v1, v2 = 0.5 * (lo[0] + hi[0]) - o0, 0.5 * (lo[1] + hi[1]) - o1, 0.5 * (lo[2] + hi[2]) - o2
    vv = v0 * v0 + v1 * v1 + v2 * v2
    dist = np.sqrt(vv)
    pad = tan_off * (dist + np.sqrt(h0 * h0 + h1 * h1 + h2 * h2)) + 1e-6
    big_r = np.sqrt((h0 + pad) ** 2 + (h1 + pad) ** 2 + (h2 + pad) ** 2)
    proj = v0 * d0 + v1 * d1 + v2 * d2
    d2_min = vv if proj <= 0.0 else vv - proj * proj
    lim = big_r * (1.0 + 1e-9) + (dist + big_r) * 4e-6 + 1e-6
    return d2_min <= lim * lim


@numba.njit(cache=True)
def _line_window(seg, line, n_k, p0, vel, rot, prf, freq, first, period, lo, hi, tan_off):
    """The across-track beam angles of one scan line that can pass :func:`_may_meet`.

    Bounds, for every slot of line ``line`` of segment ``seg`` at once, the condition that
    :func:`_may_meet` (and so the exact cone test) checks per slot: the beam must come within
    the padded box's ball of the box centre. The origin moves during the line; the ball is
    grown by that motion and the padding taken at the farthest origin, so the bound holds for
    every slot of the line. The beam ``sin r · R₀ − cos r · R₂`` (``R`` the segment's attitude)
    makes an angle ≤ α with the direction to the centre exactly when ``M cos(r − φ) ≥ cos α``.

    Returns
    -------
    mode : int
        0: no slot of the line can pass; 1: any may (origin near the box, or no bound);
        2: only angles with ``|r − φ|`` (wrapped to ±π) ≤ ``beta``.
    phi, beta : float
    """
    if period > 0:  # polygon, rotating: the lines of :func:`~vlsforest.sim.deflector.sweep`
        k_lo = 0.0 if line == 0 else first + (line - 1.0) * period - 1.0
        k_hi = min(np.float64(n_k), (first if line == 0 else first + line * period) + 1.0)
    elif freq > 0.0:
        k_lo = max(0.0, np.floor(line * prf / freq) - 1.0)
        k_hi = min(np.float64(n_k), np.ceil((line + 1.0) * prf / freq) + 1.0)
    else:
        k_lo, k_hi = 0.0, np.float64(n_k)
    km = 0.5 * (k_lo + k_hi)
    dt = km / prf
    o0 = p0[seg, 0] + dt * vel[seg, 0]
    o1 = p0[seg, 1] + dt * vel[seg, 1]
    o2 = p0[seg, 2] + dt * vel[seg, 2]
    speed = np.sqrt(vel[seg, 0] ** 2 + vel[seg, 1] ** 2 + vel[seg, 2] ** 2)
    move = speed * (0.5 * (k_hi - k_lo) + 1.0) / prf * (1.0 + 1e-9) + 1e-9
    h0, h1, h2 = 0.5 * (hi[0] - lo[0]), 0.5 * (hi[1] - lo[1]), 0.5 * (hi[2] - lo[2])
    v0, v1, v2 = 0.5 * (lo[0] + hi[0]) - o0, 0.5 * (lo[1] + hi[1]) - o1, 0.5 * (lo[2] + hi[2]) - o2
    dist = np.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
    pad = tan_off * (dist + move + np.sqrt(h0 * h0 + h1 * h1 + h2 * h2)) + 1e-6
    big_r = np.sqrt((h0 + pad) ** 2 + (h1 + pad) ** 2 + (h2 + pad) ** 2)
    # _may_meet's own slack (for its float32 directions) at the farthest origin, then the motion
    rho = big_r * (1.0 + 1e-9) + (dist + move + big_r) * 4e-6 + 1e-6
    rho = rho * (1.0 + 1e-6) + move + 1e-6
    if not (dist > rho) or not np.isfinite(dist):
        return 1, 0.0, 0.0
    cos_a = np.sqrt(1.0 - (rho / dist) ** 2)
    a = (rot[0, 0, seg] * v0 + rot[1, 0, seg] * v1 + rot[2, 0, seg] * v2) / dist
    b = -(rot[0, 2, seg] * v0 + rot[1, 2, seg] * v1 + rot[2, 2, seg] * v2) / dist
    m = np.sqrt(a * a + b * b)
    c = cos_a - 1e-6  # slack for rounding in the attitude and in the slots' float32 trigonometry
    if m < c:
        return 0, 0.0, 0.0
    if c <= 0.0 or m <= 0.0:
        return 1, 0.0, 0.0
    return 2, np.arctan2(a, b), np.arccos(min(1.0, c / m)) + 1e-6


@numba.njit(cache=True)
def _emit(start, stop, offsets, t0, p0, vel, rot, mode, lo, hi, tan_off, kind, prf, freq, a, b, lines,
          sin_cone, cos_cone, az_r, el_r, el_deg):
    """The pulses of the slots ``[start, stop)`` on the nominal trajectory, slot by slot.

    ``mode`` says which emitted pulses get a frame: every one (``_EVERY``), those whose cone
    of half angle ``atan(tan_off)`` meets the box ``[lo, hi]`` (``_TOWARD``), none
    (``_NONE``). The deflector's arguments are those of :meth:`DeflectorPattern.args`. For
    across-track deflectors the box test first bounds the angles of each scan line
    (:func:`_line_window`) and each slot (:func:`_may_meet`) before it builds the frame.

    Returns
    -------
    slot : every emitted slot
    live : index into ``slot`` of the pulses with a frame
    seg, t, origin, direction, scan_dir, angle : of those pulses
    """
    n = stop - start
    slot = np.empty(n, np.int64)
    live = np.empty(n, np.int64)
    seg_o = np.empty(n, np.int64)
    t_o = np.empty(n)
    org = np.empty((n, 3))
    dr = np.empty((n, 3))
    sd = np.empty((n, 3))
    ang = np.empty(n)
    toward = mode == _TOWARD
    seg = 0
    while offsets[seg + 1] <= start:
        seg += 1
    ne = 0
    nl = 0
    w_seg, w_line, w_mode, w_phi, w_beta = -1, -1.0, 1, 0.0, 0.0
    for sl in range(start, stop):
        while offsets[seg + 1] <= sl:
            seg += 1
        k = sl - offsets[seg]
        if mode == _NONE:
            if kind != TLS:
                _, _, angle, _ = sweep(kind, k, prf, freq, a, b, lines)
                if np.isnan(angle):
                    continue
            slot[ne] = sl
            ne += 1
            continue
        if kind == TLS:
            v0, v1, v2, w0, w1, w2, angle = node_frame(k, az_r, el_r, el_deg)
        else:
            line, frac, angle, back = sweep(kind, k, prf, freq, a, b, lines)
            if np.isnan(angle):
                continue
            if kind == CONIC:
                v0, v1, v2, w0, w1, w2, angle = conic_frame(frac, sin_cone, cos_cone)
            else:
                r = np.radians(angle)
                if toward:
                    if seg != w_seg or line != w_line:
                        w_seg, w_line = seg, line
                        w_mode, w_phi, w_beta = _line_window(seg, line, offsets[seg + 1] - offsets[seg], p0, vel,
                                                             rot, prf, freq, lines[0], lines[1], lo, hi,
                                                             tan_off)
                    if w_mode != 1:
                        off = r - w_phi
                        if off > np.pi:
                            off -= 2.0 * np.pi
                        elif off < -np.pi:
                            off += 2.0 * np.pi
                        if w_mode == 0 or abs(off) > w_beta:
                            slot[ne] = sl  # emitted; the whole scan line's bound says its beam misses the box
                            ne += 1
                            continue
                    if not _may_meet(k, seg, r, p0, vel, rot, prf, lo, hi, tan_off):
                        slot[ne] = sl  # emitted, but its beam surely misses the box: no frame needed
                        ne += 1
                        continue
                v0, v1, v2, w0, w1, w2 = across_track_frame(r, back)
        slot[ne] = sl
        ne += 1
        dt = k / prf
        o0 = p0[seg, 0] + dt * vel[seg, 0]
        o1 = p0[seg, 1] + dt * vel[seg, 1]
        o2 = p0[seg, 2] + dt * vel[seg, 2]
        d0 = rot[0, 0, seg] * v0 + rot[0, 1, seg] * v1 + rot[0, 2, seg] * v2
        d1 = rot[1, 0, seg] * v0 + rot[1, 1, seg] * v1 + rot[1, 2, seg] * v2
        d2 = rot[2, 0, seg] * v0 + rot[2, 1, seg] * v1 + rot[2, 2, seg] * v2
        if toward and not cone_meets_box(o0, o1, o2, d0, d1, d2, lo, hi, tan_off):
            continue
        live[nl] = ne - 1
        seg_o[nl] = seg
        t_o[nl] = t0[seg] + dt
        org[nl, 0], org[nl, 1], org[nl, 2] = o0, o1, o2
        dr[nl, 0], dr[nl, 1], dr[nl, 2] = d0, d1, d2
        sd[nl, 0] = rot[0, 0, seg] * w0 + rot[0, 1, seg] * w1 + rot[0, 2, seg] * w2
        sd[nl, 1] = rot[1, 0, seg] * w0 + rot[1, 1, seg] * w1 + rot[1, 2, seg] * w2
        sd[nl, 2] = rot[2, 0, seg] * w0 + rot[2, 1, seg] * w1 + rot[2, 2, seg] * w2
        ang[nl] = angle
        nl += 1
    return (slot[:ne].copy(), live[:nl].copy(), seg_o[:nl].copy(), t_o[:nl].copy(), org[:nl].copy(),
            dr[:nl].copy(), sd[:nl].copy(), ang[:nl].copy())
