"""Tests of the parametric tree generator, species draws and the true plant area per voxel."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import quad

from vlsforest.domain.leaf_angles import leaf_inclination_pdf
from vlsforest.errors import ConfigError
from vlsforest.synth import (
    ORGAN_BRANCH,
    ORGAN_FOLIAGE,
    ORGAN_STEM,
    SPECIES,
    TABLE1,
    TreeParams,
    generate_tree,
    sample_tree_params,
    target_tree_params,
    true_plant_area,
)
from vlsforest.synth.plant_area import clip_triangles_to_grid
from vlsforest.synth.species import load_bretten_summary

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"
PAD_RANGE = {"broadleaf": (1.0, 5.0), "conifer": (2.0, 8.0)}


@pytest.fixture(scope="module")
def targets():
    return target_tree_params(np.random.default_rng(11))


@pytest.fixture(scope="module")
def target_trees(targets):
    """One full-budget tree of each target species (beech, hornbeam, spruce)."""
    picks = {}
    for i, p in enumerate(targets):
        picks.setdefault(p.species, (i, p))
    return {sp: generate_tree(p, (500.0, -20.0, 240.0), np.random.default_rng(100 + i))
            for sp, (i, p) in picks.items()}


@pytest.fixture(scope="module")
def surrounding_trees():
    rng = np.random.default_rng(5)
    out = []
    for sp in SPECIES:
        p = sample_tree_params(sp, rng, height=float(rng.uniform(15, 30)), max_triangles=20_000)
        out.append(generate_tree(p, (0.0, 0.0, 0.0), rng))
    return out


def _all_trees(target_trees, surrounding_trees):
    return list(target_trees.values()) + list(surrounding_trees)


# ---------------------------------------------------------------------------------------------
# geometry matches the inputs


def test_trees_match_their_inputs(target_trees, surrounding_trees):
    for g in _all_trees(target_trees, surrounding_trees):
        p = g.params
        assert abs(g.height - p.height) <= 0.1, (g.species, g.height, p.height)
        assert abs(g.cbh - p.cbh) <= 0.5, (g.species, g.cbh, p.cbh)
        assert abs(g.cpa / p.cpa - 1) <= 0.15, (g.species, g.cpa, p.cpa)
        assert abs(g.dbh / p.dbh - 1) <= 0.01
        assert g.crown_radius == pytest.approx(math.sqrt(g.cpa / math.pi))
        assert g.n_triangles <= p.max_triangles
        # the stem base sits on the ground point, nothing lies below the ground
        assert g.vertices[:, 2].min() >= g.position[2] - 1e-9
        # every organ present, arrays typed as documented
        assert set(np.unique(g.organ)) == {ORGAN_STEM, ORGAN_BRANCH, ORGAN_FOLIAGE}
        assert g.vertices.dtype == np.float64 and g.faces.dtype == np.int32
        assert g.organ.dtype == np.uint8 and g.organ.shape == (g.n_triangles,)


def test_target_tree_triangle_budget_and_foliage_area(target_trees):
    for g in target_trees.values():
        sp = SPECIES[g.species]
        assert g.n_triangles <= 150_000
        # foliage area = crown LAI x projected envelope area, and element count x element area
        fol = g.plant_area((ORGAN_FOLIAGE,))
        assert fol == pytest.approx(sp.crown_lai * g.envelope_area, rel=1e-9)
        # a free-standing crown's envelope projects onto (nearly) the requested CPA: the star
        # outline of the modulated envelope lies inside the convex hull that has the CPA
        assert 0.9 * g.params.cpa <= g.envelope_area <= 1.005 * g.params.cpa  # (sampled outline)
        n_fol = int((g.organ == ORGAN_FOLIAGE).sum())
        assert fol == pytest.approx(n_fol * g.foliage_element_area, rel=1e-9)
        assert g.foliage_element_area >= sp.leaf_element_area - 1e-15


def test_stem_mesh_is_closed_and_has_the_profile_volume(target_trees):
    from vlsforest.synth.trees import _BREAST_HEIGHT

    for g in target_trees.values():
        m = g.stem_mesh
        e = np.sort(np.concatenate([m.faces[:, [0, 1]], m.faces[:, [1, 2]],
                                    m.faces[:, [2, 0]]]), axis=1)
        _, counts = np.unique(e, axis=0, return_counts=True)
        assert (counts == 2).all()  # every edge shared by exactly two faces: closed
        # volume of the closed stem = ∫ area of the regular ring polygon dz (frustum rule)
        sp = SPECIES[g.species]
        H, rbh = g.params.height, g.params.dbh / 2
        z = np.unique(m.vertices[:, 2])
        n = 16

        def r(zz):
            above = rbh * np.clip((H - zz) / (H - _BREAST_HEIGHT), 0, None) ** sp.stem_taper
            below = rbh * (1 + sp.butt_swell * np.clip((_BREAST_HEIGHT - zz) / _BREAST_HEIGHT,
                                                         0, 1) ** 2)
            return np.where(zz >= _BREAST_HEIGHT, above, below)

        zz = np.linspace(0, H, 200_001)
        poly = 0.5 * n * np.sin(2 * np.pi / n) * r(zz) ** 2
        vol = float(np.sum(0.5 * (poly[1:] + poly[:-1]) * np.diff(zz)))
        assert m.signed_volume() == pytest.approx(vol, rel=0.03)
        assert z.min() == pytest.approx(g.position[2]) and z.max() == pytest.approx(g.height
                                                                                     + g.position[2])


# ---------------------------------------------------------------------------------------------
# plant area density


def _foliated_voxel_pad(g, cell=0.25):
    allc = true_plant_area(g, g.position, cell, organs=(ORGAN_BRANCH, ORGAN_FOLIAGE))
    fol = true_plant_area(g, g.position, cell, organs=(ORGAN_FOLIAGE,))
    key = lambda ijk: (ijk[:, 0] * 100_000 + ijk[:, 1]) * 100_000 + ijk[:, 2]  # noqa: E731
    return allc.pad()[np.isin(key(allc.ijk), key(fol.ijk))]


def _weighted_median(v):
    """The PAD that half of the plant area exceeds (each voxel weighted by its plant area)."""
    w = np.sort(v)
    c = np.cumsum(w)
    return float(w[np.searchsorted(c, 0.5 * c[-1])])


def test_crown_pad_is_plausible(target_trees):
    for g in target_trees.values():
        sp = SPECIES[g.species]
        lo, hi = PAD_RANGE[sp.group]
        # the foliated 0.25 m voxels (what TLS-based PAD estimates describe) hold a few m²/m³:
        # half of the foliage sits in voxels denser than this (the plain median is dominated by
        # voxels that a foliage element only grazes)
        med = _weighted_median(_foliated_voxel_pad(g))
        assert lo <= med <= hi, (g.species, med)
        # the crown as a whole is much sparser: leaf area per crown projection area in the range
        # measured in closed beech / spruce stands (LAI 5–8 / 7–12), envelope mean ≤ 2 m²/m³
        lai = g.plant_area((ORGAN_FOLIAGE,)) / g.cpa
        assert (5.0 <= lai <= 8.5) if sp.group == "broadleaf" else (7.0 <= lai <= 12.0), lai
        assert 0.1 <= g.plant_area((ORGAN_BRANCH, ORGAN_FOLIAGE)) / g.crown_volume <= 2.0


def test_conifers_are_denser_than_broadleaf(target_trees):
    bl = target_trees["fagus_sylvatica"]
    co = target_trees["picea_abies"]
    assert _weighted_median(_foliated_voxel_pad(co)) > _weighted_median(_foliated_voxel_pad(bl))


def _crown_xy(g):
    return g.vertices[np.unique(g.faces[g.organ != ORGAN_STEM])]


def test_neighbour_cuts_the_crown_at_the_radius_weighted_split():
    # two equal beech crowns 6 m apart, nominal radius 5 m: alone they would overlap by 4 m;
    # cut, each stays on its side of the line 1.1 × 6 × 5/(5+5) = 3.3 m from its stem
    from vlsforest.synth.species import Neighbour

    r = 5.0
    base = dict(species="fagus_sylvatica", height=28.0, dbh=0.45, cbh=8.0, cpa=math.pi * r**2)
    free = generate_tree(TreeParams(**base), (0.0, 0.0, 0.0), np.random.default_rng(3))
    nb = Neighbour(dx=6.0, dy=0.0, cbh=8.0, height=28.0, radius=r, species="fagus_sylvatica")
    cut = generate_tree(TreeParams(**base, neighbours=(nb,)), (0.0, 0.0, 0.0),
                        np.random.default_rng(3))
    x_free, x_cut = _crown_xy(free)[:, 0], _crown_xy(cut)[:, 0]
    assert x_free.max() > 4.0
    # foliage elements (≤ 0.2 m) and their clumping may poke a little past the envelope
    assert x_cut.max() <= 3.3 + 0.5
    assert x_cut.min() == pytest.approx(x_free.min(), abs=0.6)   # the free side is untouched
    assert cut.cpa < free.cpa and cut.envelope_area < free.envelope_area
    # the foliage follows the crown that is left: LAI per envelope area is the species' value
    lai = cut.plant_area((ORGAN_FOLIAGE,)) / cut.envelope_area
    assert lai == pytest.approx(SPECIES["fagus_sylvatica"].crown_lai, rel=1e-9)
    # a neighbour whose crown starts above this tree's top does not cut it (height layers)
    high = Neighbour(dx=6.0, dy=0.0, cbh=30.0, height=40.0, radius=r, species="fagus_sylvatica")
    up = generate_tree(TreeParams(**base, neighbours=(high,)), (0.0, 0.0, 0.0),
                       np.random.default_rng(3))
    assert np.array_equal(up.vertices, free.vertices)
    # crown scale grows the free sides
    big = generate_tree(TreeParams(**base, neighbours=(nb,), crown_scale=1.3), (0.0, 0.0, 0.0),
                        np.random.default_rng(3))
    assert _crown_xy(big)[:, 0].min() < x_cut.min() - 0.8
    assert _crown_xy(big)[:, 0].max() <= 1.1 * 6.0 * 1.3 / 2.3 + 0.5


# ---------------------------------------------------------------------------------------------
# leaf angles


def _inclinations(g):
    tri = g.vertices[g.faces[g.organ == ORGAN_FOLIAGE]]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return np.arccos(np.abs(n[:, 2]))


@pytest.mark.parametrize("species,dist", [("fagus_sylvatica", "planophile"),
                                          ("picea_abies", "erectophile")])
def test_leaf_inclination_matches_de_wit(target_trees, species, dist):
    th = _inclinations(target_trees[species])
    norm = quad(lambda t: leaf_inclination_pdf(dist, t), 0, np.pi / 2)[0]
    mean = quad(lambda t: t * leaf_inclination_pdf(dist, t), 0, np.pi / 2)[0]
    sd = math.sqrt(quad(lambda t: (t - mean) ** 2 * leaf_inclination_pdf(dist, t), 0, np.pi / 2)[0])
    assert norm == pytest.approx(1.0, abs=1e-9)
    # 5 standard errors of the sample mean
    assert abs(th.mean() - mean) < 5 * sd / math.sqrt(th.size) + 1e-3, (th.mean(), mean)
    # the whole distribution: Kolmogorov–Smirnov distance against the analytic CDF
    grid = np.sort(th)
    cdf = np.array([quad(lambda t: leaf_inclination_pdf(dist, t), 0, x)[0]
                    for x in grid[:: max(1, grid.size // 400)]])
    emp = (np.arange(grid.size)[:: max(1, grid.size // 400)] + 0.5) / grid.size
    assert np.abs(cdf - emp).max() < 0.01


def test_planophile_and_erectophile_means_differ_as_expected():
    pl = quad(lambda t: t * leaf_inclination_pdf("planophile", t), 0, np.pi / 2)[0]
    er = quad(lambda t: t * leaf_inclination_pdf("erectophile", t), 0, np.pi / 2)[0]
    assert pl < np.radians(30) < np.radians(60) < er
    assert pl + er == pytest.approx(np.pi / 2)  # mirror-symmetric densities


# ---------------------------------------------------------------------------------------------
# target trees (Table 1)


def test_target_params_satisfy_table1(targets):
    assert len(targets) == 30
    counts = {}
    for p in targets:
        counts[p.species] = counts.get(p.species, 0) + 1
    assert counts == {"fagus_sylvatica": 13, "carpinus_betulus": 2, "picea_abies": 15}
    for group, members in (("broadleaf", targets[:15]), ("conifer", targets[15:])):
        assert {SPECIES[p.species].group for p in members} == {group}
        for k in ("height", "cbh", "cpa"):
            lo, hi, mean = TABLE1[group][k]
            v = np.array([getattr(p, k) for p in members])
            assert (v >= lo).all() and (v <= hi).all(), (group, k)
            assert abs(v.mean() / mean - 1) <= 0.10, (group, k, v.mean())
        assert all(0 < p.dbh < 1.2 for p in members)


def test_target_params_deterministic_per_seed():
    a = target_tree_params(np.random.default_rng(3))
    b = target_tree_params(np.random.default_rng(3))
    c = target_tree_params(np.random.default_rng(4))
    assert a == b
    assert a != c


# ---------------------------------------------------------------------------------------------
# determinism


def test_same_seed_gives_identical_arrays():
    p = TreeParams("picea_abies", height=20.0, dbh=0.3, cbh=4.0, cpa=20.0, max_triangles=20_000)
    g1 = generate_tree(p, (1.0, 2.0, 3.0), np.random.default_rng(42))
    g2 = generate_tree(p, (1.0, 2.0, 3.0), np.random.default_rng(42))
    g3 = generate_tree(p, (1.0, 2.0, 3.0), np.random.default_rng(43))
    for a in ("vertices", "faces", "organ"):
        assert getattr(g1, a).tobytes() == getattr(g2, a).tobytes()
    assert g1.stem_mesh.vertices.tobytes() == g2.stem_mesh.vertices.tobytes()
    assert g1.vertices.shape != g3.vertices.shape or \
        g1.vertices.tobytes() != g3.vertices.tobytes()
    # a tree is the same shape wherever it stands
    g4 = generate_tree(p, (11.0, 2.0, 3.0), np.random.default_rng(42))
    np.testing.assert_allclose(g4.vertices - [10.0, 0, 0], g1.vertices, atol=1e-9)


# ---------------------------------------------------------------------------------------------
# true plant area per voxel


def test_clipping_of_a_triangle_analytic():
    # right triangle (0,0)-(1,0)-(0,1) on 0.5 m cells: 0.25 in the corner cell, 0.125 in two
    tri = np.array([[[0, 0, 0.1], [1, 0, 0.1], [0, 1, 0.1]]], float)
    ijk, area = clip_triangles_to_grid(tri, np.ones(1), (0, 0, 0), 0.5)
    got = {tuple(c): a for c, a in zip(ijk.tolist(), area)}
    assert got == pytest.approx({(0, 0, 0): 0.25, (1, 0, 0): 0.125, (0, 1, 0): 0.125})
    # the same triangle tilted by 60° about the x axis: areas scale by 1/cos(60°) per xy cell
    t2 = tri.copy()
    t2[..., 2] = 0.1 + tri[..., 1] * math.tan(math.radians(60))
    ijk, area = clip_triangles_to_grid(t2, np.ones(1), (0, 0, -10), (0.5, 0.5, 100.0))
    got = {tuple(c[:2]): a for c, a in zip(ijk.tolist(), area)}
    assert got == pytest.approx({(0, 0): 0.5, (1, 0): 0.25, (0, 1): 0.25})
    # and split in z as well: the cut planes z = 0.1 + 0.5 k split it by height along y
    ijk, area = clip_triangles_to_grid(t2, np.ones(1), (0, 0, 0.1), (10.0, 10.0,
                                                                      0.5 * math.tan(
                                                                          math.radians(60))))
    got = {int(c[2]): a for c, a in zip(ijk.tolist(), area)}
    assert got == pytest.approx({0: 2 * 0.375, 1: 2 * 0.125})


def test_clipping_against_monte_carlo():
    rng = np.random.default_rng(0)
    tris = rng.uniform(0, 1.0, (20, 3, 3))
    w = rng.uniform(0.5, 1.0, 20)
    ijk, area = clip_triangles_to_grid(tris, w, (0.03, -0.02, 0.01), (0.3, 0.2, 0.25))
    exact = dict(zip(map(tuple, ijk.tolist()), area))
    # brute force: many barycentric samples per triangle, each carrying area*w/n
    n = 200_000
    u, v = rng.random((2, 20, n))
    flip = u + v > 1
    u, v = np.where(flip, 1 - u, u), np.where(flip, 1 - v, v)
    pts = tris[:, None, 0] + u[..., None] * (tris[:, None, 1] - tris[:, None, 0]) + \
        v[..., None] * (tris[:, None, 2] - tris[:, None, 0])
    a_tri = 0.5 * np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]),
                                 axis=1)
    cell = np.floor((pts - [0.03, -0.02, 0.01]) / [0.3, 0.2, 0.25]).astype(int).reshape(-1, 3)
    wts = np.repeat(a_tri * w / n, n)
    keys, inv = np.unique(cell, axis=0, return_inverse=True)
    mc = np.bincount(inv.ravel(), weights=wts)
    total = float((a_tri * w).sum())
    assert area.sum() == pytest.approx(total, rel=1e-12)
    for k, a in zip(map(tuple, keys.tolist()), mc):
        # sampling error of the per-voxel share is tiny at 200k samples per triangle
        assert exact.get(k, 0.0) == pytest.approx(a, abs=2e-3 * total / 10 + 1e-4)


def test_true_plant_area_sums_to_tree_plant_area(target_trees):
    g = target_trees["picea_abies"]
    total = g.plant_area()
    for origin, cell in (((0.0, 0.0, 0.0), 0.25), ((499.93, -20.11, 239.7), (0.1, 0.3, 0.17)),
                         ((12.3, 4.5, 6.7), 1.0)):
        r = true_plant_area(g, origin, cell)
        assert r.total == pytest.approx(total, rel=1e-9)
        assert r.outside == 0.0 and (r.area > 0).all()
    # the convention: foliage one-sided, woody half the surface
    fa = g.face_areas()
    expected = fa[g.organ == ORGAN_FOLIAGE].sum() + 0.5 * fa[g.organ != ORGAN_FOLIAGE].sum()
    assert total == pytest.approx(expected, rel=1e-12)
    # a bounded grid keeps the rest as "outside"
    x0, y0, z0 = g.position
    shape = (40, 40, 60)
    r = true_plant_area(g, (x0 - 5, y0 - 5, z0), 0.25, shape=shape)
    assert r.area.sum() + r.outside == pytest.approx(total, rel=1e-9)
    assert r.outside > 0 and (r.ijk >= 0).all() and (r.ijk < shape).all()
    assert r.dense().sum() == pytest.approx(r.area.sum())


def test_true_plant_area_of_two_trees_adds_up(surrounding_trees):
    a, b = surrounding_trees[0], surrounding_trees[3]
    both = true_plant_area([a, b], (0, 0, 0), 0.5)
    assert both.total == pytest.approx(a.plant_area() + b.plant_area(), rel=1e-9)


# ---------------------------------------------------------------------------------------------
# bad parameters


@pytest.mark.parametrize("kw,field", [
    (dict(height=-5.0), "height"),
    (dict(cbh=40.0), "cbh"),
    (dict(cbh=-1.0), "cbh"),
    (dict(species="ginkgo_biloba"), "species"),
    (dict(dbh=0.0), "dbh"),
    (dict(dbh=-0.2), "dbh"),
    (dict(dbh=35.0), "dbh"),
    (dict(cpa=0.0), "cpa"),
    (dict(height=float("nan")), "height"),
    (dict(max_triangles=10), "max_triangles"),
])
def test_bad_params_raise_config_error(kw, field):
    base = dict(species="fagus_sylvatica", height=30.0, dbh=0.4, cbh=8.0, cpa=100.0)
    base.update(kw)
    with pytest.raises(ConfigError, match=field):
        TreeParams(**base)


def test_bad_call_arguments_raise_config_error():
    p = TreeParams("fagus_sylvatica", 20.0, 0.3, 5.0, 50.0, max_triangles=5000)
    with pytest.raises(ConfigError, match="position"):
        generate_tree(p, (0.0, 1.0))
    with pytest.raises(ConfigError, match="cell_size"):
        true_plant_area([], (0, 0, 0), -1.0)


# ---------------------------------------------------------------------------------------------
# Bretten summary and draws


def test_sampled_trees_follow_the_bretten_summary():
    rng = np.random.default_rng(9)
    summ = load_bretten_summary()["species"]["Fagus sylvatica"]["joint"]
    ps = [sample_tree_params("fagus_sylvatica", rng, min_height=0.0) for _ in range(400)]
    h = np.array([p.height for p in ps])
    q = summ["height_m"]["quantiles"]
    assert h.min() >= q[0] - 1e-9 and h.max() <= q[-1] + 1e-9
    assert np.median(h) == pytest.approx(q[4], rel=0.08)
    fit = summ["dbh_cm_on_height"]
    resid = np.log([p.dbh * 100 for p in ps]) - (fit["a"] + fit["b"] * np.log(h))
    assert abs(np.mean(resid)) < 3 * fit["resid_sd"] / math.sqrt(len(ps))
    assert np.std(resid) == pytest.approx(fit["resid_sd"], rel=0.2)
    assert all(0 < p.cbh < p.height for p in ps)


@pytest.mark.realdata
def test_shipped_summary_matches_the_real_csv():
    csv = REAL / "bretten_tree_metrics.csv"
    if not csv.is_file():
        pytest.skip("real Bretten data not available")
    from vlsforest.synth._summarise import summarise_bretten

    fresh = json.loads(json.dumps(summarise_bretten(csv)))
    assert fresh == load_bretten_summary()
    # sanity of the real data: spruce is smaller in CPA than beech
    s = fresh["species"]
    assert s["Picea abies"]["joint"]["cpa_convex_m2"]["mean"] < \
        s["Fagus sylvatica"]["joint"]["cpa_convex_m2"]["mean"]
