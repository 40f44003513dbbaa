"""Analogues of the figures of Weiser et al. (2021) as PNG files (seaborn / matplotlib).

One function per figure; each takes DataFrames (or LAS paths) and the output PNG path and
returns that path:

=====================================  ===================================================
:func:`fig07_percentile_curves`         mean height-percentile curves per species and
                                        scenario, bootstrap 95 % CI bands (study Fig. 7)
:func:`fig08_density_deviation`         density deviation per height bin, bars = mean,
                                        points = trees (Fig. 8)
:func:`fig09_hsd_hmin`                  Hsd relative and Hmin absolute error violins (Fig. 9)
:func:`fig10_multireturn`               multiple-return share bars with tree points (Fig. 10)
:func:`fig11_cbh_cpa`                   CBH and CPA error violins (Fig. 11)
:func:`fig12_height`                    tree height error violins by species (Fig. 12)
:func:`fig13_side_views`                side views of simulated tree clouds (Fig. 13)
:func:`fig_voxels_vs_error`             voxel count vs error per plot × method × scenario
=====================================  ===================================================

:func:`make_figures` writes all of them under the fixed names of :data:`FIGURE_FILES`.

``metrics`` is the ``tree_metrics.csv`` table and ``errors`` the ``errors.csv`` table of
:mod:`vlsforest.stats`. PNGs are rendered with the Agg backend at a fixed size and dpi and
without a ``Software`` tag, so that the same inputs give the same bytes. A panel without finite
data shows "no data" instead of failing.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import matplotlib

matplotlib.use("Agg", force=False)
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import seaborn as sns  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from vlsforest.domain.species import species_group  # noqa: E402
from vlsforest.errors import ConfigError, InputDataError  # noqa: E402
from vlsforest.io.atomic import save_figure  # noqa: E402
from vlsforest.stats import (  # noqa: E402
    GROUP_ORDER,
    OTHER_GROUP,
    REFERENCE,
    block_rng,
    bootstrap_mean_ci,
    check_columns,
    check_errors,
    method_order,
    prepare_metrics,
    scenario_order,
    species_order,
)

__all__ = [
    "FIGURE_FILES",
    "DPI",
    "method_palette",
    "fig07_percentile_curves",
    "fig08_density_deviation",
    "fig09_hsd_hmin",
    "fig10_multireturn",
    "fig11_cbh_cpa",
    "fig12_height",
    "fig13_side_views",
    "fig_voxels_vs_error",
    "side_view_selection",
    "make_figures",
]

#: figure key → fixed file name
FIGURE_FILES = {
    "fig07": "fig07_percentile_curves.png",
    "fig08": "fig08_density_deviation.png",
    "fig09": "fig09_hsd_hmin_errors.png",
    "fig10": "fig10_multireturn.png",
    "fig11": "fig11_cbh_cpa_errors.png",
    "fig12": "fig12_height_errors.png",
    "fig13": "fig13_side_views.png",
    "voxels": "fig_voxels_vs_error.png",
}
#: resolution of every PNG
DPI = 110
_PANEL = (4.2, 3.2)  # inches per panel
_PCT_COLS = ("p01", "p05", "p10", "p20", "p30", "p40", "p50", "p60", "p70", "p80", "p90", "p95", "p99")
_PCT_RANKS = (1, 5, 10, 20, 30, 40, 50, 60, 70, 80, 90, 95, 99)
_DENS_COLS = tuple(f"dens_{k:02d}" for k in range(1, 11))
_GROUP_COLORS = {"broadleaf": "#4daf4a", "conifer": "#377eb8", "other": "#999999"}


# --------------------------------------------------------------------------- helpers


def method_palette(methods) -> dict:
    """Colour per method: ``reference`` black, the methods in their given order the colour-blind
    palette (then a dark one)."""
    base = sns.color_palette("colorblind", 10)
    pal = {REFERENCE: (0.0, 0.0, 0.0)}
    ordered = method_order(methods, list(dict.fromkeys(str(m) for m in methods)))
    more = sns.color_palette("dark", max(len(ordered) - len(base), 1))
    for i, m in enumerate(ordered):
        pal[m] = base[i] if i < len(base) else more[(i - len(base)) % len(more)]
    return pal


def _new_figure(nrows: int, ncols: int, *, sharex=False, sharey=False, panel=_PANEL):
    fig = Figure(figsize=(panel[0] * ncols, panel[1] * nrows), layout="constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False, sharex=sharex, sharey=sharey)
    return fig, axes


def _save(fig: Figure, out) -> Path:
    out = Path(out)
    if out.suffix.lower() != ".png":
        raise ConfigError(f"output: a figure path must end in .png, got {out}")
    return save_figure(out, fig, format="png", dpi=DPI, metadata={"Software": None})


def _no_data(ax, title=None):
    ax.text(0.5, 0.5, "no data", ha="center", va="center", transform=ax.transAxes, color="0.4")
    ax.set_xticks([])
    ax.set_yticks([])
    if title:
        ax.set_title(title)


def _style():
    """Context: seaborn's whitegrid style and paper-sized fonts (restored afterwards)."""
    import contextlib

    stack = contextlib.ExitStack()
    stack.enter_context(sns.axes_style("whitegrid"))
    stack.enter_context(sns.plotting_context("notebook", font_scale=0.8))
    return stack


def _errors_of(errors, metric, column="error"):
    e = errors[errors["metric"] == metric]
    return e[np.isfinite(e[column].to_numpy(float))]


def _short(m: str) -> str:
    """A method's name for crowded axes: without a trailing ``_shift``."""
    return m.removesuffix("_shift")


def _kde_outline(v: np.ndarray, n_grid: int = 64):
    """Gaussian KDE (Scott's bandwidth) on [min, max], scaled to a maximum of 1."""
    grid = np.linspace(v.min(), v.max(), n_grid)
    bw = v.std(ddof=1) * len(v) ** (-1 / 5)
    dens = np.exp(-0.5 * ((grid[:, None] - v[None, :]) / bw) ** 2).sum(axis=1)
    return grid, dens / dens.max()


def _violin(ax, v, centre, half_width, side, color):
    """One violin (``side`` -1 = left half, +1 = right half, 0 = both) with quartile lines and dots.

    A single value or values without spread are drawn as a horizontal bar at that value.
    """
    v = np.sort(v[np.isfinite(v)])
    if len(v) == 0:
        return
    lo_side = -1.0 if side <= 0 else 0.0
    hi_side = 1.0 if side >= 0 else 0.0
    if len(v) < 2 or np.ptp(v) == 0:
        ax.plot([centre + lo_side * half_width, centre + hi_side * half_width], [v[0], v[0]], color=color, lw=2.0)
    else:
        grid, w = _kde_outline(v)
        ax.fill_betweenx(grid, centre + lo_side * half_width * w, centre + hi_side * half_width * w,
                         facecolor=color, edgecolor="0.25", lw=0.5, alpha=0.8)
        for q, ls in ((25, ":"), (50, "-"), (75, ":")):
            y = np.percentile(v, q)
            wy = np.interp(y, grid, w)
            ax.plot([centre + lo_side * half_width * wy, centre + hi_side * half_width * wy], [y, y],
                    color="0.15", lw=0.7, ls=ls)
    dots_x = centre + (lo_side + hi_side) * half_width * 0.15
    ax.scatter(np.full(len(v), dots_x), v, s=3, color="0.15", lw=0, zorder=3)


def _violins(ax, data, value, order, hue, hue_order, palette, ylabel, title):
    """Violins of ``value`` per method (x) and ``hue`` level: split halves for two levels, dodged
    full violins otherwise; width-normalised, cut at the data range."""
    from matplotlib.patches import Patch

    data = data[np.isfinite(data[value].to_numpy(float))]
    if data.empty:
        _no_data(ax, title)
        return
    split = len(hue_order) == 2
    groups = {k: g[value].to_numpy(float) for k, g in data.groupby(["method", hue], sort=False)}
    for i, me in enumerate(order):
        for h, lev in enumerate(hue_order):
            v = groups.get((me, lev))
            if v is None:
                continue
            if split:
                _violin(ax, v, i, 0.42, -1 if h == 0 else 1, palette[lev])
            else:
                w = 0.84 / len(hue_order)
                _violin(ax, v, i - 0.42 + (h + 0.5) * w, 0.45 * w, 0, palette[lev])
    ax.axhline(0.0, color="0.3", lw=0.8, zorder=0)
    ax.set_xlim(-0.6, len(order) - 0.4)
    ax.set_xticks(range(len(order)))
    ax.set_xticklabels([_short(m) for m in order], rotation=35, ha="right")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    present = [lev for lev in hue_order if (data[hue] == lev).any()]
    ax.legend([Patch(facecolor=palette[lev], edgecolor="0.25") for lev in present],
              [lev.replace("_", " ") for lev in present], fontsize=6, loc="best")


def _prep_errors(errors):
    return check_errors(errors, "errors")


# --------------------------------------------------------------------------- figures


def fig07_percentile_curves(metrics: pd.DataFrame, out, *, n_boot: int = 1000, seed: int = 0) -> Path:
    """Mean height-percentile curves per species (columns) and scenario (rows).

    Every method and the reference is one line (x = height in m, y = percentile rank); the band
    is the percentile-bootstrap 95 % CI of the mean over the species' trees (``n_boot``
    resamples, seeded by ``seed`` and the panel and method names).
    """
    df = prepare_metrics(metrics, "tree metrics")
    scen = scenario_order(df["scenario"], pd.unique(df["scenario"]))
    species = species_order(df["species"])
    methods = [REFERENCE] + method_order(df["method"], pd.unique(df["method"]))
    pal = method_palette(df["method"])
    with _style():
        fig, axes = _new_figure(len(scen), len(species), sharey=True)
        for i, sc in enumerate(scen):
            for j, sp in enumerate(species):
                ax = axes[i, j]
                drawn = False
                for me in methods:
                    blk = df[(df["scenario"] == sc) & (df["species"] == sp) & (df["method"] == me)]
                    x = blk[list(_PCT_COLS)].to_numpy(float)
                    x = x[np.isfinite(x).all(axis=1)]
                    if len(x) == 0:
                        continue
                    mean = x.mean(axis=0)
                    lo, hi = bootstrap_mean_ci(x, block_rng(seed, "fig07", sc, sp, me), n_boot, 0.95)
                    ref = me == REFERENCE
                    ax.plot(mean, _PCT_RANKS, color=pal[me], lw=2.0 if ref else 1.2,
                            ls="--" if ref else "-", label=_short(me), zorder=3 if ref else 2)
                    if len(x) >= 2:
                        ax.fill_betweenx(_PCT_RANKS, lo, hi, color=pal[me], alpha=0.15, lw=0)
                    drawn = True
                title = f"{sp.replace('_', ' ')} — {sc.upper()}"
                if not drawn:
                    _no_data(ax, title)
                    continue
                ax.set_title(title)
                ax.set_xlabel("height (m)")
                if j == 0:
                    ax.set_ylabel("height percentile (%)")
        handles, labels = axes[0, 0].get_legend_handles_labels()
        for a in axes.flat:
            h, lab = a.get_legend_handles_labels()
            if len(h) > len(handles):
                handles, labels = h, lab
        if handles:
            fig.legend(handles, labels, loc="outside right center", frameon=False)
        return _save(fig, out)


def fig08_density_deviation(errors: pd.DataFrame, out) -> Path:
    """Deviation of the point density per height bin (simulated − reference, percentage points).

    Rows are scenarios, columns species groups; bars are the mean per method and bin (bin 1 at
    the bottom, 10 at the top), dots the individual trees.
    """
    err = _prep_errors(errors)
    e = err[err["metric"].isin(_DENS_COLS)].copy()
    e = e[np.isfinite(e["error"].to_numpy(float))]
    scen = scenario_order(err["scenario"], pd.unique(err["scenario"]))
    groups = [g for g in GROUP_ORDER if (err["group"] == g).any()]
    methods = method_order(err["method"], pd.unique(err["method"]))
    pal = method_palette(err["method"])
    e["bin"] = e["metric"].str.slice(5).astype(int)
    with _style():
        fig, axes = _new_figure(len(scen), len(groups), sharex=True, panel=(4.6, 4.4))
        for i, sc in enumerate(scen):
            for j, g in enumerate(groups):
                ax = axes[i, j]
                d = e[(e["scenario"] == sc) & (e["group"] == g)]
                title = f"{g} — {sc.upper()}"
                if d.empty:
                    _no_data(ax, title)
                    continue
                present = [m for m in methods if (d["method"] == m).any()]
                h = 0.84 / len(present)
                for k, me in enumerate(present):
                    dm = d[d["method"] == me]
                    b = dm["bin"].astype(int).to_numpy()
                    off = -0.42 + (k + 0.5) * h
                    means = dm.groupby("bin")["error"].mean()
                    yb = np.array([int(x) for x in means.index])
                    ax.barh(yb + off, means.to_numpy(), height=h, color=pal[me], alpha=0.75,
                            label=_short(me))
                    ax.scatter(dm["error"].to_numpy(float), b + off, s=2.5, color=pal[me],
                               edgecolors="0.2", linewidths=0.2, zorder=3)
                ax.axvline(0.0, color="0.3", lw=0.8)
                ax.set_yticks(range(1, 11))
                ax.set_ylim(0.5, 10.5)
                ax.set_title(title)
                ax.set_xlabel("density error (percentage points)")
                ax.set_ylabel("height bin (1 = bottom, 10 = top)" if j == 0 else "")
                if i == 0 and j == len(groups) - 1:
                    ax.legend(fontsize=6, loc="lower right")
        return _save(fig, out)


def fig09_hsd_hmin(errors: pd.DataFrame, out) -> Path:
    """Relative Hsd error (%) and absolute Hmin error (m) per method; violins split by group."""
    err = _prep_errors(errors)
    scen = scenario_order(err["scenario"], pd.unique(err["scenario"]))
    methods = method_order(err["method"], pd.unique(err["method"]))
    groups = [g for g in GROUP_ORDER if (err["group"] == g).any()]
    panels = (("hsd", "rel_error", "Hsd relative error (%)"), ("hmin", "error", "Hmin error (m)"))
    with _style():
        fig, axes = _new_figure(len(scen), 2, panel=(5.2, 3.4))
        for i, sc in enumerate(scen):
            for j, (k, col, label) in enumerate(panels):
                d = _errors_of(err[err["scenario"] == sc], k, col)
                _violins(axes[i, j], d, col, methods, "group", groups, _GROUP_COLORS, label,
                         f"{label.split(' (')[0]} — {sc.upper()}")
        return _save(fig, out)


def fig10_multireturn(metrics: pd.DataFrame, out) -> Path:
    """Share of pulses with multiple returns per method and group (bars = mean, dots = trees)."""
    df = prepare_metrics(metrics, "tree metrics")
    df["group"] = df["species"].map(lambda sp: species_group(sp, default=OTHER_GROUP))
    scen = scenario_order(df["scenario"], pd.unique(df["scenario"]))
    order = [REFERENCE] + method_order(df["method"], pd.unique(df["method"]))
    groups = [g for g in GROUP_ORDER if (df["group"] == g).any()]
    with _style():
        fig, axes = _new_figure(1, len(scen), sharey=True, panel=(5.2, 3.6))
        for j, sc in enumerate(scen):
            ax = axes[0, j]
            d = df[(df["scenario"] == sc) & np.isfinite(df["multi_return_pct"].to_numpy(float))]
            title = sc.upper()
            if d.empty:
                _no_data(ax, title)
                continue
            sns.barplot(data=d, x="method", y="multi_return_pct", hue="group", order=order, hue_order=groups,
                        palette=_GROUP_COLORS, errorbar=None, alpha=0.7, ax=ax)
            sns.stripplot(data=d, x="method", y="multi_return_pct", hue="group", order=order, hue_order=groups,
                          palette=_GROUP_COLORS, dodge=True, jitter=False, size=2.2, legend=False, ax=ax,
                          edgecolor="0.2", linewidth=0.3)
            ax.set_xticks(range(len(order)))
            ax.set_xticklabels([_short(m) for m in order], rotation=35, ha="right")
            ax.set_xlabel("")
            ax.set_ylabel("pulses with multiple returns (%)")
            ax.set_title(title)
            if ax.get_legend() is not None:
                ax.get_legend().set_title(None)
        return _save(fig, out)


def fig11_cbh_cpa(errors: pd.DataFrame, out) -> Path:
    """CBH error (m) and CPA error (m²) per method; violins split by group."""
    err = _prep_errors(errors)
    scen = scenario_order(err["scenario"], pd.unique(err["scenario"]))
    methods = method_order(err["method"], pd.unique(err["method"]))
    groups = [g for g in GROUP_ORDER if (err["group"] == g).any()]
    panels = (("cbh", "CBH error (m)"), ("cpa", "CPA error (m²)"))
    with _style():
        fig, axes = _new_figure(len(scen), 2, panel=(5.2, 3.4))
        for i, sc in enumerate(scen):
            for j, (k, label) in enumerate(panels):
                d = _errors_of(err[err["scenario"] == sc], k)
                _violins(axes[i, j], d, "error", methods, "group", groups, _GROUP_COLORS, label,
                         f"{label.split(' (')[0]} — {sc.upper()}")
        return _save(fig, out)


def fig12_height(errors: pd.DataFrame, out) -> Path:
    """Tree height error (m) per method, one violin per species, one panel per scenario."""
    err = _prep_errors(errors)
    scen = scenario_order(err["scenario"], pd.unique(err["scenario"]))
    methods = method_order(err["method"], pd.unique(err["method"]))
    species = species_order(err["species"])
    pal = dict(zip(species, sns.color_palette("Set2", len(species))))
    with _style():
        fig, axes = _new_figure(len(scen), 1, panel=(8.0, 3.4))
        for i, sc in enumerate(scen):
            d = _errors_of(err[err["scenario"] == sc], "height")
            _violins(axes[i, 0], d, "error", methods, "species", species, pal, "tree height error (m)",
                     f"tree height error — {sc.upper()}")
        return _save(fig, out)


def fig13_side_views(clouds: Mapping, out, *, ground_z: float = 0.0, tree_field: str | None = None,
                     tree_id=None, max_points: int = 200_000) -> Path:
    """Side views (x–z) of simulated clouds of one tree, one panel per cloud.

    Parameters
    ----------
    clouds : mapping of str to path
        Panel label (e.g. ``"scaled"``, ``"fixed_0.25"``) → LAS/LAZ file; in the given order.
    out : path
        PNG to write.
    ground_z : float
        Terrain height subtracted from z.
    tree_field, tree_id : str, optional
        Keep only the points whose attribute ``tree_field`` equals ``tree_id`` (for plot clouds).
    max_points : int
        At most this many points per panel are drawn (an evenly spaced subset, deterministic).

    Points are coloured by their ``number_of_returns`` when present (1, 2, 3, ≥4).
    """
    from vlsforest.io.las import read_las

    if not clouds:
        raise ConfigError("clouds: at least one LAS file is needed for the side views")
    if (tree_field is None) != (tree_id is None):
        raise ConfigError("tree_field/tree_id: give both or neither")
    items = list(clouds.items())
    colors = {1: "#1b9e77", 2: "#d95f02", 3: "#7570b3", 4: "#e7298a"}
    with _style():
        fig, axes = _new_figure(1, len(items), sharey=True, panel=(3.4, 5.0))
        for ax, (label, path) in zip(axes[0], items):
            c = read_las(path)
            if tree_field is not None:
                if tree_field not in c.attrs:
                    raise InputDataError(f"{path}: no field {tree_field!r}")
                c = c.subset(np.asarray(c.attrs[tree_field]) == tree_id)
            if len(c) == 0:
                _no_data(ax, str(label))
                continue
            xyz = c.xyz
            if len(xyz) > max_points:
                keep = np.linspace(0, len(xyz) - 1, max_points).astype(np.int64)
                xyz = xyz[keep]
                nor = c.attrs.get("number_of_returns")
                nor = None if nor is None else np.asarray(nor)[keep]
            else:
                nor = c.attrs.get("number_of_returns")
            x = xyz[:, 0] - xyz[:, 0].mean()
            z = xyz[:, 2] - ground_z
            if nor is None:
                ax.scatter(x, z, s=0.6, c="#1b9e77", lw=0, rasterized=True)
            else:
                nr = np.clip(np.asarray(nor, dtype=np.int64), 1, 4)
                for k in (1, 2, 3, 4):
                    sel = nr == k
                    if sel.any():
                        ax.scatter(x[sel], z[sel], s=0.6, c=colors[k], lw=0, label=f"{k}{'+' if k == 4 else ''} returns")
            ax.set_aspect("equal", adjustable="datalim")
            ax.set_title(f"{label} ({len(c)} points)")
            ax.set_xlabel("x − mean x (m)")
        axes[0, 0].set_ylabel("height above ground (m)")
        h, lab = axes[0, 0].get_legend_handles_labels()
        if h:
            fig.legend(h, lab, loc="outside lower center", ncols=4, frameon=False, markerscale=8)
        return _save(fig, out)


def fig_voxels_vs_error(errors: pd.DataFrame, voxel_counts: pd.DataFrame, out,
                        metrics=("hsd", "multi_return_pct", "cbh", "cpa")) -> Path:
    """Voxel count of a plot's model vs the mean absolute error of its trees.

    One point per plot × method × scenario (x log scale); colour = method, marker = scenario;
    one panel per metric.
    """
    err = _prep_errors(errors)
    vc = check_columns(voxel_counts, ("plot", "method", "n_voxels"), numeric=("n_voxels",), source="voxel counts")
    vc = vc.assign(plot=vc["plot"].astype(str), method=vc["method"].astype(str))
    vc = vc[vc["method"] != REFERENCE].groupby(["plot", "method"], as_index=False)["n_voxels"].sum()
    units = {"hsd": "m", "cbh": "m", "cpa": "m²", "multi_return_pct": "pp", "height": "m", "hmin": "m"}
    methods = method_order(err["method"], pd.unique(err["method"]))
    pal = method_palette(err["method"])
    scen = scenario_order(err["scenario"], pd.unique(err["scenario"]))
    markers = dict(zip(scen, ["o", "s", "^", "D", "v", "P"] * (len(scen) // 6 + 1)))
    with _style():
        fig, axes = _new_figure(1, len(metrics), panel=(3.6, 3.4))
        for ax, k in zip(axes[0], metrics):
            e = _errors_of(err, k)
            mae = e.assign(abs_error=e["error"].abs()).groupby(["plot", "method", "scenario"], as_index=False)[
                "abs_error"].mean()
            d = mae.merge(vc, on=["plot", "method"], how="inner")
            d = d[d["n_voxels"] > 0]
            if d.empty:
                _no_data(ax, k)
                continue
            sns.scatterplot(data=d, x="n_voxels", y="abs_error", hue="method", style="scenario",
                            hue_order=[m for m in methods if (d["method"] == m).any()], palette=pal,
                            style_order=scen, markers=markers, s=28, ax=ax, legend=ax is axes[0, -1])
            ax.set_xscale("log")
            ax.set_xlabel("voxels in the plot's model")
            ax.set_ylabel(f"MAE per plot ({units.get(k, '')})")
            ax.set_title(k)
        if axes[0, -1].get_legend() is not None:
            sns.move_legend(axes[0, -1], "upper left", bbox_to_anchor=(1.02, 1.0), fontsize=6, frameon=False)
        return _save(fig, out)


def side_view_selection(metrics: pd.DataFrame, clouds: Mapping, *, methods=None, scenario: str | None = None,
                        tree_field: str = "tree_id"):
    """Pick the tree and clouds of figure 13 from the tree clouds given.

    The tree is the one with the most reference points in ``scenario`` (ties: first plot and
    tree id in sort order); its clouds are those of ``clouds`` for its plot and ``scenario`` and
    the first two of ``methods`` present in ``metrics`` (else the first and the last simulated
    method). The ground height is recovered from the reference cloud of that tree as
    ``min(z) − hmin``.

    Parameters
    ----------
    metrics : pandas.DataFrame
        The tree metrics table.
    clouds : mapping
        ``(plot, source, scenario)`` → path of that source's tree cloud (LAS/LAZ with the field
        ``tree_field``); ``source`` is a method or ``reference``. Only these files are read.
    methods : sequence of str, optional
        The methods to show (default: the non-reference sources of ``clouds``, in their order).
    scenario : str, optional
        The scenario (default: the last scenario of ``clouds``).

    Returns
    -------
    dict or None
        Keyword arguments of :func:`fig13_side_views` (``clouds, ground_z, tree_field,
        tree_id``), or None when a needed cloud is not given or absent (figure 13 is then
        skipped).
    """
    from vlsforest.io.las import read_las

    if methods is None:
        methods = list(dict.fromkeys(k[1] for k in clouds if k[1] != REFERENCE))
    if scenario is None:
        scens = list(dict.fromkeys(k[2] for k in clouds))
        scenario = scens[-1] if scens else ""
    df = prepare_metrics(metrics, "tree metrics")
    if scenario not in set(df["scenario"]):
        scenario = scenario_order(df["scenario"], pd.unique(df["scenario"]))[-1]
    ref = df[(df["method"] == REFERENCE) & (df["scenario"] == scenario)]
    ref = ref[np.isfinite(ref["n_points"].to_numpy(float)) & (ref["n_points"] > 0)]
    sims = method_order(df["method"], pd.unique(df["method"]))
    chosen = [m for m in methods if m in sims][:2]
    if len(chosen) < 2 and len(sims) >= 2:
        chosen = [sims[0], sims[-1]]
    if ref.empty or not chosen:
        return None
    ref = ref.sort_values(["n_points", "plot", "tree_id"], ascending=[False, True, True], kind="stable")
    plot, tree = ref.iloc[0]["plot"], ref.iloc[0]["tree_id"]
    paths = {m: clouds.get((plot, m, scenario)) for m in chosen}
    ref_path = clouds.get((plot, REFERENCE, scenario))
    if ref_path is None or any(p is None for p in paths.values()):
        return None
    paths = {m: Path(p) for m, p in paths.items()}
    ref_path = Path(ref_path)
    if not ref_path.is_file() or not all(p.is_file() for p in paths.values()):
        return None
    try:
        tree_value = float(tree)
    except ValueError:
        return None
    c = read_las(ref_path)
    if tree_field not in c.attrs:
        raise InputDataError(f"{ref_path}: no field {tree_field!r}")
    z = c.xyz[np.asarray(c.attrs[tree_field]) == tree_value, 2]
    if len(z) == 0:
        return None
    ground_z = float(z.min() - float(ref.iloc[0]["hmin"]))
    return {"clouds": paths, "ground_z": ground_z, "tree_field": tree_field, "tree_id": tree_value}


# --------------------------------------------------------------------------- driver


def _in_order_of(metrics: pd.DataFrame, errors: pd.DataFrame) -> pd.DataFrame:
    """The metrics rows sorted (stably) by the errors table's order of methods and scenarios;
    the references first, names the errors lack last."""
    if "method" not in metrics or "method" not in errors:
        return metrics
    m_order = {REFERENCE: -1, **{m: i for i, m in enumerate(pd.unique(errors["method"]))}}
    s_order = {s: i for i, s in enumerate(pd.unique(errors["scenario"]))} if "scenario" in errors else {}
    key = pd.DataFrame({"m": metrics["method"].astype(str).map(m_order).fillna(len(m_order)),
                        "s": metrics["scenario"].astype(str).map(s_order).fillna(len(s_order))
                        if "scenario" in metrics else 0})
    return metrics.loc[key.sort_values(["m", "s"], kind="stable").index]


def make_figures(metrics: pd.DataFrame, errors: pd.DataFrame, voxel_counts: pd.DataFrame, out_dir, *,
                 side_views: Mapping | None = None, ground_z: float = 0.0, tree_field: str | None = None,
                 tree_id=None, seed: int = 0) -> dict:
    """Write every figure under ``out_dir`` with the names of :data:`FIGURE_FILES`.

    Figure 13 is written only when ``side_views`` (label → LAS path) is given. Every figure
    shows the methods and scenarios in the order of the errors table (the study configuration's
    order, :func:`vlsforest.stats.compute_errors`).

    Returns
    -------
    dict of str to Path
        Figure key → file written.
    """
    out_dir = Path(out_dir)
    f = {k: out_dir / v for k, v in FIGURE_FILES.items()}
    metrics = _in_order_of(metrics, errors)
    paths = {
        "fig07": fig07_percentile_curves(metrics, f["fig07"], seed=seed),
        "fig08": fig08_density_deviation(errors, f["fig08"]),
        "fig09": fig09_hsd_hmin(errors, f["fig09"]),
        "fig10": fig10_multireturn(metrics, f["fig10"]),
        "fig11": fig11_cbh_cpa(errors, f["fig11"]),
        "fig12": fig12_height(errors, f["fig12"]),
        "voxels": fig_voxels_vs_error(errors, voxel_counts, f["voxels"]),
    }
    if side_views:
        paths["fig13"] = fig13_side_views(side_views, f["fig13"], ground_z=ground_z, tree_field=tree_field,
                                          tree_id=tree_id)
    return paths
