"""``vlsforest stats``: simulated vs reference comparison tables and ``findings.md``.

``vlsforest stats --metrics tree_metrics.csv --voxel-counts voxel_counts.csv --sim-times
sim_times.csv -o OUTDIR [--seed N] [--n-boot 2000]`` writes ``errors.csv``,
``summary_by_species.csv``, ``tests.csv``, ``multireturn_ttest.csv``, ``table5.csv`` and
``findings.md`` (see :mod:`vlsforest.stats`). Same inputs and seed give the same bytes.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from vlsforest.errors import ConfigError


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
    p.add_argument("-o", "--output", required=True, type=Path, metavar="OUTDIR", help="output folder")
    p.add_argument("--seed", type=int, default=0, help="bootstrap seed (default 0)")
    p.add_argument("--n-boot", type=int, default=2000, help="bootstrap resamples (default 2000, at least 100)")
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    """Execute ``vlsforest stats`` with parsed ``args``; return 0."""
    from vlsforest.stats import write_stats

    if args.n_boot < 100:
        raise ConfigError(f"--n-boot: must be at least 100, got {args.n_boot}")
    if args.seed < 0:
        raise ConfigError(f"--seed: must be ≥ 0, got {args.seed}")
    paths = write_stats(args.metrics, args.voxel_counts, args.sim_times, args.output,
                        seed=args.seed, n_boot=args.n_boot)
    print(f"vlsforest stats: {len(paths)} files -> {args.output}")
    return 0
