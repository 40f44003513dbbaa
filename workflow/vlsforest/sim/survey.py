"""Surveys: SURVEY.yaml parsing, platforms, pulse slots and trajectories.

A survey is a scanner (a preset of :mod:`vlsforest.sim.scanner` with overrides) carried by a
platform. :func:`load_survey` reads SURVEY.yaml::

    scanner: riegl_vq780i              # preset name, or a mapping of ScannerSettings fields
                                       # (custom scanner, see scanner_from_dict)
    overrides: {prf_hz: 1.0e6, beam_divergence_fwhm_mrad: [1.6, 0.5], ...}   # optional
    platform:
      type: linear                     # default; or static (TLS)
      speed_mps: 51                    # default speed of the legs
      legs: [{start: [x, y, z], end: [x, y, z], active: true, speed_mps: 51}, ...]  # speed optional
    # platform: {type: static, positions: [{position: [x, y, z], heading_deg: 0, tilt_deg: 0}]}
    trajectory_noise: {position_sigma_m: 0.0, attitude_sigma_deg: 0.0, correlation_s: 1.0}
    seed: 0
    detector: {...}                    # kept as a plain dict, not validated here
    output: {...}                      # likewise

Geometry and time (deliberate choices)
--------------------------------------
World frame: x east, y north, z up (the scene's coordinates). Body frame: x right, y forward,
z up. Heading is the compass azimuth of the forward axis, clockwise from +y (north); roll is
positive right wing down, pitch positive nose up; body → world is ``H(heading)·P(pitch)·R(roll)``.

*Linear platform.* GPS time is 0 at the start of the first leg. The platform flies the legs in
order, each at its own ``speed_mps`` (default: the platform's), inactive legs included (time
passes, no slots); when a leg does not start where the previous one ended, the straight transit
to it also takes time (distance / the leg's speed) without slots. Slot k of an active leg fires at ``t_leg + k/PRF`` from
``start + (k/PRF)·speed·u`` (u = the leg's unit vector) for every ``k/PRF`` < leg duration, so a
slot every 1/PRF tick and the platform advances ``speed/PRF`` per slot. Heading = the azimuth of
the leg's horizontal direction (a vertical leg keeps the previous heading, 0 for the first);
roll and pitch are 0 (level flight, also on climbing legs). Every active leg starts a new scan
line at slot 0 (see :func:`vlsforest.sim.scanner.deflect`) and is one flight line: its
``source_id`` counts the active legs from 1.

*Static platform (TLS).* Each position is one scan: the full azimuth × elevation grid of the
scanner, ``n_az·n_el`` slots, all emitted, at 1/PRF each. Scans follow each other without a
gap. ``heading_deg`` turns the head's azimuth zero (clockwise from north), ``tilt_deg`` tilts the
head about its own x (right) axis, upwards for positive values: body → world is
``H(heading)·P(tilt)``. ``source_id`` counts the positions from 1.

*Trajectory noise.* Zero-mean, smooth perturbations of x, y, z (``position_sigma_m``, each
axis) and roll, pitch, yaw (``attitude_sigma_deg``, each angle). Each of the six channels is a
deterministic function of GPS time, ``σ·sqrt(2/K)·Σ_j cos(ω_j t + φ_j)`` with K = 64 terms,
``φ_j ~ U(0, 2π)`` and ``ω_j ~ |N(0, 1/τ²)|`` drawn from the survey seed: a Gaussian process
sample with autocorrelation ``exp(−Δt²/(2τ²))`` (τ = ``correlation_s``) whose time-averaged
variance over a long survey is exactly σ². It is evaluated on a node grid of spacing τ/16 and
interpolated linearly (error ~1e-3 σ), which keeps the cost independent of the pulse count.
It shifts the pulse origin and rotates the beam (``H(h+δyaw)·P(δpitch)·R(δroll)``) for the
ray tracing, while the returns are georeferenced from the nominal trajectory
(:meth:`PulseBatch.georeferenced`), as a system with a GNSS/INS error records them: the points
of a strip move together, by the position error plus range times the attitude error. A static
scan takes the noise at its start time for the whole scan (a registration error). Without the
``trajectory_noise`` key, or with σ = 0, it is exactly zero.

Pulses are computed from the global slot index alone, so :meth:`Survey.pulses` gives the same
result however the slot range is chunked.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numba
import numpy as np
import pandas as pd
import yaml

from vlsforest.errors import ConfigError
from vlsforest.sim.beam import cone_meets_box, cones_meet_box
from vlsforest.sim.scanner import (
    ScannerSettings,
    apply_overrides,
    deflect,
    emission_half_angle_deg,
    scanner_from_dict,
    scanner_from_preset,
    tls_grid,
    validate_scanner,
)

__all__ = ["Leg", "PulseBatch", "ScanPosition", "Survey", "TrajectoryNoise", "load_survey", "survey_from_dict"]

_TOP_KEYS = ("scanner", "overrides", "platform", "trajectory_noise", "seed", "detector", "output")
_NOISE_TERMS = 64
_NOISE_NODES_PER_TAU = 16


# --------------------------------------------------------------------------- data classes


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


@dataclass(frozen=True, eq=False)
class Leg:
    """One leg of a linear platform (times in s, coordinates in m)."""

    start: np.ndarray
    end: np.ndarray
    active: bool
    t_start: float
    duration_s: float
    heading_deg: float
    source_id: int  # 0 for inactive legs
    slot_offset: int
    n_slots: int
    speed_mps: float = 0.0


@dataclass(frozen=True, eq=False)
class ScanPosition:
    """One scan of a static platform."""

    position: np.ndarray
    heading_deg: float
    tilt_deg: float
    t_start: float
    duration_s: float
    source_id: int
    slot_offset: int
    n_slots: int


@dataclass(frozen=True)
class TrajectoryNoise:
    """Settings of the smooth trajectory perturbation."""

    position_sigma_m: float = 0.0
    attitude_sigma_deg: float = 0.0
    correlation_s: float = 1.0

    @property
    def enabled(self) -> bool:
        return self.position_sigma_m > 0 or self.attitude_sigma_deg > 0


# --------------------------------------------------------------------------- rotations


def _body_to_world(heading, pitch, roll) -> list:
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


def _apply(m: list, v: np.ndarray) -> np.ndarray:
    """Rotate vectors v (n, 3) by per-vector matrix entries m (each an array of length n).

    Written element by element (no BLAS), so each result depends on its own inputs only.
    """
    out = np.empty_like(v)
    for i in range(3):
        out[:, i] = m[i][0] * v[:, 0] + m[i][1] * v[:, 1] + m[i][2] * v[:, 2]
    return out


# --------------------------------------------------------------------------- noise


class _SmoothNoise:
    """Six smooth zero-mean channels (x, y, z in m; roll, pitch, yaw in deg) of GPS time."""

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


# --------------------------------------------------------------------------- survey


class Survey:
    """A parsed survey: scanner, platform, slots, pulses and trajectory.

    Build it with :func:`load_survey` or :func:`survey_from_dict`.

    Attributes
    ----------
    scanner : ScannerSettings
    detector : dict
        The ``detector`` section as given (not validated here).
    output : dict
        The ``output`` section as given (not validated here).
    seed : int
    platform_type : str
        ``linear`` or ``static``.
    speed_mps : float or None
        Platform speed (linear only).
    legs : list of Leg
        All legs, inactive ones included (linear only, else empty).
    positions : list of ScanPosition
        Scan positions (static only, else empty).
    noise : TrajectoryNoise
    base_dir : Path or None
        Directory for resolving relative paths in ``detector``/``output``.
    n_slots : int
        Total number of pulse slots (emitted or not) over active legs / scans.
    """

    def __init__(self, scanner, platform_type, speed_mps, legs, positions, noise, seed, detector, output,
                 base_dir=None):
        self.scanner: ScannerSettings = scanner
        self.platform_type: str = platform_type
        self.speed_mps = speed_mps
        self.legs: list[Leg] = legs
        self.positions: list[ScanPosition] = positions
        self.noise: TrajectoryNoise = noise
        self.seed: int = seed
        self.detector: dict = detector
        self.output: dict = output
        self.base_dir = base_dir
        segs = [lg for lg in legs if lg.active] if platform_type == "linear" else positions
        self._segs = segs
        self._offsets = np.array([s.slot_offset for s in segs] + [sum(s.n_slots for s in segs)], dtype=np.int64)
        self.n_slots: int = int(self._offsets[-1])
        self._t0 = np.array([s.t_start for s in segs])
        self._src = np.array([s.source_id for s in segs], dtype=np.uint16)
        if platform_type == "linear":
            self._p0 = np.array([s.start for s in segs], dtype=np.float64)
            self._vel = np.array([(s.end - s.start) / np.linalg.norm(s.end - s.start) * s.speed_mps for s in segs])
            self._tilt = np.zeros(len(segs))
        else:
            self._p0 = np.array([s.position for s in segs], dtype=np.float64)
            self._vel = np.zeros((len(segs), 3))
            self._tilt = np.radians([s.tilt_deg for s in segs])
        self._heading = np.radians([s.heading_deg for s in segs])
        self._noise = _SmoothNoise(noise, seed) if noise.enabled else None
        self._rot = _body_to_world(self._heading, self._tilt, np.zeros(len(segs)))  # per segment

    # ---------------------------------------------------------------- public API

    @property
    def n_sources(self) -> int:
        """Number of flight lines / scan positions (the largest ``source_id``)."""
        return len(self._segs)

    @property
    def duration_s(self) -> float:
        """GPS time at the end of the last leg / scan."""
        if self.platform_type == "linear":
            last = self.legs[-1]
        else:
            last = self.positions[-1]
        return last.t_start + last.duration_s

    def source_slot_ranges(self) -> list[tuple[int, int, int]]:
        """``(source_id, first_slot, stop_slot)`` of every flight line / scan."""
        return [(int(s.source_id), int(s.slot_offset), int(s.slot_offset + s.n_slots)) for s in self._segs]

    def pulses(self, start: int, stop: int) -> PulseBatch:
        """The emitted pulses of the slots ``[start, stop)``.

        Vectorised over slots; the result depends only on the slot indices, not on how a
        range is split into calls.
        """
        start, stop = int(start), int(stop)
        if not 0 <= start <= stop <= self.n_slots:
            raise ValueError(f"slot range [{start}, {stop}) outside [0, {self.n_slots})")
        if start == stop:
            return PulseBatch.empty()
        slots = np.arange(start, stop, dtype=np.int64)
        seg = np.searchsorted(self._offsets, slots, side="right") - 1
        k = slots - self._offsets[seg]
        emitted, d_body, s_body, angle = deflect(self.scanner, k)
        slots, seg, k = slots[emitted], seg[emitted], k[emitted]
        dt = k / self.scanner.prf_hz
        t = self._t0[seg] + dt
        origin = self._p0[seg] + dt[:, None] * self._vel[seg]
        rot = [[e[seg] for e in row] for row in self._rot]  # the nominal attitude
        geo = {}
        if self._noise is not None:
            # traced along the perturbed geometry, georeferenced from the nominal one
            geo = dict(geo_origin=origin, geo_direction=_apply(rot, d_body), geo_scan_dir=_apply(rot, s_body))
            heading = self._heading[seg]
            pitch = self._tilt[seg]
            roll = np.zeros(len(seg))
            tn = t if self.platform_type == "linear" else self._t0[seg]
            nz = self._noise(tn)
            origin = origin + nz[:, :3]
            roll = roll + np.radians(nz[:, 3])
            pitch = pitch + np.radians(nz[:, 4])
            heading = heading + np.radians(nz[:, 5])
            rot = _body_to_world(heading, pitch, roll)
        direction = _apply(rot, d_body)
        scan_dir = _apply(rot, s_body)
        return PulseBatch(
            slot=slots,
            gps_time=t,
            origin=origin,
            direction=direction,
            scan_dir=scan_dir,
            scan_angle_deg=np.asarray(angle, dtype=np.float64),
            source_id=self._src[seg],
            **geo,
        )

    def pulses_toward(self, start: int, stop: int, lo, hi, tan_off: float):
        """The emitted slots of ``[start, stop)`` and the pulses among them whose beam cone can
        meet a box.

        Gives what :meth:`pulses` followed by the cone test
        :func:`vlsforest.sim.beam.cone_meets_box` give, but for the usual surveys (no trajectory
        noise; polygon, rotating, oscillating or TLS deflector) in one compiled pass that builds
        the full pulse frame only for the pulses that pass (most slots of a ULS survey over a
        plot are either not emitted or aimed away from the scene).

        Parameters
        ----------
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
        start, stop = int(start), int(stop)
        finite = bool(np.isfinite(lo).all() and np.isfinite(hi).all())
        s = self.scanner
        kind = {"polygon": 0, "rotating": 1, "oscillating": 2, "tls": 3}.get(s.deflector, -1)
        if self._noise is not None or kind < 0 or not 0 <= start <= stop <= self.n_slots or start == stop:
            batch = self.pulses(start, stop)
            live = np.flatnonzero(cones_meet_box(batch.origin, batch.direction, lo, hi, float(tan_off)))
            return batch.slot, live, batch.subset(live)
        if kind == 0:
            a, b = -s.max_scan_angle_deg, 2.0 * s.max_scan_angle_deg
            window = emission_half_angle_deg(s) * (1 + 1e-12)
        elif kind == 1:
            a, b = -180.0, 360.0
            window = emission_half_angle_deg(s) * (1 + 1e-12)
        elif kind == 2:
            a, b = s.scan_angle_deg, 2.0 * s.scan_angle_deg
            window = np.inf
        if kind == 3:
            az, el = tls_grid(s)
            az_r, el_r, el_deg = np.radians(az), np.radians(el), np.asarray(el, np.float64)
            freq = 0.0
            a = b = window = 0.0
        else:
            az_r = el_r = el_deg = np.zeros(0)
            freq = float(s.scan_freq_hz)
        rot = np.array([[np.asarray(e, np.float64) for e in row] for row in self._rot]).reshape(3, 3, -1)
        out = _pulses_toward(start, stop, self._offsets, self._t0, self._p0, self._vel, np.ascontiguousarray(rot),
                             kind, freq, float(s.prf_hz), float(a), float(b), float(window), az_r, el_r, el_deg, finite,
                             lo, hi, float(tan_off))
        slot, live, seg, t, origin, direction, scan_dir, angle = out
        return slot, live, PulseBatch(slot=slot[live], gps_time=t, origin=origin, direction=direction,
                                      scan_dir=scan_dir, scan_angle_deg=angle, source_id=self._src[seg])

    def trajectory(self, rate_hz: float = 10.0, nominal: bool = False) -> pd.DataFrame:
        """Platform positions and attitude over the active legs / scans.

        Parameters
        ----------
        rate_hz : float
            Sampling rate; each active leg / scan is sampled from its start every
            ``1/rate_hz`` s, plus its end.
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
        for i, s in enumerate(self._segs):
            n = int(math.ceil(s.duration_s * rate_hz - 1e-9))
            dt = np.arange(n) / rate_hz
            dt = np.append(dt[dt < s.duration_s], s.duration_s)
            parts.append((np.full(len(dt), i), dt))
        seg = np.concatenate([p[0] for p in parts]).astype(np.int64)
        dt = np.concatenate([p[1] for p in parts])
        t = self._t0[seg] + dt
        xyz = self._p0[seg] + dt[:, None] * self._vel[seg]
        roll = np.zeros(len(t))
        pitch = np.degrees(self._tilt[seg])
        heading = np.degrees(self._heading[seg])
        if self._noise is not None and not nominal:
            nz = self._noise(t if self.platform_type == "linear" else self._t0[seg])
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
                "source_id": self._src[seg],
            }
        )

    def swath_width(self, ground_z: float) -> np.ndarray:
        """Across-track swath width on flat ground at height ``ground_z``, per active leg.

        Uses the mean platform height of each leg: ``2·h·tan(θ)`` with θ the emitted half
        angle (:func:`~vlsforest.sim.scanner.emission_half_angle_deg`; ``inf`` from 90° on).

        Returns
        -------
        ndarray, shape (n_active_legs,)
        """
        if self.platform_type != "linear":
            raise ValueError("swath_width is defined for linear (airborne) platforms only")
        theta = emission_half_angle_deg(self.scanner)
        out = []
        for lg in self._segs:
            h = 0.5 * (lg.start[2] + lg.end[2]) - ground_z
            if h <= 0:
                raise ValueError(f"leg {lg.source_id} is not above ground_z = {ground_z}")
            out.append(math.inf if theta >= 90.0 else 2.0 * h * math.tan(math.radians(theta)))
        return np.array(out)


# --------------------------------------------------------------------------- compiled pulses


@numba.njit(cache=True, inline="always")
def _may_meet(sl, k, seg, r, p0, vel, rot, prf, lo, hi, tan_off):
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
def _line_window(seg, line, n_k, p0, vel, rot, prf, freq, lo, hi, tan_off):
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
    if freq > 0.0:
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
def _pulses_toward(start, stop, offsets, t0, p0, vel, rot, kind, freq, prf, a, b, window, az_r, el_r, el_deg, finite,
                   lo, hi, tan_off):
    """:meth:`Survey.pulses_toward` without trajectory noise, slot by slot.

    Every operation repeats, in the same order and precision, what :meth:`Survey.pulses`,
    :func:`~vlsforest.sim.scanner.deflect` (``kind`` 0 polygon, 1 rotating, 2 oscillating,
    3 tls) and the cone test compute on arrays, so the pulses are bit-identical. For the
    across-track deflectors the angle is ``a + b·phase`` (oscillating: ``±(a − b·phase)`` on
    alternate lines) and a pulse is emitted when ``|angle| <= window``; ``az_r``/``el_r`` are
    the TLS grid in radians, ``el_deg`` its elevations in degrees.
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
    n_el = el_r.shape[0]
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
        if kind == 3:
            ia = k // n_el
            ie = k - ia * n_el
            ar = az_r[ia]
            er = el_r[ie]
            sa, ca, se, ce = np.sin(ar), np.cos(ar), np.sin(er), np.cos(er)
            v0, v1, v2 = ce * sa, ce * ca, se
            w0, w1, w2 = -se * sa, -se * ca, ce
            angle = el_deg[ie]
        else:
            x = np.float64(k) * freq
            line = np.floor(x / prf)
            frac = (x - line * prf) / prf
            if frac < 0:
                line -= 1
                frac += 1
            if frac >= 1:
                line += 1
                frac -= 1
            back = False
            if kind == 2:
                back = (np.int64(line) % 2) == 1
                angle = a - b * frac if back else -a + b * frac
            else:
                angle = a + b * frac
                if not abs(angle) <= window:
                    continue
            r = np.radians(angle)
            if finite and (seg != w_seg or line != w_line):
                w_seg, w_line = seg, line
                w_mode, w_phi, w_beta = _line_window(seg, line, offsets[seg + 1] - offsets[seg], p0, vel, rot, prf,
                                                     freq, lo, hi, tan_off)
            if finite and w_mode != 1:
                off = r - w_phi
                if off > np.pi:
                    off -= 2.0 * np.pi
                elif off < -np.pi:
                    off += 2.0 * np.pi
                if w_mode == 0 or abs(off) > w_beta:
                    slot[ne] = sl  # emitted; the whole scan line's bound says its beam misses the box
                    ne += 1
                    continue
            if not finite or not _may_meet(sl, k, seg, r, p0, vel, rot, prf, lo, hi, tan_off):
                slot[ne] = sl  # emitted, but its beam surely misses the box: no frame needed
                ne += 1
                continue
            sa, ca = np.sin(r), np.cos(r)
            v0, v1, v2 = sa, 0.0, -ca
            w0, w1, w2 = ca, 0.0, sa
            if back:
                w0, w1, w2 = -w0, -w1, -w2
        slot[ne] = sl
        ne += 1
        dt = k / prf
        o0 = p0[seg, 0] + dt * vel[seg, 0]
        o1 = p0[seg, 1] + dt * vel[seg, 1]
        o2 = p0[seg, 2] + dt * vel[seg, 2]
        d0 = rot[0, 0, seg] * v0 + rot[0, 1, seg] * v1 + rot[0, 2, seg] * v2
        d1 = rot[1, 0, seg] * v0 + rot[1, 1, seg] * v1 + rot[1, 2, seg] * v2
        d2 = rot[2, 0, seg] * v0 + rot[2, 1, seg] * v1 + rot[2, 2, seg] * v2
        if not (finite and cone_meets_box(o0, o1, o2, d0, d1, d2, lo, hi, tan_off)):
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


# --------------------------------------------------------------------------- parsing


class _Loader(yaml.SafeLoader):
    """Safe YAML loader that rejects duplicate keys and reads ``1e6`` as a float."""

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            try:
                dup = key in seen
            except TypeError:
                dup = False
            if dup:
                raise ConfigError(f"line {key_node.start_mark.line + 1}: duplicate key {key!r}")
            try:
                seen.add(key)
            except TypeError:
                pass
        return super().construct_mapping(node, deep=deep)


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"),
)


def load_survey_dict(path) -> dict:
    """Read a SURVEY.yaml file into a plain mapping (not yet validated; see :func:`load_survey`).

    Raises
    ------
    ConfigError
        Missing/unreadable file, YAML syntax error (with its line) or an empty file.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"survey file not found: {path}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"cannot read survey file {path}: {exc}") from None
    try:
        data = yaml.load(text, Loader=_Loader)  # noqa: S506 (a SafeLoader subclass)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise ConfigError(f"{path}:{where}: YAML syntax error: {problem}") from None
    if data is None:
        raise ConfigError(f"{path}: the survey file is empty")
    return data


def load_survey(path) -> Survey:
    """Read and validate a SURVEY.yaml file.

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    Survey

    Raises
    ------
    ConfigError
        Missing/unreadable file, YAML syntax error (with its line) or an invalid value
        (naming the key path, e.g. ``platform.legs[2].end``).
    """
    path = Path(path)
    data = load_survey_dict(path)
    try:
        return survey_from_dict(data, base_dir=path.resolve().parent)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


def _real(v, key, *, positive=False, nonneg=False) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ConfigError(f"{key} must be a number (got {v!r})")
    v = float(v)
    if not math.isfinite(v):
        raise ConfigError(f"{key} must be finite (got {v!r})")
    if positive and not v > 0:
        raise ConfigError(f"{key} must be > 0 (got {v!r})")
    if nonneg and v < 0:
        raise ConfigError(f"{key} must be >= 0 (got {v!r})")
    return v


def _vec3(v, key) -> np.ndarray:
    if not isinstance(v, (list, tuple)) or len(v) != 3:
        raise ConfigError(f"{key} must be a list of three coordinates [x, y, z] (got {v!r})")
    return np.array([_real(x, f"{key}[{i}]") for i, x in enumerate(v)], dtype=np.float64)


def _mapping(v, key, allowed) -> dict:
    if not isinstance(v, dict):
        raise ConfigError(f"{key} must be a mapping (got {type(v).__name__})")
    for k in v:
        if k not in allowed:
            raise ConfigError(f"{key}.{k} is not a known key; allowed: {', '.join(allowed)}")
    return v


def _list(v, key) -> list:
    if not isinstance(v, list) or len(v) < 1:
        raise ConfigError(f"{key} must be a list with at least one entry (got {v!r})")
    return v


def _heading_of(u: np.ndarray, previous: float) -> float:
    horiz = math.hypot(u[0], u[1])
    if horiz <= 1e-9 * np.linalg.norm(u):
        return previous
    return math.degrees(math.atan2(u[0], u[1])) % 360.0


def _parse_linear(p: dict, prf: float):
    _mapping(p, "platform", ("type", "speed_mps", "legs"))
    if "speed_mps" not in p:
        raise ConfigError("platform.speed_mps is missing")
    if "legs" not in p:
        raise ConfigError("platform.legs is missing")
    speed = _real(p["speed_mps"], "platform.speed_mps", positive=True)
    raw = _list(p["legs"], "platform.legs")
    legs = []
    t = 0.0
    prev_end = None
    heading = 0.0
    offset = 0
    source = 0
    for i, entry in enumerate(raw):
        key = f"platform.legs[{i}]"
        _mapping(entry, key, ("start", "end", "active", "speed_mps"))
        for req in ("start", "end"):
            if req not in entry:
                raise ConfigError(f"{key}.{req} is missing")
        a = _vec3(entry["start"], f"{key}.start")
        b = _vec3(entry["end"], f"{key}.end")
        active = entry.get("active", True)
        if not isinstance(active, bool):
            raise ConfigError(f"{key}.active must be true or false (got {active!r})")
        leg_speed = _real(entry["speed_mps"], f"{key}.speed_mps", positive=True) if "speed_mps" in entry else speed
        length = float(np.linalg.norm(b - a))
        if not length > 0:
            raise ConfigError(f"{key} has zero length (start == end)")
        if prev_end is not None:
            t += float(np.linalg.norm(a - prev_end)) / leg_speed
        heading = _heading_of(b - a, heading)
        duration = length / leg_speed
        n = int(math.ceil(duration * prf - 1e-9)) if active else 0
        if active:
            source += 1
        legs.append(Leg(a, b, active, t, duration, heading, source if active else 0, offset, n, leg_speed))
        offset += n
        t += duration
        prev_end = b
    if source == 0:
        raise ConfigError("platform.legs has no active leg")
    if source > 65535:
        raise ConfigError("platform.legs has more than 65535 active legs (source_id is 16-bit)")
    return speed, legs


def _parse_static(p: dict, scanner: ScannerSettings):
    _mapping(p, "platform", ("type", "positions"))
    if "positions" not in p:
        raise ConfigError("platform.positions is missing")
    raw = _list(p["positions"], "platform.positions")
    az, el = tls_grid(scanner)
    n = len(az) * len(el)
    duration = n / scanner.prf_hz
    out = []
    for i, entry in enumerate(raw):
        key = f"platform.positions[{i}]"
        _mapping(entry, key, ("position", "heading_deg", "tilt_deg"))
        if "position" not in entry:
            raise ConfigError(f"{key}.position is missing")
        pos = _vec3(entry["position"], f"{key}.position")
        heading = _real(entry.get("heading_deg", 0.0), f"{key}.heading_deg")
        tilt = _real(entry.get("tilt_deg", 0.0), f"{key}.tilt_deg")
        if abs(tilt) > 90:
            raise ConfigError(f"{key}.tilt_deg must be within [-90, 90] (got {tilt!r})")
        out.append(ScanPosition(pos, heading % 360.0, tilt, i * duration, duration, i + 1, i * n, n))
    if len(out) > 65535:
        raise ConfigError("platform.positions has more than 65535 entries (source_id is 16-bit)")
    return out


def survey_from_dict(d: dict, base_dir=None) -> Survey:
    """Validate a survey given as a dict (the parsed SURVEY.yaml).

    Parameters
    ----------
    d : dict
        The survey (see the module docstring).
    base_dir : str or Path, optional
        Directory the survey came from; kept as ``Survey.base_dir``.

    Returns
    -------
    Survey

    Raises
    ------
    ConfigError
        Naming the key path of the first invalid entry.
    """
    if not isinstance(d, dict):
        raise ConfigError(f"the survey must be a mapping of {', '.join(_TOP_KEYS)} (got {type(d).__name__})")
    for k in d:
        if k not in _TOP_KEYS:
            raise ConfigError(f"{k} is not a known survey key; allowed: {', '.join(_TOP_KEYS)}")
    for req in ("scanner", "platform"):
        if req not in d:
            raise ConfigError(f"{req} is missing")
    overrides = d.get("overrides")
    if overrides is not None and not isinstance(overrides, dict):
        raise ConfigError(f"overrides must be a mapping (got {type(overrides).__name__})")
    sc = d["scanner"]
    if isinstance(sc, ScannerSettings):  # programmatic use
        validate_scanner(sc, "scanner")
        scanner = apply_overrides(sc, overrides)
    elif isinstance(sc, dict):
        scanner = apply_overrides(scanner_from_dict(sc, "scanner"), overrides)
    else:
        scanner = scanner_from_preset(sc, overrides)

    p = d["platform"]
    if not isinstance(p, dict):
        raise ConfigError(f"platform must be a mapping (got {type(p).__name__})")
    ptype = p.get("type", "linear")
    if ptype not in ("linear", "static"):
        raise ConfigError(f"platform.type must be linear or static (got {ptype!r})")
    if (ptype == "static") != (scanner.deflector == "tls"):
        need = "static" if scanner.deflector == "tls" else "linear"
        raise ConfigError(
            f"platform.type {ptype!r} does not fit the {scanner.deflector} deflector of {scanner.name}; use {need}"
        )
    if ptype == "linear":
        speed, legs = _parse_linear(p, scanner.prf_hz)
        positions = []
    else:
        speed, legs = None, []
        positions = _parse_static(p, scanner)

    tn = d.get("trajectory_noise")
    if tn is None:
        noise = TrajectoryNoise()
    else:
        _mapping(tn, "trajectory_noise", ("position_sigma_m", "attitude_sigma_deg", "correlation_s"))
        noise = TrajectoryNoise(
            _real(tn.get("position_sigma_m", 0.0), "trajectory_noise.position_sigma_m", nonneg=True),
            _real(tn.get("attitude_sigma_deg", 0.0), "trajectory_noise.attitude_sigma_deg", nonneg=True),
            _real(tn.get("correlation_s", 1.0), "trajectory_noise.correlation_s", positive=True),
        )

    seed = d.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ConfigError(f"seed must be a non-negative integer (got {seed!r})")

    sections = {}
    for key in ("detector", "output"):
        v = d.get(key)
        if v is None:
            v = {}
        if not isinstance(v, dict):
            raise ConfigError(f"{key} must be a mapping (got {type(v).__name__})")
        sections[key] = dict(v)

    return Survey(
        scanner=scanner,
        platform_type=ptype,
        speed_mps=speed,
        legs=legs,
        positions=positions,
        noise=noise,
        seed=seed,
        detector=sections["detector"],
        output=sections["output"],
        base_dir=Path(base_dir) if base_dir is not None else None,
    )
