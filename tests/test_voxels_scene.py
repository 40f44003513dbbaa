"""Voxel models (fixed and PAD-scaled cubes, shifts), scene assembly, HELIOS++ export, reference
extraction and trajectory re-flights."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET

import numpy as np
import pandas as pd
import pytest
import yaml

from vlsforest.errors import ConfigError, InputDataError
from vlsforest.domain.cubes import scaled_cubes
from vlsforest.domain.labels import object_ids
from vlsforest.extract import extract_reference, extract_simulated, match_targets
from vlsforest.io.las import PointCloud
from vlsforest.io.mesh import TriangleMesh, write_mesh
from vlsforest.io.vox import read_vox
from vlsforest.io.voxel_model import VoxelModel
from vlsforest.scene import assemble_scene, export_helios
from vlsforest.voxels import (
    ModelInputs,
    PadGrid,
    build_model,
    cell_centroids,
    fixed_voxels,
    shift_cubes,
)


def _crown(n=4000, seed=0, centre=(3.0, -2.0, 10.0), r=1.5):
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1)[:, None]
    return np.asarray(centre) + v * r * rng.uniform(0.3, 1.0, size=(n, 1)) ** (1 / 3)


# --------------------------------------------------------------------------------------------
# fixed voxels
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("size", [0.25, 0.10, 0.05, 0.02])
def test_fixed_voxels_global_lattice_and_counts(size):
    xyz = _crown(3000)
    m = fixed_voxels(xyz, size)
    # brute force: the set of cells holding points
    cells = {tuple(c) for c in np.floor(xyz / size).astype(int)}
    assert m.n_voxels == len(cells)
    assert {tuple(c) for c in m.ijk} == cells
    # every point lies inside a cube of the model, cube corners on multiples of the size
    lo = m.centres() - 0.5 * m.sides()[:, None]
    assert np.allclose(lo / size, np.round(lo / size), atol=1e-9)
    # cells are sorted and unique
    assert len(np.unique(m.ijk, axis=0)) == m.n_voxels


@pytest.mark.parametrize("span", [40, 2 ** 40])
def test_group_cells_matches_row_unique(span):
    from vlsforest.voxels import _group_cells

    rng = np.random.default_rng(7)
    ijk = rng.integers(-span, span, size=(5000, 3))
    ijk[::3] = ijk[1::3][: len(ijk[::3])]  # repeated cells
    want_cells, want_inv, want_counts = np.unique(ijk, axis=0, return_inverse=True, return_counts=True)
    cells, inv, counts = _group_cells(ijk)
    assert np.array_equal(cells, want_cells)          # same lexicographic order
    assert np.array_equal(inv, want_inv.reshape(-1))
    assert np.array_equal(counts, want_counts)
    assert np.array_equal(cells[inv], ijk)


def test_fixed_voxels_min_points_and_owner_majority():
    size = 1.0
    pts = np.array([[0.1, 0.1, 0.1], [0.2, 0.2, 0.2], [0.3, 0.3, 0.3],  # cell 0: owners 7, 7, 3
                    [1.5, 0.5, 0.5], [1.6, 0.5, 0.5],                    # cell 1: owners 4, 2 (tie → 2)
                    [5.5, 0.5, 0.5]])                                    # cell 5: one point
    owner = np.array([7, 7, 3, 4, 2, 9])
    m = fixed_voxels(pts, size, owner)
    assert m.ijk.tolist() == [[0, 0, 0], [1, 0, 0], [5, 0, 0]]
    assert m.owner.tolist() == [7, 2, 9]
    m2 = fixed_voxels(pts, size, owner, min_points=2)
    assert m2.ijk.tolist() == [[0, 0, 0], [1, 0, 0]]
    with pytest.raises(ConfigError):
        fixed_voxels(pts, 0.0)
    with pytest.raises(ConfigError):
        fixed_voxels(pts, -0.1)
    with pytest.raises(InputDataError):
        fixed_voxels(np.zeros((0, 3)), 0.25)
    with pytest.raises(InputDataError):
        fixed_voxels(np.array([[np.nan, 0, 0]]), 0.25)


def test_voxel_counts_grow_with_resolution():
    xyz = _crown(60000, r=2.0)
    n = {s: fixed_voxels(xyz, s).n_voxels for s in (0.25, 0.10, 0.05, 0.02)}
    assert n[0.25] < n[0.10] < n[0.05] < n[0.02] <= len(xyz)
    # a crown ball of radius 2 m holds ≈ (4/3)π 2³ / 0.25³ ≈ 2,145 cells of 0.25 m (all filled)
    assert abs(n[0.25] - 4 / 3 * math.pi * 8 / 0.25 ** 3) < 0.15 * n[0.25]


# --------------------------------------------------------------------------------------------
# scaled cubes and shifts (property tests)
# --------------------------------------------------------------------------------------------
def test_scaled_cube_side_law():
    pad = np.array([0.0, 1.25, 5.0, 7.0, np.nan, -1.0])
    half = scaled_cubes(np.zeros((6, 3)), pad, 5.0, a0=0.25, alpha=0.5)
    side = 2 * half
    # face area ∝ PAD/PADmax (α = 0.5), clipped to [0, PADmax], NaN → no cube
    assert side[0] == 0 and side[4] == 0 and side[5] == 0
    assert math.isclose(side[1] ** 2, 0.25 ** 2 * 1.25 / 5.0, rel_tol=1e-12)
    assert math.isclose(side[2], 0.25) and math.isclose(side[3], 0.25)
    half1 = scaled_cubes(np.zeros((1, 3)), [2.0], 8.0, a0=0.25, alpha=1.0)
    assert math.isclose(2 * half1[0], 0.25 * 2.0 / 8.0)


@pytest.mark.parametrize("seed", range(5))
def test_scaled_sides_never_exceed_a0_and_shifted_cubes_stay_in_their_cell(seed):
    rng = np.random.default_rng(seed)
    n, a0 = 2000, 0.25
    ijk = rng.integers(-400, 400, size=(n, 3))
    pad = rng.uniform(-2, 12, n)
    pad_max = rng.choice([5.0, 8.0], n)
    half = scaled_cubes(ijk, pad, pad_max, a0, 0.5)
    assert (2 * half <= a0 + 1e-15).all()
    cog = (ijk + rng.uniform(-0.5, 1.5, size=(n, 3))) * a0  # centroids also outside the cell
    for mode in ("none", "random", "cog"):
        c = shift_cubes(ijk, half, a0, mode, seed, cog)
        lo, hi = c - half[:, None], c + half[:, None]
        assert (lo >= ijk * a0 - 1e-12).all(), mode
        assert (hi <= (ijk + 1) * a0 + 1e-12).all(), mode
    # random shift: seeded and uses the room (not all cubes centred)
    c1 = shift_cubes(ijk, half, a0, "random", 7)
    assert np.array_equal(c1, shift_cubes(ijk, half, a0, "random", 7))
    room = 0.5 * a0 - half
    assert np.abs(c1 - (ijk + 0.5) * a0)[room > 0.01].max() > 0.5 * room.max()


def test_cog_shift_reaches_centroid_when_room_allows():
    a0 = 0.25
    ijk = np.array([[0, 0, 0], [1, 0, 0]])
    half = np.array([0.025, 0.1])
    cog = np.array([[0.05, 0.2, 0.125], [0.40, 0.125, 0.125]])
    c = shift_cubes(ijk, half, a0, "cog", cog=cog)
    # cube 0 (side 0.05): centroid reachable on every axis? x: 0.05 ≥ 0.025 ok; y: 0.2 ≤ 0.225 ok
    assert np.allclose(c[0], cog[0])
    # cube 1 (side 0.2): room 0.025 around the cell centre (0.375): clamped to 0.4 exactly reachable
    assert np.allclose(c[1], [0.4, 0.125, 0.125])
    # a centroid far outside is clamped to the cell wall
    c2 = shift_cubes(ijk[:1], np.array([0.1]), a0, "cog", cog=np.array([[9.0, -9.0, 0.125]]))
    assert np.allclose(c2, [[0.15, 0.1, 0.125]])


def test_cell_centroids_brute_force():
    xyz = _crown(500, seed=3)
    m = fixed_voxels(xyz, 0.5)
    cog = cell_centroids(xyz, 0.5, m.ijk)
    for k in (0, len(m.ijk) // 2, len(m.ijk) - 1):
        inside = np.all(np.floor(xyz / 0.5).astype(int) == m.ijk[k], axis=1)
        assert np.allclose(cog[k], xyz[inside].mean(axis=0))
    assert np.isnan(cell_centroids(xyz, 0.5, np.array([[999, 999, 999]]))).all()


def _pad_grid(xyz, a0=0.25, seed=0, t_range=(0.2, 0.95)):
    occ = fixed_voxels(xyz, a0)
    rng = np.random.default_rng(seed)
    t = rng.uniform(*t_range, occ.n_voxels)
    sampled = rng.uniform(size=occ.n_voxels) > 0.1
    return PadGrid(a0, occ.ijk, t, np.zeros(occ.n_voxels), sampled)


def test_scaled_model_pad_from_transmittance_and_species():
    from vlsforest.pad import g_function

    xyz = _crown(3000)
    owner = np.where(xyz[:, 0] > 3.0, 1, 2)
    grid = _pad_grid(xyz)
    inputs = ModelInputs(xyz, owner, {1: "broadleaf", 2: "conifer"}, grid)
    m = build_model({"kind": "scaled", "a0": 0.25, "alpha": 0.5, "shift": "none", "flagged": "drop"}, inputs)
    # PAD = −ln(T)/G(0°) with planophile (tree 1, PADmax 5) or erectophile (tree 2, PADmax 8)
    pos = {tuple(c): i for i, c in enumerate(grid.ijk)}
    for k in range(0, m.n_voxels, max(1, m.n_voxels // 50)):
        i = pos[tuple(m.ijk[k])]
        lad, pmax = ("planophile", 5.0) if m.owner[k] == 1 else ("erectophile", 8.0)
        pad = min(-math.log(grid.transmittance[i]) / float(g_function(np.array([0.0]), lad)[0]), pmax)
        assert math.isclose(m.pad[k], pad, rel_tol=1e-9)
        assert math.isclose(2 * m.half[k], 0.25 * math.sqrt(pad / pmax), rel_tol=1e-9)
    assert math.isclose(float(g_function(np.array([0.0]), "planophile")[0]), 8 / (3 * math.pi), rel_tol=1e-3)
    # flagged cells dropped: no cube in an unsampled cell
    unsampled = {tuple(c) for c in grid.ijk[~grid.sampled]}
    assert not unsampled & {tuple(c) for c in m.ijk}
    # flagged: median keeps them with the tree's median PAD
    m2 = build_model({"kind": "scaled", "flagged": "median"}, inputs)
    assert m2.n_voxels > m.n_voxels
    # fewer voxels than the 0.02 m model of the same points
    assert m.n_voxels < fixed_voxels(xyz, 0.02).n_voxels


def test_build_model_errors():
    xyz = _crown(200)
    inputs = ModelInputs(xyz, np.ones(len(xyz), int), {})
    with pytest.raises(ConfigError, match="unknown kind"):
        build_model({"kind": "nope"}, inputs, "m1")
    with pytest.raises(ConfigError, match="needs a 'kind'"):
        build_model({"voxel_size": 0.1}, inputs, "m1")
    with pytest.raises(ConfigError, match="methods.m1"):
        build_model({"kind": "fixed", "voxel_size": 0.1, "bogus": 1}, inputs, "m1")
    with pytest.raises(ConfigError, match="voxel size must be > 0"):
        build_model({"kind": "fixed", "voxel_size": 0.0}, inputs)
    with pytest.raises(ConfigError, match="PAD grid"):
        build_model({"kind": "scaled"}, inputs)


def test_voxel_model_roundtrip_bytes(tmp_path):
    xyz = _crown(1000)
    m = fixed_voxels(xyz, 0.1, np.arange(len(xyz)) % 3)
    a, b = m.save(tmp_path / "a.npz"), tmp_path / "b.npz"
    m2 = VoxelModel.load(a)
    m2.save(b)
    assert a.read_bytes() == b.read_bytes()
    assert np.array_equal(m2.ijk, m.ijk) and np.array_equal(m2.owner, m.owner)
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(InputDataError, match="bad.npz"):
        VoxelModel.load(tmp_path / "bad.npz")


# --------------------------------------------------------------------------------------------
# scenes: assembly, simulation, HELIOS++ export
# --------------------------------------------------------------------------------------------
def _stem(path, x, y, z0, r=0.2, h=6.0):
    a = np.linspace(0, 2 * np.pi, 17)[:-1]
    ring = np.column_stack([x + r * np.cos(a), y + r * np.sin(a)])
    v = np.vstack([np.column_stack([ring, np.full(16, z0)]), np.column_stack([ring, np.full(16, z0 + h)])])
    f = []
    for i in range(16):
        j = (i + 1) % 16
        f += [[i, j, 16 + j], [i, 16 + j, 16 + i]]
    write_mesh(path, TriangleMesh(v, np.array(f)))
    return path


def test_assembled_scene_simulates_with_object_ids(tmp_path):
    from vlsforest.sim import Scene, simulate
    from vlsforest.sim.survey import survey_from_dict

    xyz1 = _crown(3000, centre=(0.0, 0.0, 10.0))
    xyz2 = _crown(3000, centre=(6.0, 0.0, 9.0), seed=1)
    xyz = np.vstack([xyz1, xyz2])
    owner = np.r_[np.full(len(xyz1), 5), np.full(len(xyz2), 8)]
    stems = {5: _stem(tmp_path / "s5.obj", 0.0, 0.0, 0.0)}
    for kind in ({"kind": "fixed", "voxel_size": 0.1},
                 {"kind": "scaled", "shift": "cog"}):
        inputs = ModelInputs(xyz, owner, {5: "broadleaf"}, _pad_grid(xyz, seed=2, t_range=(0.05, 0.3)))
        model = build_model(kind, inputs)
        out = assemble_scene(tmp_path / kind["kind"] / "scene.yaml", model, [5], stems, 0.0, [-10, -10, 15, 10])
        doc = yaml.safe_load(out.read_text())
        ids = {p["id"] for p in doc["parts"]}
        assert ids == {1, 2} | set(object_ids(5))
        scene = Scene.from_yaml(out)
        assert scene.n_voxels == model.n_voxels
        survey = survey_from_dict({"scanner": "riegl_minivux1uav", "overrides": {"beam_sample_quality": 1},
                                   "platform": {"type": "linear", "speed_mps": 5.0,
                                                "legs": [{"start": [-20, 0, 60], "end": [25, 0, 60]}]}})
        res = simulate(scene, survey, seed=1, workers=1, progress=False)
        oid = res.points["object_id"]
        assert {1, 2, object_ids(5)[1]} <= set(np.unique(oid).tolist())
        # target crown returns lie inside the target's voxel cubes (axis positions, small noise)
        pts = res.points["xyz"][oid == object_ids(5)[1]]
        assert np.hypot(pts[:, 0], pts[:, 1]).max() < 1.5 + 0.3
        # HELIOS++ export: XML parses, every part file exists, voxel files place cubes as we do
        xml = export_helios(out, tmp_path / kind["kind"] / "helios")
        root = ET.parse(xml).getroot()
        parts = root.findall("./scene/part")
        assert {int(p.get("id")) for p in parts} == ids
        for p in parts:
            f = p.find("./filter/param[@key='filepath']").get("value")
            assert (xml.parent / f).is_file()
        crown_id = object_ids(5)[1]
        if kind["kind"] == "fixed":
            vox = read_vox(xml.parent / f"part_{crown_id}.vox")
            sub = model.subset(model.owner == 5)
            assert np.allclose(np.sort(vox.centres(), axis=0), np.sort(sub.centres(), axis=0))


def test_assemble_scene_errors(tmp_path):
    model = fixed_voxels(_crown(100), 0.25, np.full(100, 5))
    with pytest.raises(InputDataError, match="no stem mesh"):
        assemble_scene(tmp_path / "s.yaml", model, [5], {}, 0.0, [0, 0, 1, 1])
    with pytest.raises(InputDataError, match="extent"):
        assemble_scene(tmp_path / "s.yaml", model, [], {}, 0.0, [0, 0, 0, 1])
    with pytest.raises(ConfigError, match="reflectance"):
        assemble_scene(tmp_path / "s.yaml", model, [], {}, 0.0, [0, 0, 1, 1], {"leaves": 0.3})


# --------------------------------------------------------------------------------------------
# targets and reference extraction
# --------------------------------------------------------------------------------------------
def test_match_targets():
    trees = pd.DataFrame({"tree_id": [1, 2, 3], "x": [0.0, 5.0, 10.0], "y": [0.0, 0.0, 0.2],
                          "z": [100.0, 101.0, 102.0], "dbh": [0.3, 0.4, 0.5], "height": [20, 25, 30]})
    t = match_targets(trees, [{"tree_id": 77, "x": 9.8, "y": 0.0, "species": "picea_abies"},
                              {"tree_id": 78, "x": 0.3, "y": -0.2, "species": "fagus_sylvatica"}])
    assert t.tree_id.tolist() == [3, 1] and t.target_id.tolist() == [77, 78]
    assert t.group.tolist() == ["conifer", "broadleaf"] and t.z.tolist() == [102.0, 100.0]
    with pytest.raises(InputDataError, match="no segmented stem within"):
        match_targets(trees, [{"x": 2.5, "y": 0.0, "species": "picea_abies"}])
    with pytest.raises(InputDataError, match="both match"):
        match_targets(trees, [{"x": 0.1, "y": 0, "species": "picea_abies"}, {"x": -0.1, "y": 0, "species": "picea_abies"}])
    with pytest.raises(ConfigError, match="unknown species"):
        match_targets(trees, [{"x": 0.1, "y": 0, "species": "baobab"}])


def test_extract_reference_radius_and_nearest_tree():
    t1 = np.array([[0.0, 0.0, 10.0], [0.0, 0.0, 11.0]])
    t2 = np.array([[1.0, 0.0, 10.0]])
    pts = np.array([[0.2, 0.0, 10.0],    # near t1 (0.2) and t2 (0.8) → 1
                    [0.6, 0.0, 10.0],    # t1 0.6 / t2 0.4 → 2 (radius 0.5)
                    [0.0, 0.45, 11.0],   # t1 0.45 → 1
                    [0.0, 0.0, 12.0],    # t1 1.0 → none
                    [5.0, 5.0, 5.0]])
    cloud = PointCloud(pts, {"return_number": np.ones(5, np.uint8)})
    assert extract_reference({1: t1, 2: t2}, cloud, 0.5).tolist() == [1, 2, 1, 0, 0]
    assert extract_reference({1: t1, 2: t2}, cloud, 0.3).tolist() == [1, 0, 0, 0, 0]
    with pytest.raises(ConfigError):
        extract_reference({1: t1}, cloud, 0.0)
    with pytest.raises(InputDataError):
        extract_reference({1: np.zeros((0, 3))}, cloud, 0.5)
    sim = PointCloud(pts, {"object_id": np.array([51, 52, 2, 1, 81], np.int32)})
    assert extract_simulated(sim, {51: 5, 52: 5, 81: 8}).tolist() == [5, 5, 0, 0, 8]


def _labels_by_brute_force(trees: dict, xyz: np.ndarray, radius: float) -> np.ndarray:
    """The rule of extract_reference from every tree's exact nearest distance (no shortcuts)."""
    from scipy.spatial import cKDTree

    ids = sorted(trees)
    d = np.column_stack([cKDTree(trees[t]).query(xyz, k=1)[0] for t in ids])
    d[d > radius] = np.inf
    out = np.asarray(ids)[np.argmin(d, axis=1)]  # first minimum: the smaller id on ties
    return np.where(np.isfinite(d.min(axis=1)), out, 0)


@pytest.mark.parametrize("max_cells, max_total", [(None, None), (1000, None), (None, 150000)])
def test_extract_reference_cell_shortcuts_give_the_nearest_tree_labels(monkeypatch, max_cells, max_total):
    """Dense, touching and overlapping trees, points at the radius and exact ties: the cell
    shortcuts of the labeller (and its fallback for trees without a grid: every tree's box too
    large, or the memory budget spent after some) give the labels of the exact distances."""
    from vlsforest.extract import TreeLabeller

    if max_cells is not None:
        monkeypatch.setattr(TreeLabeller, "_MAX_CELLS", max_cells)
    if max_total is not None:
        monkeypatch.setattr(TreeLabeller, "_MAX_TOTAL_CELLS", max_total)
    rng = np.random.default_rng(5)
    trees = {t: rng.normal([1.2 * t, 0.0, 8.0], [0.5, 0.5, 2.0], (4000, 3)) for t in (7, 3, 5, 1)}
    trees[11] = np.array([[0.0, 5.0, 1.0]])          # a one-point tree …
    trees[12] = np.array([[0.4, 5.0, 1.0]])          # … and its twin 0.4 m away
    xyz = np.vstack([rng.uniform([-2, -2, 2], [9, 2, 14], (30000, 3)),
                     np.array([[0.2, 5.0, 1.0],      # equally far (0.2) from trees 11 and 12: 11
                               [0.0, 5.3, 1.0],      # exactly at the radius of tree 11
                               [0.0, 5.0, 1.31]])])  # just outside it
    cloud = PointCloud(xyz, {"classification": np.full(len(xyz), 5, np.uint8)})
    lab = TreeLabeller(trees, 0.3)
    with_grid = [tid for tid, *_, codes in lab.trees if codes is not None]
    assert len(with_grid) == {(None, None): 6, (1000, None): 2, (None, 150000): 4}[(max_cells, max_total)]
    got = extract_reference(trees, cloud, 0.3)
    want = _labels_by_brute_force(trees, xyz, 0.3)
    assert np.array_equal(got, want)
    assert got[-3:].tolist() == [11, 11, 0]
    assert {1, 3, 5, 7} <= set(np.unique(got)) and (got == 0).sum() > 1000


def test_extract_reference_leaves_ground_out_so_cbh_is_the_crowns():
    """A stem foot's ground ring within 0.5 m would make the lowest slice > 1.5 m wide (CBH 0.05 m)."""
    from vlsforest.metrics import tree_metrics

    rng = np.random.default_rng(3)
    zs = np.arange(0.0, 12.0, 0.05)
    ang = rng.uniform(0, 2 * np.pi, len(zs))
    stem = np.c_[0.3 * np.cos(ang), 0.3 * np.sin(ang), zs]               # TLS stem, r 0.3 m, 0-12 m
    r, a = 2.5 * np.sqrt(rng.uniform(0, 1, 3000)), rng.uniform(0, 2 * np.pi, 3000)
    crown = np.c_[r * np.cos(a), r * np.sin(a), rng.uniform(8.0, 12.0, 3000)]  # crown 8-12 m
    tls = np.vstack([stem, crown])
    g = np.arange(-3.0, 3.0001, 0.1)
    gx, gy = np.meshgrid(g, g)
    ground = np.c_[gx.ravel(), gy.ravel(), np.zeros(gx.size)]              # ALS ground returns
    als = np.vstack([ground, crown[::3] + [0.05, 0.0, 0.0], stem[::10]])
    cls = np.r_[np.full(len(ground), 2), np.full(len(als) - len(ground), 5)].astype(np.uint8)
    cloud = PointCloud(als, {"classification": cls})
    kept = extract_reference({1: tls}, cloud, 0.5)
    every = extract_reference({1: tls}, cloud, 0.5, exclude_classes=())
    ring = every.astype(bool) & (cls == 2)
    from scipy.spatial.distance import pdist

    assert ring.sum() > 100 and pdist(als[ring, :2]).max() > 1.5    # the ring is there without the filter
    assert not (kept.astype(bool) & (cls == 2)).any()              # and gone with it
    assert np.array_equal(kept.astype(bool), every.astype(bool) & (cls != 2))
    assert tree_metrics(als[every == 1])["cbh"] == 0.05
    assert 8.0 <= tree_metrics(als[kept == 1])["cbh"] <= 8.2
    # a cloud without classification keeps every point (nothing to go by)
    assert np.array_equal(extract_reference({1: tls}, PointCloud(als, {}), 0.5), every)


def test_column_index_boxes_miss_no_point():
    from vlsforest.extract import ColumnIndex

    rng = np.random.default_rng(5)
    xy = np.round(rng.uniform(-20, 30, size=(20000, 2)), 1)  # many points exactly on column edges
    xy[::97] = np.nan
    idx = ColumnIndex(xy, cell=1.0)
    for k in range(60):
        x0, y0 = np.round(rng.uniform(-25, 32, 2), 1 if k % 2 else 3)
        x1, y1 = x0 + rng.uniform(0, 8), y0 + (0.0 if k % 3 == 0 else rng.uniform(0, 8))
        want = np.flatnonzero((xy[:, 0] >= x0) & (xy[:, 0] <= x1) & (xy[:, 1] >= y0) & (xy[:, 1] <= y1))
        got = idx.box(x0, y0, x1, y1)
        assert np.isin(want, got).all()
        assert np.isfinite(xy[got]).all() and len(np.unique(got)) == len(got)
        # only whole columns that meet the box: nothing farther than one column away
        if len(got):
            assert (xy[got, 0] > x0 - 1.0).all() and (xy[got, 0] < x1 + 1.0).all()
    assert len(idx.box(100, 100, 110, 110)) == 0 and len(ColumnIndex(np.zeros((0, 2))).box(0, 0, 1, 1)) == 0


def test_extract_reference_matches_brute_force():
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(8)
    trees = {tid: rng.normal([6.0 * (tid % 4), 5.0 * (tid // 4), 10.0], [1.5, 1.5, 4.0], size=(400, 3))
             for tid in range(1, 13)}
    pts = rng.uniform([-5, -5, 0], [25, 20, 20], size=(30000, 3))
    got = extract_reference(trees, PointCloud(pts, {}), 0.5)
    ids = sorted(trees)
    d = np.stack([cKDTree(trees[t]).query(pts)[0] for t in ids], axis=1)
    best = np.argmin(d, axis=1)  # ties: the smaller id (first column)
    want = np.where(d[np.arange(len(pts)), best] <= 0.5, np.array(ids)[best], 0)
    assert (want > 0).sum() > 500 and len(np.unique(want)) == 13
    assert np.array_equal(got, want)


# --------------------------------------------------------------------------------------------
# re-flying a recorded trajectory
# --------------------------------------------------------------------------------------------
def test_survey_from_trajectory():
    from vlsforest.sim.planning import survey_from_trajectory
    from vlsforest.sim.survey import survey_from_dict

    t = np.arange(0, 10.01, 0.1)
    rows = []
    for sid, (y0, dy) in enumerate([(0.0, 1.0), (30.0, -1.0)], start=1):
        for k, tt in enumerate(t):
            rows.append({"gps_time": tt + 20 * sid, "x": 5.0 * tt, "y": y0, "z": 70.0 + 0.0 * dy, "source_id": sid})
    traj = pd.DataFrame(rows)
    s = survey_from_trajectory({"scanner": "riegl_minivux1uav", "pattern": "trajectory",
                                "extraction_radius_m": 0.3, "overrides": {"window_size_ns": 1.5}}, traj)
    legs = s["platform"]["legs"]
    assert [lg["active"] for lg in legs] == [True, False, True]
    assert legs[0]["start"] == [0.0, 0.0, 70.0] and legs[0]["end"] == [50.0, 0.0, 70.0]
    assert math.isclose(s["platform"]["speed_mps"], 5.0)
    assert s["overrides"] == {"window_size_ns": 1.5}
    survey_from_dict(s)
    with pytest.raises(InputDataError, match="columns"):
        survey_from_trajectory({"scanner": "riegl_vq780i"}, traj.drop(columns="source_id"))


def test_reflown_lines_keep_their_own_speeds():
    """Two lines recorded at 5 and 4 m/s (as P2's two ULS grids): each is re-flown at its own
    speed, so its pulses per metre and its duration match the recording."""
    from vlsforest.sim.planning import survey_from_trajectory
    from vlsforest.sim.survey import survey_from_dict

    rows = []
    for sid, (speed, y) in enumerate([(5.0, 0.0), (4.0, 30.0)], start=1):
        for tt in np.arange(0, 10.01, 0.1):
            rows.append({"gps_time": 100.0 * sid + tt, "x": speed * tt, "y": y, "z": 70.0, "source_id": sid})
    s = survey_from_trajectory({"scanner": "riegl_minivux1uav"}, pd.DataFrame(rows))
    active = [lg for lg in s["platform"]["legs"] if lg["active"]]
    assert [lg["speed_mps"] for lg in active] == pytest.approx([5.0, 4.0])
    sv = survey_from_dict(s)
    lines = [lg for lg in sv.legs if lg.active]
    # 50 m at 5 m/s and 40 m at 4 m/s: both lines take 10 s, i.e. 10⁶ slots at 100 kHz
    assert [lg.duration_s for lg in lines] == pytest.approx([10.0, 10.0])
    assert [lg.n_slots for lg in lines] == [1_000_000, 1_000_000]
    b = sv.pulses(lines[1].slot_offset, lines[1].slot_offset + 2000)
    step = np.linalg.norm(np.diff(b.origin[[0, -1]], axis=0)) / (b.gps_time[-1] - b.gps_time[0])
    assert step == pytest.approx(4.0, rel=1e-9)


def test_extract_reference_cli_drops_ground_and_rejects_bad_classes(tmp_path, capsys):
    import pandas as pd

    from vlsforest.cli import main as cli_main
    from vlsforest.io.las import read_las, write_las

    tls = np.c_[np.zeros(40), np.zeros(40), np.linspace(0, 4, 40)]
    write_las(tmp_path / "seg" / "trees" / "7.laz", PointCloud(tls, {}))
    pd.DataFrame({"target_id": [301], "tree_id": [7]}).to_csv(tmp_path / "targets.csv", index=False)
    pts = np.array([[0.2, 0, 0.0], [0.3, 0, 0.0], [0.1, 0, 2.0], [0.0, 0.2, 3.9], [3.0, 0, 2.0]])
    cls = np.array([2, 2, 5, 7, 5], np.uint8)
    write_las(tmp_path / "als.laz", PointCloud(pts, {"classification": cls}))
    base = ["extract", "reference", str(tmp_path / "als.laz"), "--segment", str(tmp_path / "seg"),
            "--targets", str(tmp_path / "targets.csv"), "--radius", "0.5"]
    assert cli_main([*base, "-o", str(tmp_path / "a.laz")]) == 0
    assert "3 points of classes 2,7,18 left out" in capsys.readouterr().out
    a = read_las(tmp_path / "a.laz")
    assert np.allclose(a.xyz, [[0.1, 0, 2.0]], atol=1e-3) and a.attrs["tree_id"].tolist() == [301]
    assert cli_main([*base, "--exclude-classes", "", "-o", str(tmp_path / "b.laz")]) == 0
    assert "every class kept" in capsys.readouterr().out
    assert len(read_las(tmp_path / "b.laz")) == 4
    assert cli_main([*base, "--exclude-classes", "2,ground", "-o", str(tmp_path / "c.laz")]) != 0
    assert "not a comma-separated list" in capsys.readouterr().err
    assert not (tmp_path / "c.laz").exists()


def test_extract_sim_metrics_are_those_of_the_written_trees(tmp_path, capsys):
    """`extract sim --metrics` writes, in the same process, the bytes `vlsforest metrics` writes
    for the extracted trees.laz: heights above each target's ground z, a row (NaN) for a target
    without points; a targets table without z is refused before anything is written."""
    import pandas as pd

    from vlsforest.cli import main as cli_main
    from vlsforest.io.las import write_las

    rng = np.random.default_rng(3)
    n = 400
    xyz = np.c_[rng.uniform(-2, 2, n) + 100.123456, rng.uniform(-2, 2, n) + 200.98765, rng.uniform(0, 1, n)]
    oid = rng.choice([71, 72, 81, 1, 5], n)  # target 7's stem and crown, tree 8's stem, ground, other
    xyz[oid == 72, 2] = 300.0 + 20.0 * rng.uniform(0.2, 1.0, (oid == 72).sum())  # crown 306–320 m
    xyz[oid == 71, 2] = 300.0 + 6.0 * rng.uniform(0.0, 1.0, (oid == 71).sum())  # stem 300–306 m
    write_las(tmp_path / "sim.laz", PointCloud(xyz, {
        "object_id": oid.astype(np.int32),
        "return_number": np.ones(n, np.uint8), "number_of_returns": np.ones(n, np.uint8),
        "gps_time": np.arange(n, dtype=np.float64)}))
    pd.DataFrame({"target_id": [301, 302], "tree_id": [7, 9], "z": [299.5, 280.0]}).to_csv(
        tmp_path / "targets.csv", index=False)
    base = ["extract", "sim", str(tmp_path / "sim.laz"), "--targets", str(tmp_path / "targets.csv")]
    assert cli_main([*base, "-o", str(tmp_path / "t.laz"), "--metrics", str(tmp_path / "m1.csv")]) == 0
    assert cli_main(["metrics", str(tmp_path / "t.laz"), "--tree-id", "tree_id", "--ground-table",
                     str(tmp_path / "targets.csv"), "--ground-key", "target_id", "-o", str(tmp_path / "m2.csv")]) == 0
    assert (tmp_path / "m1.csv").read_bytes() == (tmp_path / "m2.csv").read_bytes()
    m = pd.read_csv(tmp_path / "m1.csv")
    assert m.tree_id.tolist() == [301, 302]
    top = xyz[np.isin(oid, (71, 72)), 2].max()
    assert m.height[0] == pytest.approx(top - 299.5, abs=1e-3)  # above the target's own ground
    assert m.n_points.tolist() == [(np.isin(oid, (71, 72))).sum(), 0]  # target 9 was not hit: NaNs
    assert m.drop(columns=["tree_id", "n_points"]).iloc[1].isna().all()
    capsys.readouterr()
    pd.DataFrame({"target_id": [301], "tree_id": [7]}).to_csv(tmp_path / "noz.csv", index=False)
    bad = ["extract", "sim", str(tmp_path / "sim.laz"), "--targets", str(tmp_path / "noz.csv"),
           "-o", str(tmp_path / "u.laz"), "--metrics", str(tmp_path / "u.csv")]
    assert cli_main(bad) == 2
    assert "targets table lacks column(s) ['z']" in capsys.readouterr().err
    assert not (tmp_path / "u.laz").exists() and not (tmp_path / "u.csv").exists()


def test_target_ids_maps_each_segment_to_its_target_in_order():
    from vlsforest.extract import target_ids

    seg_to_target = {12: 3, 5: 1, 40: 7}
    segs = np.array([40, 5, 5, 12, 40, 12])
    got = target_ids(segs, seg_to_target)
    assert got.dtype == np.int32
    assert got.tolist() == [seg_to_target[int(s)] for s in segs]
    assert target_ids(np.zeros(0, dtype=np.int64), seg_to_target).tolist() == []
    with pytest.raises(ValueError, match=r"\[6\]"):
        target_ids(np.array([5, 6]), seg_to_target)
    with pytest.raises(ValueError, match=r"\[99\]"):
        target_ids(np.array([99]), seg_to_target)
    with pytest.raises(ValueError):
        target_ids(np.array([1]), {})
