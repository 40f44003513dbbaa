"""Experiment: how much room the random shift has, and what it changes with it.

The study finds that shifting each scaled cube randomly inside its cell "changes nothing". A
cube of side ``a`` in a cell of side ``a0`` can move by at most ``(a0 − a)/2`` along each axis
(:func:`vlsforest.voxels.shift_cubes`), so the shift has room only where the cubes are small:
a crown of nearly full cubes cannot change, a crown of small cubes can change most. The
proposed cause of a change is therefore the cubes' size, i.e. the plant area density the
scaling turns into it. This experiment tests that on a finished run, across the target trees:
for each tree the mean side of its cubes in the unshifted scaled model, and the change of each
metric from the unshifted to the randomly shifted model (the run's metrics of both, per
scenario). If the room is the cause, the change shrinks as the cubes grow: its size is
correlated with the cube side, over all trees and within each species group (whose crowns
differ in more than their cube sizes).

The result gives per scenario and metric: the mean change over the trees (with its standard
error), Pearson's r between a tree's mean cube side and its change and the least-squares line
(slope per metre of cube side, with its standard error), over all trees and per species group
(with the group's mean cube side and mean change).
"""

from __future__ import annotations

import math

import numpy as np

from vlsforest.errors import ConfigError
from vlsforest.experiments.run_outputs import mean_se, method_files, plot_files, targets
from vlsforest.io.csvfile import read_csv_table
from vlsforest.io.voxel_model import VoxelModel

__all__ = ["line_fit", "run_shift_room"]


def line_fit(x, y) -> dict:
    """Least-squares line ``y = a + b·x`` through the finite pairs, with Pearson's r.

    Returns
    -------
    dict
        ``n``, ``intercept``, ``slope``, ``slope_se`` (the usual OLS standard error, n − 2
        degrees of freedom) and ``r``; NaN where fewer than 3 pairs or no spread in ``x``.
    """
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    n = len(x)
    nan = float("nan")
    if n < 3 or np.ptp(x) == 0:
        return {"n": n, "intercept": nan, "slope": nan, "slope_se": nan, "r": nan}
    xm, ym = x.mean(), y.mean()
    sxx = float(((x - xm) ** 2).sum())
    sxy = float(((x - xm) * (y - ym)).sum())
    syy = float(((y - ym) ** 2).sum())
    b = sxy / sxx
    a = ym - b * xm
    resid = y - (a + b * x)
    se = math.sqrt(float((resid ** 2).sum()) / (n - 2) / sxx)
    r = sxy / math.sqrt(sxx * syy) if syy > 0 else nan
    return {"n": n, "intercept": float(a), "slope": float(b), "slope_se": se, "r": float(r)}


def run_shift_room(manifest, base: str, shifted: str, scenarios, metrics=("hmean", "multi_return_pct", "cbh", "cpa"),
                   *, option: str = "--inputs-json", progress=None) -> dict:
    """Each target tree's cube size in the unshifted scaled model against its change under the shift.

    Parameters
    ----------
    manifest : mapping
        The run's files by plot (:mod:`vlsforest.experiments.run_outputs`): each plot's
        ``targets``, the ``base`` method's ``voxels`` and both methods' ``metrics`` by scenario.
    base, shifted : str
        The unshifted scaled method and its randomly shifted variant.
    scenarios : sequence of str
        The scenarios.
    metrics : sequence of str
        Columns of the metrics tables whose change is related to the cube size.
    option : str
        The name of the manifest in error messages.
    progress : callable, optional
        Called with a line of text after each plot.

    Returns
    -------
    dict
        ``base``, ``shifted``, ``scenarios``, ``metrics``, ``cell_m`` (the model's cell);
        ``summary`` (scenario → metric → ``change`` (mean, se, n), ``fit``
        (:func:`line_fit` of the change on the mean cube side in m), ``groups`` (group → its
        mean side, mean change and fit));
        ``trees`` (plot, tree id, group, mean cube side and the change of each metric per
        scenario).

    Raises
    ------
    ConfigError
        The same method twice, no scenario or metric, a file the manifest does not name, or
        models of different cell sizes.
    InputDataError
        A file that cannot be read or lacks a metric column (names it).
    """
    if base == shifted:
        raise ConfigError("shift room: the base and the shifted method must differ")
    scenarios, metrics = [str(s) for s in scenarios], [str(m) for m in metrics]
    if not scenarios or not metrics:
        raise ConfigError("shift room: needs at least one scenario and one metric")
    plots = plot_files(manifest, option)
    rows, cell = [], None
    for plot, entry in plots.items():
        trees = targets(plot, entry)
        model = VoxelModel.load(method_files(plot, entry, base, "voxels", option=option))
        if cell is not None and model.size != cell:
            raise ConfigError(f"shift room: the {base} models have different cells ({cell} and {model.size} m)")
        cell = model.size
        tables = {}
        for sc in scenarios:
            for m in (base, shifted):
                path = method_files(plot, entry, m, "metrics", sc, option)
                tables[m, sc] = read_csv_table(path, "metrics table", ("tree_id", *metrics)).set_index("tree_id")
        for t in trees:
            sides = model.sides()[model.owner == t.segment_id]
            row = {"plot": plot, "tree_id": t.target_id, "group": t.group, "n_cubes": int(len(sides)),
                   "side_m": float(sides.mean()) if len(sides) else math.nan, "change": {}}
            for sc in scenarios:
                a, b = tables[base, sc], tables[shifted, sc]
                row["change"][sc] = {k: (float(b.at[t.target_id, k] - a.at[t.target_id, k])
                                         if t.target_id in a.index and t.target_id in b.index else math.nan)
                                     for k in metrics}
            rows.append(row)
        if progress is not None:
            progress(f"{plot}: {len(trees)} target trees")
    summary = {}
    groups = sorted({r["group"] for r in rows})
    for sc in scenarios:
        summary[sc] = {}
        for k in metrics:
            side = [r["side_m"] for r in rows]
            ch = [r["change"][sc][k] for r in rows]
            fit = line_fit(side, ch)
            by_group = {}
            for g in groups:
                gs = [r["side_m"] for r in rows if r["group"] == g]
                gc = [r["change"][sc][k] for r in rows if r["group"] == g]
                by_group[g] = {"side_m": mean_se(gs)["mean"], "change": mean_se(gc)["mean"], "fit": line_fit(gs, gc)}
            summary[sc][k] = {"change": mean_se(ch), "fit": fit, "groups": by_group}
    return {"experiment": "shift_room", "base": base, "shifted": shifted, "scenarios": scenarios,
            "metrics": metrics, "cell_m": cell, "plots": list(plots),
            "method": ("per target tree: the mean cube side of the unshifted scaled model and the change of each "
                       "metric from it to the randomly shifted model (the run's metrics); across the trees the "
                       "least-squares line of the change on the side and Pearson's r"),
            "summary": summary, "trees": rows}
