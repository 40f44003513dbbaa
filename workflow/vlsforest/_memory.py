"""Opt-in tuning of how a ``vlsforest`` process asks the system for memory (private).

Off by default: a ``vlsforest`` process uses the C library's and the kernel's own settings.
``VLSFOREST_MALLOC_TUNING=1`` in the environment switches it on for every ``vlsforest`` command
(and the processes they start); ``0`` or unset leaves the system's behaviour.

What it changes, and when it helps: the stages allocate and free arrays of hundreds of MB to
several GB (a default-forest trace of the diagnosis holds ≈ 3.5 GB). With glibc's defaults every
array above 32 MB is its own ``mmap`` and goes back to the kernel when freed, so the next one is
fresh memory again; with transparent huge pages each first touch zeroes 2 MB pages. On virtual
machines that hand freed guest memory back to their host (free page reporting), both make the
same memory cost system time over and over. :func:`keep_freed_memory` switches a process (and the
processes it starts) to keeping what it freed for its own later allocations (glibc ``mallopt``:
no trimming, no ``mmap`` allocations) and to small pages (``prctl(PR_SET_THP_DISABLE)``). The
outputs do not change, only where the bytes live; the price is a higher peak resident size
(+10 % on the quick forest's diagnosis). A process started with its own ``MALLOC_*`` or
``GLIBC_TUNABLES`` settings is left as it is; without glibc on Linux nothing changes.

Without the tuning, :func:`release_freed_memory` hands the heap pages a step has freed back to
the system where it frees many arrays while it fills a large one (a simulation's blocks joined
or written), so that the two are not resident together.
"""

from __future__ import annotations

import ctypes
import os

from vlsforest.errors import ConfigError

#: environment variable that turns the tuning on (``1``; ``0`` or unset: the system's behaviour)
SWITCH = "VLSFOREST_MALLOC_TUNING"

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
    :func:`keep_freed_memory` itself (the tests' baseline)."""
    env = os.environ if environ is None else environ
    return {k: v for k, v in env.items() if not _own_malloc_setting(k) and k != SWITCH}


def keep_freed_memory(environ: dict | None = None) -> bool:
    """Keep freed heap memory in this process and its children, and use small pages, if
    :data:`SWITCH` is ``1``.

    Parameters
    ----------
    environ : dict, optional
        Environment to read and update (default ``os.environ``; children inherit it).

    Returns
    -------
    bool
        True when the settings were applied; False when ``VLSFOREST_MALLOC_TUNING`` is unset or
        ``0`` (the default), when the environment already carries malloc settings, or when the
        C library is not glibc on Linux.

    Raises
    ------
    ConfigError
        ``VLSFOREST_MALLOC_TUNING`` set to anything but ``0`` or ``1``.
    """
    env = os.environ if environ is None else environ
    choice = env.get(SWITCH, "").strip()
    if choice not in ("", "0", "1"):
        raise ConfigError(f"{SWITCH} must be 1 (tune malloc and huge pages) or 0 (the system's "
                          f"behaviour, the default), got {env[SWITCH]!r}")
    if choice != "1":
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


def release_freed_memory() -> None:
    """Hand the heap pages this process has freed back to the system (glibc ``malloc_trim``).

    Arrays of a few hundred kB freed in the middle of the heap stay resident until the C
    library trims them; a step that frees many of them while it fills a large array calls this
    so that the two are not resident together. Nothing happens where the tuning of
    :func:`keep_freed_memory` is on (it keeps freed memory on purpose) or without glibc.
    """
    if os.environ.get(SWITCH, "").strip() == "1":
        return
    try:
        ctypes.CDLL(None).malloc_trim(0)
    except (OSError, AttributeError):
        pass
