"""Reading YAML files (configs, scene and survey descriptions) with one-line errors.

:func:`read_yaml` is the one loader of every YAML file vlsforest reads: a missing or unreadable
file, a syntax error (with its line and column), an empty file or a document that is not a
mapping each end in one :class:`~vlsforest.errors.ConfigError` naming the file.
"""

from __future__ import annotations

from pathlib import Path

import yaml

from vlsforest.errors import ConfigError

__all__ = ["read_yaml", "parse_yaml"]


def parse_yaml(text: str, where: str, mapping: bool = True, empty=None):
    """Parse YAML ``text``; ``where`` names its source in messages.

    Parameters
    ----------
    text : str
        The document.
    where : str
        The file (or option) the text came from.
    mapping : bool
        Whether the document must be a mapping (an empty document gives ``empty``).
    empty : object, optional
        What an empty document gives; None: an empty document is an error.

    Raises
    ------
    ConfigError
        For a syntax error (naming its line and column), an empty document when ``empty`` is
        None, or a document that is not a mapping when ``mapping``.
    """
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        at = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise ConfigError(f"{where}: invalid YAML{at}: {' '.join(str(problem).split())}") from None
    if doc is None:
        if empty is None:
            raise ConfigError(f"{where}: the file is empty")
        return empty
    if mapping and not isinstance(doc, dict):
        raise ConfigError(f"{where}: must be a mapping of keys to values, got a {type(doc).__name__}")
    return doc


def read_yaml(path, what: str = "YAML", mapping: bool = True, empty=None):
    """Read a YAML file (see :func:`parse_yaml`); ``what`` names the file kind in messages.

    Raises
    ------
    ConfigError
        For a missing or unreadable file and every case of :func:`parse_yaml`; names the file.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: no such {what} file")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read the {what} file ({' '.join(str(exc).split())})") from None
    return parse_yaml(text, str(path), mapping=mapping, empty=empty)
