"""Received energy, full waveform and peak detection (HELIOS++ v1.0 legacy model, with switches).

Energy of a sub-ray hit (HELIOS++ v1.0 legacy form, reflectance ρ in percent)::

    Pe  = P_avg · w_gauss                         Gaussian beam weight of the sub-ray
    A   = π R² δa δb / 4 / N                      equal share of the footprint area
    f   = ρ · [(1 − ks) cos a + ks |cos a'|^n]    Phong BRDF (ks = 0: Lambertian)
    σ   = 4π f A cos a                             cross section
    P_r = Pe · Dr² / (4π R⁴ δa δb) · η · T_atm² · σ
    I   = 1e9 · P_r

so that ``I ≈ 740`` for the central sub-ray of a Q = 3 pulse hitting a 50 % Lambertian target
at normal incidence at 500 m with the default receiver (the reference value).

Waveform: every sub-ray hit adds the pulse shape ``p(t) = (t/τ)² e^{−t/τ}``, τ = pulse/7,
sampled on bins of ``bin_size_ns``, scaled by its energy, at the bin of its range. The time
axis is one-way (``t = d/c``) by default as in HELIOS++ — a window of w ns is then a dead zone
of ``c·w`` metres (1.5 ns → 0.45 m, the study's figures); ``two_way_time`` uses ``t = 2d/c``.

Peak detection: a bin is a return when its value is at least ``min_energy`` (and > 0) and it
is the strict maximum of its neighbourhood. ``peak_rule="physical"`` (default) compares with
every bin within ±win (win = window/bin), left neighbours strictly lower, right neighbours lower
or equal (a plateau yields its first bin). ``peak_rule="helios"`` reproduces HELIOS++ v1.0:
neighbours within ±(win−1), bin 0 never checked, and *every neighbour must itself be ≥ a
floor* (hard-coded 0.001 in v1.0) — which suppresses an echo that does not overlap earlier
energy when win ≥ 6 (quirk 3). Under the helios rule ``threshold_scope`` says where
``min_energy`` applies: ``"window"`` (default) to the peak and every neighbour, as HELIOS++
2.x's ``receivedEnergyMin_W`` replaces that floor, so that the weakest lone echo reported has a
peak several times ``min_energy`` (≈ 4.4× for the 4 ns pulse on 0.25 ns bins and a 6-bin
window, whose first bin after the pulse's start holds 23 % of its peak); ``"peak"`` to the
peak alone, the neighbours keeping the 0.001 floor, so that ``min_energy`` is the receiver's
threshold on the peak amplitude as under the physical rule. At most ``max_returns`` earliest
peaks are kept (0 = all). The return range is the range of the peak bin minus the pulse's peak offset, so a lone
flat target at range d gives exactly d (quantised down onto the bin lattice anchored at the
nearest hit, quirk 7).
"""

from __future__ import annotations

import numba
import numpy as np

from vlsforest.errors import ConfigError

C_M_PER_NS = 0.299792458

#: the amplitude that maps to the largest LAS intensity (HELIOS++'s LAS writer: intensities are
#: scaled by 65,535 / 10⁶ and clipped to [0, 10⁶])
INTENSITY_FULL_SCALE = 1.0e6

#: HELIOS++ 1.0.8's fixed detection floor (``eps`` of its full-waveform detector): the helios
#: rule's threshold without ``min_energy`` and its neighbours' floor unless ``min_energy`` covers
#: the window
HELIOS_FLOOR = 0.001


_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)


def _mix64(x: np.ndarray) -> np.ndarray:
    """The SplitMix64 finaliser: a bijection of uint64 that scatters every input bit."""
    x = x ^ (x >> np.uint64(30))
    x = x * _MIX1
    x = x ^ (x >> np.uint64(27))
    x = x * _MIX2
    return x ^ (x >> np.uint64(31))


def _unit_uniform(seed: int, slot, ret, stream: int) -> np.ndarray:
    """Uniform numbers in (0, 1), each a function of (seed, slot, ret, stream) alone."""
    with np.errstate(over="ignore"):
        key = _mix64(np.array([int(seed) & 0xFFFFFFFFFFFFFFFF], np.uint64) * _GOLDEN + np.uint64(stream))
        x = _mix64(key ^ (np.asarray(slot, np.int64).astype(np.uint64) * _GOLDEN))
        x = _mix64(x ^ (np.asarray(ret, np.int64).astype(np.uint64) + _GOLDEN))
    return ((x >> np.uint64(11)).astype(np.float64) + 0.5) * 2.0 ** -53


def range_noise(seed: int, slot, return_number, sigma: float) -> np.ndarray:
    """Gaussian range noise N(0, σ²) of returns, drawn per (seed, pulse slot, return number).

    Each value depends on those three numbers only (a counter-based generator: SplitMix64
    hashing and the Box–Muller transform), not on which other pulses a block traces, so a
    return gets the same noise whatever region, block size or number of workers the
    simulation uses, and re-detection from stored hits draws it again.

    Parameters
    ----------
    seed : int
        The survey's seed.
    slot, return_number : array_like of int
        The pulse slot and the return number (1-based) of each return.
    sigma : float
        Standard deviation (m).

    Returns
    -------
    ndarray of float64
    """
    u1 = _unit_uniform(seed, slot, return_number, 1)
    u2 = _unit_uniform(seed, slot, return_number, 2)
    return float(sigma) * np.sqrt(-2.0 * np.log(u1)) * np.cos(2.0 * np.pi * u2)


def las_intensity(amplitude) -> np.ndarray:
    """LAS ``intensity`` of peak amplitudes, as HELIOS++ writes it.

    ``uint16(65535 / 10⁶ · clip(amplitude, 0, 10⁶))`` (truncated): the study's scenes stay far
    below the clip (a full-footprint foliage echo is ≈ 4·10⁴ at the ULS's 70 m and ≈ 400 at the
    ALS's 700 m). The unscaled value is kept as the float ``amplitude`` of the points.

    Parameters
    ----------
    amplitude : array_like
        Peak amplitudes (units of the energy model).

    Returns
    -------
    ndarray of uint16
    """
    a = np.clip(np.asarray(amplitude, dtype=np.float64), 0.0, INTENSITY_FULL_SCALE)
    return np.floor(a * (65535.0 / INTENSITY_FULL_SCALE)).astype(np.uint16)


def pulse_shape(pulse_length_ns: float, bin_size_ns: float) -> np.ndarray:
    """Sampled pulse shape ``(t/τ)² exp(−t/τ)``, τ = pulse length / 7 (p[0] = 0)."""
    n = int(np.floor(pulse_length_ns / bin_size_ns + 1e-9))
    tau = pulse_length_ns / 7.0
    t = np.arange(n) * bin_size_ns
    return (t / tau) ** 2 * np.exp(-t / tau)


def atmospheric_alpha(wavelength_nm: float, visibility_km: float, convention: str = "physical") -> float:
    """Extinction coefficient per metre from visibility (Kim/Kruse), HELIOS++ or physical units."""
    v = visibility_km
    q = 1.6 if v > 50 else (1.3 if v > 6 else 0.585 * v ** (1.0 / 3.0))
    if convention == "helios":  # v1.0: λ in nm against 0.55, per-km value used per metre
        return 3.91 / v * (wavelength_nm / 0.55) ** (-q)
    return 3.91 / v * (wavelength_nm / 550.0) ** (-q) / 1000.0


def subray_energy(ranges, weights, cos_inc, reflectance_pct, n_subrays, *, average_power_w,
                  receiver_diameter_m, optical_efficiency, specularity=0.0, shininess=10.0,
                  atm_alpha=0.0) -> np.ndarray:
    """Received energy ``I`` of sub-ray hits (see the module docstring).

    Parameters
    ----------
    ranges, weights, cos_inc, reflectance_pct : ndarray
        Hit range (m), Gaussian beam weight, |cos| of the incidence angle, reflectance in %.
    n_subrays : int
        Sub-rays per pulse (N of the footprint share).
    specularity, shininess : float or ndarray
        Phong ks and exponent n (0 → Lambertian).
    atm_alpha : float
        Extinction per metre (0: no atmosphere).
    """
    r = np.ascontiguousarray(np.broadcast_to(np.asarray(ranges, dtype=np.float64), np.shape(ranges)))
    shape = r.shape
    n = r.size

    def flat(a):
        return np.ascontiguousarray(np.broadcast_to(np.asarray(a, dtype=np.float64), shape)).reshape(n)

    scale = _energy_scale(average_power_w, receiver_diameter_m, optical_efficiency, n_subrays)
    out = np.empty(n)
    _energy_kernel(r.reshape(n), flat(weights), flat(cos_inc), flat(reflectance_pct), flat(specularity),
                   flat(shininess), float(scale), float(atm_alpha), out)
    return out.reshape(shape)


def hit_energy(ranges, subray, cos_inc, part, frac, refl_pct, spec, shin, n_subrays, *, average_power_w,
               receiver_diameter_m, optical_efficiency, range0=0.0, m2=1.0, atm_alpha=0.0) -> np.ndarray:
    """:func:`subray_energy` of sub-ray hits given by sub-ray index and scene part (one pass).

    The Gaussian weight of sub-ray ``k`` is ``exp(-2 (frac[k]·M²)² R²/(R² + R0²))``; the
    reflectance (%), Phong specularity and shininess are looked up per part.
    """
    scale = _energy_scale(average_power_w, receiver_diameter_m, optical_efficiency, n_subrays)
    out = np.empty(len(ranges))
    _hit_energy_kernel(np.ascontiguousarray(ranges, np.float64), np.ascontiguousarray(subray, np.int64),
                       np.ascontiguousarray(cos_inc, np.float64), np.ascontiguousarray(part, np.int64),
                       np.ascontiguousarray(frac, np.float64), np.ascontiguousarray(refl_pct, np.float64),
                       np.ascontiguousarray(spec, np.float64), np.ascontiguousarray(shin, np.float64),
                       float(scale), float(range0), float(m2), float(atm_alpha), out)
    return out


def _energy_scale(average_power_w, receiver_diameter_m, optical_efficiency, n_subrays) -> float:
    """Constant factor of the energy: σ·Pr combined is Pe Dr² η T² ρ brdf cos a · π / (4 N R²) · 1e9
    (the divergence cancels)."""
    return float(average_power_w * receiver_diameter_m ** 2 * optical_efficiency * np.pi / (4.0 * n_subrays) * 1e9)


@numba.njit(cache=True, inline="always")
def _one_energy(r, w, cos_inc, refl, spec, shin, scale, alpha):
    """Energy of one sub-ray hit: range, Gaussian weight, |cos a|, reflectance %, Phong ks and n."""
    c = min(max(cos_inc, 0.0), 1.0)
    brdf = c
    if spec != 0.0:
        a = np.arccos(c)
        a2 = a if a <= np.pi / 2 else a - np.pi / 2
        brdf = (1.0 - spec) * c + spec * abs(np.cos(a2)) ** shin
    rr = max(r, 1e-6)
    e = scale * w * refl * brdf * c / (rr * rr)
    if alpha != 0.0:
        e *= np.exp(-2.0 * rr * alpha)
    return e


@numba.njit(cache=True)
def _weight_consts(frac, m2):
    """Per sub-ray ``a = 2 (frac·M²)²`` and ``exp(−a)``: the Gaussian beam weight far from the waist."""
    a = np.empty(frac.shape[0])
    ea = np.empty(frac.shape[0])
    for k in range(frac.shape[0]):
        f = frac[k] * m2
        a[k] = 2.0 * f * f
        ea[k] = np.exp(-a[k])
    return a, ea


@numba.njit(cache=True, inline="always")
def _beam_weight(r, a, ea, r0):
    """Gaussian beam weight ``exp(−a R²/(R² + R0²))`` of a sub-ray hit at range ``r`` given its
    ``a`` and ``ea = exp(−a)`` (:func:`_weight_consts`).

    Written as ``exp(−a) · exp(y)`` with ``y = a R0²/(R² + R0²)``; beyond a few R0 (every
    airborne hit) ``y ≤ 0.03`` and ``exp(y)`` is its Taylor polynomial to ``y⁸/8!``
    (truncation below 10⁻¹⁹): the result agrees with ``exp`` to a few units in the last
    place, without one libm ``exp`` per hit (most of the energy's cost); larger ``y`` use ``exp``.
    """
    rr = max(r, 1e-6)
    h = r0 * r0 / (rr * rr + r0 * r0)
    y = a * h
    if y <= 0.03:
        y2 = y * y
        y4 = y2 * y2
        p = ((1.0 + y) + y2 * (0.5 + y * (1.0 / 6.0))) + y4 * (
            ((1.0 / 24.0) + y * (1.0 / 120.0)) + y2 * ((1.0 / 720.0) + y * (1.0 / 5040.0)) + y4 * (1.0 / 40320.0))
        return ea * p
    return np.exp(-a * (rr * rr / (rr * rr + r0 * r0)))


@numba.njit(cache=True, inline="always")
def _subray_hit_energy(r, a, ea, cos_inc, refl, spec, shin, scale, r0, alpha):
    """Energy of one sub-ray hit: its Gaussian beam weight (:func:`_beam_weight`, ``a`` and
    ``ea`` of its sub-ray) times :func:`_one_energy`."""
    return _one_energy(r, _beam_weight(r, a, ea, r0), cos_inc, refl, spec, shin, scale, alpha)


@numba.njit(cache=True)
def _hit_energy_kernel(r, sub, cos_inc, part, frac, refl, spec, shin, scale, r0, m2, alpha, out):
    wa, wea = _weight_consts(frac, m2)
    for i in range(r.shape[0]):
        q = part[i]
        k = sub[i]
        out[i] = _subray_hit_energy(r[i], wa[k], wea[k], cos_inc[i], refl[q], spec[q], shin[q], scale, r0, alpha)


@numba.njit(cache=True)
def _energy_kernel(r, w, cos_inc, refl, spec, shin, scale, alpha, out):
    for i in range(r.shape[0]):
        out[i] = _one_energy(r[i], w[i], cos_inc[i], refl[i], spec[i], shin[i], scale, alpha)


@numba.njit(cache=True, inline="always")
def _detect_one(ranges, energy, order_buf, shape, peak_index, bin_m, win, eps, eps_nb, max_returns,
                helios_rule, dedupe, wave, out_range, out_amp, out_sub, unimodal):
    """Detect the returns of one pulse; returns the number written to the out arrays.

    ``eps`` is the peak's threshold, ``eps_nb`` the floor every neighbour of a peak must reach
    under the helios rule (:func:`detection_constants`).

    The hits' energies are summed per waveform bin in the order given (sorted by range only
    when duplicate ranges are dropped; ``order_buf`` is scratch space for that order).
    ``unimodal``: the pulse shape rises strictly up to ``peak_index`` and falls strictly after
    it (:func:`_is_unimodal`); then a pulse whose hits all lie in its first bin (most pulses:
    open ground) has the waveform ``E × shape``, whose only peak (physical rule, window > 0)
    is ``E × shape[peak_index]`` at the nearest range: that is written without building the
    waveform.
    """
    n = ranges.shape[0]
    if n == 0:
        return 0
    d_min = ranges.min()
    d_max = ranges.max()
    npulse = shape.shape[0]
    # hits are taken in the order given; only dropping duplicate ranges needs them sorted
    order = _range_order(ranges, order_buf) if dedupe else order_buf[:0]
    if unimodal and not helios_rule and win > 0 and int((d_max - d_min) / bin_m) == 0:
        e_sum = 0.0
        last = -1.0
        for q in range(n):
            s = order[q] if dedupe else q
            d = ranges[s]
            if dedupe and d == last:
                continue
            last = d
            e_sum += energy[s]
        if e_sum >= 1e-200:  # far from underflow, where E × shape could lose its strict slopes
            v = shape[peak_index] * e_sum
            if v < eps or v <= 0.0:
                return 0
            out_range[0] = d_min
            out_amp[0] = v
            out_sub[0] = _nearest_hit(ranges, d_min)
            return 1
    nbins = int((d_max - d_min) / bin_m) + npulse
    if 2 * nbins > wave.shape[0]:
        nbins = wave.shape[0] // 2
    # the hits' energies are first summed per bin (the second half of ``wave``), then each
    # occupied bin adds one pulse shape: most pulses put all their sub-ray hits in one or two bins
    ebin = wave[nbins:2 * nbins]
    for i in range(2 * nbins):
        wave[i] = 0.0
    last = -1.0
    for q in range(n):
        s = order[q] if dedupe else q
        d = ranges[s]
        if dedupe and d == last:
            continue  # HELIOS++ v1.0: a bit-identical range key is ignored (quirk 5)
        last = d
        b = int((d - d_min) / bin_m)
        if b < nbins:
            ebin[b] += energy[s]
    for b in range(nbins):
        e = ebin[b]
        if e != 0.0:
            lim = min(npulse, nbins - b)  # the pulse shape, clipped at the end of the waveform
            w = wave[b:b + lim]  # a view: the compiler vectorises the loop
            for i in range(lim):
                w[i] += shape[i] * e
    found = 0
    for i in range(nbins):
        v = wave[i]
        if v < eps or v <= 0.0:
            continue
        ok = True
        if helios_rule:
            lo = i - win + 1
            if lo < 1:
                lo = 1
            for j in range(lo, i):
                if wave[j] < eps_nb or wave[j] >= v:
                    ok = False
                    break
            if ok:
                hi = i + win
                if hi > nbins:
                    hi = nbins
                for j in range(i + 1, hi):
                    if wave[j] < eps_nb or wave[j] >= v:
                        ok = False
                        break
        else:
            # the nearest neighbours reject most bins (rising or falling edges): test them first
            if (i > 0 and win > 0 and wave[i - 1] >= v) or (i + 1 < nbins and win > 0 and wave[i + 1] > v):
                continue
            lo = i - win
            if lo < 0:
                lo = 0
            for j in range(lo, i):
                if wave[j] >= v:
                    ok = False
                    break
            if ok:
                hi = i + win + 1
                if hi > nbins:
                    hi = nbins
                for j in range(i + 1, hi):
                    if wave[j] > v:
                        ok = False
                        break
        if not ok:
            continue
        d_ret = d_min + (i - peak_index) * bin_m
        out_range[found] = d_ret
        out_amp[found] = v
        out_sub[found] = _nearest_hit(ranges, d_ret)  # its object id is the return's
        found += 1
        if max_returns > 0 and found >= max_returns:
            break
        if found >= out_range.shape[0]:
            break
    return found


@numba.njit(cache=True, inline="always")
def _nearest_hit(ranges, d):
    """Index of the first hit nearest in range to ``d``."""
    best = 0
    bestd = 1e300
    for q in range(ranges.shape[0]):
        dd = abs(ranges[q] - d)
        if dd < bestd:
            bestd = dd
            best = q
    return best


@numba.njit(cache=True)
def _is_unimodal(shape, peak_index):
    """Whether the sampled pulse shape rises strictly to ``peak_index`` and falls strictly after."""
    if peak_index <= 0:
        return False
    for i in range(1, shape.shape[0]):
        if i <= peak_index and not shape[i] > shape[i - 1]:
            return False
        if i > peak_index and not shape[i] < shape[i - 1]:
            return False
    return True


@numba.njit(cache=True, inline="always")
def _range_order(x, buf):
    """Stable ascending order of ``x``: insertion sort into ``buf`` when it fits, else merge sort."""
    if x.shape[0] <= buf.shape[0]:
        return _stable_order(x, buf)
    return np.argsort(x, kind="mergesort")


@numba.njit(cache=True, inline="always")
def _stable_order(x, buf):
    """Stable ascending order of a short array (insertion sort into ``buf``)."""
    n = x.shape[0]
    order = buf[:n]
    for i in range(n):
        j = i
        v = x[i]
        while j > 0 and x[order[j - 1]] > v:
            order[j] = order[j - 1]
            j -= 1
        order[j] = i
    return order


@numba.njit(cache=True)
def _detect_all(ptr, ranges, energy, shape, peak_index, bin_m, win, eps, eps_nb, max_returns,
                helios_rule, dedupe, max_per_pulse):
    unimodal = _is_unimodal(shape, peak_index)
    m = ptr.shape[0] - 1
    cap = m * max_per_pulse
    r_pulse = np.empty(cap, np.int64)
    r_range = np.empty(cap, np.float64)
    r_amp = np.empty(cap, np.float64)
    r_hit = np.empty(cap, np.int64)
    r_num = np.empty(cap, np.int16)
    r_nret = np.empty(cap, np.int16)
    nret = np.zeros(m, np.int16)
    maxspan = 0.0
    for p in range(m):
        a, b = ptr[p], ptr[p + 1]
        if b > a:
            span = ranges[a:b].max() - ranges[a:b].min()
            if span > maxspan:
                maxspan = span
    wave = np.empty(2 * (int(maxspan / bin_m) + shape.shape[0] + 2), np.float64)  # waveform + energy per bin
    order_buf = np.empty(1024, np.int64)
    o_range = np.empty(max_per_pulse, np.float64)
    o_amp = np.empty(max_per_pulse, np.float64)
    o_sub = np.empty(max_per_pulse, np.int64)
    k = 0
    for p in range(m):
        a, b = ptr[p], ptr[p + 1]
        if b == a:
            continue
        rr = ranges[a:b]
        f = _detect_one(rr, energy[a:b], order_buf, shape, peak_index, bin_m, win, eps, eps_nb, max_returns,
                        helios_rule, dedupe, wave, o_range, o_amp, o_sub, unimodal)
        nret[p] = f
        for q in range(f):
            r_pulse[k] = p
            r_range[k] = o_range[q]
            r_amp[k] = o_amp[q]
            r_hit[k] = a + o_sub[q]
            r_num[k] = q + 1
            r_nret[k] = f
            k += 1
    return r_pulse[:k], r_range[:k], r_amp[:k], r_hit[:k], r_num[:k], r_nret[:k], nret


def detect_returns(ptr, ranges, energy, *, pulse_length_ns=4.0, bin_size_ns=0.25, window_size_ns=1.0,
                   min_energy=0.0, max_returns=0, peak_rule="physical", two_way_time=False,
                   dedupe_ranges=False, threshold_scope="window"):
    """Full-waveform peak detection for many pulses.

    Parameters
    ----------
    ptr : ndarray of int64, shape (m+1,)
        CSR offsets: the hits of pulse p are ``ranges[ptr[p]:ptr[p+1]]``.
    ranges, energy : ndarray
        Sub-ray hit ranges (m) and energies.
    pulse_length_ns, bin_size_ns, window_size_ns : float
        Pulse length, waveform bin and detection window.
    min_energy : float
        Minimum peak amplitude of a return (the detection threshold).
    max_returns : int
        Keep at most this many earliest returns per pulse (0: all).
    peak_rule : {"physical", "helios"}
        Peak neighbourhood rule (module docstring).
    two_way_time : bool
        Use a two-way time axis instead of HELIOS++'s one-way axis.
    dedupe_ranges : bool
        Ignore a second sub-ray hit at a bit-identical range (HELIOS++ quirk 5).
    threshold_scope : {"window", "peak"}
        Under the helios rule, whether ``min_energy`` applies to the peak and every neighbour
        in its window or to the peak alone (module docstring).

    Returns
    -------
    dict of ndarray
        Per return: ``pulse`` (index into the m pulses), ``range``, ``amplitude``, ``hit``
        (index of the sub-ray hit nearest in range), ``return_number``, ``number_of_returns``;
        and ``n_returns`` per pulse.
    """
    const = detection_constants(pulse_length_ns=pulse_length_ns, bin_size_ns=bin_size_ns,
                                window_size_ns=window_size_ns, min_energy=min_energy, max_returns=max_returns,
                                peak_rule=peak_rule, two_way_time=two_way_time, dedupe_ranges=dedupe_ranges,
                                threshold_scope=threshold_scope)
    ptr = np.asarray(ptr, dtype=np.int64)
    res = _detect_all(ptr, np.asarray(ranges, np.float64), np.asarray(energy, np.float64), *const)
    keys = ("pulse", "range", "amplitude", "hit", "return_number", "number_of_returns", "n_returns")
    return dict(zip(keys, res))


def detection_constants(*, pulse_length_ns=4.0, bin_size_ns=0.25, window_size_ns=1.0, min_energy=0.0,
                        max_returns=0, peak_rule="physical", two_way_time=False, dedupe_ranges=False,
                        threshold_scope="window") -> tuple:
    """The detection settings as the positional constants of the peak-detection kernels.

    Parameters are those of :func:`detect_returns`.

    Returns
    -------
    tuple
        ``(shape, peak_index, bin_m, win, eps, eps_nb, max_returns, helios_rule, dedupe,
        max_per_pulse)``: the sampled pulse shape, the index of its maximum, the bin length in
        metres, the window in bins, the peak's amplitude threshold, the floor of a peak's
        neighbours under the helios rule, the return cap (0: none), the peak rule and
        duplicate-range switches, and the most returns one pulse can yield.
    """
    if threshold_scope not in ("window", "peak"):
        raise ConfigError(f"threshold_scope must be 'window' or 'peak', got {threshold_scope!r}")
    shape = pulse_shape(pulse_length_ns, bin_size_ns)
    peak_index = int(np.argmax(shape))
    bin_m = C_M_PER_NS * bin_size_ns / (2.0 if two_way_time else 1.0)
    win = int(np.floor(window_size_ns / bin_size_ns + 1e-9))
    helios = peak_rule == "helios"
    eps = HELIOS_FLOOR if (helios and min_energy <= 0) else float(min_energy)
    # the helios rule's neighbour floor: HELIOS++ 1.0.8's, or the threshold where it covers the window
    eps_nb = eps if (helios and threshold_scope == "window") else HELIOS_FLOOR
    max_per = int(max_returns) if max_returns and max_returns > 0 else 32
    return (shape, peak_index, float(bin_m), win, eps, eps_nb, int(max_returns), peak_rule == "helios", bool(dedupe_ranges),
            max_per)


def energy_constants(*, n_subrays, average_power_w, receiver_diameter_m, optical_efficiency, range0=0.0, m2=1.0,
                     atm_alpha=0.0) -> tuple:
    """The energy settings of :func:`hit_energy` as the constants ``(scale, range0, m2, atm_alpha)``
    of :func:`detect_traced`."""
    return (_energy_scale(average_power_w, receiver_diameter_m, optical_efficiency, n_subrays), float(range0),
            float(m2), float(atm_alpha))


def detect_traced(t, part, cos_inc, live, n_subrays, n_pulses, range_min, frac, refl_pct, spec, shin, energy_const,
                  detection_const):
    """Hits, energy, waveform and peaks of traced pulses in one pass, straight from the cast.

    Gives exactly what :func:`hit_energy` followed by :func:`detect_returns` give on the
    collected hits (the sub-ray hits with ``range_min <= t < inf`` of each pulse, in sub-ray
    order, with |cos| rounded to float32 as stored), without building the hit arrays.

    Parameters
    ----------
    t, part, cos_inc : ndarray, shape (len(live) · n_subrays,)
        The cast of the sub-rays, pulse-major: range (inf: no hit), scene part, |cos| incidence.
    live : ndarray of int64
        Row (among the ``n_pulses`` pulses of the batch) of each traced pulse.
    n_subrays, n_pulses : int
    range_min : float
        Hits nearer than this are ignored.
    frac, refl_pct, spec, shin : ndarray
        Fractional ring radius per sub-ray; reflectance (%), Phong ks and exponent per part.
    energy_const, detection_const : tuple
        From :func:`energy_constants` and :func:`detection_constants`.

    Returns
    -------
    tuple of ndarray
        Per return: ``pulse`` (row in the batch), ``range``, ``amplitude``, ``ray`` (index of
        the sub-ray hit nearest in range, into ``t``), ``return_number``,
        ``number_of_returns``; and ``n_returns`` per pulse (length ``n_pulses``).
    """
    z32, z3 = np.zeros(0, np.float32), np.zeros((0, 3), np.float32)
    return _detect_traced(False, t, part, cos_inc, z32, np.zeros(0, np.int32), z3, z3, np.zeros(0, np.int32), live,
                          int(n_subrays), int(n_pulses), float(range_min), frac, refl_pct, spec, shin, *energy_const,
                          *detection_const)


def detect_embree(tfar, geom, ng, d32, parts, live, n_subrays, n_pulses, range_min, frac, refl_pct, spec, shin,
                  energy_const, detection_const):
    """:func:`detect_traced` straight from Embree's answer (no voxel grids, no face labels).

    Reads the hit range, geometry and geometric normal of each sub-ray where Embree left them
    instead of first copying them into range / part / |cos| arrays; the results are identical.

    Parameters
    ----------
    tfar : ndarray of float32
        Embree's hit distance per sub-ray (pulse-major).
    geom : ndarray of int32
        Embree's geometry id per sub-ray (−1: no hit).
    ng : ndarray of float32, shape (n, 3)
        Embree's geometric normal per sub-ray.
    d32 : ndarray of float32, shape (n, 3)
        The sub-ray directions cast.
    parts : ndarray of int32
        Scene part of each Embree geometry.
    live, n_subrays, n_pulses, range_min, frac, refl_pct, spec, shin, energy_const, detection_const
        As for :func:`detect_traced`.

    Returns
    -------
    tuple of ndarray
        As :func:`detect_traced`.
    """
    z64, z32 = np.zeros(0), np.zeros(0, np.int32)
    return _detect_traced(True, z64, z32, z64, tfar, geom, ng, d32, parts, live, int(n_subrays), int(n_pulses),
                          float(range_min), frac, refl_pct, spec, shin, *energy_const, *detection_const)


@numba.njit(cache=True, inline="always")
def hit_cos32(ng, d, i):
    """|cos| of the incidence angle of sub-ray ``i`` from Embree's geometric normal, in float32
    arithmetic (0 for a degenerate normal)."""
    nx, ny, nz = ng[i, 0], ng[i, 1], ng[i, 2]
    nn = np.sqrt(nx * nx + ny * ny + nz * nz)
    if nn > 0:
        return np.float64(abs(nx * d[i, 0] + ny * d[i, 1] + nz * d[i, 2]) / nn)
    return 0.0


@numba.njit(cache=True)
def _detect_traced(raw, t, part, cos_inc, tfar, geom, ng, d32, parts, live, ns, m, range_min, frac, refl, spec,
                   shin, scale, r0, m2, alpha, shape, peak_index, bin_m, win, eps, eps_nb, max_returns, helios_rule, dedupe,
                   max_per_pulse):
    unimodal = _is_unimodal(shape, peak_index)
    wa, wea = _weight_consts(frac, m2)
    nl = live.shape[0]
    cap = 2 * nl + max_per_pulse
    r_pulse = np.empty(cap, np.int64)
    r_range = np.empty(cap, np.float64)
    r_amp = np.empty(cap, np.float64)
    r_ray = np.empty(cap, np.int64)
    r_num = np.empty(cap, np.int16)
    r_nret = np.empty(cap, np.int16)
    nret = np.zeros(m, np.int16)
    rr = np.empty(ns, np.float64)
    en = np.empty(ns, np.float64)
    ray = np.empty(ns, np.int64)
    order_buf = np.empty(1024, np.int64)
    wave = np.empty(2 * (shape.shape[0] + 64), np.float64)
    o_range = np.empty(max_per_pulse, np.float64)
    o_amp = np.empty(max_per_pulse, np.float64)
    o_sub = np.empty(max_per_pulse, np.int64)
    k = 0
    for j in range(nl):
        n = 0
        lo = np.inf
        hi = -np.inf
        base = j * ns
        for s in range(ns):
            i = base + s
            g = 0
            if raw:  # Embree's answer as it is
                g = geom[i]
                if g < 0:
                    continue
                d = np.float64(tfar[i])
            else:
                d = t[i]
            if d < np.inf and d >= range_min:
                if raw:
                    q = parts[g]
                    c = hit_cos32(ng, d32, i)  # float32 arithmetic, as _embree_hits stores it
                else:
                    q = part[i]
                    c = np.float64(np.float32(cos_inc[i]))  # |cos| is kept as float32 with the hits
                rr[n] = d
                en[n] = _subray_hit_energy(d, wa[s], wea[s], c, refl[q], spec[q], shin[q], scale, r0, alpha)
                ray[n] = i
                n += 1
                lo = min(lo, d)
                hi = max(hi, d)
        if n == 0:
            continue
        need = 2 * (int((hi - lo) / bin_m) + shape.shape[0] + 2)  # waveform + energy per bin
        if need > wave.shape[0]:
            wave = np.empty(2 * need, np.float64)
        r = rr[:n]
        f = _detect_one(r, en[:n], order_buf, shape, peak_index, bin_m, win, eps, eps_nb, max_returns, helios_rule,
                        dedupe, wave, o_range, o_amp, o_sub, unimodal)
        if f == 0:
            continue
        p = live[j]
        nret[p] = f
        if k + f > cap:
            cap = 2 * cap + f
            r_pulse = _grow(r_pulse, cap, k)
            r_range = _grow(r_range, cap, k)
            r_amp = _grow(r_amp, cap, k)
            r_ray = _grow(r_ray, cap, k)
            r_num = _grow(r_num, cap, k)
            r_nret = _grow(r_nret, cap, k)
        for q in range(f):
            r_pulse[k] = p
            r_range[k] = o_range[q]
            r_amp[k] = o_amp[q]
            r_ray[k] = ray[o_sub[q]]
            r_num[k] = q + 1
            r_nret[k] = f
            k += 1
    return r_pulse[:k], r_range[:k], r_amp[:k], r_ray[:k], r_num[:k], r_nret[:k], nret


@numba.njit(cache=True)
def _grow(a, cap, k):
    out = np.empty(cap, a.dtype)
    out[:k] = a[:k]
    return out
