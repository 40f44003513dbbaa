"""A finished run's plots simulated again, the target trees measured as the run measures them.

The experiments that change one thing and simulate again (the CoG shift's parts,
:mod:`vlsforest.experiments.cog_parts`; another seed, :mod:`vlsforest.experiments.reseed`)
share this: the arguments every such experiment checks (:func:`check_simulation`), a plot's
site and surveys from the run's manifest (:func:`plot_surveys`), the run's own metrics
(:func:`run_metrics`) and one simulation's target metrics (:func:`simulated_metrics`), taken as
the run takes them: the returns are written as LAS, the targets' points taken by their object
ids (:func:`vlsforest.extract.simulated_targets`), written and read again, and measured by
:func:`vlsforest.metrics.cloud_metrics` above each target's ground height, with the digits of
the run's metrics tables (:data:`vlsforest.metrics.FLOAT_FORMAT`).

Their ``run_…`` functions take these common arguments:

manifest : mapping
    The run's files by plot (:mod:`vlsforest.experiments.run_outputs`), each plot also with
    ``site`` (its ``site.json``) and ``surveys`` (scenario → SURVEY.yaml), and the method whose
    scene is simulated with ``scene`` (the folder of its SCENE.yaml).
scenarios : sequence of str
    The scenarios simulated.
seeds : mapping
    Scenario → the seed its simulations ran with.
margin_m : float
    The simulation region's margin around the targets (the run's ``simulation.region_margin_m``).
tmp_dir : path
    Folder for each simulation's temporary files (removed at the end).
workers : int, optional
    Simulation worker processes (the result does not depend on it).
progress : callable, optional
    Called with a line per simulation.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

from vlsforest.errors import ConfigError
from vlsforest.extract import simulated_targets
from vlsforest.io.atomic import flush
from vlsforest.io.csvfile import read_csv_table
from vlsforest.io.las import read_las, write_las
from vlsforest.metrics import FLOAT_FORMAT, cloud_metrics

__all__ = ["check_simulation", "plot_surveys", "run_metrics", "simulated_metrics"]


def check_simulation(scenarios: Sequence[str], seeds: Mapping, margin_m) -> None:
    """Check an experiment's scenarios, their seeds and the region margin.

    Raises
    ------
    ConfigError
        Naming the option (``--scenarios``, ``--seeds-json``, ``--region-margin``) when no scenario
        is named, a scenario has no seed, a seed is not an integer ≥ 0 or the margin is negative.
    """
    if not scenarios:
        raise ConfigError("--scenarios: at least one scenario")
    if isinstance(margin_m, bool) or not (isinstance(margin_m, (int, float)) and margin_m >= 0):
        raise ConfigError(f"--region-margin: must be ≥ 0 (m), got {margin_m!r}")
    missing = [sc for sc in scenarios if sc not in seeds]
    if missing:
        raise ConfigError(f"--seeds-json: no seed for {', '.join(missing)}")
    bad = [sc for sc in scenarios if isinstance(seeds[sc], bool) or not isinstance(seeds[sc], int) or seeds[sc] < 0]
    if bad:
        raise ConfigError(f"--seeds-json: the seed of {', '.join(bad)} must be an integer ≥ 0")


def plot_surveys(plot: str, entry: Mapping, scenarios: Sequence[str]) -> tuple[str, dict]:
    """A plot's ``site`` (its ``site.json``) and ``surveys`` (scenario → SURVEY.yaml) from its
    manifest entry.

    Raises
    ------
    ConfigError
        When the entry lacks the site or the survey of one of ``scenarios``.
    """
    site = entry.get("site")
    surveys = entry.get("surveys") or {}
    if not isinstance(site, str) or not isinstance(surveys, Mapping) or any(
            not isinstance(surveys.get(sc), str) for sc in scenarios):
        raise ConfigError(f"--inputs-json: plot {plot!r} needs its 'site' and a 'surveys' path per scenario")
    return site, {sc: surveys[sc] for sc in scenarios}


def run_metrics(path: str, metrics: Sequence[str]) -> dict:
    """A run's metrics table: target id → metric → value."""
    df = read_csv_table(path, "metrics table", tuple(metrics), ids=("tree_id",))
    return {int(r["tree_id"]): {m: float(r[m]) for m in metrics} for _, r in df.iterrows()}


def simulated_metrics(scene, survey, seed: int, region, targets, tmp: Path, metrics: Sequence[str],
                      workers: int | None = 1) -> dict:
    """The target trees' metrics of one simulation, taken as the run takes them.

    Parameters
    ----------
    scene, survey
        What :func:`vlsforest.sim.simulate_to_las` simulates.
    seed : int
        The simulation's seed.
    region : tuple or None
        The simulated region (:func:`vlsforest.sim.scene_file.targets_region`).
    targets : list of vlsforest.experiments.run_outputs.Target
        The plot's target trees.
    tmp : Path
        An empty folder for the simulated and the target clouds.
    metrics : sequence of str
        The metrics kept.
    workers : int, optional
        Simulation worker processes (the result does not depend on it).

    Returns
    -------
    dict
        Target id → metric → value, as the run's metrics tables hold it.
    """
    from vlsforest.sim import simulate_to_las

    sim = Path(tmp) / "sim.laz"
    simulate_to_las(scene, survey, sim, seed=seed, workers=workers, region=region)
    flush()  # a command's outputs are installed at its end: these temporary files are read back at once
    cloud = read_las(sim, allow_empty=True, require=("object_id",))
    seg_to_target = {t.segment_id: t.target_id for t in targets}
    keep, target = simulated_targets(cloud, seg_to_target)
    trees = Path(tmp) / "trees.laz"
    write_las(trees, cloud.subset(keep), extra={"tree_id": target})
    flush()
    df = cloud_metrics(read_las(trees, allow_empty=True), "tree_id", ground_z={t.target_id: t.ground_z for t in targets},
                       tree_ids=sorted(seg_to_target.values()), source=str(trees))
    # as the run's metrics tables hold them
    return {int(r["tree_id"]): {m: float(FLOAT_FORMAT % r[m]) for m in metrics} for _, r in df.iterrows()}
