"""Tests of vlsforest.stems (stem points, trimmed Poisson stem meshes) and ``vlsforest stems``.

* an analytic leaning, tapered stem under a crown, "scanned" from four positions (each surface
  point kept when it faces a scanner): the selection against the generating labels, the fitted
  DBH and crown base against the construction, the mesh against the analytic surface;
* the recorded quick forest (fixture ``quick_forest``): each target's TLS points (truth tree
  labels, all organs), stem selection scored with the organ labels, mesh distance to the true
  stem surface (≤ 2 cm asked) and extent beyond the stem points (≤ 10 cm asked);
* a real stem shape: the Bretten spruce F_BR08_08 Poisson stem of the study, ray cast from four
  scanner positions, meshed again and compared with itself;
* the command line: outputs, byte-identical reruns, and one clear error for bad inputs.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.spatial import cKDTree

from vlsforest.cli import main as cli_main
from vlsforest.errors import ConfigError, InputDataError
from vlsforest.io.las import PointCloud, read_las, write_las
from vlsforest.io.mesh import TriangleMesh, read_mesh
from vlsforest.stems import (
    build_stem,
    read_scanner_positions,
    select_stem_points,
    stem_mesh,
    trace_stem,
)

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"


# ----------------------------------------------------------------------------- helpers
def _sample_surface(mesh: TriangleMesh, n: int, rng) -> np.ndarray:
    """``n`` points uniformly on the mesh surface."""
    a = mesh.face_areas()
    f = rng.choice(len(a), n, p=a / a.sum())
    u, v = rng.random(n), rng.random(n)
    s = u + v > 1
    u[s], v[s] = 1 - u[s], 1 - v[s]
    t = mesh.vertices[mesh.faces[f]]
    return t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])


def _distance_to_mesh(points: np.ndarray, mesh: TriangleMesh) -> np.ndarray:
    """Exact point-to-surface distances (open3d), computed about a local origin."""
    import open3d as o3d

    origin = np.floor(mesh.vertices.min(axis=0))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor((mesh.vertices - origin).astype(np.float32)),
        o3d.core.Tensor(mesh.faces.astype(np.uint32)),
    )
    return scene.compute_distance(o3d.core.Tensor((points - origin).astype(np.float32))).numpy().astype(float)


# ----------------------------------------------------------------------------- analytic stem
H_STEM, CROWN_BASE, R_BASE, TAPER = 12.0, 6.0, 0.20, 0.011  # m, m, m, m per m
LEAN = np.array([0.03, -0.02])  # axis displacement per m of height
BASE = np.array([481_000.0, 5_430_000.0, 250.0])  # UTM-like, to exercise precision


def _axis(z):
    return BASE[:2] + np.outer(z, LEAN)


def _radius(z):
    return R_BASE - TAPER * z


@pytest.fixture(scope="module")
def analytic_tree():
    """Leaning cone stem (0–10 m visible) + crown points (6–12 m), 4 scanners; labels 1 = stem."""
    rng = np.random.default_rng(7)
    scanners = {k + 1: BASE + np.array([9 * np.cos(a), 9 * np.sin(a), 1.5]) for k, a in enumerate(np.radians([20, 110, 200, 290]))}
    # stem surface, ~2 cm spacing, kept where it faces at least one scanner (that scanner's id)
    n = 60_000
    z = rng.uniform(0.0, 10.0, n)
    th = rng.uniform(0, 2 * np.pi, n)
    r = _radius(z) + rng.normal(0, 0.003, n)
    u = np.column_stack([np.cos(th), np.sin(th)])
    xy = _axis(z) + r[:, None] * u
    pts = np.column_stack([xy, BASE[2] + z])
    sid = np.zeros(n, dtype=np.uint16)
    for k in rng.permutation(list(scanners)):
        view = scanners[k][None, :2] - xy
        vis = (np.einsum("ij,ij->i", u, view) > 0) & (sid == 0)
        sid[vis] = k
    stem = pts[sid > 0]
    stem_sid = sid[sid > 0]
    # crown: points 0.4–3 m off the axis between 6 and 12 m
    m = 30_000
    zc = rng.uniform(CROWN_BASE, H_STEM, m)
    rc = rng.uniform(0.4, 3.0, m) * (1 - 0.7 * (zc - CROWN_BASE) / (H_STEM - CROWN_BASE))
    tc = rng.uniform(0, 2 * np.pi, m)
    crown = np.column_stack([_axis(zc) + (_radius(zc) + rc)[:, None] * np.column_stack([np.cos(tc), np.sin(tc)]), BASE[2] + zc])
    xyz = np.concatenate([stem, crown])
    label = np.concatenate([np.ones(len(stem), bool), np.zeros(m, bool)])
    scan = np.concatenate([stem_sid, rng.integers(1, 5, m).astype(np.uint16)])
    order = rng.permutation(len(xyz))
    return xyz[order], label[order], scan[order], scanners


def test_analytic_selection(analytic_tree):
    xyz, label, _, _ = analytic_tree
    axis = trace_stem(xyz, BASE, dbh=None)
    sel = axis.mask
    assert np.array_equal(sel, select_stem_points(xyz, BASE))
    precision = label[sel].mean()
    recall = sel[label].mean()
    assert precision >= 0.995, precision
    assert recall >= 0.97, recall
    # fitted circles follow the construction (lean, taper)
    acc = axis.accepted
    zr = axis.z[acc] - BASE[2]
    assert acc.sum() >= 0.9 * (10.0 / axis.slice_height)
    assert np.abs(axis.radius[acc] - _radius(zr)).max() < 0.01
    assert np.hypot(*(axis.center[acc] - _axis(zr)).T).max() < 0.01
    # crown base: the crown starts at 6 m
    assert abs(axis.crown_base - BASE[2] - CROWN_BASE) < 0.3


def test_analytic_mesh(analytic_tree):
    xyz, label, scan, scanners = analytic_tree
    res = build_stem(PointCloud(xyz, {"point_source_id": scan}), scanners, BASE, dbh=2 * _radius(1.3))
    assert abs(res.summary["dbh_fitted"] - 2 * _radius(1.3)) < 0.005
    stem_pts = xyz[res.mask]
    s = _sample_surface(res.mesh, 30_000, np.random.default_rng(1))
    zr = s[:, 2] - BASE[2]
    radial = np.abs(np.hypot(*(s[:, :2] - _axis(zr)).T) - _radius(zr))
    assert radial.mean() < 0.005, radial.mean()
    assert np.quantile(radial, 0.99) < 0.03
    # nowhere more than 10 cm beyond the stem points
    ext, _ = cKDTree(stem_pts).query(s)
    assert ext.max() <= 0.10, ext.max()
    # and it covers the stem: stem points lie on the mesh
    d = _distance_to_mesh(stem_pts, res.mesh)
    assert np.mean(d < 0.02) > 0.97
    # the mesh spans the stem points' heights
    assert res.mesh.vertices[:, 2].min() < stem_pts[:, 2].min() + 0.15
    assert res.mesh.vertices[:, 2].max() > stem_pts[:, 2].max() - 0.15


# ----------------------------------------------------------------------------- quick forest
@pytest.fixture(scope="module")
def quick_targets(quick_forest):
    """Per target: (tree row, tree cloud, organ labels, StemResult), and the scanner positions."""
    tls = quick_forest / "plots" / "Q1" / "tls"
    scans = read_scanner_positions(tls / "scans.csv")
    clouds, tids, organs = [], [], []
    for sid in sorted(scans):
        clouds.append(read_las(tls / f"scan_{sid}.laz"))
        lab = np.load(quick_forest / "truth" / "Q1" / "tls" / f"scan_{sid}_labels.npz")
        tids.append(lab["tree_id"])
        organs.append(lab["organ"])
    cloud = PointCloud.concat(clouds)
    tid, organ = np.concatenate(tids), np.concatenate(organs)
    trees = pd.read_csv(quick_forest / "truth" / "trees.csv")
    out = []
    for t in trees[trees["target"].astype(bool) & (trees["plot"] == "Q1")].itertuples():
        m = tid == t.tree_id
        tree = cloud.subset(m)
        res = build_stem(tree, scans, (t.x, t.y, t.z_ground), dbh=None, source=f"tree {t.tree_id}")
        out.append((t, tree, organ[m], res))
    assert len(out) == 4
    return out, scans


def test_quick_forest_selection(quick_targets):
    from vlsforest.synth.trees import ORGAN_STEM

    for t, tree, organ, res in quick_targets[0]:
        sel = res.mask
        is_stem = organ == ORGAN_STEM
        below = (tree.xyz[:, 2] - t.z_ground) < t.cbh
        assert is_stem[sel].mean() >= 0.98, (t.tree_id, is_stem[sel].mean())
        assert sel[is_stem & below].mean() >= 0.97, (t.tree_id, sel[is_stem & below].mean())
        assert sel[is_stem].mean() >= 0.9
        # the stem is followed into the crown
        assert res.summary["stem_height_range"][1] > t.cbh
        assert abs(res.summary["crown_base_height"] - t.cbh) < 0.5, (t.tree_id, res.summary["crown_base_height"], t.cbh)
        assert abs(res.summary["dbh_fitted"] - t.dbh) < 0.02


def test_quick_forest_mesh_accuracy(quick_targets, quick_forest):
    rng = np.random.default_rng(3)
    for t, tree, _, res in quick_targets[0]:
        true = read_mesh(quick_forest / "truth" / "Q1" / "stems" / f"{t.tree_id}.ply")
        s = _sample_surface(res.mesh, 20_000, rng)
        d = _distance_to_mesh(s, true)
        assert d.mean() <= 0.02, (t.tree_id, d.mean())
        ext, _ = cKDTree(tree.xyz[res.mask]).query(s)
        assert ext.max() <= 0.10, (t.tree_id, ext.max())
        # open at the ground, no balloon below it
        assert res.mesh.vertices[:, 2].min() > t.z_ground - 0.15


# ----------------------------------------------------------------------------- real stem shape
@pytest.mark.skipif(not (REAL / "F_BR08_08_stem_Poisson.obj").is_file(), reason="real data folder absent")
def test_real_stem_shape_round_trip():
    """Ray-cast the study's Bretten spruce stem mesh from four scanners and mesh it again."""
    import open3d as o3d

    true = read_mesh(REAL / "F_BR08_08_stem_Poisson.obj")
    v = true.vertices
    z0 = v[:, 2].min()
    foot = v[v[:, 2] < z0 + 0.3]
    base = np.array([*foot[:, :2].mean(axis=0), z0])
    origin = np.floor(v.min(axis=0))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor((v - origin).astype(np.float32)), o3d.core.Tensor(true.faces.astype(np.uint32)))
    rng = np.random.default_rng(11)
    scanners, pts, sids = {}, [], []
    top = v[:, 2].max()
    for k, a in enumerate(np.radians([10, 100, 190, 280])):
        pos = base + np.array([8 * np.cos(a), 8 * np.sin(a), 1.5])
        scanners[k + 1] = pos
        az0 = np.arctan2(base[1] - pos[1], base[0] - pos[0])
        az = az0 + np.radians(np.arange(-3.0, 3.0, 0.1))
        el = np.radians(np.arange(-12.0, np.degrees(np.arctan2(top - pos[2], 8.0)) + 1, 0.1))
        A, E = np.meshgrid(az, el)
        d = np.column_stack([(np.cos(E) * np.cos(A)).ravel(), (np.cos(E) * np.sin(A)).ravel(), np.sin(E).ravel()])
        rays = np.column_stack([np.broadcast_to(pos - origin, d.shape), d]).astype(np.float32)
        t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(float)
        hit = np.isfinite(t)
        rng_ = t[hit] + rng.normal(0, 0.005, hit.sum())
        pts.append(pos + d[hit] * rng_[:, None])
        sids.append(np.full(hit.sum(), k + 1, np.uint16))
    xyz = np.concatenate(pts)
    res = build_stem(PointCloud(xyz, {"point_source_id": np.concatenate(sids)}), scanners, base)
    assert res.mask.mean() > 0.9  # all points are stem points
    s = _sample_surface(res.mesh, 20_000, rng)
    d = _distance_to_mesh(s, true)
    assert d.mean() <= 0.02, d.mean()
    ext, _ = cKDTree(xyz[res.mask]).query(s)
    assert ext.max() <= 0.10
    # the fitted DBH matches the mesh's girth at 1.3 m
    ring = v[np.abs(v[:, 2] - z0 - 1.3) < 0.1]
    r_ring = np.hypot(*(ring[:, :2] - ring[:, :2].mean(axis=0)).T).mean()
    assert abs(res.summary["dbh_fitted"] - 2 * r_ring) < 0.03


# ----------------------------------------------------------------------------- command line
def _write_target(quick_targets, tmp_path, k=0):
    t, tree, _, _ = quick_targets[0][k]
    path = tmp_path / "tree.laz"
    write_las(path, tree)
    return t, path


def test_cli_outputs_and_reproducible(quick_targets, quick_forest, tmp_path):
    t, path = _write_target(quick_targets, tmp_path)
    scans = quick_forest / "plots" / "Q1" / "tls" / "scans.csv"
    args = [str(path), "--scans", str(scans), "--base", str(t.x), str(t.y), str(t.z_ground), "--dbh", str(t.dbh)]
    assert cli_main(["stems", *args, "-o", str(tmp_path / "a")]) == 0
    assert cli_main(["stems", *args, "-o", str(tmp_path / "b")]) == 0
    for name in ("stem.ply", "stem.obj", "stem_points.laz", "stem.json"):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes(), name
    ply, obj = read_mesh(tmp_path / "a" / "stem.ply"), read_mesh(tmp_path / "a" / "stem.obj")
    assert np.array_equal(ply.faces, obj.faces) and np.allclose(ply.vertices, obj.vertices, atol=0, rtol=0)
    info = json.loads((tmp_path / "a" / "stem.json").read_text())
    tree = read_las(path)
    pts = read_las(tmp_path / "a" / "stem_points.laz")
    idx = pts.attrs["tree_point_index"].astype(np.int64)
    # a clean subset: the indices name distinct input points with the same coordinates and scan
    assert len(np.unique(idx)) == len(idx) == info["n_stem_points"]
    assert np.allclose(pts.xyz, tree.xyz[idx], rtol=0, atol=1e-8)
    assert np.array_equal(pts.attrs["point_source_id"], tree.attrs["point_source_id"][idx])
    assert info["mesh_vertices"] == ply.n_vertices and info["mesh_faces"] == ply.n_faces
    assert info["depth"] == 8 and info["n_tree_points"] == len(tree)
    assert abs(info["mean_radius_below_crown"] - t.dbh / 2) < 0.03
    z = ply.vertices[:, 2]
    assert info["mesh_z_range"] == [z.min(), z.max()]
    # results only (timings go to the log), so that stem.json is reproducible byte for byte
    assert not [k for k in info if k.startswith("time_")]
    # plot mode (the workflow rule): same tree from a segmentation folder, same bytes
    seg = tmp_path / "segment"
    (seg / "trees").mkdir(parents=True)
    tid = 4242
    (seg / "trees" / f"{tid}.laz").write_bytes(path.read_bytes())
    pd.DataFrame({"tree_id": [tid], "x": [t.x], "y": [t.y], "z": [t.z_ground], "dbh": [t.dbh]}).to_csv(
        tmp_path / "targets.csv", index=False
    )
    rc = cli_main(["stems", "--segment", str(seg), "--targets", str(tmp_path / "targets.csv"), "--scans", str(scans),
                   "--config-json", '{"depth": 8}', "-o", str(tmp_path / "plot")])
    assert rc == 0
    for name in ("stem.ply", "stem.obj", "stem_points.laz"):
        assert (tmp_path / "plot" / str(tid) / name).read_bytes() == (tmp_path / "a" / name).read_bytes(), name


@pytest.fixture
def scans_csv(tmp_path):
    p = tmp_path / "scans.csv"
    p.write_text("scan_id,x,y,z\n1,9,0,1.5\n2,-9,0,1.5\n")
    return p


def _run(tmp_path, tree, scans, *extra, base=("0", "0", "0")):
    return cli_main(["stems", str(tree), "--scans", str(scans), "--base", *base, "-o", str(tmp_path / "out"), *extra])


def test_cli_errors(tmp_path, scans_csv, capsys):
    def expect(rc, *needles):
        err = capsys.readouterr().err
        assert rc == 2
        assert err.count("\n") == 1 and "Traceback" not in err, err
        for s in needles:
            assert s in err, err

    empty = tmp_path / "empty.laz"
    write_las(empty, PointCloud(np.zeros((0, 3))))
    expect(_run(tmp_path, empty, scans_csv), "empty.laz")
    tiny = tmp_path / "tiny.laz"
    write_las(tiny, PointCloud(np.random.default_rng(0).random((5, 3)), {"point_source_id": np.ones(5, np.uint16)}))
    expect(_run(tmp_path, tiny, scans_csv), "tiny.laz", "5 points")
    bad = tmp_path / "corrupt.laz"
    bad.write_bytes(b"LASF" + b"\0" * 50)
    expect(_run(tmp_path, bad, scans_csv), "corrupt.laz")
    expect(_run(tmp_path, tmp_path / "missing.laz", scans_csv), "missing.laz")
    # a stem cylinder scanned by scan 7, which scans.csv does not list
    rng = np.random.default_rng(0)
    th, z = rng.uniform(0, 2 * np.pi, 4000), rng.uniform(0, 3, 4000)
    cyl = np.column_stack([0.15 * np.cos(th), 0.15 * np.sin(th), z])
    tree = tmp_path / "tree7.laz"
    write_las(tree, PointCloud(cyl, {"point_source_id": np.full(4000, 7, np.uint16)}))
    expect(_run(tmp_path, tree, scans_csv), "tree7.laz", "scan id")
    # no stem at the given base
    expect(_run(tmp_path, tree, scans_csv, base=("30", "0", "0")), "tree7.laz", "no stem")
    # bad scans.csv
    bad_csv = tmp_path / "bad_scans.csv"
    bad_csv.write_text("scan_id,x,y\n1,0,0\n")
    expect(_run(tmp_path, tree, bad_csv), "bad_scans.csv", "z")
    # bad settings name the option
    expect(_run(tmp_path, tree, scans_csv, "--depth", "20"), "--depth")
    expect(_run(tmp_path, tree, scans_csv, "--dbh", "-1"), "--dbh")
    expect(_run(tmp_path, tree, scans_csv, base=("nan", "0", "0")), "--base")
    expect(_run(tmp_path, tree, scans_csv, "--config-json", '{"depht": 8}'), "stems.depht")
    expect(_run(tmp_path, tree, scans_csv, "--config-json", '{"tolerance": -1}'), "stems.tolerance")
    # plot mode: a target whose tree file is missing names that file
    (tmp_path / "targets.csv").write_text("tree_id,x,y,z\n5,0,0,0\n")
    rc = cli_main(["stems", "--segment", str(tmp_path / "seg"), "--targets", str(tmp_path / "targets.csv"),
                   "--scans", str(scans_csv), "-o", str(tmp_path / "out")])
    expect(rc, str(Path("seg") / "trees" / "5.laz"))
    (tmp_path / "targets.csv").write_text("tree_id,x,y\n5,0,0\n")
    rc = cli_main(["stems", "--segment", str(tmp_path / "seg"), "--targets", str(tmp_path / "targets.csv"),
                   "--scans", str(scans_csv), "-o", str(tmp_path / "out")])
    expect(rc, "targets.csv", "z")


def test_api_errors():
    rng = np.random.default_rng(0)
    th, z = rng.uniform(0, 2 * np.pi, 3000), rng.uniform(0, 3, 3000)
    cyl = np.column_stack([0.15 * np.cos(th), 0.15 * np.sin(th), z])
    nan = cyl.copy()
    nan[10, 2] = np.nan
    with pytest.raises(InputDataError, match="plot7.laz.*NaN"):
        trace_stem(nan, (0, 0, 0), source="plot7.laz")
    with pytest.raises(InputDataError, match="no points"):
        trace_stem(np.zeros((0, 3)), (0, 0, 0))
    with pytest.raises(ConfigError, match="base"):
        trace_stem(cyl, (0, 0))
    with pytest.raises(ConfigError, match="dbh"):
        trace_stem(cyl, (0, 0, 0), dbh=0)
    with pytest.raises(ConfigError, match="tolerance"):
        trace_stem(cyl, (0, 0, 0), tolerance=-1)
    with pytest.raises(InputDataError, match="point_source_id"):
        build_stem(PointCloud(cyl), {1: (5, 0, 1)}, (0, 0, 0))
    with pytest.raises(ConfigError, match="depth"):
        stem_mesh(cyl, np.ones(len(cyl), int), {1: (5, 0, 1)}, depth=2)
    with pytest.raises(InputDataError, match="too few|only"):
        stem_mesh(cyl[:10], np.ones(10, int), {1: (5, 0, 1)})
    # the cylinder itself: every point is a stem point, and the mesh fits the radius
    scan = np.where(cyl[:, 0] > 0, 1, 2)
    assert select_stem_points(cyl, (0, 0, 0)).all()
    mesh = stem_mesh(cyl, scan, {1: (5, 0, 1), 2: (-5, 0, 1)})
    s = _sample_surface(mesh, 5000, rng)
    assert np.abs(np.hypot(s[:, 0], s[:, 1]) - 0.15).mean() < 0.005
