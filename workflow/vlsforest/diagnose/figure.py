"""Figure of a diagnosis: standardised mean residual per observable, before and after the fit."""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np

from vlsforest.io.atomic import save_figure

def plot_diagnosis(rep: dict, path) -> Path:
    """Bar chart of real − simulated per observable (before / after the accepted effects, the
    latter on held-out trees: each fold simulated with the values fitted without it).

    Each observable's mean residual is divided by its across-tree SD before the fit (a
    standardised effect size, so that every unit fits one axis).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    before, after, sd = rep["residual_before"], rep["residual_after"], rep.get("residual_sd") or {}
    names = [k for k, v in before.items() if v is not None and sd.get(k)]
    b = np.array([before[k] / sd[k] for k in names], float)
    a = np.array([(after[k] / sd[k]) if after.get(k) is not None else np.nan for k in names])
    fig, ax = plt.subplots(figsize=(8, 0.28 * len(names) + 1.6), dpi=110)
    y = np.arange(len(names))
    ax.barh(y - 0.2, b, height=0.4, color="#bbbbbb", label="simulation as given")
    ax.barh(y + 0.2, a, height=0.4, color="#2a7fb8",
            label=("with " + " + ".join(rep["accepted"]) + " (held-out trees)") if rep["accepted"]
            else "no accepted effect")
    mism = {m["metric"] for m in rep["mismatches"]}
    ax.set_yticks(y, [("* " if n in mism else "") + n for n in names], fontsize=7)
    ax.axvline(0, color="k", lw=0.8)
    ax.set_xlabel("mean residual (real − simulated) / across-tree SD   (* = significant, BH q < 0.05)")
    ax.set_title(textwrap.fill(f"{rep['scenario'].upper()}: {rep['verdict']}", 90), fontsize=9)
    ax.invert_yaxis()
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    path = Path(path)
    try:
        save_figure(path, fig, metadata={"Software": None})
    finally:
        plt.close(fig)
    return path
