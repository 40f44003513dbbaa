"""Parametric tree generator (in the spirit of Weber & Penn 1995) for the virtual Bretten forest.

:func:`generate_tree` turns :class:`~vlsforest.synth.species.TreeParams` into a triangle mesh
(:class:`TreeGeometry`) with one organ label per face:

* **stem** (organ 0): horizontal rings of a tapered stem (butt swell below 1.3 m, taper
  ``((H−z)/(H−1.3))**p`` above) along a centreline with lean (a straight tilt) and sweep (a bow),
  closed by an apex at the tree height; a separate closed copy with a base cap is kept as
  ``stem_mesh`` for mesh-distance validation;
* **branches** (organ 1): first-order branches (spiral for broadleaf, whorls for conifers) and
  second-order twigs, each a chain of frustums whose direction bends by the species' droop; their
  lengths are fitted (vectorised bisection) so that they end inside the crown envelope;
* **foliage** (organ 2): individual planar elements — leaf clusters (broadleaf) or needle shoots
  (conifers), one triangle each — placed around the outer part of the twigs (clumping), with
  metre-scale gaps (twigs in the low part of a smooth random field carry no foliage), and normals
  drawn from the species' leaf angle distribution (planophile / erectophile).

Crown envelope: a surface of revolution about the stem centreline, from the crown base (CBH) to
the tree top, with radius ``R(z, φ) = s R_max f(t) m(φ)``, ``t = (z−CBH)/(H−CBH)``; ``f``
(:func:`crown_profile`) rises from ``crown_base_fraction`` to 1 at ``crown_widest`` and falls to 0
at the top as an ellipse, paraboloid or cone; ``m(φ)`` is a small first- and second-harmonic
asymmetry.  ``R_max`` is chosen so that the convex hull of the widest outline equals the requested
CPA.

Crown plasticity (``TreeParams.neighbours``, ``crown_scale``; set by the forest layout): real
crowns in a closed stand do not interpenetrate, they fill the gaps between them.  At every height
where a neighbour's crown exists too, the envelope is cut by the line perpendicular to the stem–stem
direction that splits the stem distance ``d`` in proportion to the two crowns' radii there
(:func:`split_distance`, times :data:`CROWN_OVERLAP` = 1.1: crowns interdigitate a little); a taller
tree above its neighbour's top, or a tree below its neighbour's crown base, is not cut.  The
layout grows the crown scale ``s ≥ 1`` so that a crown cut on some sides keeps its nominal
projection area where the free sides allow (up to ``s = 1.5``).

Foliage amount and element size (the memory budget): the one-sided foliage area is the species'
``crown_lai`` (leaf area per crown projection area: beech 7, hornbeam 6, oak 5, spruce 10, Douglas
fir 8.5, pine 3.5 m²/m²) times the envelope's projected area, so a closed stand (canopy cover ≈ 1)
has a stand LAI of ≈ 6–9 as measured in beech and spruce forests.  Foliage elements have the
species' ``leaf_element_area`` (0.005–0.01 m², i.e. a cluster of a few leaves or one needle
shoot) unless the tree's ``max_triangles`` budget (after the woody parts) would be exceeded; then
the element area grows so that the element count fits, always keeping the one-sided foliage area
exact (``TreeGeometry.foliage_element_area`` reports the size used).  The foliage sits on the outer
part of the twigs, clumped, with metre-scale gaps, so the foliated 0.25 m voxels hold a plant area
density of a few m²/m³: half of the foliage of the study's target trees lies in voxels denser than
≈ 2.1 (beech), 2.5 (hornbeam), 3.8 (spruce) m²/m³ (broadleaf ≈ 1–5, conifer ≈ 2–8;
``tests/test_synth_trees.py``), while the crown as a whole (envelope mean 0.2–2 m²/m³) is much
sparser.

Truth is computed from the geometry: height = highest vertex above ground, CBH = lowest branch or
foliage vertex above ground, CPA = area of the 2-D convex hull of branch and foliage vertices,
crown radius = ``sqrt(CPA/π)``, DBH = twice the stem ring radius at 1.3 m.

Plant area convention (see :mod:`vlsforest.synth.plant_area`): foliage counts its one-sided area,
woody faces (stem, branches) half their surface area; the stem's ground cap is not part of the
scene mesh (it exists only in ``stem_mesh``).

Everything is vectorised numpy; loops run over frustum rings and bisection steps only.  The same
parameters and rng state give byte-identical arrays.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from vlsforest.errors import ConfigError
from vlsforest.synth.species import (
    SpeciesParams,
    TreeParams,
    get_species,
    sample_leaf_inclination,
)

ORGAN_STEM = 0
ORGAN_BRANCH = 1
ORGAN_FOLIAGE = 2
ORGAN_NAMES = {ORGAN_STEM: "stem", ORGAN_BRANCH: "branch", ORGAN_FOLIAGE: "foliage"}
#: plant area per unit triangle area, by organ (woody: half the surface; foliage: one side)
PLANT_AREA_WEIGHT = np.array([0.5, 0.5, 1.0])

_BREAST_HEIGHT = 1.3


@dataclass
class TriMesh:
    """A plain triangle mesh: ``vertices`` float64 (n, 3), ``faces`` int32 (m, 3)."""

    vertices: np.ndarray
    faces: np.ndarray

    def face_areas(self) -> np.ndarray:
        v = self.vertices[self.faces]
        return 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)

    def signed_volume(self) -> float:
        """Enclosed volume (positive for a closed mesh with outward faces)."""
        v = self.vertices[self.faces]
        return float(np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6.0)


@dataclass
class TreeGeometry:
    """One generated tree.

    Attributes
    ----------
    vertices : ndarray, float64 (n, 3)
        World coordinates (the ground point of the stem is ``position``).
    faces : ndarray, int32 (m, 3)
    organ : ndarray, uint8 (m,)
        0 stem, 1 branch, 2 foliage.
    stem_mesh : TriMesh
        Closed stem surface (rings, apex, ground cap), outward faces.
    species : str
    position : ndarray (3,)
        Stem base (x, y, ground z).
    height, dbh, cbh, cpa, crown_radius : float
        Truth measured on the geometry (m, m, m, m², m).
    crown_volume : float
        Volume of the crown envelope (m³), neighbour cuts included.
    envelope_area : float
        Projected area of the crown envelope (m², neighbour cuts included); the foliage area is
        the species' crown LAI times this area.
    foliage_element_area : float
        One-sided area of each foliage element actually used (m²).
    params : TreeParams
        The inputs.
    """

    vertices: np.ndarray
    faces: np.ndarray
    organ: np.ndarray
    stem_mesh: TriMesh
    species: str
    position: np.ndarray
    height: float
    dbh: float
    cbh: float
    cpa: float
    crown_radius: float
    crown_volume: float
    envelope_area: float
    foliage_element_area: float
    params: TreeParams = field(repr=False)

    @property
    def n_triangles(self) -> int:
        return int(self.faces.shape[0])

    def face_areas(self) -> np.ndarray:
        """Area of every face (m²)."""
        return TriMesh(self.vertices, self.faces).face_areas()

    def plant_area(self, organs=None) -> float:
        """Total plant area (m²): one-sided foliage plus half the woody surface.

        Parameters
        ----------
        organs : iterable of int, optional
            Restrict to these organ codes.
        """
        w = PLANT_AREA_WEIGHT[self.organ] * self.face_areas()
        if organs is not None:
            w = w[np.isin(self.organ, np.asarray(list(organs)))]
        return float(w.sum())

    def truth(self) -> dict:
        """Scalar truth of this tree as a plain dict."""
        return {
            "species": self.species,
            "x": float(self.position[0]), "y": float(self.position[1]),
            "z_ground": float(self.position[2]),
            "height": self.height, "dbh": self.dbh, "cbh": self.cbh, "cpa": self.cpa,
            "crown_radius": self.crown_radius, "crown_volume": self.crown_volume,
            "plant_area": self.plant_area(),
            "foliage_area": self.plant_area((ORGAN_FOLIAGE,)),
            "n_triangles": self.n_triangles,
        }


# ----------------------------------------------------------------------------------------------
# geometry helpers


def _normalize(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 0, n, 1.0)


def _hull_area_2d(xy: np.ndarray) -> float:
    from scipy.spatial import ConvexHull

    if xy.shape[0] < 3:
        return 0.0
    return float(ConvexHull(xy).volume)


class _Stem:
    """Centreline and radius profile of the stem (local coordinates, ground at z = 0)."""

    def __init__(self, sp: SpeciesParams, p: TreeParams, rng: np.random.Generator):
        self.H = float(p.height)
        self.r_bh = 0.5 * float(p.dbh)
        self.taper = sp.stem_taper
        self.swell = sp.butt_swell
        lean = math.radians(abs(rng.normal(0.0, sp.lean_sd)))
        a_lean, a_sweep = rng.uniform(0.0, 2 * np.pi, 2)
        self.lean = math.tan(lean) * np.array([math.cos(a_lean), math.sin(a_lean)])
        amp = sp.sweep * self.H * rng.uniform(0.5, 1.5)
        self.sweep = amp * np.array([math.cos(a_sweep), math.sin(a_sweep)])

    def centre(self, z: np.ndarray) -> np.ndarray:
        z = np.asarray(z, dtype=float)
        return z[..., None] * self.lean + np.sin(np.pi * np.clip(z / self.H, 0, 1))[..., None] \
            * self.sweep

    def radius(self, z: np.ndarray) -> np.ndarray:
        z = np.asarray(z, dtype=float)
        above = self.r_bh * np.clip((self.H - z) / (self.H - _BREAST_HEIGHT), 0, None) ** self.taper
        below = self.r_bh * (1 + self.swell * np.clip((_BREAST_HEIGHT - z) / _BREAST_HEIGHT, 0, 1)
                             ** 2)
        return np.where(z >= _BREAST_HEIGHT, above, below)


def crown_profile(sp: SpeciesParams, t) -> np.ndarray:
    """Relative envelope radius ``f(t)`` of a species' crown, ``t`` = 0 at the crown base, 1 at
    the top: rises from ``crown_base_fraction`` to 1 at ``crown_widest``, then falls to 0 as an
    ellipse, paraboloid or cone."""
    t = np.clip(np.asarray(t, dtype=float), 0.0, 1.0)
    tw, f0 = sp.crown_widest, sp.crown_base_fraction
    lo = f0 + (1 - f0) * np.sqrt(np.clip(1 - ((tw - t) / tw) ** 2, 0, 1))
    u = np.clip((t - tw) / (1 - tw), 0, 1)
    if sp.crown_shape == "ellipsoid":
        hi = np.sqrt(np.clip(1 - u**2, 0, 1))
    elif sp.crown_shape == "paraboloid":
        hi = np.sqrt(1 - u)
    elif sp.crown_shape == "cone":
        hi = 1 - u
    else:
        raise ConfigError(f"crown_shape: unknown shape {sp.crown_shape!r}")
    return np.where(t < tw, lo, hi)


def neighbour_radius(nb, z) -> np.ndarray:
    """Envelope radius (without azimuthal modulation) of a neighbour's crown at heights ``z``
    (above the confined tree's stem base); 0 outside its crown."""
    z = np.asarray(z, dtype=float)
    L = nb.height - nb.cbh
    t = (z - nb.cbh) / L
    r = nb.radius * crown_profile(get_species(nb.species), t)
    return np.where((t >= 0) & (t < 1), r, 0.0)


def split_distance(r_own, r_nb, d, overlap):
    """Distance from the own stem to the boundary with a neighbour ``d`` away: the stem distance
    split in proportion to the two crown radii at that height, times ``overlap`` (≥ 1 lets
    crowns interdigitate); ∞ where the neighbour has no crown."""
    r_own = np.asarray(r_own, dtype=float)
    r_nb = np.asarray(r_nb, dtype=float)
    tot = r_own + r_nb
    with np.errstate(divide="ignore", invalid="ignore"):
        b = overlap * d * np.where(tot > 0, r_own / np.where(tot > 0, tot, 1.0), 1.0)
    return np.where(r_nb > 0, b, np.inf)


#: crowns interdigitate by this much: the two sides of a boundary add up to 1.1 × the stem distance
CROWN_OVERLAP = 1.1


class _Envelope:
    """Crown envelope: radius R(z, φ) = s R_max f(t) m(φ) about the stem centreline, cut by the
    boundaries with competing neighbours (crown plasticity)."""

    def __init__(self, sp: SpeciesParams, p: TreeParams, stem: _Stem, rng: np.random.Generator):
        self.sp = sp
        self.cbh = float(p.cbh)
        self.H = float(p.height)
        self.L = self.H - self.cbh
        self.stem = stem
        self.a = sp.crown_asymmetry * rng.uniform(0.3, 1.0, 2)
        self.phi = rng.uniform(0.0, 2 * np.pi, 2)
        ang = np.linspace(0.0, 2 * np.pi, 720, endpoint=False)
        m = self.modulation(ang)
        hull1 = _hull_area_2d(np.c_[m * np.cos(ang), m * np.sin(ang)])
        self.scale = float(p.crown_scale)
        self.rmax = math.sqrt(float(p.cpa) / hull1) * self.scale
        # the nominal (unmodulated) widest radius, as the forest layout sees this crown
        self.r_nominal = math.sqrt(float(p.cpa) / math.pi) * self.scale
        self.neighbours = tuple(p.neighbours)
        self._nb = []
        for nb in self.neighbours:
            d = math.hypot(nb.dx, nb.dy)
            if d > 0:
                self._nb.append((nb, d, nb.dx / d, nb.dy / d))
        self.volume, self.area = self._measure()

    def _measure(self, nz: int = 64, nphi: int = 180):
        """Volume (m³) and projected area (m², star-shaped outline) of the cut envelope."""
        z = self.cbh + self.L * (np.arange(nz) + 0.5) / nz
        phi = 2 * np.pi * np.arange(nphi) / nphi
        zz, pp = np.meshgrid(z, phi, indexing="ij")
        R = self.radius_at(zz, pp)
        dphi = 2 * np.pi / nphi
        vol = float((0.5 * R**2).sum() * dphi * self.L / nz)
        # the outline over all heights, about the crown axis at mid-crown (lean is small)
        area = float(0.5 * (R.max(axis=0) ** 2).sum() * dphi)
        return vol, area

    def modulation(self, phi):
        a, p = self.a, self.phi
        return 1.0 + a[0] * np.cos(phi - p[0]) + a[1] * np.cos(2 * (phi - p[1]))

    def profile(self, t):
        return crown_profile(self.sp, t)

    def radius_at(self, z, phi):
        """Envelope radius at heights ``z`` and azimuths ``phi`` about the crown axis."""
        z = np.asarray(z, dtype=float)
        phi = np.asarray(phi, dtype=float)
        R = self.rmax * self.profile((z - self.cbh) / self.L) * self.modulation(phi)
        R = np.where(z >= self.H, 0.0, R)
        if self._nb:
            own = self.r_nominal * self.profile((z - self.cbh) / self.L)
            c = self.stem.centre(z)
            cphi, sphi = np.cos(phi), np.sin(phi)
            for nb, d, ux, uy in self._nb:
                b = split_distance(own, neighbour_radius(nb, z), d, CROWN_OVERLAP)
                # the boundary relative to the (leaning) crown axis at this height
                b = np.maximum(b - (c[..., 0] * ux + c[..., 1] * uy), 0.05)
                cosang = cphi * ux + sphi * uy
                with np.errstate(divide="ignore", invalid="ignore"):
                    lim = np.where(cosang > 1e-9, b / np.where(cosang > 1e-9, cosang, 1.0),
                                   np.inf)
                R = np.minimum(R, lim)
        return R

    def polar(self, pts: np.ndarray):
        """(r, φ, R) of points: distance from the axis, azimuth, envelope radius there."""
        z = pts[..., 2]
        d = pts[..., :2] - self.stem.centre(z)
        r = np.hypot(d[..., 0], d[..., 1])
        phi = np.arctan2(d[..., 1], d[..., 0])
        R = self.radius_at(z, phi)
        return r, phi, R, d

    def rho(self, pts: np.ndarray) -> np.ndarray:
        """Normalised radial coordinate r/R (∞ above the top)."""
        r, _, R, _ = self.polar(pts)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(R > 0, r / np.where(R > 0, R, 1.0), np.inf)


def _branch_shapes(az, alpha0, droop, K):
    """Unit-length centreline shapes (B, K, 3) of branches bending from alpha0 by droop."""
    s = np.linspace(0.0, 1.0, K)
    sm = 0.5 * (s[1:] + s[:-1])
    al = alpha0[:, None] + droop[:, None] * sm[None, :]
    d = np.stack([np.sin(al) * np.cos(az)[:, None], np.sin(al) * np.sin(az)[:, None],
                  np.cos(al)], axis=-1) * (1.0 / (K - 1))
    return np.concatenate([np.zeros((len(az), 1, 3)), np.cumsum(d, axis=1)], axis=1)


def _fit_length(env: _Envelope, base, shape, lmax, target, iters=22):
    """Largest length ≤ lmax whose centreline stays within rho ≤ target (vectorised bisection)."""

    def ok(L):
        pts = base[:, None, :] + L[:, None, None] * shape[:, 1:, :]
        return env.rho(pts).max(axis=1) <= target

    full = ok(lmax)
    lo = np.zeros_like(lmax)
    hi = lmax.copy()
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        good = ok(mid)
        lo = np.where(good, mid, lo)
        hi = np.where(good, hi, mid)
    return np.where(full, lmax, lo)


def _tubes(paths: np.ndarray, radii: np.ndarray, sides: int):
    """Frustum chains along (B, K, 3) centrelines with (B, K) radii; parallel-transport frames.

    Returns vertices (B*K*sides, 3) and faces (B*(K−1)*2*sides, 3) with outward orientation.
    """
    B, K, _ = paths.shape
    if B == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    tan = np.empty_like(paths)
    tan[:, 0] = paths[:, 1] - paths[:, 0]
    tan[:, -1] = paths[:, -1] - paths[:, -2]
    if K > 2:
        tan[:, 1:-1] = paths[:, 2:] - paths[:, :-2]
    tan = _normalize(tan)
    ref = np.where(np.abs(tan[:, 0, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    u = np.empty_like(paths)
    u[:, 0] = _normalize(np.cross(ref, tan[:, 0]))
    for k in range(1, K):
        uk = u[:, k - 1] - np.einsum("ij,ij->i", u[:, k - 1], tan[:, k])[:, None] * tan[:, k]
        u[:, k] = _normalize(uk)
    v = np.cross(tan, u)
    ang = 2 * np.pi * np.arange(sides) / sides
    ring = np.cos(ang)[None, None, :, None] * u[:, :, None, :] + \
        np.sin(ang)[None, None, :, None] * v[:, :, None, :]
    verts = paths[:, :, None, :] + radii[:, :, None, None] * ring
    idx = np.arange(B * K * sides).reshape(B, K, sides)
    a = idx[:, :-1, :]
    b = np.roll(idx, -1, axis=2)[:, :-1, :]
    c = idx[:, 1:, :]
    d = np.roll(idx, -1, axis=2)[:, 1:, :]
    faces = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3),
                            np.stack([a, d, c], -1).reshape(-1, 3)])
    return verts.reshape(-1, 3), faces


def _interp_path(paths: np.ndarray, which: np.ndarray, s: np.ndarray):
    """Points and unit tangents at fraction s along paths[which] (piecewise linear)."""
    K = paths.shape[1]
    x = np.clip(s, 0.0, 1.0) * (K - 1)
    i0 = np.minimum(np.floor(x).astype(np.int64), K - 2)
    f = (x - i0)[:, None]
    p0 = paths[which, i0]
    p1 = paths[which, i0 + 1]
    return p0 + f * (p1 - p0), _normalize(p1 - p0)


def _stem_mesh(stem: _Stem, sides: int, dz: float):
    """Ring vertices of the stem plus apex (scene faces) and base cap (closed mesh)."""
    H = stem.H
    n = max(int(math.ceil(H / dz)), 4)
    levels = np.unique(np.round(np.concatenate([
        np.linspace(0.0, H, n + 1)[:-1], [0.15, 0.5, 0.9, _BREAST_HEIGHT]]), 9))
    levels = levels[levels < H - 1e-6]
    c = stem.centre(levels)
    r = stem.radius(levels)
    ang = 2 * np.pi * np.arange(sides) / sides
    ring = np.stack([np.cos(ang), np.sin(ang)], -1)
    nl = levels.size
    verts = np.empty((nl, sides, 3))
    verts[:, :, :2] = c[:, None, :] + r[:, None, None] * ring[None]
    verts[:, :, 2] = levels[:, None]
    apex = np.r_[stem.centre(np.array(H)), H]
    base = np.r_[c[0], 0.0]
    verts = np.concatenate([verts.reshape(-1, 3), apex[None], base[None]])
    idx = np.arange(nl * sides).reshape(nl, sides)
    a, b = idx[:-1], np.roll(idx, -1, axis=1)[:-1]
    cc, d = idx[1:], np.roll(idx, -1, axis=1)[1:]
    side = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3),
                           np.stack([a, d, cc], -1).reshape(-1, 3)])
    top = np.stack([idx[-1], np.roll(idx[-1], -1), np.full(sides, nl * sides)], -1)
    cap = np.stack([np.full(sides, nl * sides + 1), np.roll(idx[0], -1), idx[0]], -1)
    scene_faces = np.concatenate([side, top])
    closed_faces = np.concatenate([side, top, cap])
    return verts, scene_faces, closed_faces, levels, r


def _foliage_elements(centres, normals, spin, area, aspect):
    """One triangle of one-sided area ``area`` per centre, face normal = ``normals``."""
    ref = np.where(np.abs(normals[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    u = _normalize(np.cross(ref, normals))
    v = np.cross(normals, u)
    e1 = np.cos(spin)[:, None] * u + np.sin(spin)[:, None] * v
    e2 = np.cross(normals, e1)
    b = math.sqrt(2.0 * area / aspect)
    h = aspect * b
    v0 = centres + (2.0 * h / 3.0) * e1
    v1 = centres - (h / 3.0) * e1 - 0.5 * b * e2
    v2 = centres - (h / 3.0) * e1 + 0.5 * b * e2
    return np.stack([v0, v2, v1], axis=1), (2.0 * h / 3.0)


# ----------------------------------------------------------------------------------------------
# the generator


def generate_tree(params: TreeParams, position=(0.0, 0.0, 0.0), rng=None,
                  stem_sides: int = 16, stem_dz: float = 0.5) -> TreeGeometry:
    """Generate one tree.

    Parameters
    ----------
    params : TreeParams
        Species, height, DBH, CBH, CPA and the detail budget.
    position : (x, y, z_ground)
        World position of the stem base.
    rng : numpy.random.Generator or int or None
        Randomness (an int is a seed; None means seed 0).  Same state → identical arrays.
    stem_sides : int
        Vertices per stem ring.
    stem_dz : float
        Vertical spacing of the stem rings (m).

    Returns
    -------
    TreeGeometry

    Raises
    ------
    ConfigError
        Invalid parameters (also raised by :class:`TreeParams` itself).
    """
    if not isinstance(params, TreeParams):
        raise ConfigError(f"params: expected TreeParams, got {type(params).__name__}")
    pos = np.asarray(position, dtype=float).reshape(-1)
    if pos.shape != (3,) or not np.isfinite(pos).all():
        raise ConfigError(f"position: expected finite (x, y, z_ground), got {position!r}")
    if stem_sides < 3 or stem_dz <= 0:
        raise ConfigError("stem_sides/stem_dz: need stem_sides >= 3 and stem_dz > 0")
    rng = np.random.default_rng(0 if rng is None else rng)
    sp = params.species_params
    H, cbh = float(params.height), float(params.cbh)
    L = H - cbh

    stem = _Stem(sp, params, rng)
    env = _Envelope(sp, params, stem, rng)
    sv, s_faces, s_closed, _, _ = _stem_mesh(stem, stem_sides, stem_dz)

    # ---- first-order branches
    top_z = H - 0.3 * min(1.0, L / 3.0)
    if sp.whorled:
        steps = sp.whorl_spacing * rng.uniform(0.8, 1.2, int(L / sp.whorl_spacing * 1.5) + 4)
        zw = cbh + np.concatenate([[0.0], np.cumsum(steps)])
        zw = zw[zw < top_z]
        nper = np.clip(sp.branches_per_whorl + rng.integers(-1, 2, zw.size), 3, None)
        zb = np.repeat(zw, nper)
        az_w = np.repeat(rng.uniform(0, 2 * np.pi, zw.size), nper)
        j = np.arange(zb.size) - np.repeat(np.cumsum(nper) - nper, nper)
        az = az_w + 2 * np.pi * j / np.repeat(nper, nper) + rng.normal(0, 0.15, zb.size)
    else:
        n1 = max(int(round(sp.branch_density * L)), 4)
        zb = cbh + (top_z - cbh) * (np.arange(n1) + np.r_[0.0, rng.uniform(0, 0.8, n1 - 1)]) / n1
        az = rng.uniform(0, 2 * np.pi) + np.arange(n1) * math.radians(137.5) + \
            rng.normal(0, 0.25, n1)
    nb = zb.size
    t_rel = (zb - cbh) / L
    alpha0 = np.radians(sp.branch_angle_base + (sp.branch_angle_top - sp.branch_angle_base)
                        * t_rel + rng.normal(0, 5.0, nb))
    droop = np.radians(sp.branch_droop * rng.uniform(0.6, 1.4, nb))
    rs = stem.radius(zb)
    base = np.concatenate([stem.centre(zb) + 0.8 * rs[:, None] * np.c_[np.cos(az), np.sin(az)],
                           zb[:, None]], axis=1)
    K1 = 6
    shape1 = _branch_shapes(az, alpha0, droop, K1)
    target1 = rng.uniform(0.85, 1.0, nb)
    L1 = _fit_length(env, base, shape1, np.full(nb, 1.8 * env.rmax * (1 + env.a.sum())), target1)
    keep = L1 > 0.2
    keep[0] |= sp.whorled is False  # the lowest broadleaf branch always marks the crown base
    L1 = np.maximum(L1, 0.2)
    base, shape1, L1, rs, az = base[keep], shape1[keep], L1[keep], rs[keep], az[keep]
    nb = L1.size
    r1 = np.minimum(sp.branch_thickness * L1 + 0.004, 0.6 * rs)
    path1 = base[:, None, :] + L1[:, None, None] * shape1
    rad1 = r1[:, None] * np.linspace(1.0, 0.0, K1)[None, :] ** 0.8 + 0.003 * \
        np.linspace(0.0, 1.0, K1)[None, :]
    path1[..., 2] = np.clip(path1[..., 2], cbh + rad1, H - rad1 - 0.05)

    # ---- second-order branches (twigs)
    n2 = np.maximum(np.round(sp.twig_density * L1 * rng.uniform(0.8, 1.2, nb)).astype(int), 1)
    parent = np.repeat(np.arange(nb), n2)
    m2 = parent.size
    first = np.cumsum(n2) - n2
    k_in = np.arange(m2) - np.repeat(first, n2)
    s2 = 0.15 + 0.8 * (k_in + rng.uniform(0, 1, m2)) / n2[parent]
    p2, tan2 = _interp_path(path1, parent, s2)
    az_p = np.arctan2(tan2[:, 1], tan2[:, 0])
    al_p = np.arccos(np.clip(tan2[:, 2], -1, 1))
    side = np.where(k_in % 2 == 0, 1.0, -1.0)
    az2 = az_p + side * np.radians(sp.twig_angle) * rng.uniform(0.7, 1.3, m2)
    al2 = np.clip(al_p + np.radians(rng.normal(0, 12.0, m2)), np.radians(20), np.radians(130))
    droop2 = np.radians(0.5 * sp.branch_droop * rng.uniform(0.5, 1.5, m2))
    lmax2 = sp.twig_length * L1[parent] * np.sqrt(1.15 - s2) * rng.uniform(0.7, 1.0, m2)
    # woody triangle budget → mesh resolution
    budget = int(params.max_triangles)
    stem_tris = s_faces.shape[0]
    sides1, sides2, K2 = 6, 4, 4
    for sides1, sides2, K2 in ((6, 4, 4), (5, 3, 4), (4, 3, 3), (3, 3, 3)):
        woody = stem_tris + nb * (K1 - 1) * 2 * sides1 + m2 * (K2 - 1) * 2 * sides2
        if woody <= 0.3 * budget:
            break
    shape2 = _branch_shapes(az2, al2, droop2, K2)
    L2 = _fit_length(env, p2, shape2, lmax2, rng.uniform(0.9, 1.0, m2))
    ok2 = L2 > 0.08
    parent, s2, p2, shape2, L2 = parent[ok2], s2[ok2], p2[ok2], shape2[ok2], L2[ok2]
    m2 = L2.size
    path2 = p2[:, None, :] + L2[:, None, None] * shape2
    r2_base = np.maximum(0.5 * np.interp(s2, [0, 1], [1, 0]) * r1[parent], 0.003)
    rad2 = r2_base[:, None] * np.linspace(1.0, 0.0, K2)[None, :] + 0.0015 * \
        np.linspace(0.0, 1.0, K2)[None, :]
    path2[..., 2] = np.clip(path2[..., 2], cbh + rad2, H - rad2 - 0.05)
    mesh_twigs = np.ones(m2, bool)
    woody = stem_tris + nb * (K1 - 1) * 2 * sides1 + m2 * (K2 - 1) * 2 * sides2
    if woody > 0.3 * budget:  # drop the meshes of the thinnest twigs (they still carry foliage)
        excess = int(math.ceil((woody - 0.3 * budget) / ((K2 - 1) * 2 * sides2)))
        order = np.argsort(r2_base, kind="stable")[:excess]
        mesh_twigs[order] = False
    bv, bf = _tubes(path1, rad1, sides1)
    tv, tf = _tubes(path2[mesh_twigs], rad2[mesh_twigs], sides2)

    # ---- foliage
    foliage_area = (params.crown_lai or sp.crown_lai) * env.area
    woody_tris = s_faces.shape[0] + bf.shape[0] + tf.shape[0]
    n_max = max(budget - woody_tris, 100)
    elem_area = max(params.leaf_element_area or sp.leaf_element_area, foliage_area / n_max)
    n_el = min(max(int(math.floor(foliage_area / elem_area * (1 + 1e-12))), 1), n_max)
    elem_area = foliage_area / n_el
    # carriers: twigs (outer part) and the outer half of first-order branches
    car_paths = np.concatenate([path2, _resample(path1, 0.5, K2)]) if m2 else \
        _resample(path1, 0.5, K2)
    car_len = np.linalg.norm(np.diff(car_paths, axis=1), axis=2).sum(axis=1)
    s_min = np.r_[np.full(m2, sp.foliage_start), np.zeros(nb)]
    weight = car_len * (1 - s_min)
    mid = car_paths[:, K2 // 2]
    kdir = _normalize(rng.normal(size=(6, 3)))
    kvec = kdir * (2 * np.pi / sp.gap_scale * rng.uniform(0.7, 1.3, 6))[:, None]
    g = np.cos(mid @ kvec.T + rng.uniform(0, 2 * np.pi, 6)).sum(axis=1)
    if sp.gap_fraction > 0 and g.size > 1:
        weight = np.where(g < np.quantile(g, sp.gap_fraction), 0.0, weight)
    if weight.sum() <= 0:
        weight = car_len.copy()
    counts = rng.multinomial(n_el, weight / weight.sum())
    which = np.repeat(np.arange(counts.size), counts)
    s = s_min[which] + (1 - s_min[which]) * rng.random(n_el)
    centres, _ = _interp_path(car_paths, which, s)
    off = rng.normal(0.0, sp.clump_radius, (n_el, 3))
    off[:, 2] *= 0.6
    centres = centres + off
    theta = sample_leaf_inclination(sp.leaf_angle_distribution, n_el, rng)
    phi = rng.uniform(0, 2 * np.pi, n_el)
    spin = rng.uniform(0, 2 * np.pi, n_el)
    # keep the element centres inside the envelope (reflect at the boundary)
    b = math.sqrt(2.0 * elem_area / sp.leaf_aspect)
    half = 2.0 / 3.0 * sp.leaf_aspect * b
    z = centres[:, 2]
    zlo, zhi = cbh + half, H - half
    if zhi > zlo:
        z = np.where(z < zlo, 2 * zlo - z, z)
        z = np.where(z > zhi, 2 * zhi - z, z)
        centres[:, 2] = np.clip(z, zlo, zhi)
    r, _, R, d = env.polar(centres)
    out = r > R
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(out, np.clip(2 * R - r, 0, None) / np.where(r > 0, r, 1.0), 1.0)
    centres[:, :2] = centres[:, :2] - d * (1 - scale)[:, None]
    normals = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi),
                        np.cos(theta)], axis=-1)
    tri, _ = _foliage_elements(centres, normals, spin, elem_area, sp.leaf_aspect)
    zmin, zmax = tri[:, :, 2].min(axis=1), tri[:, :, 2].max(axis=1)
    shift = np.maximum(cbh - zmin, 0.0) + np.minimum(H - zmax, 0.0)
    tri[:, :, 2] += shift[:, None]
    fv = tri.reshape(-1, 3)
    ff = np.arange(fv.shape[0]).reshape(-1, 3)

    # ---- assemble
    parts_v = [sv, bv, tv, fv]
    parts_f = [s_faces, bf, tf, ff]
    organs = [ORGAN_STEM, ORGAN_BRANCH, ORGAN_BRANCH, ORGAN_FOLIAGE]
    offs = np.cumsum([0] + [v.shape[0] for v in parts_v])
    vertices = np.concatenate(parts_v) + pos
    faces = np.concatenate([f + o for f, o in zip(parts_f, offs[:-1])]).astype(np.int32)
    organ = np.concatenate([np.full(f.shape[0], o, np.uint8) for f, o in zip(parts_f, organs)])
    # the closed stem mesh (shares vertex layout with sv)
    stem_mesh = TriMesh(sv + pos, s_closed.astype(np.int32))

    # ---- truth from the geometry
    used = np.zeros(vertices.shape[0], bool)
    used[faces.ravel()] = True
    zrel = vertices[:, 2] - pos[2]
    height = float(zrel[used].max())
    crown_v = np.zeros(vertices.shape[0], bool)
    crown_v[faces[organ != ORGAN_STEM].ravel()] = True
    cbh_true = float(zrel[crown_v].min())
    cpa = _hull_area_2d(vertices[crown_v, :2])
    ring = np.isclose(sv[:, 2], _BREAST_HEIGHT)
    cbh_centre = stem.centre(np.array(_BREAST_HEIGHT))
    dbh = float(2 * np.linalg.norm(sv[ring, :2] - cbh_centre, axis=1).mean())
    return TreeGeometry(
        vertices=vertices, faces=faces, organ=organ, stem_mesh=stem_mesh, species=sp.key,
        position=pos.copy(), height=height, dbh=dbh, cbh=cbh_true, cpa=cpa,
        crown_radius=math.sqrt(cpa / math.pi), crown_volume=float(env.volume),
        envelope_area=float(env.area),
        foliage_element_area=float(elem_area), params=params)


def _resample(paths: np.ndarray, s0: float, K: int) -> np.ndarray:
    """Resample (B, Kin, 3) centrelines on K points between fraction s0 and 1."""
    B = paths.shape[0]
    s = np.linspace(s0, 1.0, K)
    which = np.repeat(np.arange(B), K)
    pts, _ = _interp_path(paths, which, np.tile(s, B))
    return pts.reshape(B, K, 3)


__all__ = ["TreeGeometry", "TriMesh", "generate_tree", "ORGAN_STEM", "ORGAN_BRANCH",
           "ORGAN_FOLIAGE", "ORGAN_NAMES", "PLANT_AREA_WEIGHT"]
