"""PAD estimators on the traversal accumulators, flags, and the ``.vox`` export.

Estimators (per voxel; E = Σ bf·S entering, I = Σ bf·S intercepted, O = E − I):

``transmittance`` (the study's, AMAPVox 1.4–1.6)
    Solve ``Σ_r bsIn_r · T^{l_r} = O`` for the transmittance per metre T ∈ [0, 1] over the
    records r (one per shot and voxel; ``l_r`` the mean length of the non-intercepted free
    paths, the potential length when none). The records are kept as a histogram over l (24
    bins, each with its exact Σ bsIn·l); the root is found by safeguarded Newton iteration on
    k = −ln T. ``E = 0 → NaN``, ``I = 0 → T = 1``, ``O ≤ 1e-5·E → T = 0`` (saturated).
    PAD = −ln T / G(θ̄).
``fpl_unbiased`` (Pimont et al. 2018, bias-corrected maximum likelihood)
    ``k = I / Σ bf·S·l_eff`` minus the correction ``Σ_hits bf·S·l_eff · E / (Σ bf·S·l_eff)² / N``
    (N = shots), floored at 0; PAD = k / G(θ̄).

G is evaluated once per voxel at its mean zenith angle θ̄ (folded per shot into [0°, 90°] by
default, see :func:`estimate_pad`). Voxels crossed by fewer than ``min_pulses`` shots are
flagged and left NaN; a saturated voxel gets PADmax; values above PADmax are clipped to it.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from vlsforest.domain.leaf_angles import LAD_NAMES, check_lad, g_function
from vlsforest.errors import ConfigError
from vlsforest.pad.traverse import Accumulators

ESTIMATORS = ("transmittance", "fpl_unbiased")

#: flag bits
FLAG_UNSAMPLED = 1     # no shot crossed the voxel
FLAG_FEW_PULSES = 2    # fewer than min_pulses shots (PAD left NaN)
FLAG_SATURATED = 4     # no beam left the voxel (T = 0): PAD = PADmax
FLAG_CLIPPED = 8       # estimate above PADmax, clipped

_K_MAX = 1e4


@njit(cache=True)
def _solve_k(h0, h1, O):
    """Root k ≥ 0 of Σ_b h0_b exp(−k L_b) = O with L_b = h1_b / h0_b (decreasing in k)."""
    nb = h0.shape[0]
    # bracket
    lo = 0.0
    hi = 1.0
    while True:
        f = 0.0
        for b in range(nb):
            if h0[b] > 0.0:
                f += h0[b] * math.exp(-hi * h1[b] / h0[b])
        if f < O or hi >= _K_MAX:
            break
        lo = hi
        hi *= 2.0
    k = 0.5 * (lo + hi)
    for _ in range(200):
        f = 0.0
        df = 0.0
        for b in range(nb):
            if h0[b] > 0.0:
                L = h1[b] / h0[b]
                t = h0[b] * math.exp(-k * L)
                f += t
                df -= L * t
        g = f - O
        if g > 0.0:
            lo = k
        else:
            hi = k
        if abs(g) <= 1e-13 * O or hi - lo <= 1e-12 * max(1.0, k):
            break
        kn = k - g / df if df < 0.0 else 0.5 * (lo + hi)
        if not (lo < kn < hi):
            kn = 0.5 * (lo + hi)
        k = kn
    return k


@njit(cache=True)
def _transmittance(E, I, bsl_exit, slot, hist, out):
    """Transmittance per metre of every listed voxel (arrays of the same length)."""
    for v in range(E.shape[0]):
        if E[v] <= 0.0:
            out[v] = np.nan
            continue
        if I[v] <= 0.0:
            out[v] = 1.0
            continue
        O = E[v] - I[v]
        if O <= 1e-5 * E[v]:
            out[v] = 0.0
            continue
        sl = slot[v]
        if sl >= 0:
            k = _solve_k(hist[sl, :, 0], hist[sl, :, 1], O)
            out[v] = math.exp(-k)
        else:  # no histogram (should not happen for voxels with hits): mean exit length
            lbar = bsl_exit[v] / E[v]
            out[v] = (O / E[v]) ** (1.0 / lbar) if lbar > 0.0 else np.nan


def _select(acc: Accumulators, ijk):
    """Flat views of the accumulators, for all voxels (ijk None) or the listed ones."""
    names = ("nb_sampling", "nb_echos", "lg_total", "angle_sum", "angle_sum_folded", "bs_entering",
             "bs_intercepted", "leff_sum", "leff_hit_sum", "bsl_exit", "slot")
    if ijk is None:
        return {n: getattr(acc, n).reshape(-1) for n in names}
    ijk = np.asarray(ijk)
    if ijk.ndim != 2 or ijk.shape[1] != 3:
        raise ConfigError(f"ijk: expected shape (n, 3), got {ijk.shape}")
    ijk = ijk.astype(np.int64)
    if len(ijk) and (np.any(ijk < 0) or np.any(ijk >= np.asarray(acc.shape))):
        raise ConfigError(f"ijk: indices outside the grid {acc.shape}")
    t = (ijk[:, 0], ijk[:, 1], ijk[:, 2])
    return {n: getattr(acc, n)[t] for n in names}


def transmittance(acc: Accumulators, ijk=None) -> np.ndarray:
    """Numerical transmittance per metre (NaN where unsampled); dense or per listed voxel."""
    a = _select(acc, ijk)
    out = np.empty(len(a["bs_entering"]))
    _transmittance(a["bs_entering"], a["bs_intercepted"], a["bsl_exit"], a["slot"], acc.hist, out)
    return out.reshape(acc.shape) if ijk is None else out


def _fpl(a) -> tuple[np.ndarray, np.ndarray]:
    """Biased FPL attenuation k and its bias-correction term."""
    with np.errstate(invalid="ignore", divide="ignore"):
        L = a["leff_sum"]
        ok = (L > 0) & (a["nb_sampling"] > 0)
        k = np.where(ok, a["bs_intercepted"] / np.where(ok, L, 1.0), np.nan)
        corr = np.where(ok, a["leff_hit_sum"] * a["bs_entering"] / np.where(ok, L, 1.0) ** 2
                        / np.maximum(a["nb_sampling"], 1), np.nan)
    return k, corr


def _per_voxel(value, n, name, kind):
    """A scalar or an array of n values (or of the grid shape, flattened)."""
    if kind == "lad":
        if isinstance(value, str):
            return check_lad(value, name), None
        arr = np.asarray(value, dtype=object).reshape(-1)
    else:
        if np.ndim(value) == 0:
            v = float(value)
            if not (math.isfinite(v) and v > 0):
                raise ConfigError(f"{name}: must be a positive number, got {value!r}")
            return v, None
        arr = np.asarray(value, dtype=float).reshape(-1)
    if arr.shape[0] != n:
        raise ConfigError(f"{name}: expected one value per voxel ({n}), got {arr.shape[0]}")
    if kind == "pad_max" and not np.all(np.isfinite(arr) & (arr > 0)):
        raise ConfigError(f"{name}: every value must be a positive number")
    return None, arr


def _g_per_voxel(theta, lad, n) -> np.ndarray:
    single, arr = _per_voxel(lad, n, "lad", "lad")
    if single is not None:
        return np.asarray(g_function(theta, single), dtype=float).reshape(-1)
    names = np.array([str(x).strip().lower() for x in arr], dtype=object)
    bad = sorted(set(names) - set(LAD_NAMES))
    if bad:
        raise ConfigError(f"lad: unknown leaf angle distribution(s) {bad}; known: {', '.join(LAD_NAMES)}")
    g = np.full(n, np.nan)
    for name in sorted(set(names)):
        m = names == name
        g[m] = g_function(theta[m], name)
    return g


def estimate_pad(acc: Accumulators, lad="planophile", pad_max=5.0, estimator: str = "transmittance",
                 min_pulses: int = 5, ijk=None, fold_angles: bool = True):
    """Plant area density from the accumulators.

    Parameters
    ----------
    acc : Accumulators
        From :func:`vlsforest.pad.accumulate`.
    lad : str or array of str
        Leaf angle distribution (:data:`~vlsforest.domain.leaf_angles.LAD_NAMES`), one for all voxels or
        one per voxel (grid shape, or length n with ``ijk``).
    pad_max : float or array
        PADmax (m²/m³), one value or one per voxel like ``lad``.
    estimator : {"transmittance", "fpl_unbiased"}
    min_pulses : int
        Voxels crossed by fewer shots are flagged (:data:`FLAG_FEW_PULSES`) and left NaN.
    ijk : array (n, 3), optional
        Estimate only these voxels; the results are then arrays of length n.
    fold_angles : bool
        Evaluate G at the mean of the per-shot zenith angles folded into [0°, 90°] (default).
        False: at the raw mean over 0–180° folded afterwards (AMAPVox behaviour; up- and
        downward beams average towards 90°).

    Returns
    -------
    pad : ndarray
        PAD (m²/m³), NaN where flagged unsampled or few pulses.
    flags : ndarray of uint8
        Bit mask: 1 unsampled, 2 fewer than ``min_pulses`` shots, 4 saturated (PAD = PADmax),
        8 clipped to PADmax.
    """
    if estimator not in ESTIMATORS:
        raise ConfigError(f"estimator: must be one of {', '.join(ESTIMATORS)}, got {estimator!r}")
    if isinstance(min_pulses, bool) or not isinstance(min_pulses, (int, np.integer)) or min_pulses < 1:
        raise ConfigError(f"min_pulses: must be an integer ≥ 1, got {min_pulses!r}")
    a = _select(acc, ijk)
    n = len(a["nb_sampling"])
    pm_single, pm_arr = _per_voxel(pad_max, n, "pad_max", "pad_max")
    pmax = np.full(n, pm_single) if pm_arr is None else pm_arr
    nbs = a["nb_sampling"]
    with np.errstate(invalid="ignore", divide="ignore"):
        theta = np.where(nbs > 0, (a["angle_sum_folded"] if fold_angles else a["angle_sum"]) / np.maximum(nbs, 1),
                         np.nan)
    g = _g_per_voxel(theta, lad, n)
    flags = np.zeros(n, np.uint8)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        if estimator == "transmittance":
            T = np.empty(n)
            _transmittance(a["bs_entering"], a["bs_intercepted"], a["bsl_exit"], a["slot"], acc.hist, T)
            sat = T == 0.0
            k = -np.log(np.where(sat, 1.0, T))
        else:
            kb, corr = _fpl(a)
            k = np.maximum(kb - corr, 0.0)
            O = a["bs_entering"] - a["bs_intercepted"]
            sat = (a["bs_intercepted"] > 0) & (O <= 1e-5 * a["bs_entering"])
        pad = k / g
    pad = np.where(sat, pmax, pad)
    flags[sat] |= FLAG_SATURATED
    over = np.isfinite(pad) & (pad > pmax)
    pad = np.where(over, pmax, pad)
    flags[over] |= FLAG_CLIPPED
    few = nbs < min_pulses
    flags[nbs == 0] |= FLAG_UNSAMPLED
    flags[few] |= FLAG_FEW_PULSES
    pad = np.where(few, np.nan, pad)
    pad = np.where(pad == 0.0, 0.0, pad)  # no −0.0
    if ijk is None:
        return pad.reshape(acc.shape), flags.reshape(acc.shape)
    return pad, flags


def pad_to_vox(acc: Accumulators, pad, flags, pad_max: float, lad: str = "planophile", keep: str = "echoes",
               estimator: str = "transmittance"):
    """The estimate as an AMAPVox ``.vox`` (:class:`vlsforest.io.vox.VoxFile`).

    Parameters
    ----------
    acc : Accumulators
    pad, flags : ndarray, grid shape
        From :func:`estimate_pad` (dense).
    pad_max : float
        Written as ``#max_pad`` (the cap; with per-voxel caps give their maximum).
    lad : str
        Written as ``#lad_type``.
    keep : {"echoes", "sampled", "all"}
        Rows written: voxels holding plant echoes (default; every other sampled voxel has
        PAD 0 or is flagged NaN), every voxel crossed by a shot, or every voxel.
    estimator : str
        Written as ``#estimator``.

    Returns
    -------
    VoxFile
        Columns :data:`~vlsforest.io.vox.STANDARD_COLUMNS` (``PadBVTotal`` = PAD, NaN where
        flagged few pulses/unsampled; ``transmittance`` per metre; ``attenuation`` the biased FPL
        k; ``attenuationBiasCorrection`` its correction term; ``ground_distance`` and
        ``bsPotential`` are NaN: no terrain model here) plus ``flag`` and ``angleMeanFolded``
        (mean zenith angle with each shot folded into [0°, 90°], the angle G is taken at).
    """
    from vlsforest.io.vox import make_vox

    keeps = ("echoes", "sampled", "all")
    if keep not in keeps:
        raise ConfigError(f"keep: must be one of {', '.join(keeps)}, got {keep!r}")
    pad = np.asarray(pad)
    flags = np.asarray(flags)
    if pad.shape != tuple(acc.shape) or flags.shape != tuple(acc.shape):
        raise ConfigError(f"pad/flags: expected the grid shape {acc.shape}, got {pad.shape} / {flags.shape}")
    if keep == "echoes":
        sel = acc.nb_echos > 0
    elif keep == "sampled":
        sel = acc.nb_sampling > 0
    else:
        sel = np.ones(acc.shape, bool)
    ijk = np.argwhere(sel)
    a = _select(acc, ijk)
    nbs = a["nb_sampling"]
    T = np.empty(len(ijk))
    _transmittance(a["bs_entering"], a["bs_intercepted"], a["bsl_exit"], a["slot"], acc.hist, T)
    kb, corr = _fpl(a)
    with np.errstate(invalid="ignore", divide="ignore"):
        denom = np.maximum(nbs, 1)
        cols = {
            "PadBVTotal": pad[sel],
            "angleMean": np.where(nbs > 0, a["angle_sum"] / denom, np.nan),
            "bsEntering": a["bs_entering"],
            "bsIntercepted": a["bs_intercepted"],
            "bsPotential": np.full(len(ijk), np.nan),
            "ground_distance": np.full(len(ijk), np.nan),
            "lMeanTotal": np.where(nbs > 0, a["lg_total"] / denom, np.nan),
            "lgTotal": a["lg_total"],
            "nbEchos": a["nb_echos"].astype(float),
            "nbSampling": nbs.astype(float),
            "transmittance": T,
            "attenuation": kb,
            "attenuationBiasCorrection": corr,
            "flag": flags[sel].astype(float),
            # mean of the per-shot zenith angles folded into [0°, 90°] (what G is evaluated at)
            "angleMeanFolded": np.where(nbs > 0, a["angle_sum_folded"] / denom, np.nan),
        }
    header = {"nsubvoxel": "1", "lad_type": str(lad).capitalize(), "type": "TLS",
              "estimator": estimator, "build-version": "1.4.3"}
    return make_vox(ijk, acc.cell_size, acc.origin, columns=cols, max_pad=float(pad_max), header=header,
                    split=np.asarray(acc.shape))


__all__ = ["ESTIMATORS", "FLAG_UNSAMPLED", "FLAG_FEW_PULSES", "FLAG_SATURATED", "FLAG_CLIPPED",
           "estimate_pad", "transmittance", "pad_to_vox"]
