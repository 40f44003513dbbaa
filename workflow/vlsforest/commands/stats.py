"""``vlsforest stats``: simulated vs reference comparison tables and ``findings.md``.

``vlsforest stats --metrics tree_metrics.csv --voxel-counts voxel_counts.csv --sim-times
sim_times.csv --study-json JSON (-o OUTDIR | --out-errors CSV --out-summary CSV --out-tests CSV
--out-multireturn CSV --out-table5 CSV --out-findings MD --out-findings-table CSV)
[--experiment NAME=JSON ...] [--seed N] [--n-boot 2000]`` writes the error table, the summary by
species, the tests, the multiple-return t-test, Table 5 and the findings (see
:mod:`vlsforest.stats`): each to its ``--out-…`` file, or with ``-o`` under the names of
:data:`vlsforest.stats.STATS_FILES` in OUTDIR. ``--study-json`` holds the configuration's
``methods`` and ``scenarios`` blocks (``{"methods": {…}, "scenarios": {…}}``): the display order
and the part each plays in the study's findings (:mod:`vlsforest.stats.roles`); without it every
finding is "not testable". Same inputs and seed give the same bytes.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from vlsforest.commands import FOLDER, declare_outputs
from vlsforest.errors import ConfigError, InputDataError


#: (key of vlsforest.stats.STATS_FILES, option, what the file holds)
OUT_OPTIONS = (
    ("errors", "--out-errors", "per tree × method × scenario × metric error table (CSV)"),
    ("summary_by_species", "--out-summary", "summary by species with bootstrap CIs (CSV)"),
    ("tests", "--out-tests", "paired tests (CSV)"),
    ("multireturn_ttest", "--out-multireturn", "conifer-vs-broadleaf multiple-return t-test (CSV)"),
    ("table5", "--out-table5", "Table 5 as numbers (CSV)"),
    ("findings", "--out-findings", "findings (Markdown)"),
    ("findings_table", "--out-findings-table", "findings as a table (CSV)"),
)


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``stats`` sub-command to ``subparsers``."""
    p = subparsers.add_parser(
        "stats",
        help="compare simulated with reference tree metrics (errors, summaries, tests, Table 5, findings)",
        description=(
            "Per tree × method × scenario errors of every metric (simulated − reference), summaries "
            "by species with bootstrap CIs, paired t / Wilcoxon tests, the conifer-vs-broadleaf "
            "multiple-return t-test, Table 5 as numbers and findings.md (Weiser et al. 2021)."
        ),
    )
    p.add_argument("--metrics", required=True, type=Path, metavar="CSV", help="tree_metrics.csv")
    p.add_argument("--voxel-counts", required=True, type=Path, metavar="CSV", help="voxel_counts.csv")
    p.add_argument("--sim-times", required=True, type=Path, metavar="CSV", help="sim_times.csv")
    p.add_argument("-o", "--output", type=Path, metavar="OUTDIR",
                   help="output folder: the files not named by an --out-… option go there, under their standard names")
    for key, option, what in OUT_OPTIONS:
        p.add_argument(option, type=Path, dest=f"out_{key}", metavar="FILE", help=f"where the {what} goes")
    p.add_argument("--study-json", metavar="JSON",
                   help='the configuration\'s methods and scenarios: {"methods": {...}, "scenarios": {...}}')
    p.add_argument("--experiment", action="append", default=[], metavar="NAME=JSON",
                   help="an experiment's result file for the findings' causes (e.g. tls_step=results/experiments/tls_step.json)")
    p.add_argument("--seed", type=int, default=0, help="bootstrap seed (default 0)")
    p.add_argument("--n-boot", type=int, default=2000, help="bootstrap resamples (default 2000, at least 100)")
    p.set_defaults(func=run)
    declare_outputs(p, output=FOLDER, **{f"out_{key}": None for key, _, _ in OUT_OPTIONS})
    return p


def run(args) -> int:
    """Execute ``vlsforest stats`` with parsed ``args``; return 0."""
    from vlsforest.stats import STATS_FILES, StudyRoles, write_stats

    if args.n_boot < 100:
        raise ConfigError(f"--n-boot: must be at least 100, got {args.n_boot}")
    if args.seed < 0:
        raise ConfigError(f"--seed: must be ≥ 0, got {args.seed}")
    outputs = {}
    for key, option, _ in OUT_OPTIONS:
        path = getattr(args, f"out_{key}")
        if path is None and args.output is None:
            raise ConfigError(f"{option}: missing (or give -o OUTDIR)")
        outputs[key] = path if path is not None else args.output / STATS_FILES[key]
    roles = StudyRoles()
    if args.study_json is not None:
        study = _json_arg(args.study_json, "--study-json")
        if not isinstance(study, dict) or set(study) - {"methods", "scenarios"}:
            raise ConfigError('--study-json: must be a JSON object with keys "methods" and "scenarios"')
        roles = StudyRoles.from_config(study.get("methods"), study.get("scenarios"))
    experiments = {}
    for item in args.experiment:
        name, sep, path = item.partition("=")
        if not sep or not name or not path:
            raise ConfigError(f"--experiment: expected NAME=FILE, got {item!r}")
        experiments[name] = _read_json(Path(path), f"--experiment {name}")
    paths = write_stats(args.metrics, args.voxel_counts, args.sim_times, outputs,
                        seed=args.seed, n_boot=args.n_boot, roles=roles, experiments=experiments)
    print(f"vlsforest stats: {len(paths)} files -> {', '.join(str(p) for p in paths.values())}")
    return 0


def _json_arg(text: str, option: str):
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise ConfigError(f"{option}: not valid JSON ({exc.msg})") from None


def _read_json(path: Path, what: str):
    if not path.is_file():
        raise InputDataError(f"{path}: no such file ({what})")
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputDataError(f"{path}: not a JSON file ({exc})") from None
