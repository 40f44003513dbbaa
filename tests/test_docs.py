"""The manual: README length, generated references that cover every command, option and
configuration key, the findings table script, and the tutorials' commands run as written.

A shell block of the documentation is executed when an HTML comment stands on the line before its
fence: ``<!-- test: run -->`` (run in CI) or ``<!-- test: slow -->`` (runs a workflow; marked
``slow``). All marked blocks of one page run in order, in one fresh working folder that holds the
project's ``Snakefile``, ``workflow/``, ``config/``, ``profiles/``, ``envs/`` and ``.venv``.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
_MARK = re.compile(r"^<!-- test: (run|slow) -->\s*$")


def _load(name: str, path: Path):
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def gen():
    return _load("gen_reference", ROOT / "scripts" / "gen_reference.py")


@pytest.fixture(scope="module")
def parser(gen):
    return gen._build_parser()


# --------------------------------------------------------------------------- README


def test_readme_has_at_most_300_lines():
    n = len((ROOT / "README.md").read_text(encoding="utf-8").splitlines())
    assert n <= 300, f"README.md has {n} lines (at most 300)"


def test_readme_keeps_the_two_setup_commands():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert "bash scripts/run-study.sh" in text and "bash scripts/run-tests.sh" in text
    for script in ("run-study.sh", "run-tests.sh", "build-docs.sh"):
        assert (ROOT / "scripts" / script).is_file()


def test_readme_links_point_to_existing_files():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    links = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text)
    local = [link for link in links if "://" not in link]
    assert local
    assert not [link for link in local if not (ROOT / link).exists()]


# --------------------------------------------------------------------------- generated references


def _walk(p: argparse.ArgumentParser, prefix="vlsforest"):
    for action in p._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield f"{prefix} {name}", sub
                yield from _walk(sub, f"{prefix} {name}")


def test_cli_reference_has_every_command_and_option(gen, parser, tmp_path):
    from vlsforest.cli import COMMANDS

    paths = gen.write_all(tmp_path)
    assert sorted(p.name for p in paths) == ["benchmark-results.md", "cli.md", "config.md"]
    text = (tmp_path / "cli.md").read_text(encoding="utf-8")
    commands = dict(_walk(parser))
    assert {f"vlsforest {c}" for c in COMMANDS} <= set(commands)
    missing = []
    for full, sub in commands.items():
        if f"`{full}`" not in text:
            missing.append(full)
        for action in sub._actions:
            if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
                continue
            for name in action.option_strings or [action.metavar or action.dest]:
                if f"`{name}`" not in text:
                    missing.append(f"{full} {name}")
    assert not missing, f"not in the CLI reference: {missing}"


def _schema_keys(node, out):
    """Every property name of a JSON schema, at any depth (also in branches and name lists)."""
    if isinstance(node, dict):
        for key, sub in node.get("properties", {}).items():
            out.add(key)
            _schema_keys(sub, out)
        names = node.get("propertyNames")
        if isinstance(names, dict) and "enum" in names:
            out.update(names["enum"])
        for key in ("additionalProperties", "items", "if", "then", "else"):
            _schema_keys(node.get(key), out)
        for sub in node.get("allOf", []):
            _schema_keys(sub, out)
    return out


def test_config_reference_has_every_schema_key(gen):
    schema = yaml.safe_load((ROOT / "config" / "schema.yaml").read_text(encoding="utf-8"))
    text = gen.config_reference(schema)
    keys = _schema_keys(schema, set())
    assert keys and keys <= gen.schema_keys(schema) | {"kind"}
    missing = sorted(k for k in keys if not re.search(rf"`(?:[^`]*\.)?{re.escape(k)}`", text))
    assert not missing, f"not in the configuration reference: {missing}"
    # every top-level key has its own section
    for key in schema["properties"]:
        assert f"## `{key}`" in text


def test_benchmark_results_are_rendered_from_the_files(gen, tmp_path):
    (tmp_path / "a.csv").write_text("date,commit,machine,command,seconds\n2026-01-01,x,m,c,1.5\n")
    (tmp_path / "b.jsonl").write_text('{"case": "null", "seconds": 2.25}\n{"case": "x", "seconds": 3}\n')
    (tmp_path / "c.json").write_text('{"machine": "m", "rows": [{"n": 1}, {"n": 2}]}')
    text = gen.benchmark_results(tmp_path)
    assert "## `a.csv`" in text and "| 2026-01-01 | x | m | c | 1.5 |" in text
    assert "## `b.jsonl`" in text and "| null | 2.25 |" in text and "| x | 3 |" in text
    assert "## `c.json`" in text and "| m | 2 |" in text
    assert "No result files" in gen.benchmark_results(tmp_path / "none")


def test_a_records_summary_tables_get_tables_of_their_own(gen, tmp_path):
    old = {"benchmark": "bench_toy", "results": {"n": 1, "tables": {"costs": [{"part": "old", "mb": 9}]}}}
    new = {"benchmark": "bench_toy", "results": {"n": 2, "tables": {"costs": [{"part": "imports", "mb": 142.5},
                                                                              {"part": "kernels", "mb": 83}]}}}
    plain = {"benchmark": "bench_toy", "results": {"n": 3}}
    (tmp_path / "bench_toy.jsonl").write_text("\n".join(json.dumps(r) for r in (old, new, plain)) + "\n")
    text = gen.benchmark_results(tmp_path)
    assert "3 record(s)." in text
    assert '| bench_toy | {"n": 2} |' in text  # the tables leave the record's cell
    # the latest record that has tables, not the last record
    assert "### bench_toy: costs" in text and text.count("### ") == 1
    assert "| part | mb |" in text and "| imports | 142.5 |" in text and "| kernels | 83 |" in text
    assert "| old | 9 |" not in text


# --------------------------------------------------------------------------- findings table


def test_findings_table_is_generated_from_a_findings_file(tmp_path):
    from vlsforest.stats import findings_markdown

    ft = _load("findings_table", ROOT / "scripts" / "findings-table.py")
    findings = [
        dict(id="F1", claim="Large voxels | overestimate CBH.", verdict="agrees", evidence=["x"],
             tolerance="±0.1 m (the slices)"),
        dict(id="T5:fixed_0.25", claim="Few voxels.", verdict="disagrees", evidence=[], tolerance="",
             cause="the step", experiment="scan finer"),
    ]
    src = tmp_path / "findings.md"
    src.write_text(findings_markdown(findings), encoding="utf-8")
    readme = tmp_path / "README.md"
    readme.write_text((ROOT / "README.md").read_text(encoding="utf-8"), encoding="utf-8")
    assert ft.main(["--findings", str(src), "--readme", str(readme)]) == 0
    text = readme.read_text(encoding="utf-8")
    assert "| F1 | Large voxels \\| overestimate CBH. | agrees | ±0.1 m |  |" in text
    assert "| T5:fixed_0.25 | Few voxels. | disagrees |  | the step; scan finer |" in text
    assert "1 agree, 1 disagree, 0 not testable." in text
    assert ft.main(["--findings", str(src), "--readme", str(readme), "--check"]) == 0
    assert ft.main(["--findings", str(tmp_path / "missing.md"), "--readme", str(readme)]) == 2
    png = tmp_path / "fig.png"
    png.write_bytes(b"\x89PNG one")
    images = tmp_path / "images"
    common = ["--findings", str(src), "--readme", str(readme), "--images", str(images)]
    assert ft.main([*common, "--figure", str(png), "--check"]) == 1
    assert ft.main([*common, "--figure", str(png)]) == 0
    assert (images / "fig.png").read_bytes() == png.read_bytes()
    assert ft.main([*common, "--figure", str(png), "--check"]) == 0
    assert ft.main([*common, "--figure", str(tmp_path / "none.png")]) == 2
    assert len(text.splitlines()) <= 300 + 20  # the real table adds about 15 rows


# --------------------------------------------------------------------------- tutorials


def _blocks(page: Path):
    """The marked shell blocks of a page: ``[(kind, line, code)]``."""
    lines = page.read_text(encoding="utf-8").splitlines()
    out = []
    for i, line in enumerate(lines):
        m = _MARK.match(line)
        if not m:
            continue
        assert i + 1 < len(lines) and lines[i + 1].startswith("```bash"), \
            f"{page}:{i + 1}: a test mark must stand right before a ```bash block"
        end = next(j for j in range(i + 2, len(lines)) if lines[j].startswith("```"))
        out.append((m.group(1), i + 1, "\n".join(lines[i + 2:end])))
    return out


PAGES = sorted(p for p in DOCS.rglob("*.md") if _blocks(p))


def test_every_tutorial_has_tested_commands():
    tutorials = sorted((DOCS / "tutorials").glob("*.md"))
    assert tutorials
    assert not [t.name for t in tutorials if t not in PAGES]


def _workspace(tmp_path: Path) -> Path:
    ws = tmp_path / "ws"
    ws.mkdir()
    for name in ("Snakefile", "workflow", "profiles", "envs", "config"):
        (ws / name).symlink_to(ROOT / name)
    venv = ROOT / ".venv" if (ROOT / ".venv" / "bin" / "python").exists() else Path(sys.prefix)
    (ws / ".venv").symlink_to(venv)
    return ws


def _run_page(page: Path, tmp_path: Path):
    ws = _workspace(tmp_path)
    env = dict(os.environ, PYTHONPATH=str(ROOT / "workflow"))
    for kind, line, code in _blocks(page):
        res = subprocess.run(["bash", "-euo", "pipefail", "-c", code], cwd=ws, env=env,
                             capture_output=True, text=True, timeout=3000 if kind == "slow" else 300)
        assert res.returncode == 0, (f"{page.relative_to(ROOT)}:{line}: exit {res.returncode}\n"
                                     f"{code}\n--- stdout\n{res.stdout[-3000:]}\n--- stderr\n{res.stderr[-3000:]}")


def _params():
    for page in PAGES:
        slow = any(kind == "slow" for kind, _, _ in _blocks(page))
        yield pytest.param(page, id=page.relative_to(DOCS).as_posix(),
                           marks=[pytest.mark.slow] if slow else [])


@pytest.mark.e2e  # the documentation's commands run in a shell, as a reader runs them
@pytest.mark.parametrize("page", list(_params()))
def test_documented_commands_run_as_written(page, tmp_path):
    _run_page(page, tmp_path)
