"""Code hashes of the workflow's rules (vlsforest.workflow_support, workflow/rules/common.smk).

A rule's ``library`` param hashes the library code its command imports. The tests check the
import reading on a small made-up package, the hashes of the real commands after an edit of one
module, and Snakemake's own verdict: in a working directory whose outputs all carry Snakemake's
metadata (recorded with ``--touch``, no job run), an edit of one module in a copy of the
repository marks exactly the outputs of the rules whose commands import that module as
"params changed", and nothing else.
"""

from __future__ import annotations

import os
import re
import shutil
from pathlib import Path

import pytest
from wfrun import QUICK, REPO, SNAKEFILE, snakemake_cli

from vlsforest import workflow_support as ws

RULES = REPO / "workflow" / "rules"
PACKAGE = REPO / "workflow" / "vlsforest"

#: every sub-command a rule of the workflow runs
RULE_COMMANDS = ("synth", "segment", "stems", "extract", "pad", "scene", "voxels", "plan", "simulate",
                 "collect", "stats", "report", "diagnose", "experiment")


# ---------------------------------------------------------------------------------------------
# the import reading, on a made-up package
# ---------------------------------------------------------------------------------------------
def _write(root: Path, files: dict[str, str]) -> None:
    for rel, text in files.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)


@pytest.fixture()
def toy(tmp_path):
    """A package ``toy`` with a CLI and two commands:

    - ``commands/a.py`` imports ``toy.leaf`` at the top and ``toy.sub.deep`` inside a function;
      ``toy.sub.deep`` imports ``toy.sub.rel`` relatively and ``toy.sub`` reads ``data/``;
    - ``commands/b.py`` imports only ``toy.other``; ``toy.unused`` is imported by nothing.
    """
    root = tmp_path / "toy"
    _write(root, {
        "__init__.py": "",
        "cli.py": "import importlib\nimport sys\n",
        "commands/__init__.py": "",
        "commands/a.py": "import toy.leaf\n\ndef run():\n    from toy.sub import deep\n",
        "commands/b.py": "from toy.other import thing\n",
        "leaf.py": "import numpy\n",
        "other.py": "thing = 1\n",
        "unused.py": "import toy.leaf\n",
        "sub/__init__.py": "",
        "sub/deep.py": "from . import rel\nfrom .rel import x\n",
        "sub/rel.py": "x = 1\n",
        "sub/data/table.json": "{}",
    })
    return root


def _rel(paths, root):
    return {p.relative_to(root).as_posix() for p in paths}


def test_command_sources_follow_function_level_and_relative_imports(toy):
    assert _rel(ws.command_sources("a", toy), toy) == {
        "__init__.py", "cli.py", "commands/__init__.py", "commands/a.py", "leaf.py",
        "sub/__init__.py", "sub/deep.py", "sub/rel.py", "sub/data/table.json",
    }
    assert _rel(ws.command_sources("b", toy), toy) == {
        "__init__.py", "cli.py", "commands/__init__.py", "commands/b.py", "other.py",
    }


def test_imported_modules_is_one_level_and_names_parents(toy):
    assert ws.imported_modules(toy / "commands" / "a.py", toy) == {"toy", "toy.leaf", "toy.sub", "toy.sub.deep"}
    assert ws.imported_modules(toy / "sub" / "deep.py", toy) == {"toy", "toy.sub", "toy.sub.rel"}


@pytest.mark.parametrize("edited, changed", [
    ("sub/rel.py", {"a"}),            # two imports away from command a, relative
    ("sub/data/table.json", {"a"}),   # a data file of a package command a imports
    ("other.py", {"b"}),
    ("cli.py", {"a", "b"}),           # every command runs through the CLI
    ("unused.py", set()),
])
def test_an_edit_changes_the_hash_of_exactly_the_commands_importing_it(toy, edited, changed):
    before = {c: ws.command_hash(c, toy) for c in ("a", "b")}
    with open(toy / edited, "a") as fh:
        fh.write("\n# edited\n")
    after = {c: ws.command_hash(c, toy) for c in ("a", "b")}
    assert {c for c in before if before[c] != after[c]} == changed


def test_hash_does_not_depend_on_where_the_tree_lies(toy, tmp_path):
    copy = tmp_path / "elsewhere" / "toy"
    shutil.copytree(toy, copy)
    assert ws.command_hash("a", copy) == ws.command_hash("a", toy)


def test_unknown_command_is_an_error(toy):
    with pytest.raises(ValueError, match="toy.commands.nope"):
        ws.command_sources("nope", toy)


# ---------------------------------------------------------------------------------------------
# the real package
# ---------------------------------------------------------------------------------------------
#: module edited → the commands that import it (read from the import statements by hand):
#: _treecells is imported by extract, which commands extract and scene (match_targets), the
#: diagnosis (diagnose.simulation) and the CoG-parts experiment (commands.experiment) import;
#: stems.py only by commands.stems; stats/findings.py by
#: the stats package, which commands.stats and report.figures (commands.report) import;
#: commands/demo.py by no rule's command.
REAL_EDITS = {
    "_treecells.py": {"extract", "scene", "diagnose", "experiment"},
    "stems.py": {"stems"},
    "stats/findings.py": {"stats", "report"},
    "commands/demo.py": set(),
}


@pytest.mark.parametrize("edited", sorted(REAL_EDITS))
def test_real_commands_rehash_exactly_where_the_module_is_imported(tmp_path, edited):
    copy = tmp_path / "vlsforest"
    shutil.copytree(PACKAGE, copy, ignore=shutil.ignore_patterns("__pycache__"))
    before = {c: ws.command_hash(c, copy) for c in RULE_COMMANDS}
    with open(copy / edited, "a") as fh:
        fh.write("\n# edited\n")
    after = {c: ws.command_hash(c, copy) for c in RULE_COMMANDS}
    assert {c for c in RULE_COMMANDS if before[c] != after[c]} == REAL_EDITS[edited]


def test_every_rule_that_runs_the_library_hashes_its_own_command():
    """A rule running ``vlsforest <cmd>`` has ``library=command_hash("<cmd>")``; a script rule
    has ``library=script_hash("<its script>")``."""
    checked = 0
    for smk in sorted(RULES.rglob("*.smk")):
        for block in re.split(r"(?m)^(?=rule )", smk.read_text())[1:]:
            name = block.split(":")[0].removeprefix("rule ")
            command = re.search(r'"vlsforest ([a-z-]+)', block)
            script = re.search(r'script:\s*\n\s*"([^"]+)"', block)
            if command:
                assert f'library=command_hash("{command.group(1)}")' in block, name
            elif script:
                rel = (smk.parent / script.group(1)).relative_to(RULES).as_posix()
                assert f'library=script_hash("{rel}")' in block, name
            checked += 1
    assert checked >= 20


# ---------------------------------------------------------------------------------------------
# Snakemake's verdict
# ---------------------------------------------------------------------------------------------
#: module edited → rules of the quick study whose outputs Snakemake marks "params changed"
#: (the rules of REAL_EDITS' commands: extract → extract_reference, sim_trees; scene → targets,
#: crowns, scene; experiment → the quick config's experiments crown outline, CoG shift, CoG
#: parts and reseed; stats → stats; report → figures; the quick config has no diagnosis)
SNAKEMAKE_EDITS = {
    "_treecells.py": {"extract_reference", "sim_trees", "targets", "crowns", "scene", "experiment_crown_outline",
                      "experiment_cog_shift", "experiment_cog_parts", "experiment_reseed"},
    "stats.py": {"stats", "figures"},
    "commands/demo.py": set(),
}


def _summary(workdir, snakefile=None, env=None):
    """``snakemake --summary`` of the quick config: {output file: (rule, status)}."""
    proc = snakemake_cli("--summary", "--cores", 1, "--configfile", QUICK, "--workflow-profile", "none",
                         cwd=workdir, snakefile=snakefile or SNAKEFILE, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = [line.split("\t") for line in proc.stdout.splitlines()]
    assert rows and rows[0][:5] == ["output_file", "date", "rule", "log-file(s)", "status"], proc.stdout[:500]
    return {r[0]: (r[2], r[4]) for r in rows[1:]}


@pytest.fixture(scope="module")
def touched(tmp_path_factory):
    """A working directory holding every output of the quick study as an empty file or folder,
    each with Snakemake's metadata (``--touch --forceall``: no job runs)."""
    workdir = tmp_path_factory.mktemp("touched")
    for out in _summary(workdir):
        path = workdir / out
        if "." in path.name:  # the quick study's folder outputs have no suffix
            path.parent.mkdir(parents=True, exist_ok=True)
            path.touch()
        else:
            path.mkdir(parents=True, exist_ok=True)
    proc = snakemake_cli("--touch", "--forceall", "--cores", 1, "--configfile", QUICK,
                         "--workflow-profile", "none", cwd=workdir)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert {status for _, status in _summary(workdir).values()} == {"ok"}
    return workdir


@pytest.mark.e2e  # Snakemake runs
@pytest.mark.parametrize("edited", sorted(SNAKEMAKE_EDITS))
def test_snakemake_reruns_exactly_the_rules_importing_an_edited_module(touched, tmp_path, edited):
    copy = tmp_path / "repo"
    copy.mkdir()
    shutil.copy(REPO / "Snakefile", copy)
    for folder in ("workflow", "config", "envs"):
        shutil.copytree(REPO / folder, copy / folder, ignore=shutil.ignore_patterns("__pycache__"))
    with open(copy / "workflow" / "vlsforest" / edited, "a") as fh:
        fh.write("\n# edited\n")
    # the jobs would run the copy's package: it is the one on PYTHONPATH (so the one hashed)
    env = {**os.environ, "PYTHONPATH": str(copy / "workflow")}
    rows = _summary(touched, snakefile=copy / "Snakefile", env=env)
    changed = {rule for rule, status in rows.values() if status != "ok"}
    assert changed == SNAKEMAKE_EDITS[edited]
    assert all(status == "params changed" for rule, status in rows.values() if rule in changed)


# ---------------------------------------------------------------------------------------------
# the job environment
# ---------------------------------------------------------------------------------------------
@pytest.mark.e2e  # Snakemake dry runs
@pytest.mark.parametrize("conda", [False, True])
def test_only_conda_deployment_puts_the_source_tree_on_the_job_paths(tmp_path, conda):
    """Jobs call the installed `vlsforest`: PATH and PYTHONPATH stay as they are, except with
    --sdm conda, whose envs hold the dependencies only (then workflow/ goes on PYTHONPATH and
    workflow/bin, the env's `vlsforest` launcher, on PATH). The Snakefile of a copy of the
    repository prints both after the workflow is parsed (a conda-less machine then stops at
    `conda info`)."""
    repo = tmp_path / "repo"
    repo.mkdir()
    for folder in ("workflow", "config", "envs"):
        shutil.copytree(REPO / folder, repo / folder, ignore=shutil.ignore_patterns("__pycache__"))
    (repo / "Snakefile").write_text((REPO / "Snakefile").read_text() + (
        "\nimport os as _os\n"
        "print('JOBPATH', _os.environ.get('PATH', ''))\n"
        "print('JOBPYTHONPATH', _os.environ.get('PYTHONPATH', ''))\n"))
    env = {**os.environ, "PYTHONPATH": str(PACKAGE.parent)}
    extra = ["--sdm", "conda"] if conda else []
    proc = snakemake_cli("-n", "--cores", 1, "--configfile", QUICK, "--workflow-profile", "none", *extra,
                         cwd=tmp_path, env=env, snakefile=repo / "Snakefile")
    lines = dict(line.split(" ", 1) for line in proc.stdout.splitlines() if line.startswith("JOB") and " " in line)
    path, pythonpath = lines["JOBPATH"].split(os.pathsep), lines["JOBPYTHONPATH"].split(os.pathsep)
    if conda:
        assert path[0] == str(repo / "workflow" / "bin")
        assert pythonpath[0] == str(repo / "workflow")
        assert (repo / "workflow" / "bin" / "vlsforest").stat().st_mode & 0o111
    else:
        assert proc.returncode == 0, proc.stderr[-3000:]
        assert str(repo / "workflow" / "bin") not in path
        assert pythonpath == [str(PACKAGE.parent)]
