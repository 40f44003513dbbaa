"""``vlsforest stats``: every comparison, written to its files."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

from vlsforest.errors import ConfigError
from vlsforest.io.atomic import write_text
from vlsforest.stats.errors import compute_errors, summarize_errors
from vlsforest.stats.findings import evaluate_findings, findings_markdown, findings_table
from vlsforest.stats.roles import StudyRoles
from vlsforest.stats.significance import multireturn_ttest, paired_tests
from vlsforest.stats.table5 import table5
from vlsforest.stats.tables import load_metrics, load_sim_times, load_voxel_counts, write_table

__all__ = ["STATS_FILES", "stats_outputs", "write_stats"]

#: the files of ``vlsforest stats``: key → file name inside an output folder
STATS_FILES = {
    "errors": "errors.csv",
    "summary_by_species": "summary_by_species.csv",
    "tests": "tests.csv",
    "multireturn_ttest": "multireturn_ttest.csv",
    "table5": "table5.csv",
    "findings": "findings.md",
    "findings_table": "findings.csv",
}


def stats_outputs(outputs) -> dict:
    """The output file of each key of :data:`STATS_FILES`.

    Parameters
    ----------
    outputs : str, Path or mapping
        A folder (the files get the names of :data:`STATS_FILES` inside it) or a mapping of
        every key of :data:`STATS_FILES` to its file.

    Returns
    -------
    dict of str to Path

    Raises
    ------
    ConfigError
        A mapping that misses a key or has an unknown one.
    """
    if isinstance(outputs, Mapping):
        missing = [k for k in STATS_FILES if k not in outputs]
        unknown = [k for k in outputs if k not in STATS_FILES]
        if missing or unknown:
            raise ConfigError(f"stats outputs: missing {missing}, unknown {unknown} (keys: {', '.join(STATS_FILES)})")
        return {k: Path(outputs[k]) for k in STATS_FILES}
    return {k: Path(outputs) / name for k, name in STATS_FILES.items()}


def write_stats(metrics_path, voxel_counts_path, sim_times_path, outputs, *, seed: int = 0,
                n_boot: int = 2000, roles: StudyRoles | None = None, experiments: Mapping | None = None) -> dict:
    """Run every comparison and write the files of ``vlsforest stats``.

    Parameters
    ----------
    metrics_path, voxel_counts_path, sim_times_path : str or Path
        The input tables (see the module docstring).
    outputs : str, Path or mapping
        Where the files go: a folder, or a mapping of every key of :data:`STATS_FILES` to its
        file (:func:`stats_outputs`); parent folders are created.
    seed : int
        Bootstrap seed.
    n_boot : int
        Bootstrap resamples.
    roles : StudyRoles, optional
        The parts the run's methods and scenarios play (display order and the findings); without
        it every finding is "not testable".
    experiments : mapping, optional
        Experiment name → its result, for the findings' causes.

    Returns
    -------
    dict of str to Path
        Each key of :data:`STATS_FILES` → the file written.
    """
    files = stats_outputs(outputs)
    metrics = load_metrics(metrics_path)
    vc = load_voxel_counts(voxel_counts_path)
    st = load_sim_times(sim_times_path)
    roles = roles or StudyRoles()
    order = {"methods": roles.method_names, "scenarios": roles.scenario_names}
    errors = compute_errors(metrics, source=str(metrics_path), **order)
    summary = summarize_errors(errors, n_boot=n_boot, seed=seed)
    tests = paired_tests(errors)
    mr = multireturn_ttest(metrics, source=str(metrics_path), **order)
    t5 = table5(errors, vc, st, sources=(str(metrics_path), str(voxel_counts_path), str(sim_times_path)))
    findings = evaluate_findings(errors, tests, mr, t5, vc, roles, seed=seed, experiments=experiments)
    paths = {
        "errors": write_table(errors, files["errors"]),
        "summary_by_species": write_table(summary, files["summary_by_species"]),
        "tests": write_table(tests, files["tests"]),
        "multireturn_ttest": write_table(mr, files["multireturn_ttest"]),
        "table5": write_table(t5, files["table5"]),
        "findings_table": write_table(findings_table(findings), files["findings_table"]),
    }
    write_text(files["findings"], findings_markdown(findings))
    paths["findings"] = files["findings"]
    return paths
