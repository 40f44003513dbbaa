"""The package's layering: the import-linter contract and no private name across modules.

``pyproject.toml`` declares the layers (``[tool.importlinter]``); ``lint-imports`` checks that no
module imports a layer above its own. The second check scans the package's syntax trees: a name
starting with one underscore (not a dunder) is private to its module, so no other module of
``vlsforest`` imports it (``from m import _x``) or reads it from an imported module (``m._x``).
A private *module* (``_voxelgrid``) may be imported by the modules of its own package only.
"""

from __future__ import annotations

import ast
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "workflow" / "vlsforest"
LINT_IMPORTS = Path(sys.executable).with_name("lint-imports")


def _lint(config: Path, package_parent: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(package_parent), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([str(LINT_IMPORTS), "--no-cache", "--no-logo", str(config)], cwd=config.parent,
                          env=env, capture_output=True, text=True, timeout=300)


def test_layers_contract_kept():
    res = _lint(ROOT / "pyproject.toml", PACKAGE.parent)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "1 kept, 0 broken" in res.stdout


@pytest.mark.parametrize("module, line", [
    ("domain/labels.py", "import vlsforest.io.las"),                         # domain → io
    ("sim/_embree.py", "from vlsforest.voxels import fixed_voxels"),         # sim → a stage
    ("extract.py", "from vlsforest.synth.species import SPECIES"),          # a stage → another stage
    ("stats/run.py", "from vlsforest.commands import check_workers"),           # analysis → commands
])
def test_layers_contract_catches_an_upward_import(tmp_path, module, line):
    shutil.copytree(PACKAGE, tmp_path / "vlsforest", ignore=shutil.ignore_patterns("__pycache__"))
    target = tmp_path / "vlsforest" / module
    target.write_text(target.read_text() + f"\n\ndef _upward():\n    {line}\n")
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    res = _lint(tmp_path / "pyproject.toml", tmp_path)
    assert res.returncode != 0 and "BROKEN" in res.stdout, res.stdout + res.stderr


def test_layers_contract_places_every_module():
    # exhaustive: a top-level module missing from the layers breaks the contract
    import tomllib

    layers = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"][0]
    assert layers["exhaustive"] is True and layers["containers"] == ["vlsforest"]
    named = {m.strip() for layer in layers["layers"] for m in layer.replace("|", ":").split(":")}
    present = {p.stem for p in PACKAGE.glob("*.py") if p.name != "__init__.py"}
    present |= {p.name for p in PACKAGE.iterdir() if (p / "__init__.py").is_file()}
    assert named == present


# ------------------------------------------------------------------ private names


def _is_private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def _module_name(path: Path, base: Path) -> str:
    parts = list(path.relative_to(base).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _is_module(dotted: str, base: Path) -> bool:
    p = base.joinpath(*dotted.split("."))
    return p.with_suffix(".py").is_file() or (p / "__init__.py").is_file()


def _private_module_allowed(importer: str, is_package: bool, target: str) -> bool:
    """A private module (a path component ``_x``) is visible inside its own package only."""
    parts = target.split(".")
    own = importer if is_package else importer.rpartition(".")[0]
    for k, part in enumerate(parts):
        if _is_private(part):
            parent = ".".join(parts[:k])
            if not (own == parent or own.startswith(parent + ".")):
                return False
    return True


def private_crossings(package: Path) -> list[str]:
    """Every private name that crosses a module boundary inside ``package``.

    Parameters
    ----------
    package : Path
        The folder of the ``vlsforest`` package.

    Returns
    -------
    list of str
        ``"module:line: what"`` per crossing.
    """
    base = package.parent
    root = package.name
    found = []
    for path in sorted(package.rglob("*.py")):
        mod = _module_name(path, base)
        is_package = path.name == "__init__.py"
        tree = ast.parse(path.read_text(), str(path))
        bound = {}  # local name → dotted vlsforest module it stands for
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                if node.level:
                    pkg = mod.split(".") if is_package else mod.split(".")[:-1]
                    pkg = pkg[: len(pkg) - (node.level - 1)]
                    target = ".".join(pkg + ([node.module] if node.module else []))
                else:
                    target = node.module or ""
                if target != root and not target.startswith(root + "."):
                    continue
                if not _private_module_allowed(mod, is_package, target):
                    found.append(f"{mod}:{node.lineno}: imports from private module {target}")
                for alias in node.names:
                    full = f"{target}.{alias.name}"
                    if _is_module(full, base):
                        if not _private_module_allowed(mod, is_package, full):
                            found.append(f"{mod}:{node.lineno}: imports private module {full}")
                        bound[alias.asname or alias.name] = full
                    elif _is_private(alias.name):
                        found.append(f"{mod}:{node.lineno}: imports {alias.name} from {target}")
            elif isinstance(node, ast.Import):
                for alias in node.names:
                    if alias.name == root or alias.name.startswith(root + "."):
                        if not _private_module_allowed(mod, is_package, alias.name):
                            found.append(f"{mod}:{node.lineno}: imports private module {alias.name}")
                        if alias.asname:
                            bound[alias.asname] = alias.name
                        else:
                            bound[alias.name.split(".")[0]] = alias.name.split(".")[0]
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and _is_private(node.attr):
                chain, value = [], node.value
                while isinstance(value, ast.Attribute):
                    chain.append(value.attr)
                    value = value.value
                if isinstance(value, ast.Name) and value.id in bound:
                    owner = ".".join([bound[value.id], *reversed(chain)])
                    if _is_module(owner, base) and owner != mod:
                        found.append(f"{mod}:{node.lineno}: reads {node.attr} of {owner}")
    return found


def test_no_private_name_crosses_a_module_boundary():
    assert private_crossings(PACKAGE) == []


@pytest.mark.parametrize("source, expect", [
    ("from vlsforest.stats import _group\n", "imports _group from vlsforest.stats"),
    ("from vlsforest import stats\nstats._group('x')\n", "reads _group of vlsforest.stats"),
    ("import vlsforest.stats as st\nst._group('x')\n", "reads _group of vlsforest.stats"),
    ("from vlsforest.sim._voxelgrid import VoxelGrid\n", "imports from private module vlsforest.sim._voxelgrid"),
    ("from vlsforest.sim import _embree\n", "imports private module vlsforest.sim._embree"),
])
def test_private_crossings_are_found(tmp_path, source, expect):
    pkg = tmp_path / "vlsforest"
    (pkg / "sim").mkdir(parents=True)
    for f in ("__init__.py", "stats.py", "sim/__init__.py", "sim/_voxelgrid.py", "sim/_embree.py"):
        (pkg / f).write_text("")
    (pkg / "report.py").write_text(source)
    (pkg / "sim" / "engine.py").write_text("from vlsforest.sim import _embree\nfrom vlsforest.sim._voxelgrid import VoxelGrid\n")
    assert [f.split(": ", 1)[1] for f in private_crossings(pkg)] == [expect]


def test_io_package_names_resolve_to_their_modules_on_first_use():
    """`vlsforest.io`'s public names are its submodules' own objects, loaded when first asked for:
    importing the CLI loads neither laspy nor pandas (each command imports what it needs)."""
    import importlib

    import vlsforest.io as vio

    for name in vio.__all__:
        home = importlib.import_module(f"vlsforest.io.{vio.HOMES[name]}")
        assert getattr(vio, name) is getattr(home, name), name
    assert set(vio.HOMES) == set(vio.__all__)
    with pytest.raises(AttributeError, match="no_such_name"):
        vio.no_such_name
    code = ("import sys, vlsforest.cli; "
            "print(' '.join(m for m in ('laspy', 'pandas', 'numba') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == ""
