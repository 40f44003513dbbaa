"""Patch of Snakemake's job scheduler: at most one pending re-evaluation timer.

On by default (workflow/rules/common.smk calls :func:`apply_if_enabled`);
``VLSFOREST_SCHEDULER_PATCH=0`` in the environment of ``snakemake`` switches it off. It replaces a
private method of Snakemake (``JobScheduler._schedule_reevalutation``, spelled so upstream), so it
is applied only where that method is exactly the one it was written against
(:data:`EXPECTED_SOURCE`, the Snakemake 9.x of the project's requirements); anywhere else (a
cluster's own Snakemake, say) Snakemake stays as it is, with a warning only where
``VLSFOREST_SCHEDULER_PATCH=1`` asked for the patch. ``tests/test_scheduler_patch.py`` fails when
the installed Snakemake's method differs.

Why: with its default ``--max-jobs-per-timespan 100/1s``, Snakemake's scheduler ends every
scheduling pass by starting a 1 s timer whose firing triggers another pass, which starts the next
timer. Every pass triggered by a job's start or end therefore begins one more such chain: near
the end of a run of N jobs the scheduler makes about N passes a second, each re-evaluating the
params and resources of every ready job (on the default study about a third of a core for
Snakemake's own process). No public setting avoids it: the limiter cannot be switched off from
the command line, and a long timespan leaves non-daemon timer threads that keep Snakemake alive
after the run. One pending timer keeps what the timer is for (a pass within the timespan after
any pass, so a rate-limited job still starts) and the chains no longer pile up. Results do not
depend on it.
"""

from __future__ import annotations

import inspect
import os
import textwrap
import threading
import warnings

#: the environment variable that switches the patch off ("0") or demands it ("1": a warning where
#: it cannot be applied)
ENV_VAR = "VLSFOREST_SCHEDULER_PATCH"

#: Snakemake's method as the patch expects it (dedented source)
EXPECTED_SOURCE = '''\
def _schedule_reevalutation(self, delay: int) -> None:
    threading.Timer(
        delay,
        lambda: self._open_jobs.release(),
    ).start()
'''


def _value(environ) -> str:
    return (os.environ if environ is None else environ).get(ENV_VAR, "").strip().lower()


def enabled(environ=None) -> bool:
    """Whether the patch is wanted: unless :data:`ENV_VAR` is ``0`` (or ``false``, ``no``, ``off``)."""
    return _value(environ) not in ("0", "false", "no", "off")


def demanded(environ=None) -> bool:
    """Whether :data:`ENV_VAR` asks for the patch explicitly (``1``, ``true``, ``yes`` or ``on``)."""
    return _value(environ) in ("1", "true", "yes", "on")


def compatible(scheduler_class=None) -> bool:
    """Whether Snakemake's ``JobScheduler`` has the method the patch replaces, unpatched and as
    :data:`EXPECTED_SOURCE` writes it (a patched one counts as compatible)."""
    if scheduler_class is None:
        try:
            from snakemake.scheduling.job_scheduler import JobScheduler as scheduler_class
        except ImportError:
            return False
    method = getattr(scheduler_class, "_schedule_reevalutation", None)
    if method is None:
        return False
    if getattr(method, "one_pending", False):
        return True
    try:
        source = textwrap.dedent(inspect.getsource(method))
    except (OSError, TypeError):
        return False
    return source == EXPECTED_SOURCE


def _schedule_reevalutation(self, delay):
    """Start a timer releasing one scheduling pass after ``delay`` s, unless one is pending."""
    if getattr(self, "_vlsforest_reevaluation", None) is not None:
        return  # a pass is already due within the timespan

    def fire():
        self._vlsforest_reevaluation = None  # before the pass it triggers asks for the next
        self._open_jobs.release()

    timer = threading.Timer(delay, fire)
    timer.daemon = True
    self._vlsforest_reevaluation = timer
    timer.start()


_schedule_reevalutation.one_pending = True


def apply(scheduler_class=None, warn: bool = True) -> bool:
    """Patch ``JobScheduler`` (or ``scheduler_class``) if :func:`compatible`; return whether the
    patch is in place. An incompatible Snakemake gets no patch (and, with ``warn``, a warning)."""
    if scheduler_class is None:
        try:
            from snakemake.scheduling.job_scheduler import JobScheduler as scheduler_class
        except ImportError:
            if warn:
                warnings.warn(f"{ENV_VAR}: Snakemake's JobScheduler not found; not patched", stacklevel=2)
            return False
    if not compatible(scheduler_class):
        if warn:
            warnings.warn(
                f"{ENV_VAR}: this Snakemake's JobScheduler._schedule_reevalutation is not the one the "
                "patch was written for; not patched", stacklevel=2,
            )
        return False
    scheduler_class._schedule_reevalutation = _schedule_reevalutation
    return True


def apply_if_enabled(environ=None) -> bool:
    """:func:`apply` when :func:`enabled` (warning only when :func:`demanded`); return whether
    the patch is in place."""
    return apply(warn=demanded(environ)) if enabled(environ) else False
