"""The virtual Bretten forest: plot layouts, tree placement, geometry and truth tables.

Six plots like those of Weiser et al. (2021): each holds a few target trees near its centre, and
its extent is the smallest axis-aligned rectangle around 20 m circular buffers of the targets
(P1 … P6: 0.31, 0.25, 0.25, 0.43, 0.48, 0.19 ha; 13 beech, 2 hornbeam and 15 spruce targets in
all).  Surrounding trees fill the extent plus a margin at a realistic stand density, and the trees
stand on a gently rough ground (:class:`~vlsforest.synth.ground.GroundSurface`).

Layout (:func:`forest_from_config`, everything drawn from one seed):

1. **Targets.**  The study's 30 targets come from
   :func:`~vlsforest.synth.species.target_tree_params` (Table 1 ranges and means).  A plot asks
   for counts per species (``targets``); per species the pool is sorted by crown projection area
   and handed out to the plots in order of increasing area (the smallest plots get the smallest
   crowns).  Plots that ask for fewer trees than the pool holds get the smallest ones; more
   trees than the pool holds, or species outside it, are drawn with
   :func:`~vlsforest.synth.species.sample_tree_params` (at least 15 m tall).  Explicit target
   trees (``target_trees``: species, height, cbh, cpa and optionally dbh) can be added.
2. **Target positions.**  A plot of area ``A`` with a ``buffer_m`` buffer is a rectangle
   ``(a + 2b) × (c + 2b)`` where ``a × c`` is the bounding box of the target stems.  The width is
   drawn (aspect of the plot between 1:2 and 2:1 where the area allows), ``c`` follows from
   ``A``, and among 4000 random stem arrangements whose bounding box is exactly ``a × c`` the one
   with the largest ``min d_ij / (R_i + R_j)`` (stem distance over the sum of crown radii) is
   kept, so crowns overlap as little as the area allows.  The extent is then computed from the
   stems, so it is exactly the smallest rectangle around the buffers and its area is ``A`` (up
   to rounding).
3. **Surrounding trees.**  Species from ``surrounding_species``, parameters from the real
   Bretten distributions (:func:`~vlsforest.synth.species.sample_tree_params`), drawn until the
   crown projection areas of all trees (targets included) add up to ``canopy_cover`` × the area
   of the extent plus ``margin_m`` (or ``round(stand_density_per_ha × area)`` trees when that key
   is not null); placed largest crown first by random sequential adsorption with a hard core:
   stems at least ``min_stem_distance_m`` apart, at least ``0.6 (R_i + R_j)`` from other
   surrounding trees and ``0.7 (R_i + R_j)`` from targets (the factors relax for a tree that
   finds no place after many tries).
   **Crown plasticity** (:func:`_crown_competition`): every tree learns its competing
   neighbours, whose crowns cut its envelope where both exist (see
   :mod:`vlsforest.synth.trees`), and a crown scale ≥ 1 that lets a confined crown grow into the
   free directions so that it keeps its projection area where there is room.
4. **Ground.**  One :class:`~vlsforest.synth.ground.GroundSurface` per plot around its centre;
   every stem base sits on it (``z_ground``); :meth:`PlotLayout.ground_z` is the median height
   over the extent, the plane the simulations use.

Seeds: the target pool uses ``SeedSequence([seed, 0])``, plot ``i`` (1-based, in config order)
``SeedSequence([seed, 1, i])`` for its surrounding trees and ground, and tree ``t`` of a plot
``default_rng([plot.seed, t])`` for its geometry, so a plot (and any tree of it) can be generated
alone and changing one plot's settings leaves the others unchanged.  Tree ids are
``10000 · i + k`` with ``k < 100`` for targets and ``k ≥ 100`` for surrounding trees.

:func:`generate_plot_trees` turns a layout into meshes
(:func:`~vlsforest.synth.trees.generate_tree`) and :func:`truth_table` lists the truth measured
on them.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Iterable

import numpy as np
import pandas as pd

from vlsforest.errors import ConfigError, InputDataError
from vlsforest.io.mesh import TriangleMesh
from vlsforest.synth.ground import GroundSurface
from vlsforest.synth.species import (
    SPECIES,
    TARGET_SPECIES,
    Neighbour,
    TreeParams,
    get_species,
    sample_tree_params,
    target_tree_params,
)
from vlsforest.synth.trees import (
    CROWN_OVERLAP,
    TreeGeometry,
    crown_profile,
    generate_tree,
    split_distance,
)

#: the study's plot areas (ha), Weiser et al. (2021) §2
STUDY_AREAS_HA = {"P1": 0.31, "P2": 0.25, "P3": 0.25, "P4": 0.43, "P5": 0.48, "P6": 0.19}

#: The six study plots.  Mixed compositions as in the study (13 beech, 2 hornbeam, 15 spruce in
#: all); the small plots get spruce (narrow crowns), the two large ones the broad beech crowns.
#: Ground elevations are plausible values for the Bretten communal forest (its pytreedb plots lie
#: at about 230–325 m a.s.l.).
DEFAULT_FOREST: dict = {
    "target_area_ha": dict(STUDY_AREAS_HA),
    "plots": {
        "P1": {"targets": {"fagus_sylvatica": 2, "picea_abies": 3}, "ground_elevation_m": 255.0},
        "P2": {"targets": {"fagus_sylvatica": 1, "picea_abies": 4}, "ground_elevation_m": 248.0},
        "P3": {"targets": {"fagus_sylvatica": 1, "carpinus_betulus": 1, "picea_abies": 3},
               "ground_elevation_m": 236.0},
        "P4": {"targets": {"fagus_sylvatica": 4, "carpinus_betulus": 1},
               "ground_elevation_m": 262.0},
        "P5": {"targets": {"fagus_sylvatica": 5}, "ground_elevation_m": 290.0},
        "P6": {"targets": {"picea_abies": 5}, "ground_elevation_m": 232.0},
    },
    # How many surrounding trees: enough that the nominal crown projection areas of all trees
    # (targets included) add up to this multiple of the ground area.  Trees drawn from the
    # Bretten distributions (>= 8 m tall) have a mean crown projection area of ≈ 49 m², so 1.2
    # gives ≈ 220–240 stems/ha; crown plasticity (vlsforest.synth.trees) then cuts the crowns
    # where they meet, leaving a closed canopy: 85–90 % of the ground under a crown, stand LAI
    # ≈ 7–9 (without plasticity, crowns adding up to more than the ground area would
    # interpenetrate).
    # ``stand_density_per_ha`` (stems per hectare), when not null, is used instead.
    "canopy_cover": 1.2,
    "stand_density_per_ha": None,
    # roughly the Bretten composition: beech and spruce dominate, with oak, pine, hornbeam and
    # Douglas fir (pytreedb Bretten plots)
    "surrounding_species": {"fagus_sylvatica": 0.40, "picea_abies": 0.30,
                            "quercus_petraea": 0.10, "pinus_sylvestris": 0.10,
                            "carpinus_betulus": 0.05, "pseudotsuga_menziesii": 0.05},
    "margin_m": 10.0,
    "buffer_m": 20.0,
    "min_stem_distance_m": 1.5,
    "max_triangles_target": 150_000,
    "max_triangles_surrounding": 40_000,
    "ground": {"slope_max": 0.01, "roughness_m": 0.15, "wavelength_m": [10.0, 20.0]},
}

#: One small plot with 4 targets (2 beech, 2 spruce) for fast end-to-end runs.
QUICK_FOREST: dict = {
    "plots": {
        "Q1": {"targets": {"fagus_sylvatica": 2, "picea_abies": 2}, "area_ha": 0.22,
               "ground_elevation_m": 240.0},
    },
    "canopy_cover": 1.2,
    "stand_density_per_ha": None,
    "surrounding_species": {"fagus_sylvatica": 0.5, "picea_abies": 0.5},
    "margin_m": 5.0,
    "buffer_m": 20.0,
    "min_stem_distance_m": 1.5,
    "max_triangles_target": 30_000,
    "max_triangles_surrounding": 6_000,
    "ground": {"slope_max": 0.01, "roughness_m": 0.15, "wavelength_m": [10.0, 20.0]},
}

_ID_STRIDE = 10_000
_SURROUND_K0 = 100
_N_ARRANGEMENTS = 4000
_C_TARGET = 0.7       # surrounding-to-target stem distance ≥ 0.7 (R_t + R_s)
_C_SURROUND = 0.6     # surrounding-to-surrounding stem distance ≥ 0.6 (R_i + R_j)
_SCALE_MAX = 1.5      # crown plasticity: a confined crown grows by at most this factor
_MIN_TARGET_HEIGHT = 15.0

_FOREST_KEYS = {"target_area_ha", "plots", "canopy_cover", "stand_density_per_ha",
                "surrounding_species",
                "margin_m", "buffer_m", "min_stem_distance_m", "max_triangles_target",
                "max_triangles_surrounding", "ground"}
_PLOT_KEYS = {"targets", "target_trees", "area_ha", "ground_elevation_m", "origin_m"}
_TREE_KEYS = {"species", "height", "dbh", "cbh", "cpa"}
_GROUND_KEYS = {"slope_max", "roughness_m", "wavelength_m", "n_modes"}


# ----------------------------------------------------------------------------------------------
# data classes


@dataclass(frozen=True)
class TreeSpec:
    """One tree of a plot layout (before its geometry is generated).

    Attributes
    ----------
    tree_id : int
        Unique over the forest: ``10000 · plot index + k`` (targets ``k < 100``).
    plot : str
        Plot name.
    species : str
        Species key.
    target : bool
        True for a target tree of the study.
    x, y : float
        Stem base position (m).
    z_ground : float
        Ground height at the stem base (m).
    params : TreeParams
        Inputs of the tree generator.
    """

    tree_id: int
    plot: str
    species: str
    target: bool
    x: float
    y: float
    z_ground: float
    params: TreeParams


@dataclass
class PlotLayout:
    """Layout of one plot.

    Attributes
    ----------
    name : str
        ``"P1"`` … ``"P6"`` (quick: ``"Q1"``).
    extent : (xmin, ymin, xmax, ymax)
        The smallest axis-aligned rectangle around ``buffer_m`` circular buffers of the targets.
    ground : GroundSurface
        The terrain.
    trees : list of TreeSpec
        Targets first, then the surrounding trees (covering the extent plus ``margin``).
    seed : int
        Seed of this plot (surrounding trees, ground, tree geometry).
    margin : float
        Width (m) of the band around the extent that surrounding trees also cover.
    buffer_m : float
        Buffer radius used for the extent (m).
    """

    name: str
    extent: tuple[float, float, float, float]
    ground: GroundSurface
    trees: list[TreeSpec]
    seed: int
    margin: float = 0.0
    buffer_m: float = 20.0

    def target_ids(self) -> list[int]:
        """Ids of the target trees (in layout order)."""
        return [t.tree_id for t in self.trees if t.target]

    def area_ha(self) -> float:
        """Area of the extent (ha)."""
        xmin, ymin, xmax, ymax = self.extent
        return (xmax - xmin) * (ymax - ymin) / 1e4

    def region(self) -> tuple[float, float, float, float]:
        """The extent grown by ``margin``: the area the surrounding trees cover."""
        xmin, ymin, xmax, ymax = self.extent
        m = self.margin
        return (xmin - m, ymin - m, xmax + m, ymax + m)

    def ground_z(self) -> float:
        """Elevation of the ground plane for simulations: median ground height over the extent
        (1 m grid)."""
        _, _, z = self.ground.grid(self.extent, 1.0)
        return float(np.median(z))

    def tree(self, tree_id: int) -> TreeSpec:
        """The tree with this id (ConfigError if it is not in the plot)."""
        for t in self.trees:
            if t.tree_id == tree_id:
                return t
        raise ConfigError(f"tree_id: {tree_id} is not a tree of plot {self.name}")


# ----------------------------------------------------------------------------------------------
# validation helpers


def _num(key: str, v, lo=None, hi=None, lo_open=False) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) \
            or not math.isfinite(float(v)):
        raise ConfigError(f"{key}: must be a finite number, got {v!r}")
    v = float(v)
    if lo is not None and (v < lo or (lo_open and v == lo)):
        raise ConfigError(f"{key}: must be {'>' if lo_open else '>='} {lo}, got {v}")
    if hi is not None and v > hi:
        raise ConfigError(f"{key}: must be <= {hi}, got {v}")
    return v


def _int(key: str, v, lo: int, hi: int | None = None) -> int:
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
        if isinstance(v, float) and v.is_integer():
            v = int(v)
        else:
            raise ConfigError(f"{key}: must be an integer, got {v!r}")
    v = int(v)
    if v < lo or (hi is not None and v > hi):
        raise ConfigError(f"{key}: must be an integer in [{lo}, {hi if hi is not None else '∞'}]"
                          f", got {v}")
    return v


def _mapping(key: str, v) -> dict:
    if not isinstance(v, dict):
        raise ConfigError(f"{key}: expected a mapping, got {type(v).__name__}")
    return v


def _unknown_keys(key: str, d: dict, allowed: set):
    extra = sorted(str(k) for k in d if k not in allowed)
    if extra:
        raise ConfigError(f"{key}.{extra[0]}: unknown key (allowed: {sorted(allowed)})")


def _species(key: str, name) -> str:
    k = str(name).strip().lower().replace(" ", "_")
    if k not in SPECIES:
        raise ConfigError(f"{key}: unknown species {name!r}; known: {sorted(SPECIES)}")
    return k


@dataclass
class _PlotCfg:
    name: str
    index: int
    counts: dict
    explicit: list
    area_m2: float
    elevation: float
    origin: tuple | None
    n_targets: int = 0
    area_key: str = ""
    assigned: list = field(default_factory=list)


def _validate(cfg) -> tuple[dict, list[_PlotCfg]]:
    cfg = _mapping("forest", cfg)
    _unknown_keys("forest", cfg, _FOREST_KEYS)
    d = copy.deepcopy({k: v for k, v in DEFAULT_FOREST.items()
                       if k not in ("plots", "target_area_ha")})
    d.update({k: copy.deepcopy(v) for k, v in cfg.items() if k not in ("plots",
                                                                        "target_area_ha")})
    out = {
        "density": (None if d.get("stand_density_per_ha") is None else
                    _num("forest.stand_density_per_ha", d["stand_density_per_ha"], 0.0, 3000.0)),
        "cover": (None if d.get("canopy_cover") is None else
                  _num("forest.canopy_cover", d["canopy_cover"], 0.0, 3.0)),
        "margin": _num("forest.margin_m", d["margin_m"], 0.0, 200.0),
        "buffer": _num("forest.buffer_m", d["buffer_m"], 0.0, 200.0, lo_open=True),
        "dmin": _num("forest.min_stem_distance_m", d["min_stem_distance_m"], 0.0, 20.0),
        "tri_t": _int("forest.max_triangles_target", d["max_triangles_target"], 2000),
        "tri_s": _int("forest.max_triangles_surrounding", d["max_triangles_surrounding"], 2000),
    }
    sp = _mapping("forest.surrounding_species", d["surrounding_species"])
    weights = {}
    for name, w in sp.items():
        k = _species(f"forest.surrounding_species.{name}", name)
        weights[k] = weights.get(k, 0.0) + _num(f"forest.surrounding_species.{name}", w, 0.0)
    if out["density"] is None and out["cover"] is None:
        raise ConfigError("forest.canopy_cover: give canopy_cover or stand_density_per_ha")
    stocked = (out["density"] or 0) > 0 if out["density"] is not None else out["cover"] > 0
    if stocked and sum(weights.values()) <= 0:
        raise ConfigError("forest.surrounding_species: needs at least one positive weight")
    out["species"] = weights
    g = _mapping("forest.ground", d["ground"])
    _unknown_keys("forest.ground", g, _GROUND_KEYS)
    out["ground"] = dict(g)

    areas = cfg.get("target_area_ha", {})
    areas = _mapping("forest.target_area_ha", areas if areas is not None else {})
    if "plots" not in cfg or cfg["plots"] is None:
        raise ConfigError("forest.plots: missing (a mapping of plot names to plot settings)")
    plots = _mapping("forest.plots", cfg["plots"])
    if not plots:
        raise ConfigError("forest.plots: no plots given")
    for name in areas:
        if name not in plots:
            raise ConfigError(f"forest.target_area_ha.{name}: no plot of that name in "
                              "forest.plots")
    pcs = []
    for i, (name, p) in enumerate(plots.items(), start=1):
        key = f"forest.plots.{name}"
        if not isinstance(name, str) or not name.strip() or not name.replace("_", "").replace(
                "-", "").isalnum():
            raise ConfigError(f"{key}: plot names must be non-empty letters, digits, '_' or '-'")
        p = _mapping(key, p)
        _unknown_keys(key, p, _PLOT_KEYS)
        counts = {}
        tg = p.get("targets", {}) or {}
        tg = _mapping(f"{key}.targets", tg)
        for sname, c in tg.items():
            k = _species(f"{key}.targets.{sname}", sname)
            if isinstance(c, bool) or not isinstance(c, (int, np.integer)) or c <= 0:
                raise ConfigError(f"{key}.targets.{sname}: must be a positive integer, got {c!r}")
            counts[k] = counts.get(k, 0) + int(c)
        explicit = []
        tt = p.get("target_trees", []) or []
        if not isinstance(tt, list):
            raise ConfigError(f"{key}.target_trees: expected a list of trees")
        for j, t in enumerate(tt):
            tk = f"{key}.target_trees[{j}]"
            t = _mapping(tk, t)
            _unknown_keys(tk, t, _TREE_KEYS)
            for req in ("species", "height", "cbh", "cpa"):
                if req not in t:
                    raise ConfigError(f"{tk}.{req}: missing")
            explicit.append((tk, _species(f"{tk}.species", t["species"]),
                             {k: t[k] for k in ("height", "cbh", "cpa", "dbh") if k in t}))
        n_t = sum(counts.values()) + len(explicit)
        if n_t == 0:
            raise ConfigError(f"{key}.targets: a plot needs at least one target tree")
        if n_t >= _SURROUND_K0:
            raise ConfigError(f"{key}.targets: at most {_SURROUND_K0 - 1} targets per plot, "
                              f"got {n_t}")
        a_plot = p.get("area_ha")
        a_top = areas.get(name)
        if a_plot is None and a_top is None:
            raise ConfigError(f"{key}.area_ha: missing (give it here or in "
                              "forest.target_area_ha)")
        if a_plot is not None:
            a = _num(f"{key}.area_ha", a_plot, 0.0, 10.0, lo_open=True)
            if a_top is not None and abs(_num(f"forest.target_area_ha.{name}", a_top) - a) \
                    > 1e-9:
                raise ConfigError(f"{key}.area_ha: {a} disagrees with "
                                  f"forest.target_area_ha.{name} = {a_top}")
        else:
            a = _num(f"forest.target_area_ha.{name}", a_top, 0.0, 10.0, lo_open=True)
        side = 2 * out["buffer"]
        akey = f"{key}.area_ha" if a_plot is not None else f"forest.target_area_ha.{name}"
        if a * 1e4 < side**2 * (1 - 1e-9):
            raise ConfigError(f"{akey}: {a} ha is below the smallest possible extent "
                              f"(2 × buffer)² = {side**2 / 1e4:.4g} ha")
        if n_t == 1 and abs(a * 1e4 - side**2) > 0.01 * side**2:
            raise ConfigError(f"{akey}: a plot with one target is always (2 × buffer)² = "
                              f"{side**2 / 1e4:.4g} ha, got {a} ha")
        if "ground_elevation_m" not in p:
            raise ConfigError(f"{key}.ground_elevation_m: missing")
        elev = _num(f"{key}.ground_elevation_m", p["ground_elevation_m"], -500.0, 9000.0)
        origin = None
        if p.get("origin_m") is not None:
            o = p["origin_m"]
            if not isinstance(o, (list, tuple)) or len(o) != 2:
                raise ConfigError(f"{key}.origin_m: expected [x, y], got {o!r}")
            origin = tuple(_num(f"{key}.origin_m", v) for v in o)
        pcs.append(_PlotCfg(name=name, index=i, counts=counts, explicit=explicit,
                            area_m2=a * 1e4, elevation=elev, origin=origin, n_targets=n_t,
                            area_key=akey))
    return out, pcs


# ----------------------------------------------------------------------------------------------
# layout


def _plot_seed(seed: int, index: int) -> int:
    return int(np.random.SeedSequence([int(seed), 1, int(index)]).generate_state(1)[0])


def _assign_targets(pcs: list[_PlotCfg], opts: dict, seed: int):
    """Give every plot its target TreeParams (see the module docstring, step 1)."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0]))
    study = {k for grp in TARGET_SPECIES.values() for k, _ in grp}
    need_pool = any(k in study for pc in pcs for k in pc.counts)
    pool: dict[str, list[TreeParams]] = {}
    if need_pool:
        for tp in target_tree_params(rng, max_triangles=opts["tri_t"]):
            pool.setdefault(tp.species, []).append(tp)
    for k in pool:
        pool[k].sort(key=lambda t: t.cpa)
    order = sorted(pcs, key=lambda pc: (pc.area_m2 / pc.n_targets, pc.index))
    for sp in sorted({k for pc in pcs for k in pc.counts}):
        demand = sum(pc.counts.get(sp, 0) for pc in pcs)
        avail = pool.get(sp, [])[:demand]
        extra = [sample_tree_params(sp, rng, max_triangles=opts["tri_t"],
                                    min_height=_MIN_TARGET_HEIGHT)
                 for _ in range(demand - len(avail))]
        trees = sorted(avail + extra, key=lambda t: t.cpa)
        it = iter(trees)
        for pc in order:
            for _ in range(pc.counts.get(sp, 0)):
                pc.assigned.append(next(it))
    for pc in pcs:
        for tk, sp, vals in pc.explicit:
            try:
                h = _num(f"{tk}.height", vals["height"], 0.0, 150.0, lo_open=True)
                cbh = _num(f"{tk}.cbh", vals["cbh"], 0.0)
                cpa = _num(f"{tk}.cpa", vals["cpa"], 0.0, lo_open=True)
                if cbh >= h:
                    raise ConfigError(f"{tk}.cbh: crown base height {cbh} m must lie below the "
                                      f"tree height {h} m")
                if "dbh" in vals:
                    dbh = _num(f"{tk}.dbh", vals["dbh"], 0.0, lo_open=True)
                else:
                    dbh = sample_tree_params(sp, rng, height=max(h, 1.6)).dbh
                pc.assigned.append(TreeParams(species=sp, height=h, dbh=dbh, cbh=cbh, cpa=cpa,
                                              max_triangles=opts["tri_t"]))
            except ConfigError as exc:
                msg = str(exc)
                raise ConfigError(msg if msg.startswith(tk) else f"{tk}.{msg}") from None


def _place_targets(pc: _PlotCfg, params: list[TreeParams], buffer: float, dmin: float,
                   centre: tuple[float, float], rng: np.random.Generator) -> np.ndarray:
    """Stem positions (n, 2) whose buffered bounding box has the plot's area (step 2)."""
    n = len(params)
    b2 = 2 * buffer
    A = pc.area_m2
    if n == 1:
        return np.array([centre], dtype=float)
    radii = np.array([p.crown_radius for p in params])
    # plot width w ∈ [w_lo, w_hi]: both sides ≥ 2 buffer, aspect within 1:2 … 2:1 if possible
    w_lo = max(b2, math.sqrt(A / 2.0))
    w_hi = min(A / b2, math.sqrt(2.0 * A))
    if w_hi < w_lo:
        w_lo, w_hi = b2, A / b2
    M = _N_ARRANGEMENTS
    iu = np.triu_indices(n, 1)
    rsum = radii[iu[0]] + radii[iu[1]]

    def arrange(w, u):
        a = np.clip(w - b2, 0.0, None)
        c = np.clip(A / w - b2, 0.0, None)
        lo = u.min(axis=1, keepdims=True)
        span = u.max(axis=1, keepdims=True) - lo
        un = (u - lo) / np.where(span > 0, span, 1.0)
        return un * np.stack([a, c], -1)[:, None, :]

    def score(pts):
        diff = pts[:, iu[0], :] - pts[:, iu[1], :]
        d = np.sqrt((diff**2).sum(-1))
        return np.where(d.min(axis=1) >= dmin, (d / rsum).min(axis=1), -1.0)

    w = rng.uniform(w_lo, w_hi, M)
    u = rng.random((M, n, 2))
    sc = score(arrange(w, u))
    # local refinement of the best arrangements (random perturbations, keep improvements)
    top = np.argsort(-sc, kind="stable")[:32]
    w, u, sc = w[top], u[top], sc[top]
    for it in range(300):
        step = 0.1 * (1.0 - it / 300) + 0.005
        w2 = np.clip(w + step * (w_hi - w_lo) * rng.normal(size=w.size), w_lo, w_hi)
        u2 = u + step * rng.normal(size=u.shape)
        sc2 = score(arrange(w2, u2))
        better = sc2 > sc
        w, u, sc = np.where(better, w2, w), np.where(better[:, None, None], u2, u), \
            np.where(better, sc2, sc)
    best = int(np.argmax(sc))
    if sc[best] < 0:
        raise ConfigError(f"{pc.area_key}: {A / 1e4:.4g} ha is too small to "
                          f"place {n} targets at least {dmin} m apart")
    p = arrange(w[best:best + 1], u[best:best + 1])[0]
    lo, hi = p.min(axis=0), p.max(axis=0)
    return p - 0.5 * (lo + hi) + np.asarray(centre, dtype=float)


def _place_surrounding(params: list[TreeParams], region, fixed_xy: np.ndarray,
                       fixed_r: np.ndarray, dmin: float, rng: np.random.Generator,
                       plot_key: str) -> np.ndarray:
    """Random sequential adsorption with a crown-size dependent hard core (step 3)."""
    xmin, ymin, xmax, ymax = region
    n_fixed = fixed_xy.shape[0]
    n = len(params)
    xy = np.empty((n_fixed + n, 2))
    xy[:n_fixed] = fixed_xy
    r = np.empty(n_fixed + n)
    r[:n_fixed] = fixed_r
    coef = np.empty(n_fixed + n)
    coef[:n_fixed] = _C_TARGET
    coef[n_fixed:] = _C_SURROUND
    batch = 128
    for j, p in enumerate(params):
        m = n_fixed + j
        r_new = p.crown_radius
        relax = 1.0
        placed = False
        for attempt in range(400):
            cand = np.c_[rng.uniform(xmin, xmax, batch), rng.uniform(ymin, ymax, batch)]
            if m:
                need = np.maximum(dmin, relax * coef[:m] * (r[:m] + r_new))
                dd = np.sqrt(((cand[:, None, :] - xy[None, :m, :]) ** 2).sum(-1))
                ok = (dd >= need[None, :]).all(axis=1)
            else:
                ok = np.ones(batch, bool)
            if ok.any():
                xy[m] = cand[int(np.argmax(ok))]
                placed = True
                break
            if attempt % 20 == 19:
                relax *= 0.8
        if not placed:
            raise ConfigError(f"{plot_key}: cannot place {n} surrounding trees at least "
                              f"{dmin} m apart; lower forest.stand_density_per_ha or "
                              "forest.min_stem_distance_m")
        r[m] = r_new
    return xy[n_fixed:]


def _check_count(n_s: int, plot: str, key: str):
    if _SURROUND_K0 + n_s > _ID_STRIDE:
        raise ConfigError(f"{key}: {n_s} surrounding trees in plot {plot} exceed the "
                          f"{_ID_STRIDE - _SURROUND_K0} a plot can hold")


def _crown_competition(params: list[TreeParams], xy: np.ndarray, zg: np.ndarray,
                       iterations: int = 8, nz: int = 16, nphi: int = 72) -> list[TreeParams]:
    """Crown plasticity of a plot: every tree's competing neighbours and crown scale.

    Neighbours are the trees whose crowns can reach each other (stem distance below 1.2 × the
    sum of their scaled radii).  The crown scale ``s_i ∈ [1, 1.5]`` is found by a damped
    fixed-point iteration over all trees at once: ``s_i ← s_i sqrt(CPA_i / A_i(s))``, where
    ``A_i`` is the projected area of the cut envelope (the same cut as in
    :func:`vlsforest.synth.trees.generate_tree`, without the small random asymmetry).  The
    result is deterministic (no random numbers).
    """
    n = len(params)
    if n == 0:
        return []
    R = np.array([p.crown_radius for p in params])
    cbh = np.array([p.cbh for p in params]) + zg
    top = np.array([p.height for p in params]) + zg
    sps = [get_species(p.species) for p in params]
    d = np.sqrt(((xy[:, None, :] - xy[None, :, :]) ** 2).sum(-1))
    np.fill_diagonal(d, np.inf)
    cand = [np.flatnonzero(d[i] < 1.2 * _SCALE_MAX * (R[i] + R)) for i in range(n)]
    phi = 2 * np.pi * np.arange(nphi) / nphi
    cphi, sphi = np.cos(phi), np.sin(phi)
    tz = (np.arange(nz) + 0.5) / nz
    prof = [crown_profile(sp, tz) for sp in sps]
    s = np.ones(n)

    def area(i):
        z = cbh[i] + (top[i] - cbh[i]) * tz                       # absolute heights
        Ri = s[i] * R[i] * prof[i]                                 # (nz,)
        Rz = np.repeat(Ri[:, None], nphi, axis=1)                  # (nz, nphi)
        for j in cand[i]:
            tj = (z - cbh[j]) / (top[j] - cbh[j])
            rj = np.where((tj >= 0) & (tj < 1), s[j] * R[j] * crown_profile(sps[j], tj), 0.0)
            b = split_distance(Ri, rj, d[i, j], CROWN_OVERLAP)
            ux, uy = (xy[j] - xy[i]) / d[i, j]
            cosang = cphi * ux + sphi * uy
            with np.errstate(divide="ignore", invalid="ignore"):
                lim = np.where(cosang[None, :] > 1e-9,
                               b[:, None] / np.where(cosang > 1e-9, cosang, 1.0)[None, :], np.inf)
            Rz = np.minimum(Rz, lim)
        return float(0.5 * (Rz.max(axis=0) ** 2).sum() * 2 * np.pi / nphi)

    for _ in range(iterations):
        a = np.array([area(i) for i in range(n)])
        target = np.clip(s * np.sqrt(np.pi * R**2 / np.maximum(a, 1e-9)), 1.0, _SCALE_MAX)
        s = np.sqrt(s * target)  # damped
    out = []
    for i, p in enumerate(params):
        nbs = tuple(
            Neighbour(dx=float(xy[j, 0] - xy[i, 0]), dy=float(xy[j, 1] - xy[i, 1]),
                      cbh=float(cbh[j] - zg[i]), height=float(top[j] - zg[i]),
                      radius=float(s[j] * R[j]), species=params[j].species)
            for j in cand[i] if d[i, j] < 1.2 * (s[i] * R[i] + s[j] * R[j]))
        out.append(replace(p, crown_scale=float(round(s[i], 6)), neighbours=nbs))
    return out


def _layout_plot(pc: _PlotCfg, opts: dict, seed: int) -> PlotLayout:
    pseed = _plot_seed(seed, pc.index)
    rng = np.random.default_rng(pseed)
    centre = pc.origin if pc.origin is not None else (0.0, 0.0)
    tparams = pc.assigned
    txy = _place_targets(pc, tparams, opts["buffer"], opts["dmin"], centre, rng)
    b = opts["buffer"]
    extent = (float(txy[:, 0].min() - b), float(txy[:, 1].min() - b),
              float(txy[:, 0].max() + b), float(txy[:, 1].max() + b))
    gopt = dict(opts["ground"])
    ground = GroundSurface.random(
        int(np.random.SeedSequence([pseed, 2]).generate_state(1)[0]), pc.elevation,
        origin=(0.5 * (extent[0] + extent[2]), 0.5 * (extent[1] + extent[3])),
        **{k: gopt[k] for k in gopt})
    m = opts["margin"]
    region = (extent[0] - m, extent[1] - m, extent[2] + m, extent[3] + m)
    area_r = (region[2] - region[0]) * (region[3] - region[1])
    names = sorted(opts["species"])
    w = np.array([opts["species"][k] for k in names], dtype=float)
    if opts["density"] is not None:
        n_s = int(round(opts["density"] * area_r / 1e4))
        _check_count(n_s, pc.name, "forest.stand_density_per_ha")
        sparams = []
        if n_s:
            sp_idx = rng.choice(len(names), size=n_s, p=w / w.sum())
            sparams = [sample_tree_params(names[i], rng, max_triangles=opts["tri_s"])
                       for i in sp_idx]
    else:
        # draw trees until the crowns of all trees add up to the canopy cover of the region
        need = opts["cover"] * area_r - sum(p.cpa for p in tparams)
        sparams = []
        while need > 0:
            i = int(rng.choice(len(names), p=w / w.sum()))
            sparams.append(sample_tree_params(names[i], rng, max_triangles=opts["tri_s"]))
            need -= sparams[-1].cpa
            _check_count(len(sparams), pc.name, "forest.canopy_cover")
    n_s = len(sparams)
    if n_s:
        order = sorted(range(n_s), key=lambda i: -sparams[i].cpa)
        sparams = [sparams[i] for i in order]
    sxy = _place_surrounding(sparams, region, txy, np.array([p.crown_radius for p in tparams]),
                             opts["dmin"], rng, f"forest.plots.{pc.name}")
    allxy = np.concatenate([txy, sxy.reshape(-1, 2)])
    zg = ground.z(allxy[:, 0], allxy[:, 1]) if allxy.size else np.zeros(0)
    allp = _crown_competition(list(tparams) + list(sparams), allxy, zg)
    tparams, sparams = allp[:len(tparams)], allp[len(tparams):]
    base = _ID_STRIDE * pc.index
    trees = []
    for k, (p, (x, y), z) in enumerate(zip(tparams, txy, zg[:len(tparams)])):
        trees.append(TreeSpec(tree_id=base + k, plot=pc.name, species=p.species, target=True,
                              x=float(x), y=float(y), z_ground=float(z), params=p))
    for j, (p, (x, y), z) in enumerate(zip(sparams, sxy, zg[len(tparams):])):
        trees.append(TreeSpec(tree_id=base + _SURROUND_K0 + j, plot=pc.name, species=p.species,
                              target=False, x=float(x), y=float(y), z_ground=float(z),
                              params=p))
    return PlotLayout(name=pc.name, extent=extent, ground=ground, trees=trees, seed=pseed,
                      margin=m, buffer_m=b)


def forest_from_config(cfg: dict, seed: int) -> list[PlotLayout]:
    """Lay out the plots of the virtual forest.

    Parameters
    ----------
    cfg : dict
        The ``forest:`` block of the configuration (see :data:`DEFAULT_FOREST`): ``plots``
        (name → ``targets`` {species: count}, optional ``target_trees`` [{species, height, cbh,
        cpa, dbh?}], ``area_ha`` (or ``target_area_ha`` {name: ha}), ``ground_elevation_m``,
        optional ``origin_m`` [x, y], the centre of the target group, default (0, 0)),
        ``stand_density_per_ha``, ``surrounding_species`` {species: weight}, ``margin_m``,
        ``buffer_m`` (20), ``min_stem_distance_m``, ``max_triangles_target``,
        ``max_triangles_surrounding``, ``ground`` {slope_max, roughness_m, wavelength_m,
        n_modes}.  Missing optional keys take the values of :data:`DEFAULT_FOREST`.
    seed : int
        Seed of the whole forest.

    Returns
    -------
    list of PlotLayout
        One per plot, in config order.

    Raises
    ------
    ConfigError
        Any invalid value; the message starts with the key, e.g.
        ``forest.plots.P2.targets.fagus_sylvatica: must be a positive integer``.
    """
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ConfigError(f"seed: must be a non-negative integer, got {seed!r}")
    opts, pcs = _validate(cfg)
    _assign_targets(pcs, opts, int(seed))
    return [_layout_plot(pc, opts, int(seed)) for pc in pcs]


def plot_layout(cfg: dict, seed: int, plot: str) -> PlotLayout:
    """The layout of one plot of the virtual forest.

    Parameters
    ----------
    cfg, seed
        As :func:`forest_from_config` takes them.
    plot : str
        The plot's name.

    Returns
    -------
    PlotLayout
        The plot's layout, the same as in the whole forest's.

    Raises
    ------
    ConfigError
        An invalid forest, or a plot that is not in it (``plot: unknown plot …``, naming the plots).
    """
    layouts = {p.name: p for p in forest_from_config(cfg, seed)}
    if plot not in layouts:
        raise ConfigError(f"plot: unknown plot {plot!r} (known: {', '.join(layouts)})")
    return layouts[plot]


def layouts_from_settings(path) -> list[PlotLayout]:
    """The plot layouts of a recorded forest, rebuilt from its ``synth_settings.yaml``.

    Parameters
    ----------
    path : path
        A ``truth/synth_settings.yaml`` (or a plot's copy) written by ``vlsforest synth``.

    Returns
    -------
    list of PlotLayout
        As :func:`forest_from_config` with the file's ``forest`` block and ``seed``.

    Raises
    ------
    InputDataError
        The file is not a synth settings file.
    """
    import yaml

    try:
        st = yaml.safe_load(Path(path).read_text())
        seed = int(st["seed"])
        forest_cfg = st["forest"]
    except (yaml.YAMLError, KeyError, TypeError, ValueError) as exc:
        raise InputDataError(f"{path}: not a synth settings file ({exc})") from None
    return forest_from_config(forest_cfg, seed)


# ----------------------------------------------------------------------------------------------
# geometry and truth


def tree_rng(plot_seed: int, tree_id: int) -> np.random.Generator:
    """The generator of one tree's geometry (independent of every other tree)."""
    return np.random.default_rng([int(plot_seed), int(tree_id)])


def generate_plot_trees(plot: PlotLayout, rng_seed: int | None = None,
                        tree_ids: Iterable[int] | None = None) -> dict[int, TreeGeometry]:
    """Generate the meshes of a plot's trees.

    Parameters
    ----------
    plot : PlotLayout
    rng_seed : int, optional
        Seed of the geometry; default ``plot.seed``.  Tree ``t`` uses
        ``default_rng([rng_seed, t])``, so each tree is the same whichever others are generated.
    tree_ids : iterable of int, optional
        Generate only these trees (default: all, in layout order).

    Returns
    -------
    dict
        tree_id → :class:`~vlsforest.synth.trees.TreeGeometry` (stem base at (x, y, z_ground)).
    """
    s = plot.seed if rng_seed is None else rng_seed
    if tree_ids is None:
        specs = plot.trees
    else:
        specs = [plot.tree(int(t)) for t in tree_ids]
    return {t.tree_id: generate_tree(t.params, (t.x, t.y, t.z_ground), tree_rng(s, t.tree_id))
            for t in specs}


TRUTH_COLUMNS = ["tree_id", "plot", "species", "target", "x", "y", "z_ground", "height", "dbh",
                 "cbh", "cpa", "crown_radius"]
_EXTRA_COLUMNS = ["crown_volume", "plant_area", "foliage_area", "n_triangles"]


def truth_table(plots, geometries: dict[int, TreeGeometry]) -> pd.DataFrame:
    """Per-tree truth measured on the generated geometry.

    Parameters
    ----------
    plots : PlotLayout or list of PlotLayout
    geometries : dict
        tree_id → TreeGeometry (e.g. from :func:`generate_plot_trees`); trees without a geometry
        are left out.

    Returns
    -------
    pandas.DataFrame
        Columns ``tree_id, plot, species, target, x, y, z_ground, height, dbh, cbh, cpa,
        crown_radius`` (m, m², from :meth:`TreeGeometry.truth`), then ``crown_volume,
        plant_area, foliage_area, n_triangles``; rows in plot and layout order.

    Raises
    ------
    InputDataError
        A geometry whose id is not a tree of the plots.
    """
    if isinstance(plots, PlotLayout):
        plots = [plots]
    known = {t.tree_id: t for p in plots for t in p.trees}
    stray = sorted(set(geometries) - set(known))
    if stray:
        raise InputDataError(f"geometries: tree id {stray[0]} is not a tree of the given plots")
    rows = []
    for p in plots:
        for t in p.trees:
            g = geometries.get(t.tree_id)
            if g is None:
                continue
            tr = g.truth()
            rows.append({"tree_id": t.tree_id, "plot": t.plot, "species": tr["species"],
                         "target": t.target, **{k: tr[k] for k in TRUTH_COLUMNS[4:]},
                         **{k: tr[k] for k in _EXTRA_COLUMNS}})
    df = pd.DataFrame(rows, columns=TRUTH_COLUMNS + _EXTRA_COLUMNS)
    return df.astype({"tree_id": "int64", "target": "bool", "n_triangles": "int64"})


def stem_meshes(geometries: dict[int, TreeGeometry]) -> dict[int, TriangleMesh]:
    """The closed stem surface of every tree as a :class:`~vlsforest.io.mesh.TriangleMesh`."""
    return {k: TriangleMesh(g.stem_mesh.vertices, g.stem_mesh.faces)
            for k, g in geometries.items()}


__all__ = ["TreeSpec", "PlotLayout", "DEFAULT_FOREST", "QUICK_FOREST", "STUDY_AREAS_HA",
           "TRUTH_COLUMNS", "forest_from_config", "plot_layout", "generate_plot_trees", "truth_table",
           "stem_meshes", "tree_rng"]
