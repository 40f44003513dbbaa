"""Tests of vlsforest.report.figures and ``vlsforest report figures``."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from matplotlib.image import imread

from vlsforest import stats
from vlsforest.errors import ConfigError, InputDataError
from vlsforest.io.las import PointCloud, write_las
from vlsforest.metrics import METRIC_COLUMNS
from vlsforest.report import figures as F

SPECIES = ["fagus_sylvatica", "picea_abies", "carpinus_betulus", "picea_abies", "fagus_sylvatica", "picea_abies"]
METHODS = ("fixed_0.25", "scaled", "my_method")


def make_metrics(n_trees=6, methods=METHODS, seed=0):
    rng = np.random.default_rng(seed)
    rows = []
    for t in range(n_trees):
        sp = SPECIES[t % len(SPECIES)]
        h = rng.uniform(20, 35)
        for sc in ("als", "uls"):
            for k, me in enumerate(("reference",) + tuple(methods)):
                z = np.sort(rng.uniform(0, h, 13)) + 0.5 * k
                vals = {c: rng.uniform(1, 20) for c in METRIC_COLUMNS}
                vals.update({f"p{p:02d}": v for p, v in zip(F._PCT_RANKS, z)})
                vals["height"] = h + 0.2 * k + rng.normal(0, 0.3)
                vals["multi_return_pct"] = (70.0 if sp == "picea_abies" else 55.0) + rng.normal(0, 3) - 5 * k
                rows.append(dict(plot=f"P{t % 2 + 1}", tree_id=str(t + 1), species=sp, scenario=sc, method=me, **vals))
    return pd.DataFrame(rows)


@pytest.fixture(scope="module")
def tables():
    m = make_metrics()
    e = stats.compute_errors(m)
    vc = pd.DataFrame([dict(plot=p, method=me, n_voxels=100 * (k + 1) * (i + 1))
                       for i, p in enumerate(("P1", "P2")) for k, me in enumerate(METHODS)])
    return m, e, vc


@pytest.fixture
def captured(monkeypatch):
    """Keep every Figure that figures._save writes, for inspecting its axes."""
    figs = []
    orig = F._save

    def keep(fig, out):
        figs.append(fig)
        return orig(fig, out)

    monkeypatch.setattr(F, "_save", keep)
    return figs


def _png_ok(path, min_std=0.05):
    img = imread(path)
    assert img.ndim == 3 and img.shape[0] > 200 and img.shape[1] > 200
    assert img[..., :3].std() > min_std  # not blank
    return img


def test_percentile_curves_lines_and_bands(tables, tmp_path, captured):
    m, _, _ = tables
    out = F.fig07_percentile_curves(m, tmp_path / "f7.png", n_boot=200)
    _png_ok(out)
    fig = captured[-1]
    axes = fig.axes
    assert len(axes) == 2 * 3  # scenarios × species
    ax = axes[0]
    # reference + 3 methods, one line each, with the mean percentile heights as x data
    assert len(ax.lines) == 4
    sel = m[(m["scenario"] == "als") & (m["species"] == "carpinus_betulus") & (m["method"] == "reference")]
    np.testing.assert_allclose(ax.lines[0].get_xdata(), sel[list(F._PCT_COLS)].mean().to_numpy())
    np.testing.assert_array_equal(ax.lines[0].get_ydata(), F._PCT_RANKS)
    assert len(ax.collections) == 0  # one carpinus tree: no CI band
    assert len(axes[1].collections) == 4  # two fagus trees: a CI band per line


def test_density_bars_and_points(tables, tmp_path, captured):
    _, e, _ = tables
    _png_ok(F.fig08_density_deviation(e, tmp_path / "f8.png"))
    ax = captured[-1].axes[0]  # broadleaf, ALS
    assert len(ax.patches) == 3 * 10  # methods × bins
    widths = sorted(p.get_width() for p in ax.patches)
    d = e[(e["scenario"] == "als") & (e["group"] == "broadleaf") & e["metric"].str.startswith("dens_")]
    expect = sorted(d.groupby(["method", "metric"])["error"].mean())
    np.testing.assert_allclose(widths, expect)
    n_points = sum(len(c.get_offsets()) for c in ax.collections)
    assert n_points == len(d)


@pytest.mark.parametrize("fn", ["fig09_hsd_hmin", "fig11_cbh_cpa", "fig12_height"])
def test_violin_figures(tables, tmp_path, captured, fn):
    _, e, _ = tables
    _png_ok(getattr(F, fn)(e, tmp_path / f"{fn}.png"))
    ax = captured[-1].axes[0]
    metric = {"fig09_hsd_hmin": "hsd", "fig11_cbh_cpa": "cbh", "fig12_height": "height"}[fn]
    hue = "species" if fn == "fig12_height" else "group"
    d = e[(e["scenario"] == "als") & (e["metric"] == metric)]
    # one filled violin per method × hue level with ≥ 2 distinct values, plus the tree dots
    n_violins = int((d.groupby(["method", hue])["error"].nunique() >= 2).sum())
    polys = [c for c in ax.collections if "Poly" in type(c).__name__]
    assert len(polys) == n_violins > 3
    dots = sum(len(c.get_offsets()) for c in ax.collections if type(c).__name__ == "PathCollection")
    assert dots == len(e[(e["scenario"] == "als") & (e["metric"] == metric)])


def test_multireturn_bars(tables, tmp_path, captured):
    m, _, _ = tables
    _png_ok(F.fig10_multireturn(m, tmp_path / "f10.png"))
    ax = captured[-1].axes[0]
    heights = sorted(p.get_height() for p in ax.patches if p.get_height() != 0)
    groups = {"fagus_sylvatica": "broadleaf", "carpinus_betulus": "broadleaf", "picea_abies": "conifer"}
    als = m[m["scenario"] == "als"].assign(group=lambda d: d["species"].map(groups))
    expect = sorted(als.groupby(["method", "group"])["multi_return_pct"].mean())
    np.testing.assert_allclose(heights, expect)


def test_voxels_vs_error(tables, tmp_path, captured):
    _, e, vc = tables
    _png_ok(F.fig_voxels_vs_error(e, vc, tmp_path / "fv.png"))
    ax = captured[-1].axes[0]
    pts = np.concatenate([c.get_offsets() for c in ax.collections])
    assert len(pts) == 2 * 3 * 2  # plots × methods × scenarios
    assert ax.get_xscale() == "log"
    assert set(np.round(pts[:, 0]).astype(int)) == {100, 200, 400, 300, 600}


def test_side_views(tmp_path, captured):
    rng = np.random.default_rng(0)
    paths = {}
    for k, name in enumerate(("scaled", "fixed_0.25")):
        xyz = rng.normal(size=(3000, 3)) * [1.5, 1.5, 4] + [500.0, 800.0, 120.0 + k]
        tree = np.repeat([1, 2], 1500).astype(np.int32)
        p = write_las(tmp_path / f"{name}.laz", PointCloud(xyz, {
            "number_of_returns": rng.integers(1, 4, 3000).astype(np.uint8), "tree": tree}))
        paths[name] = p
    out = F.fig13_side_views(paths, tmp_path / "f13.png", ground_z=100.0, tree_field="tree", tree_id=2)
    _png_ok(out)
    axes = captured[-1].axes
    assert [a.get_title() for a in axes] == ["scaled (1500 points)", "fixed_0.25 (1500 points)"]
    z = np.concatenate([c.get_offsets()[:, 1] for c in axes[0].collections])
    assert len(z) == 1500 and 10 < z.mean() < 30
    with pytest.raises(ConfigError):
        F.fig13_side_views({}, tmp_path / "x.png")
    with pytest.raises(InputDataError, match="no field"):
        F.fig13_side_views(paths, tmp_path / "x.png", tree_field="nope", tree_id=1)
    with pytest.raises(InputDataError, match="no such file"):
        F.fig13_side_views({"a": tmp_path / "missing.laz"}, tmp_path / "x.png")


def test_figures_byte_identical_reruns(tables, tmp_path):
    m, e, _ = tables
    for fn, data in (("fig07_percentile_curves", m), ("fig09_hsd_hmin", e)):
        a = getattr(F, fn)(data, tmp_path / f"a_{fn}.png")
        b = getattr(F, fn)(data, tmp_path / f"b_{fn}.png")
        assert a.read_bytes() == b.read_bytes(), fn
    # other data → other pixels
    m2 = m.copy()
    m2.loc[m2["method"] == "scaled", ["p50", "p60"]] += 3.0
    c = F.fig07_percentile_curves(m2, tmp_path / "c.png")
    assert c.read_bytes() != (tmp_path / "a_fig07_percentile_curves.png").read_bytes()


def test_degenerate_inputs_render(tmp_path):
    m = make_metrics(n_trees=6, methods=("scaled",))
    one = m[(m["method"] == "scaled") & (m["tree_id"] == "1")].copy()
    one["method"] = "lonely"  # one tree only
    m = pd.concat([m, one], ignore_index=True)
    m.loc[m["method"] == "scaled", ["cbh", "hsd"]] = np.nan  # all-NaN metrics
    m.loc[m["scenario"] == "uls", "cpa"] = np.nan
    e = stats.compute_errors(m)
    vc = pd.DataFrame({"plot": ["P1"], "method": ["scaled"], "n_voxels": [10]})
    paths = F.make_figures(m, e, vc, tmp_path)
    assert set(paths) == set(F.FIGURE_FILES) - {"fig13"}  # no side views given
    for k, p in paths.items():
        assert p.name == F.FIGURE_FILES[k]
        _png_ok(p)
    with pytest.raises(ConfigError, match="png"):
        F.fig10_multireturn(m, tmp_path / "x.jpg")


def test_cli_report_figures(tables, tmp_path):
    from vlsforest.cli import main

    m, e, vc = tables
    m.to_csv(tmp_path / "tree_metrics.csv", index=False)
    e.to_csv(tmp_path / "errors.csv", index=False)
    vc.to_csv(tmp_path / "voxel_counts.csv", index=False)
    xyz = np.random.default_rng(1).normal(size=(500, 3)) + [0, 0, 10]
    write_las(tmp_path / "s.las", PointCloud(xyz))
    rc = main(["report", "figures", "--metrics", str(tmp_path / "tree_metrics.csv"), "--errors",
               str(tmp_path / "errors.csv"), "--voxel-counts", str(tmp_path / "voxel_counts.csv"),
               "-o", str(tmp_path / "figs"), "--side-view", f"scaled={tmp_path / 's.las'}"])
    assert rc == 0
    assert sorted(p.name for p in (tmp_path / "figs").iterdir()) == sorted(F.FIGURE_FILES.values())
    e.drop(columns=["error"]).to_csv(tmp_path / "errors.csv", index=False)
    rc = main(["report", "figures", "--metrics", str(tmp_path / "tree_metrics.csv"), "--errors",
               str(tmp_path / "errors.csv"), "--voxel-counts", str(tmp_path / "voxel_counts.csv"),
               "-o", str(tmp_path / "figs")])
    assert rc == 2
    e.to_csv(tmp_path / "errors.csv", index=False)
    rc = main(["report", "figures", "--metrics", str(tmp_path / "tree_metrics.csv"), "--errors",
               str(tmp_path / "errors.csv"), "--voxel-counts", str(tmp_path / "voxel_counts.csv"),
               "-o", str(tmp_path / "figs"), "--side-view", "nolabel"])
    assert rc == 2
    rc = main(["report", "figures", "--metrics", str(tmp_path / "tree_metrics.csv"), "--errors",
               str(tmp_path / "errors.csv"), "--voxel-counts", str(tmp_path / "voxel_counts.csv"),
               "-o", str(tmp_path / "figs"), "--tree-cloud", f"Q1/scaled={tmp_path / 's.las'}"])
    assert rc == 2


def test_side_view_selection_from_the_given_clouds(tmp_path):
    m = make_metrics(n_trees=4, methods=("fixed_0.25", "scaled"))
    m["n_points"] = 10.0
    m.loc[(m["method"] == "reference") & (m["tree_id"] == "3") & (m["scenario"] == "uls"), "n_points"] = 500.0
    m.loc[(m["method"] == "reference") & (m["tree_id"] == "3") & (m["scenario"] == "uls"), "hmin"] = 2.0
    plot = m.loc[m["tree_id"] == "3", "plot"].iloc[0]
    clouds = {(plot, me, "uls"): tmp_path / plot / me / "uls" / "trees.laz" for me in ("scaled", "fixed_0.25", "reference")}
    assert F.side_view_selection(m, clouds) is None  # the files do not exist yet
    rng = np.random.default_rng(2)
    for me in ("reference", "fixed_0.25", "scaled"):
        xyz = rng.uniform(0, 1, (200, 3)) + [0, 0, 300.0]
        tid = np.repeat([3, 4], 100).astype(np.int32)
        (tmp_path / plot / me / "uls").mkdir(parents=True)
        write_las(tmp_path / plot / me / "uls" / "trees.laz", PointCloud(xyz, {"tree_id": tid}))
    sel = F.side_view_selection(m, clouds)
    assert list(sel["clouds"]) == ["scaled", "fixed_0.25"]
    assert sel["clouds"]["scaled"] == clouds[(plot, "scaled", "uls")]
    # only the clouds given are read: without the reference's, no figure 13
    assert F.side_view_selection(m, {k: v for k, v in clouds.items() if k[1] != "reference"}) is None
    assert sel["tree_id"] == 3.0 and sel["tree_field"] == "tree_id"
    from vlsforest.io.las import read_las

    c = read_las(tmp_path / plot / "reference" / "uls" / "trees.laz")
    assert sel["ground_z"] == pytest.approx(c.xyz[c.attrs["tree_id"] == 3, 2].min() - 2.0)
