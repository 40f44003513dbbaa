"""Sub-commands of the ``vlsforest`` CLI, one module per stage (see :mod:`vlsforest.cli`).

Each (sub-)command declares its output options with :func:`declare_outputs`; the command line
checks every declared output path with :func:`check_outputs` before the command's work starts
(:func:`vlsforest.io.atomic.check_output_path`), so a folder, an unwritable place or a wrong
suffix ends in one line and exit 2 instead of a traceback after the computation.
"""

from __future__ import annotations

#: the kind of an output that is a folder of parts (:func:`declare_outputs`)
FOLDER = "folder"
LAS = (".las", ".laz")
CSV = (".csv",)
YAML = (".yaml", ".yml")
JSON = (".json",)
NPZ = (".npz",)
PNG = (".png",)
#: a per-pulse table (``simulate``/``detect --pulses``; :data:`vlsforest.sim.output.PULSES_SUFFIXES`)
PULSES = (".npz", ".csv")


def check_workers(workers) -> None:
    """Raise :class:`~vlsforest.errors.ConfigError` for a ``--workers`` below 1 (None: the default)."""
    if workers is not None and workers < 1:
        from vlsforest.errors import ConfigError

        raise ConfigError(f"--workers must be ≥ 1, got {workers}")


def declare_outputs(parser, **outputs) -> None:
    """Declare the output options of a (sub-)command parser.

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The parser whose parsed arguments hold the options.
    **outputs
        Argument ``dest`` → the documented suffixes of that output file (a tuple), ``None``
        (a file of any name) or :data:`FOLDER` (a folder of parts).
    """
    parser.set_defaults(declared_outputs=outputs)


def option_name(dest: str) -> str:
    """The command-line option of an argument ``dest`` (``output`` → ``-o``, ``out_errors`` →
    ``--out-errors``)."""
    return "-o" if dest == "output" else "--" + dest.replace("_", "-")


def check_outputs(args) -> None:
    """Check every output path declared for the parsed command before its work starts.

    Raises
    ------
    vlsforest.errors.OutputPathError
        For the first output that cannot be written (names the option and the path).
    """
    from vlsforest.io.atomic import check_output_dir, check_output_path

    for dest, kind in (getattr(args, "declared_outputs", None) or {}).items():
        path = getattr(args, dest, None)
        if path is None:
            continue
        if kind == FOLDER:
            check_output_dir(path, option_name(dest))
        else:
            check_output_path(path, kind, option_name(dest))
