"""Deflector patterns: the beam direction of a pulse slot in the platform (body) frame.

A scanner's deflector turns the slot index *within one flight line or scan* into the beam
direction in the body frame: x = right, y = forward (flight direction), z = up; nadir is −z.
Angles are in degrees unless the name says otherwise. ``f = scan_freq_hz / prf_hz`` is the
fraction of a line swept per slot, and every flight line starts a new scan line (and, for
``polygon`` and ``rotating``, a new sweep from nadir).

``polygon``
    Sawtooth over the device half-sweep M = ``max_scan_angle_deg``, stepped as HELIOS++ 1.0.8's
    ``PolygonMirrorBeamDeflector`` steps it: a line starts at the angle 0 (nadir), each slot
    first adds the step ``δ = 2M·f`` and the slot is then emitted at that angle, and when the
    sum reaches +M it is reset to −M (that slot's angle). So slot k of the first line looks at
    ``(k+1)·δ`` and every later line runs ``−M, −M+δ, −M+2δ, …`` up to the last angle below
    +M. The sum is accumulated in float64 radians, so a line holds ``⌈1/f⌉`` slots, or one
    more when ``1/f`` is whole and the rounded sum stays below +M (:func:`helios_line_slots`;
    the VQ-780i at 1 MHz / 250 Hz and the miniVUX-1UAV at 100 kHz / 50 Hz: 4,001 and 2,001).
    A pulse is emitted only if the sum's ``|angle| ≤ min(effective_max_scan_angle_deg,
    scan_angle_deg)`` (compared in radians, as HELIOS++ compares it): the RIEGL VQ-780i's
    mirror sweeps ±45° and the device measures within ±30°, so it emits 2/3 of its PRF. The
    slots, angles and emitted pulses are those of HELIOS++ 1.0.8 on the same survey, so that
    both tools' beams fall on the same spots.
``rotating``
    A 360° mirror turning ``scan_freq_hz`` times a second, stepped as ``polygon`` with M = 180°
    (a leg's first line turns from nadir to the right up to the zenith, every later line from
    the zenith over the left, nadir and the right back to it). Emitted as ``polygon``; with the
    ±90° survey window of the miniVUX-1UAV about half of the slots are emitted.
``oscillating``
    Triangle wave between ±scan_angle_deg, ``PRF/scan_freq`` slots per line (one line = one
    sweep from one side to the other; even lines sweep left → right, odd lines back). The
    turn-around is a sharp corner (no quadratic turn-around offsets as in HELIOS++ v1.0.x,
    no turning pulses as at HEAD). Every slot is emitted.
``conic`` (Palmer)
    Fixed cone of half angle ``scan_angle_deg`` about nadir; the azimuth φ (from forward
    towards right) advances ``360·f`` per slot. Uses the survey frequency (HELIOS++ uses the
    device's maximum frequency: a quirk not reproduced). Every slot is emitted.
``tls``
    A grid of nodes (:func:`tls_grid`): azimuths ``tls_h_fov_deg[0] + i·tls_h_step_deg``
    (clockwise from the head's forward axis; a full 360° circle does not repeat its start),
    elevations ``tls_v_fov_deg[0] + j·tls_v_step_deg`` up to ``tls_v_fov_deg[1]``; slot order is
    azimuth-major (one vertical line after another). Every slot is emitted. ``scan_freq_hz``,
    ``scan_angle_deg`` and ``max_scan_angle_deg`` are not used.

:func:`~vlsforest.sim.scanner.emission_half_angle_deg` gives the emitted half angle of each
pattern.

Every pattern also gives ``scan_dir``: the unit vector, perpendicular to the beam, in which the
beam sweeps at that instant (the time derivative of the direction, normalised; for ``tls`` the
direction of increasing elevation; for the back sweep of ``oscillating`` it points back), and the
signed scan angle written to LAS: the across-track deflection from nadir, ``atan2(d_x, −d_z)``
(positive = right of track; equal to the mirror angle for polygon, rotating and oscillating), or
the elevation for ``tls``.

One implementation
------------------
The patterns are compiled per-slot functions (:func:`sweep`, :func:`across_track_frame`,
:func:`conic_frame`, :func:`node_frame`). :func:`deflect` runs them over an array of slots; the
compiled pulse pass of :mod:`vlsforest.sim.pulses` calls the same functions slot by slot, so
both give the same bits. A scanner's pattern enters them as the numbers of a
:class:`DeflectorPattern` (:func:`deflector_pattern`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from vlsforest.errors import ConfigError
from vlsforest.sim.scanner import DEFLECTORS, ScannerSettings, TlsGrid, emission_half_angle_deg

__all__ = [
    "CONIC",
    "OSCILLATING",
    "POLYGON",
    "ROTATING",
    "TLS",
    "DeflectorPattern",
    "across_track_frame",
    "conic_frame",
    "deflect",
    "deflect_pattern",
    "deflector_pattern",
    "helios_line_slots",
    "node_frame",
    "sweep",
    "tls_grid",
]

#: the pattern codes of the compiled functions, in the order of
#: :data:`~vlsforest.sim.scanner.DEFLECTORS`
POLYGON, ROTATING, OSCILLATING, CONIC, TLS = range(5)


@dataclass(frozen=True, eq=False)
class DeflectorPattern:
    """A scanner's deflector as the numbers the compiled per-slot functions take.

    Attributes
    ----------
    kind : int
        :data:`POLYGON`, :data:`ROTATING`, :data:`OSCILLATING`, :data:`CONIC` or :data:`TLS`.
    prf : float
        Pulse repetition frequency, Hz.
    freq : float
        Scan lines (conic: rotations) per second; 0 for tls.
    a, b : float
        Polygon and rotating: the angle ``a = −M`` a line after the first starts at and the
        step ``b = δ`` per slot (degrees); oscillating sweeps ``−a + b·phase`` on even lines and
        ``a − b·phase`` on odd ones; 0 for conic and tls.
    lines : ndarray of int64, shape (6,)
        Polygon and rotating: the slots of the first line and of every later one, and the
        emitted ones of each, ``[first, period, first_on, first_off, on, off]``
        (:func:`helios_line_slots`); zeros for the other patterns.
    sin_cone, cos_cone : float
        Sine and cosine of the conic half angle (0 and 1 for the other patterns).
    az_r, el_r : ndarray
        The tls grid (:func:`tls_grid`) in radians; empty for the other patterns.
    el_deg : ndarray
        The tls elevations in degrees (the scan angle of a tls slot).
    """

    kind: int
    prf: float
    freq: float
    a: float
    b: float
    lines: np.ndarray
    sin_cone: float
    cos_cone: float
    az_r: np.ndarray
    el_r: np.ndarray
    el_deg: np.ndarray

    def args(self) -> tuple:
        """The attributes in the order the compiled functions of this module and of
        :mod:`vlsforest.sim.pulses` take them."""
        return (self.kind, self.prf, self.freq, self.a, self.b, self.lines, self.sin_cone,
                self.cos_cone, self.az_r, self.el_r, self.el_deg)


def tls_grid(grid: TlsGrid) -> tuple[np.ndarray, np.ndarray]:
    """Azimuth and elevation nodes of one TLS scan (degrees).

    Parameters
    ----------
    grid : TlsGrid
        The scanner's angular grid (``ScannerSettings.tls``).

    Returns
    -------
    azimuth_deg : ndarray, shape (n_az,)
        ``h0 + i·h_step`` up to ``h1``; a full 360° circle stops before ``h0 + 360``.
    elevation_deg : ndarray, shape (n_el,)
        ``v0 + j·v_step`` up to ``v1``.
    """
    h0, h1 = grid.h_fov_deg
    v0, v1 = grid.v_fov_deg
    span = h1 - h0
    if span >= 360.0 - 1e-9:
        n_az = int(math.ceil(360.0 / grid.h_step_deg - 1e-9))
    else:
        n_az = int(math.floor(span / grid.h_step_deg + 1e-9)) + 1
    n_el = int(math.floor((v1 - v0) / grid.v_step_deg + 1e-9)) + 1
    return h0 + np.arange(n_az) * grid.h_step_deg, v0 + np.arange(n_el) * grid.v_step_deg


def deflector_pattern(s: ScannerSettings) -> DeflectorPattern:
    """The :class:`DeflectorPattern` of a scanner.

    Raises
    ------
    ConfigError
        An unknown deflector.
    """
    d = s.deflector
    if d.kind not in DEFLECTORS:
        raise ConfigError(f"scanner deflector must be one of {', '.join(DEFLECTORS)} (got {d.kind!r})")
    kind = DEFLECTORS.index(d.kind)
    a = b = 0.0
    sin_cone, cos_cone = 0.0, 1.0
    none = np.zeros(0)
    az_r = el_r = el_deg = none
    freq = float(d.scan_freq_hz)
    lines = np.zeros(6, np.int64)
    if kind in (POLYGON, ROTATING):
        half = d.max_scan_angle_deg if kind == POLYGON else 180.0
        a = -half
        b, lines = helios_line_slots(half, freq, float(s.emitter.prf_hz), emission_half_angle_deg(s))
    elif kind == OSCILLATING:
        a, b = d.scan_angle_deg, 2.0 * d.scan_angle_deg
    elif kind == CONIC:
        c = math.radians(d.scan_angle_deg)
        sin_cone, cos_cone = math.sin(c), math.cos(c)
    else:
        az, el = tls_grid(s.tls)
        az_r, el_r, el_deg = np.radians(az), np.radians(el), np.asarray(el, np.float64)
        freq = 0.0
    return DeflectorPattern(kind, float(s.emitter.prf_hz), freq, float(a), float(b), lines, sin_cone,
                            cos_cone, az_r, el_r, el_deg)


def helios_line_slots(half_deg: float, freq: float, prf: float, window_deg: float) -> tuple[float, np.ndarray]:
    """The lines of a polygon or rotating mirror and their emitted slots, as HELIOS++ 1.0.8 steps them.

    HELIOS++'s ``PolygonMirrorBeamDeflector`` starts a leg at the angle 0, adds
    ``(freq · 2M) / prf`` radians before each pulse (M the half sweep, ``degrees · (π/180)``)
    and, once the sum reaches +M, sets it to −M; a pulse leaves the device when the sum's
    absolute value is at most the window (in radians). The sum is repeated here in the same
    float64 operations, so the slots per line and the emitted ones are HELIOS++'s. Within a line
    the angle only grows, so each line's emitted slots are one run.

    Parameters
    ----------
    half_deg : float
        The mirror's half sweep M, degrees (polygon: ``max_scan_angle_deg``; rotating: 180).
    freq, prf : float
        Lines per second and pulses per second.
    window_deg : float
        The emission window: pulses within ± this angle leave the device (degrees).

    Returns
    -------
    step_deg : float
        The angle step per slot, degrees.
    lines : ndarray of int64, shape (6,)
        ``[first, period, first_on, first_off, on, off]``: a leg's first line holds the slots
        ``[0, first)`` (the slot after nadir up to the last angle below +M) and emits
        ``[first_on, first_off)`` of them; every later line holds ``period`` slots (from −M up
        to the last angle below +M) and emits its slots ``[on, off)`` (counted from its start).

    Raises
    ------
    ConfigError
        A half sweep, line frequency or PRF that is not positive, or more than 10⁹ slots per line.
    """
    if not (half_deg > 0 and freq > 0 and prf > 0):
        raise ConfigError(f"scanner deflector: half sweep {half_deg}°, {freq} lines/s (scan_freq_hz) and "
                          f"prf_hz {prf} must be positive")
    if prf / freq > 1e9:
        raise ConfigError(f"scanner deflector: scan_freq_hz {freq} at prf_hz {prf} gives {prf / freq:.3g} slots "
                          "per line (at most 10⁹)")
    m = half_deg * (math.pi / 180.0)
    w = window_deg * (math.pi / 180.0)
    step = (freq * (m - (-m))) / prf
    first, first_on, first_off = _walk(0.0, step, m, w)
    rest, on, off = _walk(-m, step, m, w)
    # a later line starts with the slot set to −M itself, then the sums from −M
    on, off = (0, off + 1) if m <= w else (on + 1, off + 1)
    return math.degrees(step), np.array([first, rest + 1, first_on, first_off, on, off], np.int64)


@numba.njit(cache=True)
def _walk(start, step, top, window):
    """Add ``step`` to ``start`` one addition at a time (float64) while the sum stays below ``top``.

    Returns the number of sums below ``top`` and the run ``[on, off)`` of those (numbered from
    0) whose absolute value is at most ``window`` (``on == off`` when none is).
    """
    n = 0
    on = off = -1
    x = start + step
    while x < top:
        if abs(x) <= window:
            if on < 0:
                on = n
            off = n + 1
        n += 1
        x += step
    if on < 0:
        on = off = 0
    return n, on, off


# --------------------------------------------------------------------------- per-slot functions


@numba.njit(cache=True, inline="always")
def sweep(kind, k, prf, freq, a, b, lines):
    """Scan line, phase, sweep angle and sweep direction of slot ``k`` (not tls).

    Polygon and rotating (``lines = [first, period, first_on, first_off, on, off]``): line 0
    holds the slots ``[0, first)`` at the angles ``(k+1)·b``, line ``L ≥ 1`` the slots
    ``[first + (L−1)·period, first + L·period)`` at ``a + j·b`` (``j`` the slot's place in its
    line); the phase is ``j / period``, and the angle is NaN for a slot the mirror does not
    emit (outside ``[first_on, first_off)`` or ``[on, off)``). Oscillating and conic:
    the line is ``floor(k·freq / prf)`` and the phase in [0, 1) what remains: exact for
    integer-valued frequencies (``k·freq`` and ``line·prf`` are exact in float64), so that line
    boundaries fall on the right slots.

    Returns
    -------
    line : float
        Scan line number (integer-valued).
    frac : float
        Phase within the line, [0, 1).
    angle : float
        Across-track angle, degrees (conic: 0; its angle comes with :func:`conic_frame`).
    back : bool
        An odd line of an oscillating deflector (sweeping right → left).
    """
    if kind == POLYGON or kind == ROTATING:
        first, period = lines[0], lines[1]
        if k < first:
            angle = (k + 1.0) * b if lines[2] <= k < lines[3] else np.nan
            return 0.0, (k + 1.0) / period, angle, False
        q = k - first
        j = q % period
        angle = a + j * b if lines[4] <= j < lines[5] else np.nan
        return np.float64(1 + q // period), j / period, angle, False
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
    if kind == OSCILLATING:
        back = (np.int64(line) % 2) == 1
        angle = a - b * frac if back else -a + b * frac
    else:
        angle = a + b * frac
    return line, frac, angle, back


@numba.njit(cache=True, inline="always")
def across_track_frame(r, back):
    """Body-frame beam direction and sweep direction of an across-track deflection of ``r`` radians.

    Returns
    -------
    v0, v1, v2, w0, w1, w2 : float
        Direction ``(sin r, 0, −cos r)`` and sweep direction ``(cos r, 0, sin r)``, reversed on
        a back sweep.
    """
    sa, ca = np.sin(r), np.cos(r)
    w0, w1, w2 = ca, 0.0, sa
    if back:
        w0, w1, w2 = -w0, -w1, -w2
    return sa, 0.0, -ca, w0, w1, w2


@numba.njit(cache=True, inline="always")
def conic_frame(frac, sin_cone, cos_cone):
    """Body-frame beam direction, sweep direction and scan angle (degrees) of a conic slot of phase ``frac``."""
    phi = 2.0 * np.pi * frac
    sp, cp = np.sin(phi), np.cos(phi)
    v0, v1, v2 = sin_cone * sp, sin_cone * cp, -cos_cone
    return v0, v1, v2, cp, -sp, 0.0, np.degrees(np.arctan2(v0, -v2))


@numba.njit(cache=True, inline="always")
def node_frame(k, az_r, el_r, el_deg):
    """Body-frame beam direction, sweep direction and scan angle (the elevation, degrees) of tls slot ``k``."""
    n_el = el_r.shape[0]
    ia = k // n_el
    ie = k - ia * n_el
    ar = az_r[ia]
    er = el_r[ie]
    sa, ca, se, ce = np.sin(ar), np.cos(ar), np.sin(er), np.cos(er)
    return ce * sa, ce * ca, se, -se * sa, -se * ca, ce, el_deg[ie]


@numba.njit(cache=True)
def _deflect(k, kind, prf, freq, a, b, lines, sin_cone, cos_cone, az_r, el_r, el_deg):
    n = k.shape[0]
    emitted = np.zeros(n, np.bool_)
    direction = np.empty((n, 3))
    scan_dir = np.empty((n, 3))
    angle = np.empty(n)
    m = 0
    for i in range(n):
        if kind == TLS:
            v0, v1, v2, w0, w1, w2, ang = node_frame(k[i], az_r, el_r, el_deg)
        else:
            _, frac, ang, back = sweep(kind, k[i], prf, freq, a, b, lines)
            if np.isnan(ang):  # a polygon or rotating slot the device does not emit
                continue
            if kind == CONIC:
                v0, v1, v2, w0, w1, w2, ang = conic_frame(frac, sin_cone, cos_cone)
            else:
                v0, v1, v2, w0, w1, w2 = across_track_frame(np.radians(ang), back)
        emitted[i] = True
        direction[m, 0], direction[m, 1], direction[m, 2] = v0, v1, v2
        scan_dir[m, 0], scan_dir[m, 1], scan_dir[m, 2] = w0, w1, w2
        angle[m] = ang
        m += 1
    return emitted, direction[:m].copy(), scan_dir[:m].copy(), angle[:m].copy()


def deflect(s: ScannerSettings, k: np.ndarray):
    """Beam pattern of slots ``k`` (counted from the start of a flight line or scan).

    Parameters
    ----------
    s : ScannerSettings
        The scanner.
    k : ndarray of int
        Slot indices within the line/scan, ``k ≥ 0``.

    Returns
    -------
    emitted : ndarray of bool, shape (n,)
        Whether the slot's pulse is emitted.
    direction : ndarray, shape (m, 3)
        Unit beam directions in the body frame (x right, y forward, z up), emitted slots only.
    scan_dir : ndarray, shape (m, 3)
        Unit sweep directions, perpendicular to ``direction``, emitted slots only.
    scan_angle_deg : ndarray, shape (m,)
        Signed across-track angle from nadir (tls: elevation), emitted slots only.

    Raises
    ------
    ValueError
        A tls slot beyond the scan's grid.
    """
    return deflect_pattern(deflector_pattern(s), k)


def deflect_pattern(pattern: DeflectorPattern, k: np.ndarray):
    """:func:`deflect` for a scanner's :class:`DeflectorPattern`."""
    k = np.ascontiguousarray(k, dtype=np.int64)
    if pattern.kind == TLS and len(k):
        n = len(pattern.az_r) * len(pattern.el_r)
        if int(k.max()) >= n:
            raise ValueError(f"slot {int(k.max())} beyond the {n} slots of a TLS scan")
    return _deflect(k, *pattern.args())
