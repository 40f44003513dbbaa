"""Platforms: the legs of a linear platform and the scan positions of a static one, in time.

The frames and the attitude convention are those of :mod:`vlsforest.sim.trajectory`.

*Linear platform.* GPS time is 0 at the start of the first leg. The platform flies the legs in
order, each at its own ``speed_mps`` (default: the platform's), inactive legs included (time
passes, no slots); when a leg does not start where the previous one ended, the straight transit
to it also takes time (distance / the leg's speed) without slots. Slot k of an active leg fires
at ``t_leg + k/PRF`` from ``start + (k/PRF)·speed·u`` (u = the leg's unit vector) for every
``k/PRF`` < leg duration, so a slot every 1/PRF tick and the platform advances ``speed/PRF`` per
slot. Heading = the azimuth of the leg's horizontal direction (a vertical leg keeps the previous
heading, 0 for the first); roll and pitch are 0 (level flight, also on climbing legs). Every
active leg starts a new scan line at slot 0 (see :mod:`vlsforest.sim.deflector`) and is one
flight line: its ``source_id`` counts the active legs from 1.

*Static platform (TLS).* Each position is one scan: the full azimuth × elevation grid of the
scanner, ``n_az·n_el`` slots, all emitted, at 1/PRF each. Scans follow each other without a
gap. ``heading_deg`` turns the head's azimuth zero (clockwise from north), ``tilt_deg`` tilts the
head about its own x (right) axis, upwards for positive values: body → world is
``H(heading)·P(tilt)``. ``source_id`` counts the positions from 1.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

__all__ = ["Leg", "ScanPosition", "fly_legs", "place_scans"]


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


def _heading_of(u: np.ndarray, previous: float) -> float:
    """Compass azimuth of the horizontal part of ``u``, degrees in [0, 360); ``previous`` for a
    vertical ``u``."""
    horiz = math.hypot(u[0], u[1])
    if horiz <= 1e-9 * np.linalg.norm(u):
        return previous
    return math.degrees(math.atan2(u[0], u[1])) % 360.0


def fly_legs(legs: Sequence[tuple], prf_hz: float) -> list[Leg]:
    """Times, headings, pulse slots and flight-line numbers of the legs of a linear platform.

    Parameters
    ----------
    legs : sequence of (start, end, active, speed_mps)
        The legs in flight order: start and end points (arrays of 3, distinct), whether the
        leg scans, its speed (> 0).
    prf_hz : float
        Pulse repetition frequency: an active leg of duration T has ``ceil(T·prf_hz)`` slots.

    Returns
    -------
    list of Leg
    """
    out = []
    t = 0.0
    prev_end = None
    heading = 0.0
    offset = 0
    source = 0
    for a, b, active, speed in legs:
        length = float(np.linalg.norm(b - a))
        if prev_end is not None:
            t += float(np.linalg.norm(a - prev_end)) / speed
        heading = _heading_of(b - a, heading)
        duration = length / speed
        n = int(math.ceil(duration * prf_hz - 1e-9)) if active else 0
        if active:
            source += 1
        out.append(Leg(a, b, active, t, duration, heading, source if active else 0, offset, n, speed))
        offset += n
        t += duration
        prev_end = b
    return out


def place_scans(positions: Sequence[tuple], n_slots: int, prf_hz: float) -> list[ScanPosition]:
    """Times, pulse slots and scan numbers of the scans of a static platform.

    Parameters
    ----------
    positions : sequence of (position, heading_deg, tilt_deg)
        The scan positions (arrays of 3) in scan order, the head's heading and tilt.
    n_slots : int
        Slots of one scan (the scanner's tls grid).
    prf_hz : float
        Pulse repetition frequency.

    Returns
    -------
    list of ScanPosition
    """
    duration = n_slots / prf_hz
    return [ScanPosition(pos, heading % 360.0, tilt, i * duration, duration, i + 1, i * n_slots, n_slots)
            for i, (pos, heading, tilt) in enumerate(positions)]
