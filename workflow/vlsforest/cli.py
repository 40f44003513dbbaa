"""The ``vlsforest`` command line: ``vlsforest <stage> …``.

Each stage lives in :mod:`vlsforest.commands` as a module with a ``register(subparsers)``
function that adds its sub-command and sets ``func`` to a callable taking the parsed
arguments. Deliberate errors (:class:`vlsforest.errors.VlsforestError`) end in one line on
stderr and exit code 2, never a traceback. Every command runs inside one
:func:`vlsforest.io.atomic.output_transaction`: its output files appear together when it
succeeds, and none appears when it fails or is interrupted.
"""

from __future__ import annotations

import argparse
import importlib
import sys
import warnings

from vlsforest import __version__
from vlsforest._memory import keep_freed_memory
from vlsforest.commands import check_outputs
from vlsforest.errors import VlsforestError
from vlsforest.io.atomic import output_transaction

#: sub-command modules under vlsforest.commands, in the order ``--help`` lists them
COMMANDS = (
    "synth", "segment", "extract", "stems", "voxels", "pad", "scene", "demo", "plan", "simulate",
    "detect", "metrics", "collect", "stats", "report", "diagnose", "experiment",
)


def module_name(command: str) -> str:
    """Module of a sub-command (``extract`` → ``vlsforest.commands.extract``; a ``-`` in a name
    becomes ``_``)."""
    return f"vlsforest.commands.{command.replace('-', '_')}"


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """Build the argument parser with every registered stage (or only the stage ``only``).

    Registering a stage imports its library module; a run of one stage registers just that one
    (about 2 s less start-up per workflow job), ``vlsforest --help`` lists them all.
    """
    parser = argparse.ArgumentParser(
        prog="vlsforest",
        description="Virtual laser scanning of voxelised forests (Weiser et al. 2021, reproduced).",
    )
    parser.add_argument("--version", action="version", version=f"vlsforest {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="<stage>")
    sub.required = True
    for name in COMMANDS if only is None else (only,):
        importlib.import_module(module_name(name)).register(sub)
    return parser


def one_line(exc: BaseException) -> str:
    """The message of ``exc`` on one line (line breaks of wrapped parser messages become spaces)."""
    return " ".join(str(exc).split())


def main(argv: list[str] | None = None) -> int:
    """Run the command line; return the exit code."""
    argv = sys.argv[1:] if argv is None else list(argv)
    only = argv[0] if argv and argv[0] in COMMANDS else None
    parser = build_parser(only)
    args = parser.parse_args(argv)
    with warnings.catch_warnings():
        # a warning is one line naming the stage (vlsforest.io.las.DataWarning and the like)
        warnings.showwarning = lambda message, category, *_, **__: print(
            f"vlsforest {args.command}: warning: {one_line(message)}", file=sys.stderr)
        return _run(args)


def _run(args) -> int:
    """Run the parsed command: check its outputs, run it in one output transaction, turn
    deliberate errors and interrupts into one line."""
    try:
        keep_freed_memory()  # only with VLSFOREST_MALLOC_TUNING=1 (vlsforest._memory)
        check_outputs(args)
        with output_transaction():
            rc = args.func(args)
    except VlsforestError as exc:
        print(f"vlsforest {args.command}: error: {one_line(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"vlsforest {args.command}: error: interrupted, no output written", file=sys.stderr)
        return 130
    return int(rc or 0)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
