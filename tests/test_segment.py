"""Tests of vlsforest.segment: circle fits, terrain, stems, competitive growth, CLI and errors."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from vlsforest.cli import main
from vlsforest.errors import ConfigError, InputDataError
from vlsforest.io.las import PointCloud, read_las, write_las
from vlsforest.segment import (
    TREE_COLUMNS,
    Dtm,
    SegmentConfig,
    classify_ground,
    fit_circle,
    match_stems,
    segment_cloud,
    segment_files,
)

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"


# ------------------------------------------------------------------ synthetic scenes


def _terrain(x, y):
    """Gently sloped, undulating ground (amplitude 0.15 m)."""
    return 100.0 + 0.03 * x - 0.02 * y + 0.15 * np.sin(2 * np.pi * x / 12.0) * np.cos(2 * np.pi * y / 17.0)


def _scene(rng, stems=((-3.0, 1.0, 0.20), (4.0, -2.0, 0.12)), ground=True, half=10.0):
    """Ground points, vertical stems (cylinder surfaces, 0–12 m) and a spherical crown per stem."""
    parts, labels = [], []
    if ground:
        g = rng.uniform(-half, half, size=(60000, 2))
        parts.append(np.column_stack([g, _terrain(g[:, 0], g[:, 1]) + rng.normal(0, 0.005, len(g))]))
        labels.append(np.zeros(len(g), int))
    for k, (sx, sy, r) in enumerate(stems, start=1):
        n = 8000
        a = rng.uniform(0, 2 * np.pi, n)
        h = rng.uniform(0, 12.0, n)
        z0 = _terrain(sx, sy)
        parts.append(np.column_stack([sx + r * np.cos(a), sy + r * np.sin(a), z0 + h]))
        labels.append(np.full(n, k))
        m = 6000
        v = rng.normal(size=(m, 3))
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        rad = 2.0 * rng.uniform(0.3, 1.0, m) ** (1 / 3)
        parts.append(np.array([sx, sy, z0 + 11.0]) + v * rad[:, None])
        labels.append(np.full(m, k))
    xyz = np.vstack(parts)
    return xyz, np.concatenate(labels)


# ------------------------------------------------------------------ unit tests


def test_fit_circle_recovers_noisy_circle_and_arc():
    rng = np.random.default_rng(1)
    a = rng.uniform(0, 2 * np.pi, 400)
    xy = np.column_stack([3.0 + 0.25 * np.cos(a), -1.0 + 0.25 * np.sin(a)]) + rng.normal(0, 0.002, (400, 2))
    cx, cy, r, rms = fit_circle(xy)
    assert abs(cx - 3.0) < 1e-3 and abs(cy + 1.0) < 1e-3 and abs(r - 0.25) < 1e-3
    assert 0.001 < rms < 0.004
    # a 90° arc still gives the radius within a few millimetres
    a = rng.uniform(0, np.pi / 2, 300)
    xy = np.column_stack([0.1 * np.cos(a), 0.1 * np.sin(a)]) + rng.normal(0, 0.001, (300, 2))
    assert abs(fit_circle(xy)[2] - 0.1) < 0.005
    assert all(math.isnan(v) for v in fit_circle(xy[:2]))


def test_dtm_bilinear_is_exact_on_a_plane_and_round_trips(tmp_path):
    x0, y0, c = -5.0, 2.0, 0.5
    ny, nx = 8, 11
    jj, ii = np.mgrid[:ny, :nx]
    plane = lambda x, y: 3.0 + 0.2 * x - 0.1 * y  # noqa: E731
    z = plane(x0 + (ii + 0.5) * c, y0 + (jj + 0.5) * c)
    dtm = Dtm(x0, y0, c, z)
    x = np.array([-4.75, -3.1, 0.0, 0.2])
    y = np.array([2.25, 3.3, 4.9, 5.6])
    np.testing.assert_allclose(dtm.height_at(x, y), plane(x, y), atol=1e-12)
    p = dtm.save(tmp_path / "dtm.npz")
    back = Dtm.load(p)
    np.testing.assert_array_equal(back.z, dtm.z)
    assert (back.x0, back.y0, back.cell) == (x0, y0, c)
    with pytest.raises(InputDataError, match="no such file"):
        Dtm.load(tmp_path / "missing.npz")


def test_match_stems_one_to_one_within_distance():
    found = np.array([[0.0, 0.0], [0.1, 0.0], [5.0, 5.0]])
    true = np.array([[0.05, 0.0], [5.6, 5.0]])
    assert match_stems(found, true, 0.5) == [(0, 0)]
    assert match_stems(found, true, 0.7) == [(0, 0), (2, 1)]


def test_config_errors_name_the_key():
    with pytest.raises(ConfigError, match="segment.voxel"):
        SegmentConfig(voxel=0)
    with pytest.raises(ConfigError, match="segment.slice_max"):
        SegmentConfig(slice_min=2.0, slice_max=1.5)
    with pytest.raises(ConfigError, match="segment.bogus"):
        SegmentConfig.from_dict({"bogus": 1})
    with pytest.raises(ConfigError, match="segment.graph_radius"):
        SegmentConfig(graph_radius=float("nan"))


def test_ground_of_rough_terrain_and_no_ground_error():
    rng = np.random.default_rng(2)
    xyz, lab = _scene(rng)
    is_ground, is_noise, dtm = classify_ground(xyz)
    truth = lab == 0
    assert (is_ground & truth).sum() / truth.sum() > 0.995
    assert (is_ground & ~truth).sum() / is_ground.sum() < 0.01
    g = rng.uniform(-8, 8, size=(2000, 2))
    err = dtm.height_at(g[:, 0], g[:, 1]) - _terrain(g[:, 0], g[:, 1])
    assert np.abs(err).max() < 0.03
    assert not is_noise.any()
    tree_only = xyz[lab > 0]
    with pytest.raises(InputDataError, match="no ground"):
        classify_ground(tree_only, source="trees.laz")


def test_segment_synthetic_two_trees():
    rng = np.random.default_rng(3)
    xyz, lab = _scene(rng)
    res = segment_cloud(PointCloud(xyz), SegmentConfig())
    t = res.trees
    assert list(t.columns) == list(TREE_COLUMNS)
    assert list(t["tree_id"]) == [1, 2]  # ordered by x: the stem at x = -3 first
    np.testing.assert_allclose(t[["x", "y"]].to_numpy(), [[-3.0, 1.0], [4.0, -2.0]], atol=0.01)
    np.testing.assert_allclose(t["dbh"].to_numpy(), [0.40, 0.24], atol=0.01)
    np.testing.assert_allclose(t["z"].to_numpy(), _terrain(np.array([-3.0, 4.0]), np.array([1.0, -2.0])), atol=0.03)
    # height: the crown top (11 + 2 m) above the stem base
    np.testing.assert_allclose(t["height"].to_numpy(), 13.0, atol=0.15)
    for k in (1, 2):
        tp = ((res.tree_id == k) & (lab == k)).sum()
        iou = tp / ((res.tree_id == k) | (lab == k)).sum()
        assert iou > 0.98
    assert (res.classification[lab == 0] == 2).mean() > 0.995
    assert t["n_points"].sum() == (res.tree_id > 0).sum()
    # deterministic
    res2 = segment_cloud(PointCloud(xyz), SegmentConfig())
    np.testing.assert_array_equal(res.tree_id, res2.tree_id)


def _stem(rng, sx, sy, r, h0, h1, n):
    a = rng.uniform(0, 2 * np.pi, n)
    h = rng.uniform(h0, h1, n)
    return np.column_stack([sx + r * np.cos(a), sy + r * np.sin(a), _terrain(sx, sy) + h])


def test_low_slice_finds_a_stem_whose_breast_height_slice_is_cluttered():
    rng = np.random.default_rng(5)
    xyz, lab = _scene(rng, stems=((-3.0, 1.0, 0.15),))
    # a low-crowned tree at (4, -2): dense foliage from 0.9 m up hides its stem in the 1–2 m slice
    stem = _stem(rng, 4.0, -2.0, 0.10, 0.0, 8.0, 6000)
    v = rng.uniform(-1.5, 1.5, size=(60000, 3))
    v = v[np.hypot(v[:, 0], v[:, 1]) > 0.15]
    foliage = np.column_stack([4.0 + v[:, 0], -2.0 + v[:, 1], _terrain(4.0, -2.0) + 2.4 + v[:, 2]])
    cloud = PointCloud(np.vstack([xyz, stem, foliage]))
    res = segment_cloud(cloud, SegmentConfig())
    xy = res.trees[["x", "y"]].to_numpy()
    assert len(xy) == 2 and np.hypot(*(xy[1] - [4.0, -2.0])) < 0.03
    assert res.trees["dbh"].iloc[1] == pytest.approx(0.20, abs=0.02)
    # the foliage belongs to that tree, not to its neighbour
    own = res.tree_id[len(xyz) + len(stem):]
    assert (own == 2).mean() > 0.95
    # without the low slice the stem is missed and its crown is left without a tree
    off = segment_cloud(cloud, SegmentConfig(low_slice_min=0.4, low_slice_max=0.4))
    assert len(off.trees) == 1 and (off.tree_id[len(xyz):] == 0).mean() > 0.95
    with pytest.raises(ConfigError, match="segment.low_slice_min"):
        SegmentConfig(low_slice_min=0.05, low_slice_max=1.0)


def test_unreached_crown_pieces_join_whole_and_chain():
    rng = np.random.default_rng(6)
    stem = _stem(rng, 0.0, 0.0, 0.15, 0.0, 8.0, 8000)
    z0 = _terrain(0.0, 0.0)
    ground = rng.uniform(-10, 10, size=(40000, 2))
    ground = np.column_stack([ground, _terrain(ground[:, 0], ground[:, 1])])
    # piece A: 0.8 m above the stem top (beyond graph_radius 0.5, within attach_dist 1.0), 3 m
    # tall, so that most of it lies farther than attach_dist from any reached point;
    # piece B: 0.8 m above A; piece C: 4 m to the side of A (beyond attach_dist)
    def blob(cx, cy, zlo, zhi, n):
        return np.column_stack([cx + rng.uniform(-0.6, 0.6, n), cy + rng.uniform(-0.6, 0.6, n),
                                z0 + rng.uniform(zlo, zhi, n)])
    a = blob(0.0, 0.0, 8.8, 11.8, 20000)
    b = blob(0.0, 0.0, 12.6, 14.0, 8000)
    c = blob(5.5, 0.0, 9.0, 10.0, 5000)
    xyz = np.vstack([ground, stem, a, b, c])
    res = segment_cloud(PointCloud(xyz), SegmentConfig())
    lab = res.tree_id[len(ground):]
    n_s, n_a, n_b = len(stem), len(a), len(b)
    assert len(res.trees) == 1
    assert (lab[:n_s] == 1).mean() > 0.98  # the lowest centimetres are ground
    assert (lab[n_s:n_s + n_a] == 1).all() and (lab[n_s + n_a:n_s + n_a + n_b] == 1).all()
    assert (lab[n_s + n_a + n_b:] == 0).all()
    assert res.trees["height"].iloc[0] == pytest.approx(14.0, abs=0.1)


def test_hidden_stem_is_bridged_to_its_own_crown():
    """A stem seen only up to 3 m still gets its crown 7 m above; a neighbour that touches it does not."""
    rng = np.random.default_rng(8)
    ground = rng.uniform(-8, 8, size=(40000, 2))
    ground = np.column_stack([ground, _terrain(ground[:, 0], ground[:, 1])])

    def crown(cx, n):
        v = rng.normal(size=(n, 3))
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        return np.array([cx, 0.0, _terrain(cx, 0.0) + 12.0]) + v * (2.0 * rng.uniform(0.3, 1, n) ** (1 / 3))[:, None]

    # tree A at x = 0: stem visible 0–3 m only (understorey hides the rest), crown 10–14 m;
    # tree B at x = 3.5: stem visible 0–12 m, crown 10–14 m, overlapping A's by 0.5 m
    stem_a = _stem(rng, 0.0, 0.0, 0.15, 0.0, 3.0, 3000)
    stem_b = _stem(rng, 3.5, 0.0, 0.15, 0.0, 12.0, 9000)
    crown_a, crown_b = crown(0.0, 15000), crown(3.5, 15000)
    xyz = np.vstack([ground, stem_a, stem_b, crown_a, crown_b])
    sl = np.cumsum([len(ground), len(stem_a), len(stem_b), len(crown_a), len(crown_b)])
    cloud = PointCloud(xyz)

    def own(res):
        """Fractions labelled A of A's crown half away from B, and labelled B of B's own side."""
        a, b = res.tree_id[sl[2]:sl[3]], res.tree_id[sl[3]:sl[4]]
        return (a[crown_a[:, 0] < 0.5] == 1).mean(), (b[crown_b[:, 0] > 1.75] == 2).mean()

    res = segment_cloud(cloud, SegmentConfig())
    assert len(res.trees) == 2 and res.trees["x"].iloc[0] < res.trees["x"].iloc[1]
    assert res.info["n_bridges"] >= 1
    fa, fb = own(res)
    assert fa > 0.98 and fb > 0.98
    # A's path is longer by its hidden stem, so the boundary of the competition moves towards
    # A (about x = 1.2 instead of the mid-plane 1.75), but most of A's crown is A's
    assert 0.75 < (res.tree_id[sl[2]:sl[3]] == 1).mean() < 0.95
    assert (res.tree_id[sl[0]:sl[1]] == 1).mean() > 0.95
    # A's crown height comes back: the tree reaches its crown top, not its visible stem top
    assert res.trees["height"].iloc[0] == pytest.approx(14.0, abs=0.3)
    # without a bridge (switched off, or a gap longer than allowed) the neighbour takes the crown
    for cfg in (SegmentConfig(stem_bridge=0), SegmentConfig(stem_bridge=5.0)):
        off = segment_cloud(cloud, cfg)
        assert (off.info["n_bridges"] == 0) == (cfg.stem_bridge == 0)  # 5 m: only gaps inside A's hollow crown
        fa_off, fb_off = own(off)
        assert fa_off < 0.05 and fb_off > 0.98
    with pytest.raises(ConfigError, match="segment.stem_bridge"):
        SegmentConfig(stem_bridge=-1)


def test_deviation_filter_drops_noisy_pulses():
    rng = np.random.default_rng(4)
    xyz, lab = _scene(rng)
    dev = np.where(rng.uniform(size=len(xyz)) < 0.05, 200, 5).astype(np.uint16)
    res = segment_cloud(PointCloud(xyz, {"Deviation": dev}), SegmentConfig(max_deviation=50))
    assert np.all(res.tree_id[dev > 50] == 0) and np.all(res.classification[dev > 50] == 7)
    assert f"{int((dev > 50).sum())} points dropped" in res.info["deviation_filter"]
    res0 = segment_cloud(PointCloud(xyz), SegmentConfig())
    assert "no pulse-shape deviation field" in res0.info["deviation_filter"]


# ------------------------------------------------------------------ errors through the CLI


def _write(path, xyz, **attrs):
    return write_las(path, PointCloud(np.asarray(xyz, float).reshape(-1, 3), attrs))


def test_cli_errors_are_one_clear_line(tmp_path, capsys):
    rng = np.random.default_rng(5)
    empty = _write(tmp_path / "empty.laz", np.zeros((0, 3)))
    tiny = _write(tmp_path / "tiny.laz", rng.uniform(0, 1, (10, 3)))
    xyz, lab = _scene(rng)
    trees = _write(tmp_path / "trees_only.laz", xyz[lab > 0])
    for f, msg in (
        (empty, "holds no points"),
        (tiny, "only 10 points"),
        (trees, "no ground"),
        (tmp_path / "missing.laz", "no such file"),
    ):
        rc = main(["segment", str(f), "-o", str(tmp_path / "out")])
        err = capsys.readouterr().err
        assert rc == 2, f
        assert str(f) in err and msg in err and "Traceback" not in err
    with pytest.raises(InputDataError, match="NaN"):
        xyz_nan = xyz.copy()
        xyz_nan[5, 2] = np.nan
        segment_cloud(PointCloud(xyz_nan), source="nan.laz")
    assert main(["segment", str(trees), "-o", str(tmp_path / "out"), "--stem-bridge", "-1"]) == 2
    assert "segment.stem_bridge" in capsys.readouterr().err
    bad = tmp_path / "bad.laz"
    bad.write_bytes(b"not a las file at all")
    assert main(["segment", str(bad), "-o", str(tmp_path / "out")]) == 2
    assert "bad.laz" in capsys.readouterr().err


# ------------------------------------------------------------------ virtual truth


def _truth_labels(forest, scans):
    return np.concatenate(
        [np.load(forest / "truth" / "Q1" / "tls" / f"{p.stem}_labels.npz")["tree_id"] for p in scans]
    )


@pytest.fixture(scope="module")
def quick_segmentation(quick_forest, tmp_path_factory):
    """``vlsforest segment`` of the quick forest's TLS scans: (scan files, output folder)."""
    tls = quick_forest / "plots" / "Q1" / "tls"
    scans = sorted(tls.glob("scan_*.laz"), key=lambda p: int(p.stem.split("_")[1]))
    out = tmp_path_factory.mktemp("segment") / "seg"
    assert main(["segment", *map(str, scans), "-o", str(out)]) == 0
    return scans, out


def _target_ious(quick_forest, scans, out):
    """Point IoU of each target tree found within 0.5 m (truth labels against ``tree_id``)."""
    trees = pd.read_csv(out / "trees.csv")
    tid = read_las(out / "segmented.laz", require=("tree_id",)).attrs["tree_id"].astype(np.int64)
    lab = _truth_labels(quick_forest, scans)
    truth = pd.read_csv(quick_forest / "truth" / "trees.csv")
    targets = truth[(truth["plot"] == "Q1") & truth["target"]].reset_index(drop=True)
    pairs = match_stems(trees[["x", "y"]].to_numpy(), targets[["x", "y"]].to_numpy(), 0.5)
    return [((lab == targets["tree_id"][t]) & (tid == trees["tree_id"][f])).sum()
            / ((lab == targets["tree_id"][t]) | (tid == trees["tree_id"][f])).sum() for f, t in pairs]


def test_quick_forest_against_truth(quick_forest, quick_segmentation):
    scans, out = quick_segmentation
    trees = pd.read_csv(out / "trees.csv")
    assert list(trees.columns) == list(TREE_COLUMNS)
    assert list(trees["tree_id"]) == list(range(1, len(trees) + 1))
    seg = read_las(out / "segmented.laz", require=("tree_id", "classification", "gps_time"))
    tid = seg.attrs["tree_id"].astype(np.int64)
    lab = _truth_labels(quick_forest, scans)
    assert len(tid) == len(lab)
    truth = pd.read_csv(quick_forest / "truth" / "trees.csv")
    truth = truth[truth["plot"] == "Q1"].reset_index(drop=True)
    targets = truth[truth["target"]].reset_index(drop=True)
    # detection of target stems: F1 with matching within 0.5 m; a false positive is a found stem
    # matching no true stem at all that stands within 5 m of a target
    pairs = match_stems(trees[["x", "y"]].to_numpy(), targets[["x", "y"]].to_numpy(), 0.5)
    all_pairs = match_stems(trees[["x", "y"]].to_numpy(), truth[["x", "y"]].to_numpy(), 0.5)
    unmatched = np.setdiff1d(np.arange(len(trees)), [f for f, _ in all_pairs])
    dmin = np.hypot(trees["x"].to_numpy()[unmatched, None] - targets["x"].to_numpy()[None],
                    trees["y"].to_numpy()[unmatched, None] - targets["y"].to_numpy()[None])
    fp = int((dmin.min(axis=1) < 5.0).sum()) if len(unmatched) else 0
    tp = len(pairs)
    f1 = 2 * tp / (2 * tp + fp + (len(targets) - tp))
    # the segmentation's requirement (issue 4, replacing the study's manually corrected
    # CompuTree segmentation): target stems found with F1 ≥ 0.95
    assert f1 >= 0.95
    # … and a median DBH error ≤ 2 cm (issue 4)
    dbh_err = [trees["dbh"][f] - truth["dbh"][t] for f, t in all_pairs]
    assert np.median(np.abs(dbh_err)) <= 0.02
    # the stem base height is every tree metric's zero (targets.csv → `vlsforest extract`): within
    # half of the metrics' 0.1 m CBH slice, so that it moves a crown base by one slice at most
    z_err = [trees["z"][f] - truth["z_ground"][t] for f, t in all_pairs]
    assert np.median(np.abs(z_err)) <= 0.05
    # ground: LAS class 2 agrees with the truth's ground points
    g = seg.attrs["classification"] == 2
    assert (g & (lab == 0)).sum() / (lab == 0).sum() > 0.99
    assert (g & (lab != 0)).sum() / g.sum() < 0.02
    assert np.all(tid[g] == 0)
    # per-tree files keep the original attributes
    first = trees.iloc[0]
    one = read_las(out / "trees" / f"{int(first.tree_id)}.laz",
                   require=("gps_time", "return_number", "number_of_returns", "point_source_id"))
    assert len(one) == first.n_points
    assert set(np.unique(one.attrs["point_source_id"])) <= set(range(1, len(scans) + 1))
    assert np.all(one.attrs["tree_id"] == first.tree_id)
    dtm = Dtm.load(out / "dtm.npz")
    ground_z = json.loads((quick_forest / "plots" / "Q1" / "plot.json").read_text())["ground_z"]
    assert abs(np.median(dtm.z[dtm.measured]) - ground_z) < 0.3


@pytest.mark.xfail(strict=True, reason=(
    "issue 4's point-IoU requirement (mean over the targets ≥ 0.90) is not met on the quick "
    "forest: 0.895 (targets 0.846, 0.952, 0.836, 0.945); tests/test_default_forest.py checks it on "
    "the default forest's 30 targets"))
def test_quick_forest_target_iou_meets_the_requirement(quick_forest, quick_segmentation):
    ious = _target_ious(quick_forest, *quick_segmentation)
    # issue 4: mean per-tree point IoU of the target trees ≥ 0.90
    assert np.mean(ious) >= 0.90, np.round(ious, 3)


# ------------------------------------------------------------------ real data


def test_real_tls_plot_lpine(tmp_path):
    f = REAL / "LPine1_demo.laz"
    if not f.is_file():
        pytest.skip("real data folder absent")
    # the demo plot has its ground removed: detected as such, then segmented with no_ground
    with pytest.raises(InputDataError, match="no ground"):
        segment_files([f], tmp_path / "a", write_trees=False)
    res = segment_files([f], tmp_path / "b", SegmentConfig(no_ground=True), write_trees=False)
    t = res.trees
    big = t[t["n_points"] > 20000]
    assert 7 <= len(big) <= 12
    assert big["height"].between(15, 25).all()
    assert big["dbh"].between(0.1, 0.5).all()
    assert (res.tree_id > 0).mean() > 0.95
