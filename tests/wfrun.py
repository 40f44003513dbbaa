"""Support for tests that run the Snakemake workflow (imported by conftest.py and test modules).

Every run uses a temporary working directory with the repository's ``Snakefile``; nothing is
written into the repository.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SNAKEFILE = REPO / "Snakefile"
QUICK = REPO / "config" / "quick.yaml"


def snakemake_command(*args, snakefile=SNAKEFILE):
    """The Snakemake CLI on the repository's Snakefile (or ``snakefile``), with ``args``, as an
    argument list."""
    return [sys.executable, "-m", "snakemake", "--snakefile", str(snakefile), *map(str, args)]


def snakemake_cli(*args, cwd, timeout=300, env=None, snakefile=SNAKEFILE):
    """Run the Snakemake CLI on the repository's Snakefile (or ``snakefile``) in ``cwd``; return
    the process."""
    return subprocess.run(snakemake_command(*args, snakefile=snakefile), cwd=cwd, capture_output=True,
                          text=True, timeout=timeout, env=job_env(env if env is not None else os.environ))


def job_env(env):
    """``env`` with the folder of the Python running the tests first on PATH: the workflow's jobs
    call the installed ``vlsforest`` command of the project's environment, as with the venv
    activated."""
    env = dict(env)
    bindir = os.path.dirname(sys.executable)
    parts = [p for p in env.get("PATH", "").split(os.pathsep) if p and p != bindir]
    env["PATH"] = os.pathsep.join([bindir, *parts])
    return env


def run_quick(workdir, *extra, timeout=900):
    """Run the quick config to completion in ``workdir``; return (process, seconds)."""
    t0 = time.perf_counter()
    proc = snakemake_cli("--cores", 2, "--configfile", QUICK, *extra, cwd=workdir, timeout=timeout)
    dt = time.perf_counter() - t0
    assert proc.returncode == 0, proc.stderr[-4000:]
    return proc, dt
