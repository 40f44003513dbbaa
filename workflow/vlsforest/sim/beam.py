"""Sub-ray sampling of a laser beam (circular or elliptical) and its Gaussian energy profile.

A pulse is traced as a fan of sub-rays on concentric rings (HELIOS++ v1.0 pattern): ring
``k = 0 … Q-1`` (Q = beam sample quality) holds ``1`` sub-ray for k = 0 and ``6k`` sub-rays
otherwise (1, 7, 19, 37, 61 … sub-rays for Q = 1 … 5), evenly spaced in azimuth starting at
azimuth 0, at the fractional radius ``k / Q`` of the sampled beam extent.

Beam extent
-----------
``beam_divergence_mrad`` (``div``) is HELIOS++'s ``beamDivergence``: ring k sits at the angle
``k/Q · div`` off the axis and its Gaussian weight is the beam profile there,
``exp(-2 (k/Q)² M² R²/(R² + R0²))`` (1, 0.80, 0.41 for Q = 3, R ≫ R0), so the weight falls to
1/e² at ``div`` off the axis: ``div`` is the beam's 1/e² **half** angle, and its 1/e² energy
footprint has the diameter ``2·div·R``. (HELIOS++'s footprint-area formula reads it as a full
angle, quirk 2 of the reference notes; that area cancels from the received power.) A datasheet
full angle θ is therefore given as ``div = θ/2``
(:func:`vlsforest.sim.scanner.datasheet_divergence`). An elliptical beam has a major and a
minor ``div`` and an orientation of the major axis relative to the scan direction; it scales
the ring pattern along its two axes, so each sub-ray sits on the ellipse ``k/Q`` of the
footprint and carries the same weight as on a circular beam.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from vlsforest.errors import ConfigError


def ring_counts(quality: int) -> np.ndarray:
    """Number of sub-rays per ring for a beam sample quality (HELIOS++ v1.0: 1, 6, 12, 18 …)."""
    if int(quality) != quality or quality < 1:
        raise ConfigError(f"beam_sample_quality must be an integer ≥ 1, got {quality!r}")
    k = np.arange(int(quality))
    return np.where(k == 0, 1, 6 * k)


@dataclass(frozen=True)
class SubrayPattern:
    """The sub-ray fan of one pulse, in the beam frame.

    Attributes
    ----------
    offsets : ndarray, shape (n, 2)
        Angular offsets in radians along the scan direction and across it
        (right-handed with the beam direction).
    frac : ndarray, shape (n,)
        Fractional ring radius ``k/Q`` of each sub-ray (0 for the central ray).
    quality : int
        Beam sample quality Q.
    divergence : tuple of float
        1/e² half angle (major, minor) in radians.
    """

    offsets: np.ndarray
    frac: np.ndarray
    quality: int
    divergence: tuple

    @property
    def n(self) -> int:
        """Number of sub-rays."""
        return len(self.frac)

    def weights(self, ranges, range0: float = 0.0, m2: float = 1.0) -> np.ndarray:
        """Gaussian beam weight of each sub-ray at the given ranges.

        Parameters
        ----------
        ranges : ndarray
            Range of the sub-ray's hit (broadcast against ``frac``).
        range0 : float
            The range parameter R0 of the beam-waist model (HELIOS++: ``rangeMin``).
        m2 : float
            Beam quality factor M².
        """
        return gaussian_weight(self.frac, ranges, range0, m2)


def gaussian_weight(frac, ranges, range0: float = 0.0, m2: float = 1.0) -> np.ndarray:
    """Gaussian beam weight ``exp(-2 (frac·M²)² R²/(R² + R0²))`` of sub-rays at fractional radius ``frac``."""
    r = np.asarray(ranges, dtype=np.float64)
    return np.exp(-2.0 * (np.asarray(frac) * m2) ** 2 * r * r / (r * r + range0 * range0))


def subray_pattern(quality: int, divergence_mrad, orientation_deg: float = 0.0) -> SubrayPattern:
    """Build the sub-ray pattern of a pulse.

    Parameters
    ----------
    quality : int
        Beam sample quality Q (number of rings).
    divergence_mrad : float or (float, float)
        The 1/e² half angle (HELIOS++'s ``beamDivergence``), one value (circular) or
        (major, minor).
    orientation_deg : float
        Angle of the major axis from the scan direction, degrees.

    Returns
    -------
    SubrayPattern
    """
    div = np.atleast_1d(np.asarray(divergence_mrad, dtype=np.float64)) * 1e-3
    if div.size == 1:
        div = np.array([div[0], div[0]])
    if div.size != 2 or not np.all(np.isfinite(div)) or np.any(div <= 0):
        raise ConfigError(f"beam_divergence_mrad must be one or two positive numbers, got {divergence_mrad!r}")
    if div[1] > div[0]:
        raise ConfigError("beam_divergence_mrad: the minor divergence exceeds the major one")
    counts = ring_counts(quality)
    extent = div
    fr, az = [], []
    for k, n in enumerate(counts):
        fr.append(np.full(n, k / quality))
        az.append(np.arange(n) * (2.0 * np.pi / n))
    frac = np.concatenate(fr)
    azim = np.concatenate(az)
    a_major = frac * extent[0] * np.cos(azim)
    a_minor = frac * extent[1] * np.sin(azim)
    rot = np.deg2rad(orientation_deg)
    c, s = np.cos(rot), np.sin(rot)
    offsets = np.column_stack([c * a_major - s * a_minor, s * a_major + c * a_minor])
    return SubrayPattern(offsets=offsets, frac=frac, quality=int(quality), divergence=(float(div[0]), float(div[1])))


def subray_directions(direction, scan_dir, pattern: SubrayPattern) -> np.ndarray:
    """Directions of every sub-ray of every pulse.

    Parameters
    ----------
    direction : ndarray, shape (m, 3)
        Unit central beam directions.
    scan_dir : ndarray, shape (m, 3)
        Unit vectors perpendicular to ``direction`` along the scan motion.
    pattern : SubrayPattern

    Returns
    -------
    ndarray, shape (m, n, 3)
        Unit sub-ray directions; sub-ray 0 is the central ray.
    """
    d = np.ascontiguousarray(direction, dtype=np.float64)
    e1 = np.ascontiguousarray(scan_dir, dtype=np.float64)
    out = np.empty((len(d), pattern.n, 3))
    _fan(d, e1, np.ascontiguousarray(np.tan(pattern.offsets)), out)
    return out


@numba.njit(cache=True)
def _fan(d, e1, tan_off, out):
    for p in range(d.shape[0]):
        dx, dy, dz = d[p, 0], d[p, 1], d[p, 2]
        ax, ay, az = e1[p, 0], e1[p, 1], e1[p, 2]
        bx, by, bz = dy * az - dz * ay, dz * ax - dx * az, dx * ay - dy * ax  # d × e1
        for k in range(tan_off.shape[0]):
            u, v = tan_off[k, 0], tan_off[k, 1]
            x = dx + u * ax + v * bx
            y = dy + u * ay + v * by
            z = dz + u * az + v * bz
            n = np.sqrt(x * x + y * y + z * z)
            out[p, k, 0] = x / n
            out[p, k, 1] = y / n
            out[p, k, 2] = z / n


def subray_rays32(origin, direction, scan_dir, pattern: SubrayPattern, shift):
    """All sub-rays of the pulses as float32 origins (minus ``shift``) and directions, (m·n, 3)."""
    m, n = len(direction), pattern.n
    o32 = np.empty((m * n, 3), np.float32)
    d32 = np.empty((m * n, 3), np.float32)
    _fan32(np.ascontiguousarray(origin, np.float64), np.ascontiguousarray(direction, np.float64),
           np.ascontiguousarray(scan_dir, np.float64), np.ascontiguousarray(np.tan(pattern.offsets)),
           np.asarray(shift, np.float64), o32, d32)
    return o32, d32


@numba.njit(cache=True)
def _fan32(o, d, e1, tan_off, shift, out_o, out_d):
    n = tan_off.shape[0]
    for p in range(d.shape[0]):
        ox, oy, oz = o[p, 0] - shift[0], o[p, 1] - shift[1], o[p, 2] - shift[2]
        dx, dy, dz = d[p, 0], d[p, 1], d[p, 2]
        ax, ay, az = e1[p, 0], e1[p, 1], e1[p, 2]
        bx, by, bz = dy * az - dz * ay, dz * ax - dx * az, dx * ay - dy * ax
        for k in range(n):
            u, v = tan_off[k, 0], tan_off[k, 1]
            x = dx + u * ax + v * bx
            y = dy + u * ay + v * by
            z = dz + u * az + v * bz
            nn = np.sqrt(x * x + y * y + z * z)
            r = p * n + k
            out_o[r, 0] = ox
            out_o[r, 1] = oy
            out_o[r, 2] = oz
            out_d[r, 0] = x / nn
            out_d[r, 1] = y / nn
            out_d[r, 2] = z / nn


@numba.njit(cache=True, inline="always")
def cone_meets_box(o0, o1, o2, d0, d1, d2, lo, hi, tan_off):
    """Whether the cone of half-angle ``atan(tan_off)`` around the ray ``o + t·d`` (t ≥ 0) can
    meet the box ``[lo, hi]``: the box, padded by the cone's radius at the farthest distance
    from ``o`` to the box, is tested against the central ray (a conservative test)."""
    e0, e1, e2 = hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]
    half_diag = 0.5 * np.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
    c0, c1, c2 = 0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), 0.5 * (lo[2] + hi[2])
    reach = np.sqrt((o0 - c0) ** 2 + (o1 - c1) ** 2 + (o2 - c2) ** 2) + half_diag
    pad = tan_off * reach + 1e-6
    t_enter, t_exit = 0.0, np.inf
    for ax in range(3):
        o = o0 if ax == 0 else (o1 if ax == 1 else o2)
        d = d0 if ax == 0 else (d1 if ax == 1 else d2)
        a = lo[ax] - pad
        b = hi[ax] + pad
        if d == 0.0:
            if o < a or o > b:
                return False
            continue
        t1 = (a - o) / d
        t2 = (b - o) / d
        if t1 > t2:
            t1, t2 = t2, t1
        if t1 > t_enter:
            t_enter = t1
        if t2 < t_exit:
            t_exit = t2
    return t_exit >= t_enter


def cones_meet_box(origin, direction, lo, hi, tan_off: float) -> np.ndarray:
    """:func:`cone_meets_box` for many beams: whether the cone of half-angle ``atan(tan_off)``
    around each central ray meets the box ``[lo, hi]`` (False for every beam when a corner of
    the box is not finite).

    Parameters
    ----------
    origin, direction : ndarray, shape (n, 3)
        Ray origins and unit directions.
    lo, hi : array_like, shape (3,)
        The box.
    tan_off : float
        Tangent of the cone's half angle.

    Returns
    -------
    ndarray of bool, shape (n,)
    """
    lo = np.asarray(lo, np.float64)
    hi = np.asarray(hi, np.float64)
    out = np.zeros(len(origin), dtype=np.bool_)
    if np.isfinite(lo).all() and np.isfinite(hi).all():
        _cones_box(np.ascontiguousarray(origin, np.float64), np.ascontiguousarray(direction, np.float64),
                   lo, hi, float(tan_off), out)
    return out


@numba.njit(cache=True)
def _cones_box(origin, direction, lo, hi, tan_off, out):
    for i in range(origin.shape[0]):
        out[i] = cone_meets_box(origin[i, 0], origin[i, 1], origin[i, 2], direction[i, 0], direction[i, 1],
                                direction[i, 2], lo, hi, tan_off)
