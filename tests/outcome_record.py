"""pytest plugin: the outcome of every test of a run, written as JSON rows at the end of the run.

``scripts/run-slow-tests.sh`` runs the slow tests with it::

    PYTHONPATH=tests python -m pytest -p outcome_record --record-outcomes FILE -m slow

``FILE`` (JSON Lines) is replaced at the end of each run that ran at least one test, so it holds
the last run only (git keeps the earlier ones). One row per test, in the order they ran:

- ``date`` (UTC, ISO 8601, when the run started), ``commit`` (``git describe --always --dirty``),
  ``machine`` (host, OS, CPU, CPUs, memory, Python, NumPy), ``command`` (the pytest command line, after the
  ``VLSFOREST_DEFAULT_RESULTS`` setting where one is given),
  ``exit_code`` (the run's) — the provenance fields of ``benchmarks/benchresult.py``;
- ``test`` (the node id), ``outcome`` (``passed``, ``failed``, ``error``, ``skipped``,
  ``xfailed`` or ``xpassed``, as pytest reports them; a strict xfail that passes is ``failed``),
  ``seconds`` (setup + call + teardown) and ``message`` (the skip or xfail reason, or the
  exception line of the failure; empty when the test passed).

Under pytest-xdist only the controller writes.
"""

from __future__ import annotations

import datetime as _dt
import importlib.util
import json
import os
import shlex
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

#: outcome rank: a worse phase outcome replaces a better one (a failing teardown after a pass)
_RANK = {"passed": 0, "skipped": 1, "xfailed": 1, "xpassed": 1, "failed": 2, "error": 2}


def _benchresult():
    spec = importlib.util.spec_from_file_location("benchresult", REPO / "benchmarks" / "benchresult.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _message(report, outcome) -> str:
    if outcome == "passed":
        return ""
    if outcome in ("xfailed", "xpassed"):
        return str(getattr(report, "wasxfail", ""))
    if outcome == "skipped" and isinstance(report.longrepr, tuple):
        return str(report.longrepr[2]).removeprefix("Skipped: ")
    crash = getattr(getattr(report.longrepr, "reprcrash", None), "message", "")  # "Error: message"
    lines = [ln.strip() for ln in (crash or report.longreprtext).splitlines() if ln.strip()]
    return (lines[0] if crash else lines[-1])[:500] if lines else ""


#: environment variables written in front of the command when they are set
_ENVIRONMENT = ("VLSFOREST_DEFAULT_RESULTS",)


class OutcomeRecorder:
    """Collects each test's outcome and duration; writes the rows when the run ends."""

    def __init__(self, config, path: Path):
        self.config, self.path = config, path
        self.date = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
        # the environment that changes what the slow tests check (tests/test_default_forest.py)
        env = [f"{k}={os.environ[k]}" for k in _ENVIRONMENT if os.environ.get(k)]
        self.command = shlex.join([*env, "python", "-m", "pytest", *config.invocation_params.args])
        self.tests: dict[str, dict] = {}

    def pytest_runtest_logreport(self, report):
        entry = self.tests.setdefault(report.nodeid, {"outcome": None, "seconds": 0.0, "message": ""})
        entry["seconds"] += report.duration
        category = self.config.hook.pytest_report_teststatus(report=report, config=self.config)[0]
        if not category or (report.when != "call" and category == "passed"):
            return
        if entry["outcome"] is None or _RANK.get(category, 2) > _RANK.get(entry["outcome"], 2):
            entry["outcome"], entry["message"] = category, _message(report, category)

    def rows(self, exit_code: int) -> list[dict]:
        """One row per test that ran (see the module's docstring)."""
        br = _benchresult()
        head = {"date": self.date, "commit": br.commit(), "machine": br.machine(), "command": self.command,
                "exit_code": int(exit_code)}
        return [{**head, "test": nodeid, "outcome": e["outcome"] or "passed", "seconds": round(e["seconds"], 3),
                 "message": e["message"]} for nodeid, e in self.tests.items()]

    @pytest.hookimpl(trylast=True)
    def pytest_sessionfinish(self, exitstatus):
        reporter = self.config.pluginmanager.get_plugin("terminalreporter")
        say = reporter.write_line if reporter else (lambda line: print(line, file=sys.stderr))
        if not self.tests:
            say(f"outcome_record: no test ran; {self.path} left as it is")
            return
        rows = self.rows(exitstatus)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
        tmp.write_text("".join(json.dumps(r, ensure_ascii=False) + "\n" for r in rows), encoding="utf-8")
        os.replace(tmp, self.path)
        say(f"outcome_record: {len(rows)} test outcome(s) written to {self.path}")


def pytest_addoption(parser):
    parser.getgroup("outcome_record").addoption(
        "--record-outcomes", metavar="FILE", default=None, type=Path,
        help="write one JSON row per test (outcome, seconds, provenance) to FILE, replacing it")


def pytest_configure(config):
    path = config.getoption("record_outcomes")
    if path is not None and not hasattr(config, "workerinput"):  # the xdist controller or no xdist
        config.pluginmanager.register(OutcomeRecorder(config, Path(path).resolve()), "outcome_recorder")


__all__ = ["OutcomeRecorder"]

