"""Species parameter sets, per-tree parameters and the draws of plausible Bretten trees.

Three pieces:

* :class:`SpeciesParams` — architecture of one species (crown shape, branching, stem taper,
  foliage elements, leaf angle distribution, target crown plant area density, clumping, gaps);
  :data:`SPECIES` holds the sets for *Fagus sylvatica*, *Carpinus betulus*, *Picea abies* (the
  study's targets) and *Pinus sylvestris*, *Quercus petraea*, *Pseudotsuga menziesii* (surrounding
  trees).  The numbers are plausible textbook values, not fitted to data.
* :class:`TreeParams` — the inputs of one tree (species, height, DBH, CBH, CPA, detail budget);
  validated on construction (:class:`~vlsforest.errors.ConfigError` naming the field).
* :func:`sample_tree_params` draws a surrounding tree from the real Bretten distributions summarised
  in ``data/bretten_species.json`` (see :mod:`vlsforest.synth._summarise`);
  :func:`target_tree_params` draws the study's 30 target trees, constrained to Table 1 of
  Weiser et al. (2021).

Leaf angle distributions are de Wit's (planophile, erectophile, plagiophile, extremophile,
uniform) plus spherical (:mod:`vlsforest.domain.leaf_angles` gives the density of the leaf
*normal* inclination θL ∈ [0, π/2]); :func:`sample_leaf_inclination` draws from it by inverse CDF.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from vlsforest.domain.leaf_angles import check_lad, leaf_inclination_pdf
from vlsforest.errors import ConfigError, InputDataError

_DATA = Path(__file__).resolve().parent / "data" / "bretten_species.json"

# ----------------------------------------------------------------------------------------------
# leaf angle distributions


@lru_cache(maxsize=None)
def _inclination_table(name: str) -> tuple[np.ndarray, np.ndarray]:
    th = np.linspace(0.0, np.pi / 2, 20001)
    pdf = leaf_inclination_pdf(check_lad(name, "leaf_angle_distribution"), th)
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (pdf[1:] + pdf[:-1]) * np.diff(th))])
    cdf /= cdf[-1]
    return cdf, th


def sample_leaf_inclination(name: str, n: int, rng: np.random.Generator) -> np.ndarray:
    """Draw ``n`` leaf-normal inclinations (radians) from a leaf angle distribution."""
    cdf, th = _inclination_table(name)
    return np.interp(rng.random(n), cdf, th)


# ----------------------------------------------------------------------------------------------
# species


@dataclass(frozen=True)
class SpeciesParams:
    """Architecture of one species.

    Attributes (lengths in metres, angles in degrees from the vertical)
    ----------
    key, latin, group : str
        Snake-case key, Latin name (as in the Bretten table), ``"broadleaf"`` or ``"conifer"``.
    crown_shape : {"ellipsoid", "paraboloid", "cone"}
        Shape of the crown envelope above its widest level.
    crown_widest : float
        Relative height in the crown (0 = crown base, 1 = top) of the widest level.
    crown_base_fraction : float
        Envelope radius at the crown base relative to the widest radius.
    crown_asymmetry : float
        Amplitude of the azimuthal radius modulation (first and second harmonic).
    stem_taper, butt_swell : float
        Stem radius ``r(z) = r_bh ((H−z)/(H−1.3))**stem_taper`` above breast height; below it the
        radius grows to ``r_bh (1 + butt_swell)`` at the ground.
    lean_sd, sweep : float
        SD of the stem lean (degrees) and bow amplitude as a fraction of the height.
    whorled : bool
        Conifer-like whorls (``whorl_spacing`` m, ``branches_per_whorl``) or a spiral with
        ``branch_density`` first-order branches per metre of crown length.
    branch_angle_base, branch_angle_top : float
        Insertion angle at the crown base / top (linear in between).
    branch_droop : float
        Change of the branch angle from base to tip (positive bends down).
    branch_thickness : float
        First-order branch base radius per metre of branch length (capped by the stem radius).
    twig_density, twig_angle, twig_length : float
        Second-order branches per metre of parent, their angle to the parent, and their maximum
        length relative to the parent's length.
    leaf_angle_distribution : str
        Distribution of the foliage element normals (see :func:`vlsforest.domain.leaf_angles.leaf_inclination_pdf`).
    leaf_element_area : float
        Default one-sided area (m²) of one foliage element (a leaf cluster for broadleaf, a needle
        shoot for conifers); enlarged automatically to stay within a tree's triangle budget.
    leaf_aspect : float
        Length/width of a foliage element (triangle height over base).
    crown_lai : float
        One-sided foliage area per unit of crown projection area (m²/m²): the leaf area index
        under the tree's own crown.  Literature values for closed stands (stand LAI ≈ crown LAI ×
        canopy cover): beech 5–8, hornbeam 5–6, sessile oak 4–6, Norway spruce 7–12 (hemi-surface),
        Douglas fir 8–10, Scots pine 2.5–4.
    foliage_start : float
        Foliage sits on the outer ``1 − foliage_start`` of each twig (a foliated shell).
    clump_radius : float
        SD (m) of the foliage element offsets around their twig (clumping).
    gap_fraction : float
        Fraction of twigs without foliage, chosen by a smooth random field (metre-scale gaps).
    gap_scale : float
        Wavelength (m) of that random field.
    """

    key: str
    latin: str
    group: str
    crown_shape: str
    crown_widest: float
    crown_base_fraction: float
    crown_asymmetry: float
    stem_taper: float
    butt_swell: float
    lean_sd: float
    sweep: float
    whorled: bool
    branch_density: float
    whorl_spacing: float
    branches_per_whorl: int
    branch_angle_base: float
    branch_angle_top: float
    branch_droop: float
    branch_thickness: float
    twig_density: float
    twig_angle: float
    twig_length: float
    leaf_angle_distribution: str
    leaf_element_area: float
    leaf_aspect: float
    crown_lai: float
    foliage_start: float
    clump_radius: float
    gap_fraction: float
    gap_scale: float


_BROADLEAF_DEFAULTS = dict(
    group="broadleaf", crown_shape="ellipsoid", crown_asymmetry=0.08, stem_taper=0.9,
    butt_swell=0.25, lean_sd=2.0, sweep=0.006, whorled=False, whorl_spacing=0.0,
    branches_per_whorl=0, branch_thickness=0.011, leaf_angle_distribution="planophile",
    leaf_aspect=1.3, gap_scale=2.5,
)
_CONIFER_DEFAULTS = dict(
    group="conifer", crown_shape="cone", crown_asymmetry=0.05, stem_taper=1.0, butt_swell=0.2,
    lean_sd=1.0, sweep=0.003, whorled=True, branch_density=0.0, branch_thickness=0.008,
    leaf_angle_distribution="erectophile", leaf_aspect=4.0, gap_scale=1.5,
)

SPECIES: dict[str, SpeciesParams] = {
    "fagus_sylvatica": SpeciesParams(
        key="fagus_sylvatica", latin="Fagus sylvatica", crown_widest=0.45,
        crown_base_fraction=0.35, branch_density=2.5, branch_angle_base=72.0,
        branch_angle_top=35.0, branch_droop=-12.0, twig_density=1.6, twig_angle=45.0,
        twig_length=0.45, leaf_element_area=0.01, crown_lai=7.0, foliage_start=0.35,
        clump_radius=0.3, gap_fraction=0.15, **_BROADLEAF_DEFAULTS),
    "carpinus_betulus": SpeciesParams(
        key="carpinus_betulus", latin="Carpinus betulus", crown_widest=0.4,
        crown_base_fraction=0.4, branch_density=3.0, branch_angle_base=70.0,
        branch_angle_top=40.0, branch_droop=-8.0, twig_density=1.8, twig_angle=50.0,
        twig_length=0.45, leaf_element_area=0.008, crown_lai=6.0, foliage_start=0.35,
        clump_radius=0.25, gap_fraction=0.15, **_BROADLEAF_DEFAULTS),
    "quercus_petraea": SpeciesParams(
        key="quercus_petraea", latin="Quercus petraea", crown_widest=0.5,
        crown_base_fraction=0.5, branch_density=1.6, branch_angle_base=68.0,
        branch_angle_top=45.0, branch_droop=-5.0, twig_density=1.5, twig_angle=55.0,
        twig_length=0.5, leaf_element_area=0.01, crown_lai=5.0, foliage_start=0.4,
        clump_radius=0.35, gap_fraction=0.2, **_BROADLEAF_DEFAULTS),
    "picea_abies": SpeciesParams(
        key="picea_abies", latin="Picea abies", crown_widest=0.08,
        crown_base_fraction=0.8, whorl_spacing=0.5, branches_per_whorl=5,
        branch_angle_base=95.0, branch_angle_top=65.0, branch_droop=12.0, twig_density=2.0,
        twig_angle=55.0, twig_length=0.35, leaf_element_area=0.005, crown_lai=10.0,
        foliage_start=0.15, clump_radius=0.2, gap_fraction=0.1, **_CONIFER_DEFAULTS),
    "pseudotsuga_menziesii": SpeciesParams(
        key="pseudotsuga_menziesii", latin="Pseudotsuga menziesii", crown_widest=0.15,
        crown_base_fraction=0.7, whorl_spacing=0.6, branches_per_whorl=5,
        branch_angle_base=90.0, branch_angle_top=60.0, branch_droop=8.0, twig_density=2.0,
        twig_angle=55.0, twig_length=0.4, leaf_element_area=0.006, crown_lai=8.5,
        foliage_start=0.2, clump_radius=0.2, gap_fraction=0.15, **_CONIFER_DEFAULTS),
    "pinus_sylvestris": SpeciesParams(
        key="pinus_sylvestris", latin="Pinus sylvestris", crown_widest=0.35,
        crown_base_fraction=0.5, whorl_spacing=0.7, branches_per_whorl=4,
        branch_angle_base=80.0, branch_angle_top=50.0, branch_droop=5.0, twig_density=1.5,
        twig_angle=50.0, twig_length=0.45, leaf_element_area=0.006, crown_lai=3.5,
        foliage_start=0.5, clump_radius=0.22, gap_fraction=0.25,
        **{**_CONIFER_DEFAULTS, "crown_shape": "paraboloid"}),
}


def get_species(key: str) -> SpeciesParams:
    """The parameter set of a species key (e.g. ``"fagus_sylvatica"``) or Latin name."""
    if isinstance(key, SpeciesParams):
        return key
    k = str(key).strip().lower().replace(" ", "_")
    if k in SPECIES:
        return SPECIES[k]
    raise ConfigError(f"species: unknown species {key!r}; known: {sorted(SPECIES)}")


# ----------------------------------------------------------------------------------------------
# per-tree parameters


@dataclass(frozen=True)
class Neighbour:
    """A competing crown, relative to the stem base of the tree it confines.

    Attributes
    ----------
    dx, dy : float
        Horizontal offset of the neighbour's stem base (m).
    cbh, height : float
        Its crown base and top, as heights above the confined tree's stem base (m).
    radius : float
        Its widest envelope radius (m, crown scale included).
    species : str
        Its species key (the crown profile shape).
    """

    dx: float
    dy: float
    cbh: float
    height: float
    radius: float
    species: str


@dataclass(frozen=True)
class TreeParams:
    """Inputs of one generated tree.

    Attributes
    ----------
    species : str
        Key in :data:`SPECIES`.
    height : float
        Tree height above ground (m).
    dbh : float
        Diameter at breast height, 1.3 m (m, not cm).
    cbh : float
        Crown base height: height of the lowest living branch or foliage (m).
    cpa : float
        Crown projection area (m²), 2-D convex hull of the crown.
    crown_lai : float or None
        One-sided foliage area per crown projection area (m²/m²); None → the species default.
    leaf_element_area : float or None
        Minimum one-sided area of one foliage element (m²); None → the species default.
    max_triangles : int
        Triangle budget of the whole tree; the foliage element area grows to respect it.
    crown_scale : float
        Crown plasticity: the envelope radius is multiplied by this factor (≥ 1) so that a crown
        that neighbours confine on some sides grows into the free ones (set by the forest layout).
    neighbours : tuple of Neighbour
        Competing crowns (set by the forest layout): in the height range where both crowns
        exist, the crown stays on its side of the boundary that splits the stem distance in
        proportion to the two crowns' radii at that height (see :mod:`vlsforest.synth.trees`).
    """

    species: str
    height: float
    dbh: float
    cbh: float
    cpa: float
    crown_lai: float | None = None
    leaf_element_area: float | None = None
    max_triangles: int = 150_000
    crown_scale: float = 1.0
    neighbours: tuple = ()

    def __post_init__(self):
        get_species(self.species)
        for name in ("height", "dbh", "cbh", "cpa"):
            v = getattr(self, name)
            if not isinstance(v, (int, float, np.floating, np.integer)) or not math.isfinite(v):
                raise ConfigError(f"{name}: must be a finite number, got {v!r}")
        if self.height <= 1.5:
            raise ConfigError(f"height: must be > 1.5 m, got {self.height}")
        if self.dbh <= 0:
            raise ConfigError(f"dbh: must be > 0 (metres), got {self.dbh}")
        if self.dbh > 0.2 * self.height:
            raise ConfigError(f"dbh: {self.dbh} m is implausible for height {self.height} m "
                              "(is it in cm? dbh is in metres)")
        if self.cbh < 0:
            raise ConfigError(f"cbh: must be >= 0, got {self.cbh}")
        if self.cbh > self.height - 1.0:
            raise ConfigError(f"cbh: {self.cbh} m must lie at least 1 m below the height "
                              f"{self.height} m")
        if self.cpa <= 0:
            raise ConfigError(f"cpa: must be > 0, got {self.cpa}")
        if self.crown_lai is not None and not (0 < self.crown_lai < 50):
            raise ConfigError(f"crown_lai: must be in (0, 50) m²/m², got {self.crown_lai}")
        if not (isinstance(self.crown_scale, (int, float, np.floating, np.integer))
                and 0.2 <= self.crown_scale <= 5.0):
            raise ConfigError(f"crown_scale: must be in [0.2, 5], got {self.crown_scale!r}")
        for nb in self.neighbours:
            if not isinstance(nb, Neighbour):
                raise ConfigError(f"neighbours: expected Neighbour entries, got {type(nb).__name__}")
        if self.leaf_element_area is not None and not (0 < self.leaf_element_area < 1):
            raise ConfigError(f"leaf_element_area: must be in (0, 1) m², got "
                              f"{self.leaf_element_area}")
        if int(self.max_triangles) < 2000:
            raise ConfigError(f"max_triangles: must be >= 2000, got {self.max_triangles}")

    @property
    def crown_radius(self) -> float:
        """Radius of the circle with area ``cpa`` (m)."""
        return math.sqrt(self.cpa / math.pi)

    @property
    def species_params(self) -> SpeciesParams:
        return get_species(self.species)


# ----------------------------------------------------------------------------------------------
# Bretten summary and draws


@lru_cache(maxsize=1)
def load_bretten_summary() -> dict:
    """The shipped per-species summary of the real Bretten trees (``data/bretten_species.json``)."""
    try:
        return json.loads(_DATA.read_text())
    except FileNotFoundError as exc:
        raise InputDataError(f"{_DATA}: Bretten species summary missing "
                             "(run tools/summarise_bretten.py)") from exc
    except json.JSONDecodeError as exc:
        raise InputDataError(f"{_DATA}: corrupt JSON ({exc})") from exc


def _joint(species: str) -> dict:
    sp = get_species(species)
    summ = load_bretten_summary()
    entry = summ["species"].get(sp.latin)
    if entry is None or "joint" not in entry:
        raise InputDataError(f"{_DATA}: no joint statistics for {sp.latin}")
    return entry["joint"]


def _inv_quantile(stats: dict, u: np.ndarray) -> np.ndarray:
    levels = np.asarray(load_bretten_summary()["quantile_levels"], dtype=float)
    return np.interp(u, levels, np.asarray(stats["quantiles"], dtype=float))


def sample_tree_params(species: str, rng: np.random.Generator, height: float | None = None,
                       max_triangles: int = 40_000, min_height: float = 8.0) -> TreeParams:
    """Draw a plausible (surrounding) tree of a species from the real Bretten distributions.

    Height from the species' height quantiles (piecewise-linear inverse CDF, at least
    ``min_height``), CBH as height × a ratio drawn from the CBH/height quantiles, DBH and crown
    radius from the log-linear fits on height with their residual scatter (truncated at ±2 SD).

    Parameters
    ----------
    species : str
        Key in :data:`SPECIES`.
    rng : numpy.random.Generator
    height : float, optional
        Fix the height instead of drawing it.
    max_triangles : int
        Triangle budget passed to :class:`TreeParams` (smaller than a target tree's).
    min_height : float
        Lower bound of drawn heights (m).
    """
    j = _joint(species)
    if height is None:
        height = float(max(_inv_quantile(j["height_m"], rng.random()), min_height))
    ratio = float(np.clip(_inv_quantile(j["cbh_ratio"], rng.random()), 0.03, 0.65))
    z = np.clip(rng.standard_normal(2), -2.0, 2.0)
    fd, fr = j["dbh_cm_on_height"], j["crown_radius_m_on_height"]
    dbh_cm = math.exp(fd["a"] + fd["b"] * math.log(height) + fd["resid_sd"] * z[0])
    radius = math.exp(fr["a"] + fr["b"] * math.log(height) + fr["resid_sd"] * z[1])
    cbh = max(ratio * height, 0.5)
    return TreeParams(species=get_species(species).key, height=round(height, 3),
                      dbh=round(dbh_cm / 100.0, 4), cbh=round(cbh, 3),
                      cpa=round(math.pi * radius**2, 3), max_triangles=max_triangles)


#: Table 1 of Weiser et al. (2021): (min, max, mean) per group and metric.
TABLE1 = {
    "broadleaf": {"height": (23.5, 36.4, 31.0), "cbh": (1.5, 17.1, 8.3),
                  "cpa": (34.5, 263.8, 121.2)},
    "conifer": {"height": (17.7, 35.4, 28.6), "cbh": (1.4, 13.5, 6.0),
                "cpa": (13.9, 59.6, 38.0)},
}
#: the study's target trees per group: (species key, count)
TARGET_SPECIES = {"broadleaf": (("fagus_sylvatica", 13), ("carpinus_betulus", 2)),
                  "conifer": (("picea_abies", 15),)}


def _stratified_beta(rng, n, lo, hi, mean, conc=4.0):
    """n stratified draws from a Beta on [lo, hi] with the given mean (random order)."""
    from scipy.stats import beta as _beta

    m = (mean - lo) / (hi - lo)
    a, b = m * conc, (1 - m) * conc
    u = (np.arange(n) + rng.random(n)) / n
    return lo + (hi - lo) * _beta.ppf(u, a, b)


def target_tree_params(rng: np.random.Generator, max_triangles: int = 150_000,
                       mean_tolerance: float = 0.05, max_tries: int = 1000) -> list[TreeParams]:
    """The study's 30 target trees (13 beech, 2 hornbeam, 15 spruce) constrained to Table 1.

    Per group (broadleaf, conifer; 15 trees each) height, CBH and CPA are stratified draws from
    Beta distributions on the Table 1 ranges with the Table 1 means; they are paired through a
    Gaussian copula (rank correlation: CPA and CBH rise with height) and the draw is rejected
    and repeated until every value lies inside its range, every CBH leaves a crown of at least
    30 % of the height, and each group mean lies within ``mean_tolerance`` of Table 1.  DBH
    comes from the species' Bretten fit on height.  Two random broadleaf trees are hornbeam.
    Deterministic per ``rng`` state.

    Returns
    -------
    list of TreeParams
        15 broadleaf (beech and hornbeam mixed) followed by 15 spruce.
    """
    out = []
    corr = np.array([[1.0, 0.4, 0.5], [0.4, 1.0, 0.0], [0.5, 0.0, 1.0]])
    chol = np.linalg.cholesky(corr)
    for group in ("broadleaf", "conifer"):
        t = TABLE1[group]
        n = sum(c for _, c in TARGET_SPECIES[group])
        for _ in range(max_tries):
            cols = [np.sort(_stratified_beta(rng, n, *t[k])) for k in ("height", "cbh", "cpa")]
            g = rng.standard_normal((n, 3)) @ chol.T
            ranks = np.argsort(np.argsort(g, axis=0), axis=0)
            h, cbh, cpa = (cols[i][ranks[:, i]] for i in range(3))
            ok = (cbh <= 0.7 * h).all()
            for k, v in zip(("height", "cbh", "cpa"), (h, cbh, cpa)):
                lo, hi, mean = t[k]
                ok &= bool((v >= lo).all() and (v <= hi).all())
                ok &= abs(v.mean() - mean) <= mean_tolerance * mean
            if ok:
                break
        else:  # pragma: no cover - practically unreachable
            raise ConfigError(f"target_tree_params: no valid {group} draw in {max_tries} tries")
        species = np.concatenate([[k] * c for k, c in TARGET_SPECIES[group]])
        species = species[rng.permutation(n)]
        z = np.clip(rng.standard_normal(n), -1.5, 1.5)
        for i in range(n):
            fd = _joint(species[i])["dbh_cm_on_height"]
            dbh_cm = math.exp(fd["a"] + fd["b"] * math.log(h[i]) + fd["resid_sd"] * z[i])
            out.append(TreeParams(species=str(species[i]), height=round(float(h[i]), 3),
                                  dbh=round(dbh_cm / 100.0, 4), cbh=round(float(cbh[i]), 3),
                                  cpa=round(float(cpa[i]), 3), max_triangles=max_triangles))
    return out


__all__ = [
    "SpeciesParams", "SPECIES", "get_species", "Neighbour", "TreeParams",
    "sample_leaf_inclination", "load_bretten_summary", "sample_tree_params",
    "target_tree_params", "TABLE1", "TARGET_SPECIES",
]
