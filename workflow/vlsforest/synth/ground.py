"""A gently rough ground surface for the plots of the virtual Bretten forest.

The terrain of a plot is a tilted plane plus smooth random bumps:

``z(x, y) = elevation + g · (p − origin) + Σ_k a_k cos(k_k · (p − origin) + φ_k)``

with a gradient ``g`` of small magnitude (at most ``slope_max``, random direction) and ``n_modes``
cosine waves whose wavelengths lie in ``wavelength_m`` (random directions and phases) and whose
amplitudes ``a_k = roughness_m · sqrt(2 / n_modes)`` give the bumps a root-mean-square height of
``roughness_m`` (default 0.15 m on 10–20 m scales, slope ≤ 1 %): the trees stand on a slightly
uneven forest floor, while the simulations of the study use one plane at the approximate terrain
elevation (:meth:`vlsforest.synth.forest.PlotLayout.ground_z`).

The surface is a pure function of its parameters, which are drawn once from a seed
(:meth:`GroundSurface.random`); :meth:`GroundSurface.z` is vectorised and
:meth:`GroundSurface.mesh` triangulates it on a regular grid over an extent.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from vlsforest.errors import ConfigError
from vlsforest.io.mesh import TriangleMesh


def _finite(name: str, v, lo: float | None = None, hi: float | None = None) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) \
            or not math.isfinite(float(v)):
        raise ConfigError(f"{name}: must be a finite number, got {v!r}")
    v = float(v)
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        raise ConfigError(f"{name}: must lie in [{lo}, {hi}], got {v}")
    return v


@dataclass(frozen=True)
class GroundSurface:
    """A tilted plane plus a sum of cosine waves (all lengths in metres).

    Parameters
    ----------
    elevation : float
        Height of the plane at ``origin`` (m a.s.l.).
    origin : (float, float)
        Reference point of the plane and the waves (usually the plot centre).
    gradient : (float, float)
        Slope of the plane, dz/dx and dz/dy.
    wavevectors : tuple of (float, float)
        Wave vectors k (rad/m) of the bumps.
    amplitudes : tuple of float
        Amplitude of each wave (m).
    phases : tuple of float
        Phase of each wave (rad).

    The parameters are plain tuples so that two surfaces compare equal exactly when they are the
    same function.
    """

    elevation: float
    origin: tuple[float, float] = (0.0, 0.0)
    gradient: tuple[float, float] = (0.0, 0.0)
    wavevectors: tuple[tuple[float, float], ...] = ()
    amplitudes: tuple[float, ...] = ()
    phases: tuple[float, ...] = ()

    def __post_init__(self):
        _finite("ground.elevation", self.elevation)
        if not (len(self.wavevectors) == len(self.amplitudes) == len(self.phases)):
            raise ConfigError("ground: wavevectors, amplitudes and phases differ in length")

    # ------------------------------------------------------------------ construction
    @classmethod
    def random(cls, seed: int, elevation: float, origin=(0.0, 0.0), slope_max: float = 0.01,
               roughness_m: float = 0.15, wavelength_m=(10.0, 20.0),
               n_modes: int = 16) -> "GroundSurface":
        """Draw a gently rough surface from a seed.

        Parameters
        ----------
        seed : int
            Seed of the draw (same seed and arguments → the same surface).
        elevation : float
            Plane height at ``origin`` (m).
        origin : (float, float)
            Reference point (e.g. the plot centre).
        slope_max : float
            The plane's gradient magnitude is uniform in ``[0, slope_max]`` (dimensionless).
        roughness_m : float
            Root-mean-square height of the bumps (m); 0 gives a tilted plane.
        wavelength_m : (float, float)
            Range of the bump wavelengths (m).
        n_modes : int
            Number of cosine waves.

        Raises
        ------
        ConfigError
            A parameter outside its range (names it, as ``forest.ground.<name>``).
        """
        slope_max = _finite("forest.ground.slope_max", slope_max, 0.0, 0.3)
        roughness_m = _finite("forest.ground.roughness_m", roughness_m, 0.0, 2.0)
        try:
            lam = [float(v) for v in wavelength_m]
        except TypeError:
            raise ConfigError("forest.ground.wavelength_m: expected [min, max] in metres, got "
                              f"{wavelength_m!r}") from None
        if len(lam) != 2 or not all(math.isfinite(v) and v > 0 for v in lam) or lam[0] > lam[1]:
            raise ConfigError("forest.ground.wavelength_m: expected [min, max] with "
                              f"0 < min <= max, got {wavelength_m!r}")
        if isinstance(n_modes, bool) or not isinstance(n_modes, (int, np.integer)) \
                or not 1 <= n_modes <= 256:
            raise ConfigError(f"forest.ground.n_modes: must be an integer in [1, 256], "
                              f"got {n_modes!r}")
        ox, oy = (_finite("ground.origin", v) for v in origin)
        rng = np.random.default_rng(seed)
        s = slope_max * rng.random()
        a = rng.uniform(0.0, 2 * np.pi)
        wl = rng.uniform(lam[0], lam[1], n_modes)
        direc = rng.uniform(0.0, 2 * np.pi, n_modes)
        k = (2 * np.pi / wl)[:, None] * np.c_[np.cos(direc), np.sin(direc)]
        ph = rng.uniform(0.0, 2 * np.pi, n_modes)
        amp = np.full(n_modes, roughness_m * math.sqrt(2.0 / n_modes))
        return cls(elevation=float(elevation), origin=(ox, oy),
                   gradient=(float(s * math.cos(a)), float(s * math.sin(a))),
                   wavevectors=tuple((float(u), float(v)) for u, v in k),
                   amplitudes=tuple(float(v) for v in amp), phases=tuple(float(v) for v in ph))

    # ------------------------------------------------------------------ evaluation
    def z(self, x, y) -> np.ndarray:
        """Ground height at (x, y); broadcasts like numpy (scalars give a 0-d array)."""
        dx = np.asarray(x, dtype=float) - self.origin[0]
        dy = np.asarray(y, dtype=float) - self.origin[1]
        z = self.elevation + self.gradient[0] * dx + self.gradient[1] * dy
        for (kx, ky), a, p in zip(self.wavevectors, self.amplitudes, self.phases):
            z = z + a * np.cos(kx * dx + ky * dy + p)
        return z

    def gradient_at(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Analytic gradient (dz/dx, dz/dy) at (x, y)."""
        dx = np.asarray(x, dtype=float) - self.origin[0]
        dy = np.asarray(y, dtype=float) - self.origin[1]
        gx = np.full(np.broadcast(dx, dy).shape, self.gradient[0])
        gy = np.full(gx.shape, self.gradient[1])
        for (kx, ky), a, p in zip(self.wavevectors, self.amplitudes, self.phases):
            s = -a * np.sin(kx * dx + ky * dy + p)
            gx = gx + kx * s
            gy = gy + ky * s
        return gx, gy

    def grid(self, extent, spacing: float = 1.0):
        """Regular grid over ``extent`` = (xmin, ymin, xmax, ymax), edges included.

        Returns
        -------
        xs, ys : ndarray
            Node coordinates along x and y (the last node lies exactly on the far edge; the
            spacing is at most ``spacing``).
        Z : ndarray (len(ys), len(xs))
            Heights at the nodes.
        """
        xmin, ymin, xmax, ymax = (float(v) for v in extent)
        if not (np.isfinite([xmin, ymin, xmax, ymax]).all() and xmax > xmin and ymax > ymin):
            raise ConfigError(f"extent: expected finite (xmin, ymin, xmax, ymax) with "
                              f"xmax > xmin and ymax > ymin, got {extent!r}")
        if not (isinstance(spacing, (int, float)) and spacing > 0 and math.isfinite(spacing)):
            raise ConfigError(f"spacing: must be a positive number, got {spacing!r}")
        nx = max(int(math.ceil((xmax - xmin) / spacing - 1e-9)), 1) + 1
        ny = max(int(math.ceil((ymax - ymin) / spacing - 1e-9)), 1) + 1
        xs = np.linspace(xmin, xmax, nx)
        ys = np.linspace(ymin, ymax, ny)
        return xs, ys, self.z(xs[None, :], ys[:, None])

    def mesh(self, extent, spacing: float = 1.0) -> TriangleMesh:
        """Triangulated surface over ``extent`` (two triangles per grid cell, normals up).

        Parameters
        ----------
        extent : (xmin, ymin, xmax, ymax)
        spacing : float
            Largest grid spacing (m).
        """
        xs, ys, Z = self.grid(extent, spacing)
        X, Y = np.meshgrid(xs, ys)
        verts = np.c_[X.ravel(), Y.ravel(), Z.ravel()]
        nx = xs.size
        idx = np.arange(verts.shape[0]).reshape(ys.size, nx)
        a, b = idx[:-1, :-1], idx[:-1, 1:]
        c, d = idx[1:, :-1], idx[1:, 1:]
        faces = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3),
                                np.stack([a, d, c], -1).reshape(-1, 3)])
        return TriangleMesh(verts, faces.astype(np.int32))


__all__ = ["GroundSurface"]
