"""Folders built once per test run and shared by every pytest-xdist worker (used by conftest.py).

Under pytest-xdist each worker is its own process with its own fixtures, so a fixture of
the widest scope alone builds once per worker. :func:`built_once` builds a folder in the
run's shared temporary folder (:func:`run_dir`) under an exclusive lock: the first process that
needs it builds it while the others wait, and every later caller reads the finished folder and
the build's JSON record. A failed build is recorded too, so that the other workers fail at once
with its message instead of repeating it.

POSIX only (``fcntl.flock``), standard library only.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import shutil
import traceback
from pathlib import Path


class SharedBuildError(RuntimeError):
    """A shared build failed (here or in another worker of the same run)."""


def run_dir(tmp_path_factory) -> Path:
    """The temporary folder that every process of this test run sees.

    Without pytest-xdist that is the run's own base folder; on a worker it is the controller's
    base folder, the parent of the worker's own (``…/pytest-N/popen-gw0`` → ``…/pytest-N``).
    Both are new for each run, so nothing is shared between runs.
    """
    base = Path(tmp_path_factory.getbasetemp())
    return base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base


@contextlib.contextmanager
def exclusive(lock_path: Path):
    """Hold an exclusive ``flock`` on ``lock_path`` (created if missing) for the block."""
    with open(lock_path, "a+") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def built_once(root: Path, name: str, build) -> tuple[Path, dict]:
    """The folder ``root/name``, built by ``build(folder) -> dict`` the first time it is asked for.

    Parameters
    ----------
    root : Path
        The run's shared folder (:func:`run_dir`).
    name : str
        The build's name: its folder ``root/name`` and its record ``root/name.json``.
    build : callable
        ``build(folder)`` fills the empty ``folder`` and returns a JSON-serialisable record.

    Returns
    -------
    (Path, dict)
        The folder and the record ``build`` returned (read back from ``root/name.json``).

    Raises
    ------
    SharedBuildError
        When the build failed, in this process or earlier in another one of the same run.
    """
    root = Path(root)
    folder, record, failed = root / name, root / f"{name}.json", root / f"{name}.failed"
    with exclusive(root / f"{name}.lock"):
        if failed.exists():
            raise SharedBuildError(f"the shared build {name!r} failed earlier in this run:\n{failed.read_text()}")
        if not record.exists():
            if folder.exists():
                shutil.rmtree(folder)
            folder.mkdir(parents=True)
            try:
                result = build(folder)
            except BaseException as exc:
                failed.write_text("".join(traceback.format_exception(exc))[-6000:])
                raise SharedBuildError(f"the shared build {name!r} failed: {exc}") from exc
            tmp = record.with_suffix(".json.tmp")
            tmp.write_text(json.dumps(result))
            os.replace(tmp, record)
        return folder, json.loads(record.read_text())
