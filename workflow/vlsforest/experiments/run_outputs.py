"""The files of a finished run that the analysis experiments read, named by a manifest.

The crown-outline and shift-room experiments compute nothing new with the simulator: they take
the run's target trees, voxel models, simulated and reference tree clouds and metrics apart.
The workflow names every file it hands them in one JSON manifest (the library never builds a
workflow path itself)::

    {"P1": {"targets": "results/P1/targets.csv",
            "reference": {"als": "results/P1/reference/als/trees.laz", ...},
            "methods": {"fixed_0.25": {"voxels": "results/P1/fixed_0.25/voxels.npz",
                                        "trees": {"als": "results/P1/fixed_0.25/als/trees.laz", ...},
                                        "metrics": {"als": "results/P1/fixed_0.25/als/metrics.csv", ...}},
                        ...}},
     ...}

A plot's ``targets`` table gives each target's id (the ``tree_id`` of the tree clouds and
metrics), its segment id (``tree_id`` there; the owner of its cubes in the voxel model), its
species group and its ground height ``z``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from vlsforest.errors import ConfigError
from vlsforest.io.csvfile import read_height_table

__all__ = ["Target", "plot_files", "targets", "method_files", "cloud_points", "mean_se"]


@dataclass(frozen=True)
class Target:
    """One target tree of a plot, as its ``targets.csv`` row gives it."""

    plot: str
    target_id: int
    segment_id: int
    group: str
    ground_z: float


def plot_files(manifest, option: str = "manifest") -> dict:
    """The manifest's plots, checked for shape: plot → its entry (``targets``, ``methods``, …).

    Raises
    ------
    ConfigError
        When the manifest is not a mapping of plots to mappings with a ``targets`` path.
    """
    if not isinstance(manifest, Mapping) or not manifest:
        raise ConfigError(f"{option}: must map plot names to their files")
    for plot, entry in manifest.items():
        if not isinstance(entry, Mapping) or not isinstance(entry.get("targets"), str):
            raise ConfigError(f"{option}: plot {plot!r} needs a 'targets' path")
    return dict(manifest)


def targets(plot: str, entry: Mapping) -> list[Target]:
    """The plot's target trees from its ``targets`` table (in its row order)."""
    t = read_height_table(entry["targets"], "targets table", ids=("target_id", "tree_id"), columns=("group",))
    return [Target(plot, int(r.target_id), int(r.tree_id), str(r.group), float(r.z)) for r in t.itertuples()]


def method_files(plot: str, entry: Mapping, method: str, kind: str, scenario: str | None = None,
                 option: str = "manifest") -> str:
    """The path of one of a method's files: ``kind`` ``voxels``, or ``trees``/``metrics`` of a scenario.

    Raises
    ------
    ConfigError
        When the manifest does not name that file.
    """
    m = (entry.get("methods") or {}).get(method)
    value = None if not isinstance(m, Mapping) else m.get(kind)
    if scenario is not None:
        value = value.get(scenario) if isinstance(value, Mapping) else None
    if not isinstance(value, str):
        what = f"{method} {kind}" + (f" of scenario {scenario}" if scenario else "")
        raise ConfigError(f"{option}: plot {plot!r} does not name the {what}")
    return value


def cloud_points(cloud, target_id: int) -> np.ndarray:
    """A tree's points (n, 3) in a labelled tree cloud."""
    return cloud.xyz[np.asarray(cloud.attrs["tree_id"]).astype(np.int64) == int(target_id)]


def mean_se(values) -> dict:
    """Mean, standard error (ddof 1; NaN for fewer than 2) and count of the finite values."""
    v = np.asarray([x for x in values if np.isfinite(x)], np.float64)
    n = len(v)
    return {"mean": float(v.mean()) if n else float("nan"),
            "se": float(v.std(ddof=1) / np.sqrt(n)) if n > 1 else float("nan"), "n": n}
