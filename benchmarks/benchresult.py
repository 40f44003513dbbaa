"""Machine-readable results of the benchmarks: one JSON row per run under benchmarks/results/.

Every benchmark ends with ``raise SystemExit(benchresult.run("<name>", main))``. :func:`run` runs
the benchmark's ``main``, shows its output as usual and appends one row to
``benchmarks/results/<name>.jsonl`` (``--results-dir`` or ``VLSFOREST_BENCH_RESULTS`` elsewhere):

- ``benchmark``, ``date`` (UTC, ISO 8601), ``command`` (as typed), ``exit_code``, ``seconds``;
- ``commit``: ``git describe --always --dirty`` of the repository (None outside a checkout);
- ``machine``: host name, OS, CPU model, logical CPUs, memory, Python and NumPy versions;
- ``results``: the values the benchmark passed to :func:`record` (seconds, rates, peak memory …);
- ``output``: the lines it printed.

A run that ends with exit code 2 (a usage error: bad arguments, missing input) appends no row,
nor does a run that only printed its help (``-h``, ``--help`` or an abbreviation of it):
neither measured anything.

Standard library only, so that it adds nothing to what a benchmark imports.
"""

from __future__ import annotations

import contextvars
import datetime as _dt
import io
import json
import os
import platform
import shlex
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
#: where rows go unless VLSFOREST_BENCH_RESULTS names another folder
RESULTS_DIR = REPO / "benchmarks" / "results"

#: the exit code of a usage error (argparse's, and bad input named in one line): no row is written
USAGE_ERROR = 2

_current: contextvars.ContextVar[dict | None] = contextvars.ContextVar("benchmark_results", default=None)


def record(**values) -> None:
    """Add named results (JSON-serialisable numbers, strings, lists, dicts) to the running
    benchmark's row; outside :func:`run` nothing happens."""
    row = _current.get()
    if row is not None:
        row.update(values)


def commit() -> str | None:
    """``git describe --always --dirty`` of the repository, or None."""
    try:
        out = subprocess.run(["git", "-C", str(REPO), "describe", "--always", "--dirty"], capture_output=True,
                             text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() or None if out.returncode == 0 else None


def machine() -> dict:
    """What the numbers were measured on."""
    cpu = platform.processor() or None
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem_gb = None
    try:
        mem_gb = round(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 1e9, 1)
    except (ValueError, OSError, AttributeError):
        pass
    try:
        import numpy

        np_version = numpy.__version__
    except ImportError:
        np_version = None
    return {"host": platform.node(), "os": platform.platform(), "cpu": cpu, "cpus": os.cpu_count(),
            "memory_gb": mem_gb, "python": platform.python_version(), "numpy": np_version}


class _Tee(io.TextIOBase):
    """Writes to the real stream and keeps a copy."""

    def __init__(self, stream):
        self.stream, self.copy = stream, io.StringIO()

    def write(self, text):
        self.copy.write(text)
        return self.stream.write(text)

    def flush(self):
        self.stream.flush()


def run(name: str, main, argv: list[str] | None = None, results_dir: Path | str | None = None) -> int:
    """Run ``main(argv)`` and append its row to ``<results_dir>/<name>.jsonl``; return its exit code.

    Parameters
    ----------
    name : str
        The benchmark's name (the results file's stem).
    main : callable
        The benchmark's ``main(argv) -> int``.
    argv : list of str, optional
        Arguments (default ``sys.argv[1:]``).
    results_dir : path-like, optional
        Folder of the results file (default ``VLSFOREST_BENCH_RESULTS`` or :data:`RESULTS_DIR`).

    Returns
    -------
    int
        The benchmark's exit code (a ``SystemExit`` it raised counts as its code); with
        :data:`USAGE_ERROR`, or ``-h``/``--help`` among the arguments, no row is appended.
    """
    argv = sys.argv[1:] if argv is None else list(argv)
    folder = Path(results_dir or os.environ.get("VLSFOREST_BENCH_RESULTS") or RESULTS_DIR)
    row = {"benchmark": name, "date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
           "command": shlex.join(["python", f"benchmarks/{name}.py", *argv]),
           "commit": commit(), "machine": machine()}
    results: dict = {}
    token = _current.set(results)
    tee, stdout = _Tee(sys.stdout), sys.stdout
    sys.stdout = tee
    t0 = time.perf_counter()
    try:
        rc = main(argv)
    except SystemExit as exc:
        rc = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        if not isinstance(exc.code, int) and exc.code is not None:
            print(exc.code, file=sys.stderr)
    finally:
        sys.stdout = stdout
        _current.reset(token)
    row.update(exit_code=int(rc or 0), seconds=round(time.perf_counter() - t0, 3), results=results,
               output=tee.copy.getvalue().splitlines())
    if row["exit_code"] == USAGE_ERROR:
        return USAGE_ERROR
    asked_help = {"-h", "--help"} & set(argv) or (
        not results and row["output"][:1] and row["output"][0].startswith("usage:"))
    if asked_help and row["exit_code"] == 0:
        return 0
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{name}.jsonl"
    with path.open("a") as fh:
        fh.write(json.dumps(row, default=_jsonable) + "\n")
    print(f"result row appended to {path}", file=sys.stderr)
    return int(rc or 0)


def _jsonable(value):
    """numpy scalars and arrays, paths → plain JSON values."""
    if hasattr(value, "tolist"):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    return str(value)
