"""The platform's trajectory: position and attitude over the active legs / scans, and its noise.

Frames and attitude
-------------------
World frame: x east, y north, z up (the scene's coordinates). Body frame: x right, y forward,
z up. Heading is the compass azimuth of the forward axis, clockwise from +y (north); roll is
positive right wing down, pitch positive nose up; body → world is ``H(heading)·P(pitch)·R(roll)``
(:func:`body_to_world`). A linear platform flies level (roll = pitch = 0); a static one pitches
its head by the scan's tilt (:mod:`vlsforest.sim.platform`).

Trajectory noise
----------------
Zero-mean, smooth perturbations of x, y, z (``position_sigma_m``, each axis) and roll, pitch,
yaw (``attitude_sigma_deg``, each angle). Each of the six channels is a deterministic function
of GPS time, ``σ·sqrt(2/K)·Σ_j cos(ω_j t + φ_j)`` with K = 64 terms, ``φ_j ~ U(0, 2π)`` and
``ω_j ~ |N(0, 1/τ²)|`` drawn from the survey seed: a Gaussian process sample with
autocorrelation ``exp(−Δt²/(2τ²))`` (τ = ``correlation_s``) whose time-averaged variance over a
long survey is exactly σ². It is evaluated on a node grid of spacing τ/16 and interpolated
linearly (error ~1e-3 σ), which keeps the cost independent of the pulse count. It shifts the
pulse origin and rotates the beam (``H(h+δyaw)·P(δpitch)·R(δroll)``) for the ray tracing, while
the returns are georeferenced from the nominal trajectory
(:meth:`vlsforest.sim.pulses.PulseBatch.georeferenced`), as a system with a GNSS/INS error
records them: the points of a strip move together, by the position error plus range times the
attitude error. A static scan takes the noise at its start time for the whole scan (a
registration error). Without the ``trajectory_noise`` key, or with σ = 0, it is exactly zero.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import pandas as pd

__all__ = ["SmoothNoise", "Trajectory", "TrajectoryNoise", "body_to_world", "rotate"]

_NOISE_TERMS = 64
_NOISE_NODES_PER_TAU = 16


@dataclass(frozen=True)
class TrajectoryNoise:
    """Settings of the smooth trajectory perturbation."""

    position_sigma_m: float = 0.0
    attitude_sigma_deg: float = 0.0
    correlation_s: float = 1.0

    @property
    def enabled(self) -> bool:
        return self.position_sigma_m > 0 or self.attitude_sigma_deg > 0


def body_to_world(heading, pitch, roll) -> list:
    """Entries ``[[m00, m01, m02], …]`` of ``H(heading)·P(pitch)·R(roll)`` (radians, arrays).

    H = [[ch, sh, 0], [−sh, ch, 0], [0, 0, 1]], P = [[1, 0, 0], [0, cp, −sp], [0, sp, cp]],
    R = [[cr, 0, sr], [0, 1, 0], [−sr, 0, cr]]. Columns of the product are the body's right,
    forward and up axes in the world frame.
    """
    ch, sh = np.cos(heading), np.sin(heading)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cr, sr = np.cos(roll), np.sin(roll)
    return [
        [ch * cr + sh * sp * sr, sh * cp, ch * sr - sh * sp * cr],
        [-sh * cr + ch * sp * sr, ch * cp, -sh * sr - ch * sp * cr],
        [-cp * sr, sp, cp * cr],
    ]


def rotate(m: list, v: np.ndarray) -> np.ndarray:
    """Rotate vectors v (n, 3) by per-vector matrix entries m (each an array of length n).

    Written element by element (no BLAS), so each result depends on its own inputs only; the
    compiled pulse pass (:mod:`vlsforest.sim.pulses`) sums in the same order.
    """
    out = np.empty_like(v)
    for i in range(3):
        out[:, i] = m[i][0] * v[:, 0] + m[i][1] * v[:, 1] + m[i][2] * v[:, 2]
    return out


class SmoothNoise:
    """Six smooth zero-mean channels (x, y, z in m; roll, pitch, yaw in deg) of GPS time.

    Parameters
    ----------
    noise : TrajectoryNoise
        The standard deviations and the correlation time.
    seed : int
        The survey seed: the same seed gives the same realisation.
    """

    def __init__(self, noise: TrajectoryNoise, seed: int):
        self.noise = noise
        rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(0x7E1A,)))
        tau = noise.correlation_s
        self.omega = np.abs(rng.standard_normal((6, _NOISE_TERMS))) / tau
        self.phase = rng.uniform(0.0, 2.0 * np.pi, (6, _NOISE_TERMS))
        sig = [noise.position_sigma_m] * 3 + [noise.attitude_sigma_deg] * 3
        self.amp = np.asarray(sig) * math.sqrt(2.0 / _NOISE_TERMS)
        self.dt = tau / _NOISE_NODES_PER_TAU

    def _nodes(self, idx: np.ndarray) -> np.ndarray:
        x = idx.astype(np.float64) * self.dt
        out = np.zeros((len(idx), 6))
        for c in range(6):
            if self.amp[c] == 0:
                continue
            acc = np.zeros(len(idx))
            for j in range(_NOISE_TERMS):
                acc += np.cos(self.omega[c, j] * x + self.phase[c, j])
            out[:, c] = self.amp[c] * acc
        return out

    def __call__(self, t: np.ndarray) -> np.ndarray:
        """Noise at times t, shape (len(t), 6)."""
        t = np.asarray(t, dtype=np.float64)
        if len(t) == 0:
            return np.zeros((0, 6))
        u = t / self.dt
        lo = np.floor(u).astype(np.int64)
        w = (u - lo)[:, None]
        first, last = int(lo.min()), int(lo.max())
        if last - first < 4 * len(t):  # dense (the usual case): every node of the span
            vals = self._nodes(np.arange(first, last + 2, dtype=np.int64))
            i_lo = lo - first
            i_hi = i_lo + 1
        else:  # sparse times: only the nodes needed
            nodes, inv = np.unique(np.concatenate([lo, lo + 1]), return_inverse=True)
            vals = self._nodes(nodes)
            i_lo, i_hi = inv[: len(t)], inv[len(t):]
        v_lo = vals[i_lo]
        return v_lo + w * (vals[i_hi] - v_lo)


class Trajectory:
    """Position and attitude of a platform over its active legs (linear) or scans (static).

    The active legs / scans are the segments, numbered from 0 in time order. Segment ``s``
    holds the pulse slots ``offsets[s] … offsets[s + 1] − 1``; slot k of it fires at
    ``t0[s] + k/PRF`` from ``p0[s] + (k/PRF)·vel[s]``, with the segment's attitude ``rot[:, :, s]``
    (body → world), plus the trajectory noise where there is one.

    Parameters
    ----------
    segments : sequence of Leg or ScanPosition
        The active legs (linear) or the scans (static), in time order.
    linear : bool
        A linear platform (legs) or a static one (scans).
    noise : TrajectoryNoise
    seed : int
        Seed of the noise realisation.

    Attributes
    ----------
    linear : bool
    offsets : ndarray of int64, shape (n + 1,)
        First slot of each segment, then the number of slots.
    n_slots : int
    t0, duration_s : ndarray, shape (n,)
        GPS time at the start of each segment and its duration, s.
    source_id : ndarray of uint16, shape (n,)
    p0, vel : ndarray, shape (n, 3)
        Position at the start of each segment and velocity (0 for scans).
    heading, tilt : ndarray, shape (n,)
        Heading and pitch of each segment, radians.
    rot : ndarray, shape (3, 3, n)
        Nominal body → world matrix of each segment (C-contiguous).
    noise : SmoothNoise or None
        The noise realisation; None without trajectory noise.
    """

    def __init__(self, segments: Sequence, linear: bool, noise: TrajectoryNoise, seed: int):
        self.linear = bool(linear)
        self.offsets = np.array([s.slot_offset for s in segments] + [sum(s.n_slots for s in segments)],
                                dtype=np.int64)
        self.n_slots = int(self.offsets[-1])
        self.t0 = np.array([s.t_start for s in segments])
        self.duration_s = np.array([s.duration_s for s in segments], dtype=np.float64)
        self.source_id = np.array([s.source_id for s in segments], dtype=np.uint16)
        if self.linear:
            self.p0 = np.array([s.start for s in segments], dtype=np.float64)
            self.vel = np.array([(s.end - s.start) / np.linalg.norm(s.end - s.start) * s.speed_mps for s in segments])
            self.tilt = np.zeros(len(segments))
        else:
            self.p0 = np.array([s.position for s in segments], dtype=np.float64)
            self.vel = np.zeros((len(segments), 3))
            self.tilt = np.radians([s.tilt_deg for s in segments])
        self.heading = np.radians([s.heading_deg for s in segments])
        self.noise = SmoothNoise(noise, seed) if noise.enabled else None
        entries = body_to_world(self.heading, self.tilt, np.zeros(len(segments)))
        self.rot = np.ascontiguousarray(
            np.array([[np.asarray(e, np.float64) for e in row] for row in entries]).reshape(3, 3, -1))

    def segment_of(self, slots: np.ndarray) -> np.ndarray:
        """Segment index of each slot."""
        return np.searchsorted(self.offsets, slots, side="right") - 1

    def noise_at(self, seg: np.ndarray, t: np.ndarray) -> np.ndarray:
        """The six noise channels at GPS times ``t`` of segments ``seg`` (a scan: its start time).

        Returns
        -------
        ndarray, shape (m, 6)
            x, y, z offsets (m), roll, pitch, yaw (deg).
        """
        return self.noise(t if self.linear else self.t0[seg])

    def perturbed(self, seg: np.ndarray, t: np.ndarray):
        """The position offsets and body → world matrices of pulses with the trajectory noise.

        Parameters
        ----------
        seg : ndarray of int
            Segment of each pulse.
        t : ndarray
            GPS time of each pulse.

        Returns
        -------
        shift : ndarray, shape (m, 3)
            Added to the nominal origins.
        rot : list
            Per-pulse matrix entries (:func:`body_to_world`), for :func:`rotate`.
        """
        nz = self.noise_at(seg, t)
        roll = np.zeros(len(seg)) + np.radians(nz[:, 3])
        pitch = self.tilt[seg] + np.radians(nz[:, 4])
        heading = self.heading[seg] + np.radians(nz[:, 5])
        return nz[:, :3], body_to_world(heading, pitch, roll)

    def sample(self, rate_hz: float = 10.0, nominal: bool = False) -> pd.DataFrame:
        """Platform positions and attitude over the segments.

        Parameters
        ----------
        rate_hz : float
            Sampling rate (> 0); each segment is sampled from its start every ``1/rate_hz`` s,
            plus its end.
        nominal : bool
            Leave out the trajectory noise (by default it is included, as it is in the pulses).

        Returns
        -------
        pandas.DataFrame
            Columns ``gps_time, x, y, z, roll_deg, pitch_deg, heading_deg, source_id``;
            heading in [0, 360).
        """
        if not rate_hz > 0:
            raise ValueError("rate_hz must be > 0")
        parts = []
        for i, duration in enumerate(self.duration_s):
            duration = float(duration)
            n = int(math.ceil(duration * rate_hz - 1e-9))
            dt = np.arange(n) / rate_hz
            dt = np.append(dt[dt < duration], duration)
            parts.append((np.full(len(dt), i), dt))
        seg = np.concatenate([p[0] for p in parts]).astype(np.int64)
        dt = np.concatenate([p[1] for p in parts])
        t = self.t0[seg] + dt
        xyz = self.p0[seg] + dt[:, None] * self.vel[seg]
        roll = np.zeros(len(t))
        pitch = np.degrees(self.tilt[seg])
        heading = np.degrees(self.heading[seg])
        if self.noise is not None and not nominal:
            nz = self.noise_at(seg, t)
            xyz = xyz + nz[:, :3]
            roll = roll + nz[:, 3]
            pitch = pitch + nz[:, 4]
            heading = heading + nz[:, 5]
        return pd.DataFrame(
            {
                "gps_time": t,
                "x": xyz[:, 0],
                "y": xyz[:, 1],
                "z": xyz[:, 2],
                "roll_deg": roll,
                "pitch_deg": pitch,
                "heading_deg": np.mod(heading, 360.0),
                "source_id": self.source_id[seg],
            }
        )
