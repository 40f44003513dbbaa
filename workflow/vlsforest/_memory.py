"""How a ``vlsforest`` process asks the system for memory (private).

The stages allocate and free arrays of hundreds of MB to several GB (a default-forest trace of
the diagnosis holds ≈ 3.5 GB). With glibc's defaults every array above 32 MB is its own
``mmap`` and goes back to the kernel when freed, so the next one is fresh memory again; with
transparent huge pages each first touch zeroes 2 MB pages. On virtual machines that hand freed
guest memory back to their host (free page reporting), both make the same memory cost system
time over and over (``benchmarks/bench_fresh_memory.py``; README, Performance).

:func:`keep_freed_memory` switches a process (and the processes it starts) to keeping what it
freed for its own later allocations, and to small pages. The outputs do not change, only where
the bytes live; the price is a somewhat higher peak resident size (+10 % on the quick forest's
diagnosis). Set ``VLSFOREST_MEMORY=system`` to keep the system's defaults; a process started
with its own ``MALLOC_*`` or ``GLIBC_TUNABLES`` settings is left as it is.
"""

from __future__ import annotations

import ctypes
import os

from vlsforest.errors import ConfigError

#: environment variable that turns the behaviour off (``system``; ``keep`` or unset: on)
SWITCH = "VLSFOREST_MEMORY"

_M_TRIM_THRESHOLD = -1  # mallopt parameters (malloc.h)
_M_MMAP_MAX = -4
_PR_SET_THP_DISABLE = 41  # prctl option (linux/prctl.h); inherited by children, kept across exec

#: what child processes read at their start (glibc reads these before any Python runs)
CHILD_ENV = {"MALLOC_MMAP_MAX_": "0", "MALLOC_TRIM_THRESHOLD_": str(1 << 40)}


def _own_malloc_setting(name: str) -> bool:
    """Whether an environment variable is a malloc setting of the user's (or a parent's)."""
    return name == "GLIBC_TUNABLES" or name.startswith("MALLOC_")


def plain_environ(environ: dict | None = None) -> dict:
    """A copy of ``environ`` (default ``os.environ``) without malloc settings and without
    :data:`SWITCH`: a child started with it begins with the system's defaults and may apply
    :func:`keep_freed_memory` itself (the benchmark's and the tests' baseline)."""
    env = os.environ if environ is None else environ
    return {k: v for k, v in env.items() if not _own_malloc_setting(k) and k != SWITCH}


def keep_freed_memory(environ: dict | None = None) -> bool:
    """Keep freed heap memory in this process and its children, and use small pages.

    Parameters
    ----------
    environ : dict, optional
        Environment to read and update (default ``os.environ``; children inherit it).

    Returns
    -------
    bool
        True when the settings were applied; False when ``VLSFOREST_MEMORY=system``, when the
        environment already carries malloc settings, or when the C library is not glibc on Linux.

    Raises
    ------
    ConfigError
        ``VLSFOREST_MEMORY`` set to anything but ``system`` or ``keep``.
    """
    env = os.environ if environ is None else environ
    choice = env.get(SWITCH, "").strip().lower()
    if choice not in ("", "keep", "system"):
        raise ConfigError(f"{SWITCH} must be 'system' (the C library's defaults) or 'keep' "
                          f"(the default), got {env[SWITCH]!r}")
    if choice == "system":
        return False
    if any(_own_malloc_setting(k) for k in env):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        mallopt, prctl = libc.mallopt, libc.prctl
    except (OSError, AttributeError):
        return False  # not glibc on Linux: nothing to tune
    mallopt.argtypes, prctl.argtypes = [ctypes.c_int, ctypes.c_int], [ctypes.c_int] + [ctypes.c_ulong] * 4
    # -1 turns trimming off altogether (mallopt(3)); 0 maps nothing, all from the heap
    if not (mallopt(_M_TRIM_THRESHOLD, -1) and mallopt(_M_MMAP_MAX, 0)):
        return False
    prctl(_PR_SET_THP_DISABLE, 1, 0, 0, 0)  # fails harmlessly on kernels without it
    env.update(CHILD_ENV)
    return True
