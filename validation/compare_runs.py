"""Validation: two runs of the workflow give the same bytes (timing files aside).

Compares every file under two ``results/`` folders: a run of one revision against a run of
another (a restructuring must not change a result), or a run against itself (determinism). Files
whose bytes may differ between runs of the same code are left out and listed:
:data:`TIMING_FILES` (wall-clock times) and the figures and tables that carry them
(:data:`TIMING_DERIVED`); ``--expect-changed`` names further files the compared revisions change
on purpose (e.g. the statistics when only they changed).

Prints the files that differ or exist on one side only, and appends one JSON row to ``--out``
(default ``validation/results/compare_runs.jsonl``): date, both folders and their revisions
(``git describe`` of each folder's checkout), the command, the numbers of files compared, equal,
different and one-sided, and their names. Exit 1 when a file differs that is not expected to.

    python validation/compare_runs.py RUN_A/results RUN_B/results [--expect-changed summary/stats/*]
"""

from __future__ import annotations

import argparse
import datetime as dt
import fnmatch
import json
import platform
import shlex
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
#: the comparisons' results (one JSON row per comparison)
RESULTS = REPO / "validation" / "results" / "compare_runs.jsonl"
#: wall-clock times: differ between any two runs
TIMING_FILES = ("*/timing.json", "summary/sim_times.csv")
#: outputs that carry wall-clock times (Table 5's seconds columns)
TIMING_DERIVED = ("summary/stats/table5.csv",)


def revision(folder: Path) -> str | None:
    """``git describe --always --dirty`` of the checkout that holds ``folder``, or None."""
    try:
        out = subprocess.run(["git", "-C", str(folder), "describe", "--always", "--dirty"], capture_output=True,
                             text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() or None if out.returncode == 0 else None


def files_of(root: Path) -> set[str]:
    """Relative paths (POSIX) of every file under ``root``, hidden ones included."""
    return {p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file()}


def compare(a: Path, b: Path, skip=(), expect=()) -> dict:
    """Compare two results folders byte for byte.

    Parameters
    ----------
    a, b : Path
        The two ``results/`` folders.
    skip : sequence of str
        Glob patterns (relative paths) left out of the comparison.
    expect : sequence of str
        Glob patterns of files that may differ.

    Returns
    -------
    dict
        ``compared``, ``equal`` (counts), ``different``, ``expected_different``, ``only_a``,
        ``only_b``, ``skipped`` (sorted names).
    """
    def match(name, pats):
        return any(fnmatch.fnmatch(name, p) for p in pats)

    fa, fb = files_of(a), files_of(b)
    skipped = sorted(n for n in fa | fb if match(n, skip))
    common = sorted((fa & fb) - set(skipped))
    diff = [n for n in common if (a / n).read_bytes() != (b / n).read_bytes()]
    return {"compared": len(common), "equal": len(common) - len(diff),
            "different": [n for n in diff if not match(n, expect)],
            "expected_different": [n for n in diff if match(n, expect)],
            "only_a": sorted(fa - fb - set(skipped)), "only_b": sorted(fb - fa - set(skipped)),
            "skipped": skipped}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="compare_runs", description=__doc__.split("\n\n")[0])
    ap.add_argument("a", type=Path, help="results/ folder of the first run")
    ap.add_argument("b", type=Path, help="results/ folder of the second run")
    ap.add_argument("--expect-changed", nargs="*", default=[], metavar="GLOB",
                    help="files the compared revisions change on purpose")
    ap.add_argument("--out", type=Path, default=RESULTS, help="results file (JSON Lines)")
    args = ap.parse_args(argv)
    for p in (args.a, args.b):
        if not p.is_dir():
            print(f"compare_runs: error: {p}: no such folder", file=sys.stderr)
            return 2
    res = compare(args.a, args.b, skip=TIMING_FILES + TIMING_DERIVED, expect=args.expect_changed)
    row = {"date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
           "command": shlex.join(["python", "validation/compare_runs.py", *(argv if argv is not None else sys.argv[1:])]),
           "machine": {"host": platform.node(), "os": platform.platform()},
           "a": {"folder": str(args.a), "revision": revision(args.a)},
           "b": {"folder": str(args.b), "revision": revision(args.b)}, **res}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with open(args.out, "a", encoding="utf-8") as fh:
        fh.write(json.dumps(row, sort_keys=True) + "\n")
    print(f"compare_runs: {res['compared']} files compared, {res['equal']} equal, "
          f"{len(res['different'])} different, {len(res['expected_different'])} expected to differ, "
          f"{len(res['only_a'])} only in A, {len(res['only_b'])} only in B")
    for n in res["different"]:
        print(f"  differs: {n}")
    for n in res["only_a"]:
        print(f"  only in A: {n}")
    for n in res["only_b"]:
        print(f"  only in B: {n}")
    return 1 if res["different"] or res["only_a"] else 0


if __name__ == "__main__":
    sys.exit(main())
