"""The one exception hierarchy of vlsforest.

Every error that vlsforest raises on purpose derives from :class:`VlsforestError`, so that the
command line can turn it into one clear message and exit code 2 without a traceback.
"""

from __future__ import annotations


class VlsforestError(Exception):
    """Base class of every deliberate vlsforest error."""


class ConfigError(VlsforestError):
    """A configuration file or value is invalid (names the key or the line)."""


class InputDataError(VlsforestError):
    """An input data file is missing, corrupt, empty or lacks required fields (names the file)."""


class OutputPathError(VlsforestError):
    """An output path cannot be written (a folder, a wrong suffix, an unwritable place; names the path)."""
