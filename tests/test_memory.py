"""Opt-in malloc and huge-page tuning of the command line (vlsforest._memory):
VLSFOREST_MALLOC_TUNING=1 keeps freed memory in the process; unset, nothing changes."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from vlsforest._memory import SWITCH, keep_freed_memory, plain_environ
from vlsforest.errors import ConfigError

WORKFLOW = Path(__file__).resolve().parents[1] / "workflow"

# allocates and frees 400 MB in 4 arrays, then prints the resident MB and the THP flag. "keep"
# and "default" first clear the THP flag, which a test process may have inherited (a test that
# ran `vlsforest` in-process with the tuning on set it); "inherited" runs as it was started.
PROBE = r"""
import ctypes, os, sys, numpy as np
if sys.argv[1] != "inherited":
    ctypes.CDLL(None).prctl(41, 0, 0, 0, 0)  # PR_SET_THP_DISABLE off
if sys.argv[1] == "keep":
    from vlsforest._memory import keep_freed_memory
    os.environ["VLSFOREST_MALLOC_TUNING"] = "1"
    assert keep_freed_memory()
base = int(open("/proc/self/statm").read().split()[1])
arrays = [np.ones(100_000_000, np.uint8) for _ in range(4)]
del arrays
rss = (int(open("/proc/self/statm").read().split()[1]) - base) * 4096 / 1e6
thp = [l.split()[1] for l in open("/proc/self/status") if l.startswith("THP_enabled")]
print(round(rss), thp[0] if thp else "?")
"""

# runs a `vlsforest` command in-process (it fails at once: the input is missing), then prints its
# exit code, the malloc settings its environment carries and the THP flag
CLI_PROBE = r"""
import ctypes, os, sys
ctypes.CDLL(None).prctl(41, 0, 0, 0, 0)
from vlsforest.cli import main
missing = sys.argv[1]
rc = main(["stats", "--metrics", missing, "--voxel-counts", missing, "--sim-times", missing, "-o", sys.argv[2]])
thp = [l.split()[1] for l in open("/proc/self/status") if l.startswith("THP_enabled")]
print(rc, ",".join(sorted(k for k in os.environ if k.startswith("MALLOC_"))) or "-", thp[0] if thp else "?")
"""

linux_glibc = pytest.mark.skipif(not sys.platform.startswith("linux") or os.confstr("CS_GNU_LIBC_VERSION") is None,
                                 reason="glibc on Linux only")


def _clean_env() -> dict:
    env = plain_environ()
    env["PYTHONPATH"] = str(WORKFLOW)
    return env


def _probe(mode: str) -> tuple[float, str]:
    env = _clean_env()
    out = subprocess.run([sys.executable, "-c", PROBE, mode], env=env, capture_output=True, text=True,
                         check=True).stdout.split()
    return float(out[0]), out[1]


@linux_glibc
def test_with_the_switch_freed_arrays_stay_in_the_process_and_pages_are_small():
    kept, thp_kept = _probe("keep")
    freed, thp_default = _probe("default")
    assert kept > 350  # the 400 MB freed stay resident for the next allocation
    assert freed < 50  # glibc's default: each > 32 MB array went back to the kernel
    if thp_kept != "?":
        assert thp_kept == "0" and thp_default == "1"


@linux_glibc
@pytest.mark.parametrize("value, tuned", [(None, False), ("0", False), ("1", True)])
def test_the_command_line_tunes_only_when_asked(tmp_path, value, tuned):
    env = _clean_env()
    if value is not None:
        env[SWITCH] = value
    out = subprocess.run([sys.executable, "-c", CLI_PROBE, str(tmp_path / "missing.csv"), str(tmp_path / "out")],
                         env=env, capture_output=True, text=True, check=True).stdout.split()
    assert out[0] == "2"  # the missing input: the command ran and failed as it should
    assert out[1] == ("MALLOC_MMAP_MAX_,MALLOC_TRIM_THRESHOLD_" if tuned else "-")
    if out[2] != "?":
        assert out[2] == ("0" if tuned else "1")


def test_unset_zero_and_the_users_own_malloc_settings_change_nothing():
    for env in ({}, {SWITCH: "0"}, {SWITCH: "1", "MALLOC_ARENA_MAX": "2"},
                {SWITCH: "1", "GLIBC_TUNABLES": "glibc.malloc.mmap_max=4"}):
        before = dict(env)
        assert keep_freed_memory(env) is False and env == before


@linux_glibc
def test_a_child_process_inherits_the_settings():
    """The synthesis' spawned workers are new interpreters: with the switch on they keep freed
    memory too."""
    code = ("import ctypes, subprocess, sys; from vlsforest._memory import keep_freed_memory; "
            "ctypes.CDLL(None).prctl(41, 0, 0, 0, 0); assert keep_freed_memory(); "
            "subprocess.run([sys.executable, '-c', sys.argv[1], 'inherited'], check=True)")
    env = {**_clean_env(), SWITCH: "1"}
    out = subprocess.run([sys.executable, "-c", code, PROBE], env=env, capture_output=True, text=True,
                         check=True).stdout.split()
    assert float(out[0]) > 350
    assert out[1] in ("0", "?")


def test_a_misspelt_switch_is_one_clear_error(tmp_path):
    env = {SWITCH: "yes"}
    with pytest.raises(ConfigError, match="VLSFOREST_MALLOC_TUNING must be 1 .* or 0 .*'yes'"):
        keep_freed_memory(env)
    assert env == {SWITCH: "yes"}  # nothing applied
    missing = tmp_path / "missing.csv"
    cmd = [sys.executable, "-m", "vlsforest.cli", "stats", "--metrics", str(missing), "--voxel-counts",
           str(missing), "--sim-times", str(missing), "-o", str(tmp_path / "out")]
    r = subprocess.run(cmd, env={**plain_environ(), SWITCH: "yes", "PYTHONPATH": str(WORKFLOW)},
                       capture_output=True, text=True)
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == [
        "vlsforest stats: error: VLSFOREST_MALLOC_TUNING must be 1 (tune malloc and huge pages) or 0 "
        "(the system's behaviour, the default), got 'yes'"]
    assert not (tmp_path / "out").exists()
