"""Sub-commands of the ``vlsforest`` CLI, one module per stage (see :mod:`vlsforest.cli`)."""

from __future__ import annotations


def check_workers(workers) -> None:
    """Raise :class:`~vlsforest.errors.ConfigError` for a ``--workers`` below 1 (None: the default)."""
    if workers is not None and workers < 1:
        from vlsforest.errors import ConfigError

        raise ConfigError(f"--workers must be ≥ 1, got {workers}")
