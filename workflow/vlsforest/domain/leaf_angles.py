"""Leaf angle distributions and the projection function G(θ).

G(θ) is the mean projection, on a plane normal to a beam of zenith angle θ, of a unit of
one-sided leaf area whose normal inclinations θL follow a density f on [0, π/2] (azimuths
uniform):

    G(θ) = ∫₀^{π/2} A(θ, θL) f(θL) dθL,

    A = cos θ cos θL                                          if θ + θL ≤ π/2,
    A = cos θ cos θL (1 − 2ψ/π) + (2/π) sin θ sin θL sin ψ    otherwise, ψ = arccos(cot θ cot θL).

The second form is the usual ``cos θ cos θL [1 + (2/π)(tan ψ − ψ)]`` rewritten so that it stays
finite at θ = 90°. The integral is evaluated by Gauss–Legendre quadrature split at the kink
θL = π/2 − θ, tabulated on a 0.1° grid and interpolated linearly; angles are folded into
[0°, 90°] (θ → 180° − θ for upward beams).

Leaf inclination densities (de Wit 1965, plus spherical), θL = leaf normal zenith angle:

=============  ==========================
planophile     (2/π)(1 + cos 2θL)
erectophile    (2/π)(1 − cos 2θL)
plagiophile    (2/π)(1 − cos 4θL)
extremophile   (2/π)(1 + cos 4θL)
uniform        2/π
spherical      sin θL   (G ≡ 0.5)
=============  ==========================
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from vlsforest.errors import ConfigError

#: the supported leaf angle distributions (de Wit's five and spherical)
LAD_NAMES = ("planophile", "erectophile", "plagiophile", "extremophile", "uniform", "spherical")

#: LUT step (degrees)
_STEP_DEG = 0.1
_N_GAUSS = 96


def leaf_inclination_pdf(lad: str, theta_l) -> np.ndarray:
    """Density of the leaf-normal inclination θL (radians) on [0, π/2].

    Parameters
    ----------
    lad : str
        One of :data:`LAD_NAMES`.
    theta_l : array_like
        Inclinations in radians.

    Returns
    -------
    ndarray
        f(θL); integrates to 1 over [0, π/2].
    """
    t = np.asarray(theta_l, dtype=float)
    c = 2.0 / np.pi
    name = check_lad(lad)
    if name == "planophile":
        return c * (1.0 + np.cos(2.0 * t))
    if name == "erectophile":
        return c * (1.0 - np.cos(2.0 * t))
    if name == "plagiophile":
        return c * (1.0 - np.cos(4.0 * t))
    if name == "extremophile":
        return c * (1.0 + np.cos(4.0 * t))
    if name == "uniform":
        return np.full_like(t, c)
    return np.sin(t)  # spherical


def check_lad(lad, key: str = "lad") -> str:
    """Normalised name of a leaf angle distribution.

    Parameters
    ----------
    lad : str
        One of :data:`LAD_NAMES` (any case, surrounding blanks ignored).
    key : str
        Name of the setting, for the error message.

    Returns
    -------
    str
        The name in lower case.

    Raises
    ------
    ConfigError
        For a name not in :data:`LAD_NAMES`.
    """
    name = str(lad).strip().lower()
    if name not in LAD_NAMES:
        raise ConfigError(f"{key}: unknown leaf angle distribution {lad!r}; known: {', '.join(LAD_NAMES)}")
    return name


def _projection(theta: float, theta_l: np.ndarray) -> np.ndarray:
    """A(θ, θL) for one beam angle θ (radians, in [0, π/2]) and leaf inclinations θL."""
    ct, st = np.cos(theta), np.sin(theta)
    cl, sl = np.cos(theta_l), np.sin(theta_l)
    out = ct * cl
    kink = theta + theta_l > np.pi / 2
    if np.any(kink):
        # cot θ cot θL = (ct·cl)/(st·sl); st, sl > 0 wherever θ + θL > π/2
        x = np.clip((ct * cl[kink]) / (st * sl[kink]), -1.0, 1.0)
        psi = np.arccos(x)
        out = out.copy()
        out[kink] = ct * cl[kink] * (1.0 - 2.0 * psi / np.pi) + (2.0 / np.pi) * st * sl[kink] * np.sin(psi)
    return out


@lru_cache(maxsize=1)
def _gauss() -> tuple[np.ndarray, np.ndarray]:
    return np.polynomial.legendre.leggauss(_N_GAUSS)


def _g_exact(theta: float, lad: str) -> float:
    """G(θ) by Gauss–Legendre quadrature split at the kink (θ in radians, [0, π/2])."""
    x, w = _gauss()
    kink = np.pi / 2 - theta
    total = 0.0
    for a, b in ((0.0, kink), (kink, np.pi / 2)):
        if b - a <= 0.0:
            continue
        t = 0.5 * (b - a) * x + 0.5 * (a + b)
        total += 0.5 * (b - a) * float(np.sum(w * _projection(theta, t) * leaf_inclination_pdf(lad, t)))
    return total


@lru_cache(maxsize=None)
def _lut(lad: str) -> np.ndarray:
    n = int(round(90.0 / _STEP_DEG)) + 1
    th = np.radians(np.linspace(0.0, 90.0, n))
    if lad == "spherical":
        return np.full(n, 0.5)
    table = np.array([_g_exact(t, lad) for t in th])
    table.setflags(write=False)
    return table


def fold_zenith(theta_deg) -> np.ndarray:
    """Fold zenith angles (degrees, 0–180) into [0°, 90°]: θ → 180° − θ above 90°."""
    t = np.asarray(theta_deg, dtype=float)
    return np.where(t > 90.0, 180.0 - t, t)


def g_function(theta_deg, lad: str = "planophile") -> np.ndarray:
    """Projection function G(θ) of a leaf angle distribution.

    Parameters
    ----------
    theta_deg : array_like
        Beam zenith angles in **degrees** (0–180; folded into [0, 90]). NaN gives NaN.
    lad : str
        Leaf angle distribution, one of :data:`LAD_NAMES`.

    Returns
    -------
    ndarray or float
        G(θ), linear interpolation in a 0.1° table of the exact integral (error < 1e-5).

    Raises
    ------
    ConfigError
        Unknown ``lad`` or an angle outside [0, 180].
    """
    name = check_lad(lad)
    t = np.asarray(theta_deg, dtype=float)
    finite = np.isfinite(t)
    if np.any((t[finite] < -1e-9) | (t[finite] > 180.0 + 1e-9)):
        raise ConfigError(f"theta_deg: zenith angles must lie in [0, 180] degrees, got {t[finite].min()}..{t[finite].max()}")
    f = np.clip(fold_zenith(np.where(finite, t, 0.0)), 0.0, 90.0)
    table = _lut(name)
    out = np.interp(f / _STEP_DEG, np.arange(len(table)), table)
    out = np.where(finite, out, np.nan)
    return out if out.ndim else float(out)


def g_closed_form(lad: str, end: str) -> float:
    """G at nadir/zenith (``end="0"``) or horizontal (``end="90"``) in closed form.

    ``G(0) = ∫ cos θL f`` and ``G(π/2) = (2/π) ∫ sin θL f``; e.g. planophile 8/(3π) and 8/(3π²).
    """
    name = check_lad(lad)
    g0 = {"planophile": 8 / (3 * np.pi), "erectophile": 4 / (3 * np.pi), "plagiophile": 32 / (15 * np.pi),
          "extremophile": 28 / (15 * np.pi), "uniform": 2 / np.pi, "spherical": 0.5}
    g90 = {"planophile": 8 / (3 * np.pi ** 2), "erectophile": 16 / (3 * np.pi ** 2),
           "plagiophile": 64 / (15 * np.pi ** 2), "extremophile": 56 / (15 * np.pi ** 2),
           "uniform": 4 / np.pi ** 2, "spherical": 0.5}
    if end == "0":
        return float(g0[name])
    if end == "90":
        return float(g90[name])
    raise ConfigError(f"end: must be '0' or '90', got {end!r}")


__all__ = ["LAD_NAMES", "check_lad", "leaf_inclination_pdf", "g_function", "fold_zenith", "g_closed_form"]
