"""Validation of PAD estimates against the virtual truth (true plant area per voxel).

An analysis of two stages' outputs: the PAD estimates (:mod:`vlsforest.pad`) and the recorded
virtual forest (:mod:`vlsforest.synth`).

The truth of a recorded virtual forest folder (``truth/synth_settings.yaml`` + seed) is rebuilt
deterministically: the plot layout with :func:`vlsforest.synth.forest_from_config`, the tree
meshes with :func:`vlsforest.synth.generate_plot_trees`, and the exact one-sided plant area per
voxel of every tree with :func:`vlsforest.synth.true_plant_area` on the estimate's grid.

Each voxel is given to the tree with most true plant area in it (its species and crown); voxels
holding plant echoes but no true area (range noise at a face) go to the tree of the nearest
true voxel when one lies within 1.75 cells. The height band is the voxel centre's relative height in its tree's crown,
``(z − z_ground − cbh) / (height − cbh)``: ``below_crown`` (< 0), ``lower`` (< 1/3),
``middle`` (< 2/3), ``upper``; ``crown`` pools the three crown bands (stem voxels below the
crown, where the opaque stem is no turbid medium, are reported apart only).

Statistics per (species, estimator, height band) over the voxels crossed by at least
``min_shots`` shots (estimates computed with each voxel's species: broadleaf planophile and
PADmax 5, conifer erectophile and PADmax 8, unless overridden):

* ``bias_pct`` = 100 · (Σ PAD_est − Σ PAD_true) / Σ PAD_true,
* ``rmse`` = √mean((PAD_est − PAD_true)²) (m²/m³),
* ``bias_pct_capped``, the bias against the truth capped at the voxel's PADmax (the most an
  estimate can say: voxels denser than PADmax are clipped by design),
* ``mean_true_pad``, ``mean_est_pad`` and ``frac_undersampled``, the share of the band's true
  plant area in voxels crossed by fewer than ``min_shots`` shots (where TLS occlusion leaves the
  crown unseen).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from vlsforest.domain.species import PAD_GROUPS, species_group
from vlsforest.errors import ConfigError, InputDataError
from vlsforest.io.atomic import save_figure, write_csv
from vlsforest.io.csvfile import read_csv_table
from vlsforest.pad.estimate import estimate_pad
from vlsforest.pad.traverse import Accumulators

#: columns of the validation table (the contract columns first)
TABLE_COLUMNS = ["plot", "species", "estimator", "height_band", "n_voxels", "bias_pct", "rmse",
                 "bias_pct_capped", "mean_true_pad", "mean_est_pad", "frac_undersampled"]
HEIGHT_BANDS = ("below_crown", "lower", "middle", "upper")


def load_truth_geometries(forest_dir, plot: str, targets_only: bool = False):
    """Regenerate the tree geometries and read the truth table of one plot.

    Parameters
    ----------
    forest_dir : path
        A folder written by ``vlsforest synth`` (``truth/{plot}/synth_settings.yaml`` and
        ``truth/{plot}/trees.csv``, else the forest's ``truth/synth_settings.yaml`` and
        ``truth/trees.csv``).
    plot : str
        Plot name.
    targets_only : bool
        Generate only the target trees and the trees whose crowns may reach into theirs
        (horizontal stem distance < sum of crown radii + 1 m); the others cannot share a voxel
        with a target crown.

    Returns
    -------
    geometries : dict tree_id → TreeGeometry
    trees : pandas.DataFrame
        The plot's rows of ``truth/trees.csv`` (all trees).
    """
    from vlsforest.synth.forest import generate_plot_trees, layouts_from_settings

    forest_dir = Path(forest_dir)
    # the plot's own truth folder (a plot recorded alone, `vlsforest synth --part`), else the forest's
    truth = forest_dir / "truth" / plot
    if not (truth / "synth_settings.yaml").is_file():
        truth = forest_dir / "truth"
    st_path = truth / "synth_settings.yaml"
    tr_path = truth / "trees.csv"
    for p in (st_path, tr_path):
        if not p.is_file():
            raise InputDataError(f"{p}: no such file (the truth of a virtual forest is needed)")
    layouts = {p.name: p for p in layouts_from_settings(st_path)}
    if plot not in layouts:
        raise InputDataError(f"{st_path}: no plot {plot!r} (plots: {sorted(layouts)})")
    trees = read_csv_table(tr_path, "tree table", ("plot", "target", "x", "y", "crown_radius"), ids=("tree_id",))
    trees = trees[trees["plot"] == plot].reset_index(drop=True)
    layout = layouts[plot]
    if set(trees["tree_id"]) != {t.tree_id for t in layout.trees}:
        raise InputDataError(f"{tr_path}: the trees of plot {plot} do not match the regenerated forest")
    ids = None
    if targets_only:
        tg = trees[trees["target"].astype(bool)]
        if tg.empty:
            raise InputDataError(f"{tr_path}: plot {plot} has no target tree")
        dx = trees["x"].to_numpy()[:, None] - tg["x"].to_numpy()[None, :]
        dy = trees["y"].to_numpy()[:, None] - tg["y"].to_numpy()[None, :]
        reach = trees["crown_radius"].to_numpy()[:, None] + tg["crown_radius"].to_numpy()[None, :] + 1.0
        near = (np.hypot(dx, dy) < reach).any(axis=1) | trees["target"].astype(bool).to_numpy()
        ids = trees.loc[near, "tree_id"].astype(int).tolist()
    geoms = generate_plot_trees(layout, tree_ids=ids)
    return geoms, trees


def truth_on_grid(geometries: dict, origin, cell_size: float, shape):
    """True plant area per voxel and the owning tree.

    Returns
    -------
    ijk : ndarray int64 (n, 3)
        Voxels with plant area (inside the grid).
    area : ndarray (n,)
        Total one-sided plant area (m²).
    owner : ndarray int64 (n,)
        Tree id with the largest share.
    """
    from vlsforest.synth.plant_area import true_plant_area

    shape = tuple(int(v) for v in shape)
    keys, areas, tids = [], [], []
    for tid, g in geometries.items():
        pa = true_plant_area(g, origin, cell_size, shape=shape)
        if len(pa.area) == 0:
            continue
        keys.append((pa.ijk[:, 0] * shape[1] + pa.ijk[:, 1]) * shape[2] + pa.ijk[:, 2])
        areas.append(pa.area)
        tids.append(np.full(len(pa.area), tid, np.int64))
    if not keys:
        return np.zeros((0, 3), np.int64), np.zeros(0), np.zeros(0, np.int64)
    key = np.concatenate(keys)
    area = np.concatenate(areas)
    tid = np.concatenate(tids)
    order = np.lexsort((-area, key))  # per voxel, largest share first
    key, area, tid = key[order], area[order], tid[order]
    uk, first = np.unique(key, return_index=True)
    total = np.add.reduceat(area, first)
    owner = tid[first]
    ijk = np.stack([uk // (shape[1] * shape[2]), (uk // shape[2]) % shape[1], uk % shape[2]], axis=1)
    return ijk.astype(np.int64), total, owner


def voxel_table(acc: Accumulators, truth_ijk, truth_area, owner, trees: pd.DataFrame,
                estimators=("transmittance", "fpl_unbiased"), min_pulses: int = 5,
                group_settings: dict | None = None, targets_only: bool = True) -> pd.DataFrame:
    """Per-voxel estimate and truth for the validation population.

    The population is every voxel with true plant area or with plant echoes (owned by a target
    tree when ``targets_only``). Returns one row per voxel with ``i, j, k, tree_id, species,
    group, height_band, rel_height, nb_sampling, true_pad`` and one ``pad_<estimator>`` column
    per estimator.
    """
    from scipy.spatial import cKDTree

    gs = PAD_GROUPS if group_settings is None else group_settings
    shape = np.asarray(acc.shape)
    echo_ijk = np.argwhere(acc.nb_echos > 0)
    k_t = (truth_ijk[:, 0] * shape[1] + truth_ijk[:, 1]) * shape[2] + truth_ijk[:, 2]
    k_e = (echo_ijk[:, 0] * shape[1] + echo_ijk[:, 1]) * shape[2] + echo_ijk[:, 2]
    if len(truth_ijk) == 0:
        raise InputDataError("the truth holds no plant area inside the grid")
    extra = np.flatnonzero(~np.isin(k_e, k_t))
    own_extra = np.zeros(0, np.int64)
    if len(extra):
        # echoes in voxels next to a true voxel (range noise, faces); farther ones belong to
        # trees that were not generated (targets_only) and are left out
        dist, nn = cKDTree(truth_ijk).query(echo_ijk[extra], distance_upper_bound=1.75)
        near = np.isfinite(dist)
        extra, own_extra = extra[near], owner[nn[near]]
    ijk = np.concatenate([truth_ijk, echo_ijk[extra]]).astype(np.int64)
    area = np.concatenate([truth_area, np.zeros(len(extra))])
    own = np.concatenate([owner, own_extra])
    tt = trees.set_index("tree_id")
    missing = sorted(set(np.unique(own)) - set(tt.index))
    if missing:
        raise InputDataError(f"truth: tree id {missing[0]} is not in trees.csv")
    if targets_only:
        keep = tt.loc[own, "target"].to_numpy().astype(bool)
        ijk, area, own = ijk[keep], area[keep], own[keep]
    species = tt.loc[own, "species"].to_numpy()
    groups = np.array([species_group(s) for s in species], dtype=object)
    unknown = sorted(set(groups) - set(gs))
    if unknown:
        raise ConfigError(f"group_settings: no LAD/PADmax for species group(s) {unknown}")
    lad = np.array([gs[g]["lad"] for g in groups], dtype=object)
    pmax = np.array([gs[g]["pad_max"] for g in groups], dtype=float)
    zc = acc.origin[2] + (ijk[:, 2] + 0.5) * acc.cell_size
    zg, h, cbh = (tt.loc[own, c].to_numpy(float) for c in ("z_ground", "height", "cbh"))
    rel = (zc - zg - cbh) / np.maximum(h - cbh, 1e-6)
    band = np.select([rel < 0, rel < 1 / 3, rel < 2 / 3], list(HEIGHT_BANDS[:3]), HEIGHT_BANDS[3])
    df = pd.DataFrame({"i": ijk[:, 0], "j": ijk[:, 1], "k": ijk[:, 2], "tree_id": own, "species": species,
                       "group": groups, "height_band": band, "rel_height": rel,
                       "nb_sampling": acc.nb_sampling[tuple(ijk.T)],
                       "true_pad": area / acc.cell_size ** 3, "pad_max": pmax})
    for est in estimators:
        pad, _ = estimate_pad(acc, lad=lad, pad_max=pmax, estimator=est, min_pulses=min_pulses, ijk=ijk)
        df[f"pad_{est}"] = pad
    return df


def summarize(voxels: pd.DataFrame, plot: str, estimators=("transmittance", "fpl_unbiased"),
              min_shots: int = 20) -> pd.DataFrame:
    """Bias and RMSE per species, estimator and height band (see the module docstring)."""
    rows = []
    for est in estimators:
        col = f"pad_{est}"
        for sp, g in voxels.groupby("species", sort=True):
            for band in HEIGHT_BANDS + ("crown",):
                b = g[g["height_band"] != "below_crown"] if band == "crown" else g[g["height_band"] == band]
                if b.empty:
                    continue
                ok = (b["nb_sampling"] >= min_shots) & np.isfinite(b[col])
                tot_true = float(b["true_pad"].sum())
                under = float(b.loc[b["nb_sampling"] < min_shots, "true_pad"].sum()) / tot_true if tot_true > 0 else np.nan
                v = b[ok]
                n = len(v)
                st = float(v["true_pad"].sum())
                se = float(v[col].sum())
                sc = float(np.minimum(v["true_pad"], v["pad_max"]).sum())
                rows.append({
                    "plot": plot, "species": sp, "estimator": est, "height_band": band, "n_voxels": n,
                    "bias_pct": 100.0 * (se - st) / st if n and st > 0 else np.nan,
                    "rmse": float(np.sqrt(np.mean((v[col] - v["true_pad"]) ** 2))) if n else np.nan,
                    "bias_pct_capped": 100.0 * (se - sc) / sc if n and sc > 0 else np.nan,
                    "mean_true_pad": st / n if n else np.nan,
                    "mean_est_pad": se / n if n else np.nan,
                    "frac_undersampled": under,
                })
    return pd.DataFrame(rows, columns=TABLE_COLUMNS)


def _pool_plots(table: pd.DataFrame) -> pd.DataFrame:
    """One row per species × estimator × height band: voxel-weighted means over plots (RMSE
    pooled as the root of the weighted mean square)."""
    keys = ["species", "estimator", "height_band"]
    if not table.duplicated(keys).any():
        return table
    rows = []
    for key, g in table.groupby(keys, sort=True):
        w = g["n_voxels"].to_numpy(float)
        row = dict(zip(keys, key))
        row["n_voxels"] = int(w.sum())
        for col in ("bias_pct", "frac_undersampled"):
            if col in g:
                v = g[col].to_numpy(float)
                ok = np.isfinite(v) & (w > 0)
                row[col] = float(np.average(v[ok], weights=w[ok])) if ok.any() else np.nan
        v = g["rmse"].to_numpy(float)
        ok = np.isfinite(v) & (w > 0)
        row["rmse"] = float(np.sqrt(np.average(v[ok] ** 2, weights=w[ok]))) if ok.any() else np.nan
        rows.append(row)
    return pd.DataFrame(rows)


def plot_validation(table: pd.DataFrame, path) -> Path:
    """Figure of the validation table: bias, RMSE and under-sampled share by height band."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    plots = ", ".join(sorted(table["plot"].astype(str).unique()))
    table = _pool_plots(table)
    bands = [b for b in ("below_crown", "lower", "middle", "upper", "crown") if b in set(table["height_band"])]
    species = sorted(table["species"].unique())
    ests = sorted(table["estimator"].unique())
    combos = [(sp, e) for sp in species for e in ests]
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5))
    x = np.arange(len(bands))

    def _vals(sub, col):
        sub = sub.set_index("height_band")
        return np.array([float(sub[col].get(b, np.nan)) for b in bands])

    w = 0.8 / max(len(combos), 1)
    for n, (sp, est) in enumerate(combos):
        sub = table[(table["species"] == sp) & (table["estimator"] == est)]
        off = (n - (len(combos) - 1) / 2) * w
        axes[0].bar(x + off, _vals(sub, "bias_pct"), w, label=f"{sp} · {est}")
        axes[1].bar(x + off, _vals(sub, "rmse"), w, label=f"{sp} · {est}")
    w = 0.8 / max(len(species), 1)
    for n, sp in enumerate(species):
        sub = table[(table["species"] == sp) & (table["estimator"] == ests[0])]
        axes[2].bar(x + (n - (len(species) - 1) / 2) * w, 100 * _vals(sub, "frac_undersampled"), w, label=sp)
    titles = ("bias of PAD (%)", "RMSE of PAD (m²/m³)", "true plant area in under-sampled voxels (%)")
    for ax, t in zip(axes, titles):
        ax.set_xticks(x, bands, rotation=20)
        ax.set_title(t)
        ax.grid(axis="y", alpha=0.3)
    axes[0].axhline(0, color="k", lw=0.8)
    for lim in (-10, 10):
        axes[0].axhline(lim, color="grey", lw=0.6, ls="--")
    axes[0].legend(fontsize=7)
    axes[2].legend(fontsize=7)
    fig.suptitle(f"TLS PAD vs virtual truth, plot(s) {plots}")
    fig.tight_layout()
    try:
        save_figure(path, fig, dpi=120, metadata={"Software": None})
    finally:
        plt.close(fig)
    return path


def validate_pad(acc: Accumulators, forest_dir, plot: str, estimators=("transmittance", "fpl_unbiased"),
                 min_pulses: int = 5, min_shots: int = 20, table_path=None, figure_path=None,
                 group_settings: dict | None = None, targets_only: bool = True):
    """Validate the PAD estimates of a plot against its virtual truth.

    Parameters
    ----------
    acc : Accumulators
        The plot's traversal (any grid on the global lattice).
    forest_dir : path
        The recorded virtual forest folder (``truth/`` is read).
    plot : str
    estimators : sequence of str
    min_pulses : int
        Flag threshold of :func:`~vlsforest.pad.estimate_pad`.
    min_shots : int
        Voxels crossed by fewer shots are left out of bias and RMSE (counted in
        ``frac_undersampled``).
    table_path, figure_path : path, optional
        Where to write the CSV table and the PNG figure.
    group_settings : dict, optional
        Species group → ``{"lad": …, "pad_max": …}``; default
        :data:`vlsforest.domain.species.PAD_GROUPS`.
    targets_only : bool
        Validate the voxels of the target trees only (the trees the study models; default).

    Returns
    -------
    table : pandas.DataFrame
        Columns :data:`TABLE_COLUMNS`.
    voxels : pandas.DataFrame
        The per-voxel comparison (:func:`voxel_table`).
    """
    if isinstance(min_shots, bool) or not isinstance(min_shots, (int, np.integer)) or min_shots < 1:
        raise ConfigError(f"min_shots: must be an integer ≥ 1, got {min_shots!r}")
    geoms, trees = load_truth_geometries(forest_dir, plot, targets_only=targets_only)
    t_ijk, t_area, owner = truth_on_grid(geoms, acc.origin, acc.cell_size, acc.shape)
    del geoms
    voxels = voxel_table(acc, t_ijk, t_area, owner, trees, estimators, min_pulses, group_settings, targets_only)
    table = summarize(voxels, plot, estimators, min_shots)
    if table_path is not None:
        table_path = Path(table_path)
        write_csv(table_path, table, index=False, float_format="%.6f", na_rep="NaN", lineterminator="\n")
    if figure_path is not None:
        plot_validation(table, figure_path)
    return table, voxels


def median_abs_bias(table: pd.DataFrame, column: str = "bias_pct") -> pd.Series:
    """Median |bias| per estimator over the species × crown-band rows (lower, middle, upper)."""
    t = table[table["height_band"].isin(["lower", "middle", "upper"])].dropna(subset=[column])
    return t.groupby("estimator")[column].apply(lambda b: float(np.median(np.abs(b))))


__all__ = ["TABLE_COLUMNS", "HEIGHT_BANDS", "load_truth_geometries", "truth_on_grid",
           "voxel_table", "summarize", "plot_validation", "validate_pad", "median_abs_bias"]
