"""The ``vlsforest`` command line registers every stage it lists (a broken or missing stage
module is an error, not a silently absent stage)."""

from __future__ import annotations

import pytest

from vlsforest import cli


def test_every_listed_stage_is_registered():
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    assert list(sub.choices) == list(cli.COMMANDS)


def test_a_missing_stage_module_is_an_error(monkeypatch):
    monkeypatch.setattr(cli, "COMMANDS", cli.COMMANDS + ("no-such-stage",))
    with pytest.raises(ModuleNotFoundError, match="vlsforest.commands.no_such_stage"):
        cli.build_parser()
