"""Comparison of simulated and reference tree metrics (Weiser et al. 2021, Sections 3–4).

The modules, in the order the analysis runs:

* :mod:`~vlsforest.stats.tables` — table names, display order, reading and checking;
* :mod:`~vlsforest.stats.errors` — per-tree errors (simulated − reference) and their summaries
  with bootstrap intervals;
* :mod:`~vlsforest.stats.significance` — paired tests and the conifer-vs-broadleaf t-test;
* :mod:`~vlsforest.stats.table5` — Table 5 as numbers;
* :mod:`~vlsforest.stats.roles` — which configured method and scenario plays which part of
  the study;
* :mod:`~vlsforest.stats.claims` — what the paper states and the tolerances its own words give;
* :mod:`~vlsforest.stats.findings` — each finding judged, with its tolerance, cause and
  experiment;
* :mod:`~vlsforest.stats.run` — :func:`write_stats`, the files of ``vlsforest stats``.

The names below are the public API; each lives in the module named beside it in the
documentation.
"""

from vlsforest.stats.errors import block_rng, bootstrap_mean_ci, compute_errors, summarize_errors
from vlsforest.stats.findings import evaluate_findings, findings_markdown, findings_table
from vlsforest.stats.roles import MethodRole, StudyRoles
from vlsforest.stats.run import STATS_FILES, stats_outputs, write_stats
from vlsforest.stats.significance import multireturn_ttest, paired_difference, paired_tests
from vlsforest.stats.table5 import penetration_class, table5
from vlsforest.stats.tables import (
    FLOAT_FORMAT,
    GROUP_ORDER,
    ID_COLUMNS,
    OTHER_GROUP,
    REFERENCE,
    check_columns,
    check_errors,
    group_of,
    load_metrics,
    load_sim_times,
    load_voxel_counts,
    method_order,
    prepare_metrics,
    read_table,
    scenario_order,
    species_order,
)

__all__ = [
    "REFERENCE",
    "OTHER_GROUP",
    "GROUP_ORDER",
    "ID_COLUMNS",
    "FLOAT_FORMAT",
    "group_of",
    "method_order",
    "scenario_order",
    "species_order",
    "read_table",
    "check_columns",
    "prepare_metrics",
    "check_errors",
    "block_rng",
    "bootstrap_mean_ci",
    "load_metrics",
    "load_voxel_counts",
    "load_sim_times",
    "compute_errors",
    "summarize_errors",
    "paired_difference",
    "paired_tests",
    "multireturn_ttest",
    "penetration_class",
    "table5",
    "MethodRole",
    "StudyRoles",
    "evaluate_findings",
    "findings_markdown",
    "findings_table",
    "STATS_FILES",
    "stats_outputs",
    "write_stats",
]
