"""Tests of the virtual Bretten forest: plot layouts, ground surface, tree geometry and truth."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest

from vlsforest.errors import ConfigError, InputDataError
from vlsforest.synth import (
    DEFAULT_FOREST,
    QUICK_FOREST,
    TABLE1,
    GroundSurface,
    PlotLayout,
    forest_from_config,
    generate_plot_trees,
    stem_meshes,
    truth_table,
)
from vlsforest.synth.forest import STUDY_AREAS_HA, TRUTH_COLUMNS

SEED = 7
GROUP = {"fagus_sylvatica": "broadleaf", "carpinus_betulus": "broadleaf",
         "picea_abies": "conifer"}


@pytest.fixture(scope="module")
def forest():
    return forest_from_config(DEFAULT_FOREST, SEED)


@pytest.fixture(scope="module")
def quick():
    plots = forest_from_config(QUICK_FOREST, SEED)
    assert len(plots) == 1
    return plots[0]


@pytest.fixture(scope="module")
def quick_geoms(quick):
    """Geometry of a few trees of the quick plot: one target and two surrounding trees."""
    ids = [quick.target_ids()[0]] + [t.tree_id for t in quick.trees if not t.target][:2]
    return generate_plot_trees(quick, tree_ids=ids)


def _targets(plot):
    return [t for t in plot.trees if t.target]


def _xy(trees):
    return np.array([[t.x, t.y] for t in trees])


# ---------------------------------------------------------------------------------- plots
def test_plot_names_and_extent_is_smallest_rectangle_around_buffers(forest):
    assert [p.name for p in forest] == ["P1", "P2", "P3", "P4", "P5", "P6"]
    for p in forest:
        xy = _xy(_targets(p))
        expect = (xy[:, 0].min() - 20.0, xy[:, 1].min() - 20.0,
                  xy[:, 0].max() + 20.0, xy[:, 1].max() + 20.0)
        assert p.extent == expect
        # the buffers touch all four sides: each side has a target exactly 20 m inside
        assert p.buffer_m == 20.0
        # targets near the centre: their bounding box is centred in the extent
        cx, cy = 0.5 * (p.extent[0] + p.extent[2]), 0.5 * (p.extent[1] + p.extent[3])
        assert abs(0.5 * (xy[:, 0].min() + xy[:, 0].max()) - cx) < 1e-9
        assert abs(0.5 * (xy[:, 1].min() + xy[:, 1].max()) - cy) < 1e-9


def test_plot_areas_match_the_study(forest):
    for p in forest:
        study = STUDY_AREAS_HA[p.name]
        assert abs(p.area_ha() / study - 1) < 0.10
        # the layout solves for the area, so it is met to rounding
        assert p.area_ha() == pytest.approx(study, rel=1e-9)
        xmin, ymin, xmax, ymax = p.extent
        assert p.area_ha() == pytest.approx((xmax - xmin) * (ymax - ymin) / 1e4)
        # aspect between 1:2 and 2:1
        assert 0.5 <= (xmax - xmin) / (ymax - ymin) <= 2.0


def test_thirty_targets_with_the_study_species_and_table1_ranges(forest):
    tg = [t for p in forest for t in _targets(p)]
    assert len(tg) == 30
    assert all(len(_targets(p)) == 5 for p in forest)
    counts = {}
    for t in tg:
        counts[t.species] = counts.get(t.species, 0) + 1
        assert t.params.species == t.species
    assert counts == {"fagus_sylvatica": 13, "carpinus_betulus": 2, "picea_abies": 15}
    for t in tg:
        rng = TABLE1[GROUP[t.species]]
        for k in ("height", "cbh", "cpa"):
            lo, hi, _ = rng[k]
            assert lo <= getattr(t.params, k) <= hi, (t.tree_id, k)
        assert t.params.max_triangles == DEFAULT_FOREST["max_triangles_target"]
    # group means close to Table 1 (target_tree_params constrains them to 5 %)
    for grp in ("broadleaf", "conifer"):
        h = [t.params.height for t in tg if GROUP[t.species] == grp]
        assert abs(np.mean(h) / TABLE1[grp]["height"][2] - 1) <= 0.05


def test_targets_first_ids_unique_and_positions_on_the_ground(forest):
    ids = [t.tree_id for p in forest for t in p.trees]
    assert len(ids) == len(set(ids))
    for i, p in enumerate(forest, start=1):
        flags = [t.target for t in p.trees]
        n_t = sum(flags)
        assert flags[:n_t] == [True] * n_t and not any(flags[n_t:])
        assert p.target_ids() == [t.tree_id for t in p.trees[:n_t]]
        assert all(t.tree_id // 10000 == i and (t.tree_id % 10000 < 100) == t.target
                   for t in p.trees)
        assert all(t.plot == p.name for t in p.trees)
        z = p.ground.z(_xy(p.trees)[:, 0], _xy(p.trees)[:, 1])
        assert np.array_equal(z, np.array([t.z_ground for t in p.trees]))


def test_small_plots_get_the_small_crowns(forest):
    by = {p.name: p for p in forest}

    def cpa(name, sp):
        return [t.params.cpa for t in _targets(by[name]) if t.species == sp]

    assert max(cpa("P6", "picea_abies")) <= min(cpa("P1", "picea_abies"))
    assert max(cpa("P1", "fagus_sylvatica")) <= min(cpa("P5", "fagus_sylvatica"))


def test_target_crowns_spread_as_far_as_the_area_allows(forest):
    for p in forest:
        tg = _targets(p)
        xy = _xy(tg)
        r = np.array([t.params.crown_radius for t in tg])
        i, j = np.triu_indices(len(tg), 1)
        d = np.hypot(*(xy[i] - xy[j]).T)
        assert d.min() >= DEFAULT_FOREST["min_stem_distance_m"]
        if p.area_ha() >= 0.25:
            # enough room: stems at least ~0.7 crown-radius sums apart
            assert (d / (r[i] + r[j])).min() > 0.7, p.name
        # upper bound from geometry: the stems' bounding box limits the spread
        a = p.extent[2] - p.extent[0] - 40.0
        b = p.extent[3] - p.extent[1] - 40.0
        assert d.min() <= math.hypot(a, b) + 1e-9


def test_canopy_cover_of_surrounding_trees(forest):
    cover = DEFAULT_FOREST["canopy_cover"]
    band_n, band_area, n_all, area_all = 0, 0.0, 0, 0.0
    for p in forest:
        s = [t for t in p.trees if not t.target]
        xy = _xy(s)
        rx0, ry0, rx1, ry1 = p.region()
        assert p.margin == DEFAULT_FOREST["margin_m"]
        assert (xy[:, 0] >= rx0).all() and (xy[:, 0] <= rx1).all()
        assert (xy[:, 1] >= ry0).all() and (xy[:, 1] <= ry1).all()
        area = (rx1 - rx0) * (ry1 - ry0)
        # trees are drawn until the nominal crown areas of all trees reach cover × area: the
        # last tree crosses the line
        cpa = np.array([t.params.cpa for t in p.trees])
        assert cpa.sum() >= cover * area > cpa.sum() - cpa[len(p.target_ids()):].max()
        n_all += len(s)
        area_all += area
        # the band between the extent and the region is stocked too (the edge is no clearing)
        x0, y0, x1, y1 = p.extent
        inside = (xy[:, 0] > x0) & (xy[:, 0] < x1) & (xy[:, 1] > y0) & (xy[:, 1] < y1)
        band_n += int((~inside).sum())
        band_area += area / 1e4 - p.area_ha()
        # and so is the interior away from the targets: each quadrant of the extent has trees
        cx, cy = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
        dens = len(s) / (area / 1e4)
        for sx in (-1, 1):
            for sy in (-1, 1):
                q = inside & (sx * (xy[:, 0] - cx) > 0) & (sy * (xy[:, 1] - cy) > 0)
                assert q.sum() >= 0.5 * dens * p.area_ha() / 4 * 0.5, (p.name, sx, sy)
    # ≈ 49 m² mean crown → a mature stand of ≈ 200–260 stems/ha (targets' large crowns included)
    dens = n_all / (area_all / 1e4)
    assert 180 <= dens <= 280, dens
    assert abs(band_n / band_area / dens - 1) < 0.25
    # species mix of all surrounding trees follows the weights (multinomial, n ≈ 800)
    s = [t for p in forest for t in p.trees if not t.target]
    w = DEFAULT_FOREST["surrounding_species"]
    tot = sum(w.values())
    for sp, wi in w.items():
        frac = sum(t.species == sp for t in s) / len(s)
        p0 = wi / tot
        assert abs(frac - p0) < 4 * math.sqrt(p0 * (1 - p0) / len(s)) + 1e-9, sp


def test_stand_density_instead_of_cover():
    cfg = copy.deepcopy(QUICK_FOREST)
    cfg["stand_density_per_ha"] = 150.0
    (p,) = forest_from_config(cfg, 3)
    rx0, ry0, rx1, ry1 = p.region()
    n_s = len(p.trees) - len(p.target_ids())
    assert n_s == round(150.0 * (rx1 - rx0) * (ry1 - ry0) / 1e4)


def test_crowns_are_plastic_not_interpenetrating(forest):
    """Every crown knows its competitors; cut crowns keep their area where there is room."""
    from vlsforest.synth.trees import CROWN_OVERLAP, split_distance

    for p in forest:
        by = {(round(t.x, 9), round(t.y, 9)): t for t in p.trees}
        scales = np.array([t.params.crown_scale for t in p.trees])
        assert (scales >= 1.0).all() and (scales <= 1.5 + 1e-9).all()
        for t in p.trees:
            r = t.params.crown_radius * t.params.crown_scale
            for nb in t.params.neighbours:
                other = by[(round(t.x + nb.dx, 9), round(t.y + nb.dy, 9))]
                # the neighbour record describes that tree, heights relative to this stem base
                assert nb.height == pytest.approx(other.params.height + other.z_ground
                                                  - t.z_ground)
                assert nb.radius == pytest.approx(other.params.crown_radius
                                                  * other.params.crown_scale)
                d = math.hypot(nb.dx, nb.dy)
                # at the widest levels the two sides of a boundary sum to 1.1 × the distance
                b1 = split_distance(r, nb.radius, d, CROWN_OVERLAP)
                b2 = split_distance(nb.radius, r, d, CROWN_OVERLAP)
                assert b1 + b2 == pytest.approx(CROWN_OVERLAP * d)
            # symmetric: a neighbour of mine has me as its neighbour
            for nb in t.params.neighbours:
                other = by[(round(t.x + nb.dx, 9), round(t.y + nb.dy, 9))]
                assert any(abs(o.dx + nb.dx) < 1e-9 and abs(o.dy + nb.dy) < 1e-9
                           for o in other.params.neighbours)
    # the targets of the crowded plot (P6: five spruces in a 3.6 m box) grow into the free side
    p6 = next(p for p in forest if p.name == "P6")
    assert max(t.params.crown_scale for t in p6.trees if t.target) > 1.1


def test_no_two_stems_too_close(forest):
    dmin = DEFAULT_FOREST["min_stem_distance_m"]
    for p in forest:
        xy = _xy(p.trees)
        r = np.array([t.params.crown_radius for t in p.trees])
        tg = np.array([t.target for t in p.trees])
        d = np.sqrt(((xy[:, None] - xy[None]) ** 2).sum(-1))
        np.fill_diagonal(d, np.inf)
        assert d.min() >= dmin
        # neighbours keep a crown-size dependent distance from the targets (hard core 0.5 ΣR,
        # relaxed only for a rare tree that found no place)
        rel = d[np.ix_(tg, ~tg)] / (r[tg][:, None] + r[~tg][None, :])
        assert (rel >= 0.5).mean() > 0.98
        assert rel.min() > 0.2


# ---------------------------------------------------------------------------------- determinism
def test_same_seed_same_layout_and_geometry_different_seed_differs(forest, quick, quick_geoms):
    again = forest_from_config(copy.deepcopy(DEFAULT_FOREST), SEED)
    assert again == forest
    other = forest_from_config(DEFAULT_FOREST, SEED + 1)
    assert all(a.extent != b.extent for a, b in zip(forest, other))
    assert all(a.ground != b.ground for a, b in zip(forest, other))
    assert [t.x for t in forest[0].trees[:5]] != [t.x for t in other[0].trees[:5]]
    # geometry: the same tree alone, among others, or in another call → identical bytes
    tid = [t.tree_id for t in quick.trees if not t.target][1]
    g1 = generate_plot_trees(quick, tree_ids=[tid])[tid]
    g2 = quick_geoms[tid]
    for a, b in ((g1.vertices, g2.vertices), (g1.faces, g2.faces), (g1.organ, g2.organ)):
        assert a.tobytes() == b.tobytes()
    g3 = generate_plot_trees(quick, rng_seed=quick.seed + 1, tree_ids=[tid])[tid]
    assert g3.vertices.shape != g1.vertices.shape or not np.array_equal(g3.vertices, g1.vertices)


def test_changing_one_plot_leaves_the_others_unchanged(forest):
    cfg = copy.deepcopy(DEFAULT_FOREST)
    cfg["plots"]["P3"]["ground_elevation_m"] = 300.0
    plots = forest_from_config(cfg, SEED)
    assert plots[0] == forest[0] and plots[4] == forest[4]
    assert plots[2] != forest[2]
    assert plots[2].ground.elevation == 300.0


def test_quick_forest_has_one_small_plot_with_four_targets(quick):
    assert quick.name == "Q1"
    tg = _targets(quick)
    assert sorted(t.species for t in tg) == ["fagus_sylvatica"] * 2 + ["picea_abies"] * 2
    assert quick.area_ha() == pytest.approx(QUICK_FOREST["plots"]["Q1"]["area_ha"])
    for t in tg:
        lo, hi, _ = TABLE1[GROUP[t.species]]["height"]
        assert lo <= t.params.height <= hi
    rx0, ry0, rx1, ry1 = quick.region()
    cpa = sum(t.params.cpa for t in quick.trees)
    assert cpa >= QUICK_FOREST["canopy_cover"] * (rx1 - rx0) * (ry1 - ry0)


def test_explicit_target_trees():
    cfg = copy.deepcopy(QUICK_FOREST)
    cfg["plots"]["Q1"]["target_trees"] = [
        {"species": "Quercus petraea", "height": 27.5, "cbh": 9.0, "cpa": 80.0},
        {"species": "picea_abies", "height": 25.0, "cbh": 5.0, "cpa": 30.0, "dbh": 0.4}]
    (p,) = forest_from_config(cfg, 3)
    tg = _targets(p)
    assert len(tg) == 6
    ex = [t.params for t in tg if t.params.cpa in (80.0, 30.0)]
    assert {(e.species, e.height, e.cbh, e.cpa) for e in ex} == {
        ("quercus_petraea", 27.5, 9.0, 80.0), ("picea_abies", 25.0, 5.0, 30.0)}
    assert [e.dbh for e in ex if e.species == "picea_abies"] == [0.4]
    assert all(0.05 < e.dbh < 1.5 for e in ex)


# ---------------------------------------------------------------------------------- bad config
def _bad(mut):
    cfg = copy.deepcopy(DEFAULT_FOREST)
    mut(cfg)
    return cfg


def _set(path, value):
    def mut(cfg):
        d = cfg
        for k in path[:-1]:
            d = d[k]
        d[path[-1]] = value
    return mut


def _del(path):
    def mut(cfg):
        d = cfg
        for k in path[:-1]:
            d = d[k]
        del d[path[-1]]
    return mut


BAD = [
    (_set(("plots", "P2", "area_ha"), -0.1), "forest.plots.P2.area_ha"),
    (_set(("target_area_ha", "P2"), -0.25), "forest.target_area_ha.P2"),
    (_set(("plots", "P2", "area_ha"), 0.3), "forest.plots.P2.area_ha"),  # disagrees
    (_set(("plots", "P6", "area_ha"), 0.19), None),  # agrees: fine
    (_set(("target_area_ha", "P1"), 0.1), "forest.target_area_ha.P1"),  # < (2·20 m)²
    (_set(("target_area_ha", "P9"), 0.3), "forest.target_area_ha.P9"),
    (_del(("target_area_ha", "P4")), "forest.plots.P4.area_ha"),
    (_set(("plots", "P2", "targets", "fagus_silvatica"), 1),
     "forest.plots.P2.targets.fagus_silvatica"),
    (_set(("plots", "P2", "targets", "fagus_sylvatica"), 0),
     "forest.plots.P2.targets.fagus_sylvatica"),
    (_set(("plots", "P2", "targets", "fagus_sylvatica"), -2),
     "forest.plots.P2.targets.fagus_sylvatica"),
    (_set(("plots", "P2", "targets", "fagus_sylvatica"), 1.5),
     "forest.plots.P2.targets.fagus_sylvatica"),
    (_set(("plots", "P2", "targets", "fagus_sylvatica"), "2"),
     "forest.plots.P2.targets.fagus_sylvatica"),
    (_set(("plots", "P2", "targets", "fagus_sylvatica"), True),
     "forest.plots.P2.targets.fagus_sylvatica"),
    (_set(("plots", "P2", "targets"), {}), "forest.plots.P2.targets"),
    (_del(("plots",)), "forest.plots"),
    (_set(("plots",), {}), "forest.plots"),
    (_set(("plots",), ["P1"]), "forest.plots"),
    (_del(("plots", "P3", "ground_elevation_m")), "forest.plots.P3.ground_elevation_m"),
    (_set(("plots", "P3", "ground_elevation_m"), float("nan")),
     "forest.plots.P3.ground_elevation_m"),
    (_set(("plots", "P3", "grund_elevation_m"), 1.0), "forest.plots.P3.grund_elevation_m"),
    (_set(("stand_density",), 400), "forest.stand_density"),
    (_set(("stand_density_per_ha",), -5), "forest.stand_density_per_ha"),
    (_set(("canopy_cover",), -0.5), "forest.canopy_cover"),
    (_set(("canopy_cover",), "full"), "forest.canopy_cover"),
    (_set(("canopy_cover",), None), "forest.canopy_cover"),
    (_set(("surrounding_species",), {"ulmus_minor": 1.0}), "forest.surrounding_species.ulmus"),
    (_set(("surrounding_species",), {"picea_abies": -1.0}),
     "forest.surrounding_species.picea_abies"),
    (_set(("margin_m",), -1), "forest.margin_m"),
    (_set(("max_triangles_target",), 100), "forest.max_triangles_target"),
    (_set(("max_triangles_surrounding",), "many"), "forest.max_triangles_surrounding"),
    (_set(("ground",), {"roughness_m": -0.1}), "forest.ground.roughness_m"),
    (_set(("ground",), {"wavelength_m": [20, 10]}), "forest.ground.wavelength_m"),
    (_set(("plots", "P1", "target_trees"),
          [{"species": "picea_abies", "height": -20.0, "cbh": 5.0, "cpa": 30.0}]),
     "forest.plots.P1.target_trees[0].height"),
    (_set(("plots", "P1", "target_trees"),
          [{"species": "picea_abies", "height": 20.0, "cbh": 25.0, "cpa": 30.0}]),
     "forest.plots.P1.target_trees[0].cbh"),
    (_set(("plots", "P1", "target_trees"),
          [{"species": "tilia_cordata", "height": 20.0, "cbh": 5.0, "cpa": 30.0}]),
     "forest.plots.P1.target_trees[0].species"),
    (_set(("plots", "P1", "target_trees"), [{"species": "picea_abies", "height": 20.0}]),
     "forest.plots.P1.target_trees[0].cbh"),
    (_set(("plots", "P1", "target_trees"),
          [{"species": "picea_abies", "height": 20.0, "cbh": 5.0, "cpa": 30.0, "dbh": 40}]),
     "forest.plots.P1.target_trees[0].dbh"),  # cm instead of m
]


@pytest.mark.parametrize("mut,key", BAD)
def test_bad_config_names_the_key(mut, key):
    cfg = _bad(mut)
    if key is None:
        assert len(forest_from_config(cfg, 1)) == 6
        return
    with pytest.raises(ConfigError) as exc:
        forest_from_config(cfg, 1)
    assert str(exc.value).startswith(key), str(exc.value)


def test_bad_config_too_many_targets_for_the_area_and_bad_seed():
    cfg = copy.deepcopy(QUICK_FOREST)
    cfg["plots"]["Q1"]["targets"] = {"picea_abies": 20}
    cfg["plots"]["Q1"]["area_ha"] = 0.161
    with pytest.raises(ConfigError, match=r"^forest\.plots\.Q1\.area_ha"):
        forest_from_config(cfg, 0)
    with pytest.raises(ConfigError, match="^seed"):
        forest_from_config(QUICK_FOREST, -1)
    with pytest.raises(ConfigError, match="^forest"):
        forest_from_config(None, 0)


# ---------------------------------------------------------------------------------- ground
def test_ground_is_gently_rough_and_smooth(forest):
    for p in forest:
        xs, ys, z = p.ground.grid(p.region(), 1.0)
        dev = z - z.mean()
        assert np.abs(dev).max() <= 1.0, p.name
        # rough, not a plane: residual of a least-squares plane of a few cm at least
        X, Y = np.meshgrid(xs, ys)
        A = np.c_[np.ones(X.size), X.ravel(), Y.ravel()]
        res = z.ravel() - A @ np.linalg.lstsq(A, z.ravel(), rcond=None)[0]
        assert 0.03 < res.std() < 0.4, p.name
        # smooth: finite-difference slopes on the 1 m grid stay below 30 % everywhere and
        # are ≈ 7 % (RMS) on average: a few dm over 10–20 m
        gx = np.diff(z, axis=1) / np.diff(xs)[None, :]
        gy = np.diff(z, axis=0) / np.diff(ys)[:, None]
        assert np.abs(gx).max() < 0.3 and np.abs(gy).max() < 0.3
        assert math.sqrt(np.mean(gx**2) + np.mean(gy**2)) < 0.12
        # and the curvature is small (no steps or spikes): radius of curvature > ~7 m, bounded
        # by the waves' Σ a_k |k|²
        k = np.array(p.ground.wavevectors)
        bound = float((np.array(p.ground.amplitudes) * (k**2).sum(1)).sum())
        for ax in (0, 1):
            d2 = np.abs(np.diff(z, 2, axis=ax)).max()
            assert d2 < 0.15 and d2 <= bound * 1.001
        # the plane the simulations use lies within the ground's range, close to the elevation
        gz = p.ground_z()
        assert z.min() < gz < z.max()
        assert abs(gz - p.ground.elevation) < 1.0


def test_ground_rms_roughness_and_gradient_match_the_parameters():
    g = GroundSurface.random(4, 100.0, origin=(10.0, -5.0), slope_max=0.0, roughness_m=0.2,
                             wavelength_m=(10.0, 20.0), n_modes=16)
    assert g.gradient == (0.0, 0.0)
    xs, ys, z = g.grid((-1000.0, -1000.0, 1000.0, 1000.0), 2.0)
    # a sum of cosines with amplitudes a·sqrt(2/n): mean elevation, RMS = a over a large area
    assert z.mean() == pytest.approx(100.0, abs=0.01)
    assert z.std() == pytest.approx(0.2, rel=0.05)
    # analytic gradient against central differences
    rng = np.random.default_rng(0)
    x, y = rng.uniform(-50, 50, 200), rng.uniform(-50, 50, 200)
    h = 1e-4
    gx, gy = g.gradient_at(x, y)
    assert np.allclose(gx, (g.z(x + h, y) - g.z(x - h, y)) / (2 * h), atol=1e-6)
    assert np.allclose(gy, (g.z(x, y + h) - g.z(x, y - h)) / (2 * h), atol=1e-6)
    # a pure plane: z is linear and the median over a symmetric extent is the centre value
    plane = GroundSurface(elevation=50.0, origin=(0.0, 0.0), gradient=(0.01, -0.02))
    assert plane.z(3.0, 4.0) == pytest.approx(50.0 + 0.03 - 0.08)
    lay = PlotLayout(name="T", extent=(-20.0, -30.0, 40.0, 10.0), ground=plane, trees=[], seed=0)
    assert lay.ground_z() == pytest.approx(plane.z(10.0, -10.0))
    assert lay.area_ha() == pytest.approx(0.24)
    # slope magnitude bounded by slope_max
    for s in range(20):
        gs = GroundSurface.random(s, 0.0, slope_max=0.01)
        assert math.hypot(*gs.gradient) <= 0.01


def test_ground_determinism_and_mesh():
    a = GroundSurface.random(11, 240.0, origin=(1.0, 2.0))
    assert a == GroundSurface.random(11, 240.0, origin=(1.0, 2.0))
    assert a != GroundSurface.random(12, 240.0, origin=(1.0, 2.0))
    ext = (-10.3, -5.0, 20.0, 7.5)
    m = a.mesh(ext, spacing=1.0)
    lo, hi = m.bounds()
    assert tuple(lo[:2]) == (ext[0], ext[1]) and tuple(hi[:2]) == (ext[2], ext[3])
    assert np.array_equal(m.vertices[:, 2], a.z(m.vertices[:, 0], m.vertices[:, 1]))
    nx, ny = math.ceil(30.3) + 1, math.ceil(12.5) + 1
    assert m.n_vertices == nx * ny and m.n_faces == 2 * (nx - 1) * (ny - 1)
    n = m.face_normals()
    assert (n[:, 2] > 0.95).all()  # all facing up, gentle
    planar = (ext[2] - ext[0]) * (ext[3] - ext[1])
    proj = 0.5 * np.abs(np.cross(*(m.vertices[m.faces[:, k], :2] - m.vertices[m.faces[:, 0], :2]
                                   for k in (1, 2)))).sum()
    assert proj == pytest.approx(planar, rel=1e-9)  # the grid tiles the extent exactly
    assert planar < m.area() < 1.01 * planar
    with pytest.raises(ConfigError, match="^extent"):
        a.mesh((0.0, 0.0, -1.0, 5.0))


# ---------------------------------------------------------------------------------- geometry/truth
def test_truth_table_equals_the_geometry_truth(quick, quick_geoms):
    df = truth_table([quick], quick_geoms)
    assert list(df.columns[:len(TRUTH_COLUMNS)]) == TRUTH_COLUMNS
    assert len(df) == len(quick_geoms) == 3
    assert df["tree_id"].tolist() == list(quick_geoms)
    assert df["target"].tolist() == [True, False, False]
    for row in df.itertuples(index=False):
        g = quick_geoms[row.tree_id]
        spec = quick.tree(row.tree_id)
        tr = g.truth()
        for k in TRUTH_COLUMNS[4:]:
            assert getattr(row, k) == tr[k], k
        assert row.species == spec.species == g.species
        assert row.plot == "Q1"
        assert (row.x, row.y, row.z_ground) == (spec.x, spec.y, spec.z_ground)
        # the tree stands on the ground: lowest stem vertex at z_ground, height as requested
        stem = g.vertices[g.faces[g.organ == 0].ravel()]
        assert stem[:, 2].min() == pytest.approx(spec.z_ground, abs=1e-9)
        assert abs(row.height - spec.params.height) < 0.5
        assert row.crown_radius == pytest.approx(math.sqrt(row.cpa / math.pi))
        assert g.n_triangles <= spec.params.max_triangles
    tgt = df[df.target].iloc[0]
    assert TABLE1[GROUP[tgt.species]]["height"][0] - 0.5 <= tgt.height
    # closed stem surfaces for validation
    sm = stem_meshes(quick_geoms)
    for k, m in sm.items():
        v = m.vertices[m.faces]
        vol = np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6.0
        d = quick.tree(k).params.dbh
        # volume of a tapering stem: between a cone and a cylinder of the DBH (plus butt swell)
        h = quick.tree(k).params.height
        assert math.pi * (d / 2) ** 2 * h / 4 < vol < math.pi * (0.75 * d) ** 2 * h
    # subsets and strays
    assert truth_table(quick, {}).empty
    with pytest.raises(InputDataError, match="99999"):
        truth_table([quick], {99999: next(iter(quick_geoms.values()))})
    with pytest.raises(ConfigError, match="tree_id"):
        generate_plot_trees(quick, tree_ids=[123])
