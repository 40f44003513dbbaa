"""What a workflow job runs: the source files behind a ``vlsforest`` command, and their hash.

Snakemake reruns a job when its ``shell:`` string, its ``script:`` file or one of its params
changes, but it cannot see the code of an imported package. The workflow therefore gives every
rule that runs library code a ``library`` param: a hash over the source files that the rule's
command imports. The file set is derived from the code itself, by reading the ``import``
statements of the modules (with :mod:`ast`, without importing anything) and following them
transitively inside the ``vlsforest`` package, so it cannot drift from what the command runs:
an edit of a module reruns exactly the rules whose commands import it, directly or through other
modules, and no others.

What counts as imported by a module:

- every ``import`` and ``from … import`` statement anywhere in it (also inside functions, which
  most command modules use to keep start-up short), absolute or relative;
- for ``import a.b.c`` and ``from a.b import c``: the packages ``a`` and ``a.b`` (importing a
  sub-module runs its parents' ``__init__.py``), and ``a.b.c`` where that is a module;
- beside a package's modules, the files of its ``data/`` folder (read at run time, e.g. the
  species table of :mod:`vlsforest.synth.species`).

Imports that only some paths of a module execute still count: the file set is a superset of what
one call runs, never a subset. ``importlib.import_module`` with a computed name is not seen; the
CLI imports its sub-command modules that way, so :func:`command_sources` adds the command module
by name.
"""

from __future__ import annotations

import ast
import functools
import hashlib
from collections.abc import Iterable
from pathlib import Path

__all__ = [
    "PACKAGE",
    "PACKAGE_DIR",
    "module_file",
    "imported_modules",
    "import_closure",
    "command_sources",
    "script_sources",
    "source_hash",
    "command_hash",
    "script_hash",
]

#: the package whose imports are followed
PACKAGE = "vlsforest"
#: its source folder (the one this module lies in)
PACKAGE_DIR = Path(__file__).resolve().parent

#: length of the hex digests :func:`source_hash` returns
HASH_LENGTH = 16


def module_file(name: str, package_dir: Path | str = PACKAGE_DIR) -> Path | None:
    """The source file of module ``name`` (dotted, starting with the package name), or None.

    Parameters
    ----------
    name : str
        Dotted module name, e.g. ``"vlsforest.sim.engine"``.
    package_dir : path-like
        Folder of the package ``name`` starts with.

    Returns
    -------
    pathlib.Path or None
        ``<package_dir>/sim/engine.py`` or ``<package_dir>/sim/__init__.py``; None when ``name``
        is not a module of the package.
    """
    parts = name.split(".")
    if not parts or parts[0] != Path(package_dir).name:
        return None
    base = Path(package_dir).joinpath(*parts[1:])
    for candidate in (base.with_suffix(".py") if len(parts) > 1 else None, base / "__init__.py"):
        if candidate is not None and candidate.is_file():
            return candidate
    return None


def _module_name(path: Path, package_dir: Path) -> tuple[str, bool]:
    """Dotted name of the source file ``path`` of the package, and whether it is a package."""
    rel = path.relative_to(package_dir).with_suffix("")
    parts = [package_dir.name, *rel.parts]
    is_package = parts[-1] == "__init__"
    if is_package:
        parts = parts[:-1]
    return ".".join(parts), is_package


def _with_parents(name: str) -> list[str]:
    """``a.b.c`` → ``["a", "a.b", "a.b.c"]``."""
    parts = name.split(".")
    return [".".join(parts[: i + 1]) for i in range(len(parts))]


def imported_modules(path: Path | str, package_dir: Path | str = PACKAGE_DIR,
                     module: str | None = None) -> set[str]:
    """Modules of the package that the source file ``path`` imports (one level, not transitive).

    Parameters
    ----------
    path : path-like
        A Python source file, inside the package or not (e.g. a workflow script).
    package_dir : path-like
        Folder of the package whose modules are followed.
    module : str, optional
        Dotted name of ``path``, needed to resolve relative imports; derived from the path when
        it lies inside ``package_dir``.

    Returns
    -------
    set of str
        Dotted names of the package's modules and packages that importing ``path`` imports,
        parents included; names without a source file are left out.
    """
    path, package_dir = Path(path), Path(package_dir).resolve()
    stat = path.stat()
    return set(_imported_modules(str(path), stat.st_mtime_ns, stat.st_size, str(package_dir), module))


@functools.lru_cache(maxsize=1024)
def _imported_modules(path: str, mtime_ns: int, size: int, package_dir: str,
                      module: str | None) -> frozenset[str]:
    """:func:`imported_modules`, parsed once per file version (a workflow computes a hash per
    command, and the commands share most of their modules)."""
    path, package_dir = Path(path), Path(package_dir)
    is_package = path.name == "__init__.py"
    if module is None:
        try:
            module, is_package = _module_name(path.resolve(), package_dir)
        except ValueError:
            module = None
    tree = ast.parse(path.read_bytes(), filename=str(path))
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                names.update(_with_parents(alias.name))
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                if module is None:
                    continue  # a relative import outside the package
                anchor = module.split(".")
                if not is_package:
                    anchor = anchor[:-1]
                anchor = anchor[: len(anchor) - (node.level - 1)]
                base = ".".join(anchor + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            names.update(_with_parents(base))
            names.update(f"{base}.{alias.name}" for alias in node.names if alias.name != "*")
    return frozenset(n for n in names if module_file(n, package_dir) is not None)


def import_closure(modules: Iterable[str], package_dir: Path | str = PACKAGE_DIR) -> set[str]:
    """The modules ``modules`` and everything of the package they import, transitively.

    Parameters
    ----------
    modules : iterable of str
        Dotted names of the package's modules to start from (their parent packages count too).
    package_dir : path-like
        Folder of the package.

    Returns
    -------
    set of str
        Dotted module names.

    Raises
    ------
    ValueError
        If one of ``modules`` has no source file in the package.
    """
    package_dir = Path(package_dir).resolve()
    todo = []
    for name in modules:
        if module_file(name, package_dir) is None:
            raise ValueError(f"no module {name!r} in {package_dir}")
        todo += _with_parents(name)
    seen: set[str] = set()
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        todo += imported_modules(module_file(name, package_dir), package_dir, module=name) - seen
    return seen


def _with_data(files: set[Path]) -> set[Path]:
    """``files`` plus the files of the ``data/`` folder beside each."""
    out = set(files)
    for folder in {f.parent / "data" for f in files}:
        if folder.is_dir():
            out.update(p for p in folder.rglob("*") if p.is_file() and "__pycache__" not in p.parts)
    return out


def command_sources(command: str, package_dir: Path | str = PACKAGE_DIR) -> list[Path]:
    """Source files that ``vlsforest <command>`` (or ``python -m vlsforest.cli <command>``) runs.

    Parameters
    ----------
    command : str
        A sub-command of the CLI, e.g. ``"extract"``; its module is
        ``vlsforest.commands.<command with - as _>``.
    package_dir : path-like
        Folder of the package.

    Returns
    -------
    list of pathlib.Path
        The CLI module, the command module and what they import, transitively, plus the
        ``data/`` files of those packages; sorted.
    """
    package_dir = Path(package_dir).resolve()
    roots = [f"{package_dir.name}.cli", f"{package_dir.name}.commands.{command.replace('-', '_')}"]
    closure = import_closure(roots, package_dir)
    return sorted(_with_data({module_file(n, package_dir) for n in closure}))


def script_sources(script: Path | str, package_dir: Path | str = PACKAGE_DIR) -> list[Path]:
    """Source files of the package that the script ``script`` imports, transitively.

    The script itself is not included (Snakemake already reruns a ``script:`` rule when its
    script changes).

    Parameters
    ----------
    script : path-like
        A Python file outside the package, e.g. ``workflow/rules/methods/linear_pad.py``.
    package_dir : path-like
        Folder of the package.

    Returns
    -------
    list of pathlib.Path
        Sorted source files (and ``data/`` files) of the package.
    """
    package_dir = Path(package_dir).resolve()
    closure = import_closure(imported_modules(script, package_dir), package_dir)
    return sorted(_with_data({module_file(n, package_dir) for n in closure}))


def source_hash(files: Iterable[Path | str], root: Path | str = PACKAGE_DIR) -> str:
    """Short SHA-256 over the files ``files``: their paths relative to ``root`` and contents.

    Parameters
    ----------
    files : iterable of path-like
        Files below ``root``; the order does not matter.
    root : path-like
        Folder the recorded paths are relative to (so that a copy of the tree elsewhere hashes
        the same).

    Returns
    -------
    str
        The first :data:`HASH_LENGTH` hex digits of the digest.
    """
    root = Path(root).resolve()
    h = hashlib.sha256()
    for rel, path in sorted((Path(f).resolve().relative_to(root).as_posix(), Path(f)) for f in files):
        h.update(rel.encode())
        h.update(b"\0")
        h.update(path.read_bytes())
        h.update(b"\0")
    return h.hexdigest()[:HASH_LENGTH]


def command_hash(command: str, package_dir: Path | str = PACKAGE_DIR) -> str:
    """:func:`source_hash` of :func:`command_sources` (a rule's ``library`` param).

    Examples
    --------
    >>> len(command_hash("stats"))
    16
    """
    return source_hash(command_sources(command, package_dir), package_dir)


def script_hash(script: Path | str, package_dir: Path | str = PACKAGE_DIR) -> str:
    """:func:`source_hash` of :func:`script_sources` (the ``library`` param of a script rule)."""
    return source_hash(script_sources(script, package_dir), package_dir)
