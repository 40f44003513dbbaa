"""Whole-or-nothing output files and up-front checks of output paths.

Every file vlsforest writes goes through :func:`atomic_path` (or :func:`atomic_dir` for a
folder of parts): the content is written under a temporary name in the same folder and renamed
into place with :func:`os.replace` only when it is complete, so an error or an interrupt during
the write leaves no partial file at the output path.

A command that writes several files runs inside :func:`output_transaction` (the command line
wraps every command in one): the renames are then deferred to the end of the transaction, so
either every output appears or none does — a failing side output leaves no main output behind.
Work done in other processes joins the transaction too: a worker runs inside
:func:`collect_outputs`, which leaves its finished files under their temporary names and hands
them back as :class:`PendingOutputs`, and the parent takes them into its transaction with
:func:`adopt_outputs`.

:func:`check_output_path` checks an output path before any work starts (not a folder, a
documented suffix, a parent that exists or can be created, a place that can be written).
"""

from __future__ import annotations

import contextlib
import contextvars
import glob
import os
import secrets
import shutil
import tempfile
from pathlib import Path

from vlsforest.errors import OutputPathError

__all__ = ["atomic_path", "atomic_dir", "output_transaction", "collect_outputs", "adopt_outputs", "PendingOutputs",
           "flush", "make_folder", "write_text", "write_bytes", "write_csv", "save_figure", "check_output_path",
           "check_output_dir"]


class PendingOutputs:
    """The outputs of a transaction: renames ``(temporary, final)`` still to do, the folders made
    for them and the outputs installed early (:func:`flush`), in order. Plain paths: it can be
    sent from a worker process to its parent."""

    def __init__(self):
        self.renames: list = []
        self.made: list = []
        self.flushed: list = []


#: the transaction in progress, or None
_PENDING: contextvars.ContextVar[PendingOutputs | None] = contextvars.ContextVar("vlsforest_pending_outputs",
                                                                                 default=None)


def _temporary_name(path: Path) -> Path:
    """A fresh hidden sibling of ``path`` that keeps its suffixes (``out.laz`` →
    ``.tmp-{pid}-{random}-out.laz``).

    Keeping the suffixes matters to writers that choose a format by them (LAZ, pandas, matplotlib).
    The process id in the name lets a later writer of the same output remove what a killed
    process left (:func:`_remove_stale`).
    """
    _remove_stale(path)
    fd, name = tempfile.mkstemp(prefix=f".tmp-{os.getpid()}-", suffix=f"-{path.name}", dir=path.parent)
    os.close(fd)
    return Path(name)


def _remove_stale(path: Path) -> None:
    """Remove temporary siblings of ``path`` left by processes that no longer run (``kill -9``)."""
    for tmp in path.parent.glob(f".tmp-*-{glob.escape(path.name)}"):
        pid = tmp.name.split("-")[1]
        if pid.isdigit() and not _alive(int(pid)):
            _remove(tmp)


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _remove(path: Path) -> None:
    """Remove a file or folder if it exists (best effort: cleanup must not mask the first error)."""
    try:
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path, ignore_errors=True)
        else:
            path.unlink(missing_ok=True)
    except OSError:
        pass


def _install(tmp: Path, final: Path) -> None:
    """Move a finished temporary file or folder onto its final name."""
    if tmp.is_dir() and final.is_dir() and not final.is_symlink():
        # os.replace cannot replace a non-empty folder: move the old one aside first
        old = final.with_name(f".old-{os.getpid()}-{final.name}")
        _remove(old)
        os.replace(final, old)
        os.replace(tmp, final)
        _remove(old)
    else:
        os.replace(tmp, final)


def _make_parent(path: Path) -> list:
    """Create the missing folders above ``path``; return them, outermost first."""
    missing = []
    folder = path.parent
    while not folder.exists() and folder != folder.parent:
        missing.append(folder)
        folder = folder.parent
    if not folder.is_dir():
        raise OutputPathError(f"{path}: {folder} is a file, expected a folder")
    made = []
    try:
        for folder in reversed(missing):
            try:
                folder.mkdir()
            except FileExistsError:  # made meanwhile by another process: not ours to remove
                if not folder.is_dir():
                    raise
                continue
            made.append(folder)
    except OSError as exc:
        _remove_empty(made)
        raise OutputPathError(f"{path}: cannot create its folder ({exc.strerror or exc})") from None
    pending = _PENDING.get()
    if pending is not None:
        pending.made.extend(made)
    return made


def _remove_empty(folders: list) -> None:
    """Remove folders (innermost first) that are empty; leave any that hold something.

    Deepest first, not last made first: the folders of several worker processes
    (:func:`adopt_outputs`) interleave, one worker's folder inside another's.
    """
    for folder in sorted(folders, key=lambda f: len(Path(f).parts), reverse=True):
        try:
            folder.rmdir()
        except OSError:
            pass


def _commit_or_defer(tmp: Path, final: Path) -> None:
    pending = _PENDING.get()
    if pending is None:
        _install(tmp, final)
    else:
        pending.renames.append((tmp, final))


@contextlib.contextmanager
def atomic_path(path):
    """Yield a temporary path to write ``path``'s content to; rename it into place when done.

    Parameters
    ----------
    path : str or Path
        The output file; its folder is created.

    Yields
    ------
    Path
        A temporary sibling of ``path`` with the same suffixes. When the block ends without an
        exception it replaces ``path`` (inside :func:`output_transaction`: at the transaction's
        end); on any exception, :class:`KeyboardInterrupt` included, it is removed.
    """
    path = Path(path)
    made = _make_parent(path)
    tmp = _temporary_name(path)
    with _discarded_on_error(tmp, made):
        yield tmp
    if not tmp.exists():
        raise OutputPathError(f"{path}: the writer produced no file")
    os.chmod(tmp, 0o666 & ~_umask())
    _commit_or_defer(tmp, path)


@contextlib.contextmanager
def _discarded_on_error(tmp: Path, made):
    """Remove ``tmp`` (and, outside a transaction, the folders ``made`` for it when left empty)
    if the block raises anything, :class:`KeyboardInterrupt` included; re-raise."""
    try:
        yield
    except BaseException:
        _remove(tmp)
        if _PENDING.get() is None:
            _remove_empty(made)
        raise


@contextlib.contextmanager
def atomic_dir(path):
    """Yield a temporary folder to fill with a folder of parts; rename it to ``path`` when done.

    Parameters
    ----------
    path : str or Path
        The output folder; its parent is created. An existing folder is replaced as a whole.

    Yields
    ------
    Path
        A temporary sibling folder. On any exception it is removed with everything in it.
    """
    path = Path(path)
    made = _make_parent(path)
    _remove_stale(path)
    tmp = Path(tempfile.mkdtemp(prefix=f".tmp-{os.getpid()}-", suffix=f"-{path.name}", dir=path.parent))
    with _discarded_on_error(tmp, made):
        yield tmp
    os.chmod(tmp, 0o755 & ~_umask())
    _commit_or_defer(tmp, path)


@contextlib.contextmanager
def output_transaction():
    """Defer every :func:`atomic_path`/:func:`atomic_dir` rename inside the block to its end.

    When the block ends without an exception, the finished files are renamed into place in the
    order they were written; on an exception (an interrupt included) every temporary file and
    folder is removed, so are the folders made for them when empty, and no output appears.
    Nested transactions join the outer one.
    """
    if _PENDING.get() is not None:
        yield
        return
    pending = PendingOutputs()
    token = _PENDING.set(pending)
    try:
        yield
    except BaseException:
        _PENDING.reset(token)
        _abandon(pending, 0)
        raise
    _PENDING.reset(token)
    done = 0
    try:
        for tmp, final in pending.renames:
            _install(tmp, final)
            done += 1
    except BaseException:
        _abandon(pending, done)
        raise


@contextlib.contextmanager
def collect_outputs():
    """Run a worker's part of its parent's outputs: like :func:`output_transaction`, but at the
    end the finished files stay under their temporary names.

    Yields
    ------
    PendingOutputs
        Filled when the block ends without an exception; return it to the parent, which takes it
        into its transaction with :func:`adopt_outputs`. On an exception, an interrupt included,
        everything the block wrote is removed, as in :func:`output_transaction`.

    Raises
    ------
    RuntimeError
        Inside a transaction of the same process (use the transaction itself there).
    """
    if _PENDING.get() is not None:
        raise RuntimeError("collect_outputs: a transaction of this process is in progress")
    pending = PendingOutputs()
    token = _PENDING.set(pending)
    try:
        yield pending
    except BaseException:
        _PENDING.reset(token)
        _abandon(pending, 0)
        raise
    _PENDING.reset(token)


def adopt_outputs(pending: PendingOutputs) -> None:
    """Take the outputs a worker collected (:func:`collect_outputs`) into this process's transaction.

    They are then installed, or removed, with the transaction's own outputs; outside a transaction
    they are installed at once. Their temporary files are renamed to names of this process, so
    that no later writer takes them for the leftovers of a finished worker (:func:`_remove_stale`).
    """
    renames = []
    try:
        for tmp, final in pending.renames:
            own = final.with_name(f".tmp-{os.getpid()}-{secrets.token_hex(4)}-{final.name}")
            os.rename(tmp, own)
            renames.append((own, final))
    except BaseException:
        for own, _ in renames:
            _remove(own)
        _abandon(pending, len(renames))
        raise
    current = _PENDING.get()
    if current is None:
        for own, final in renames:
            _install(own, final)
        return
    current.renames.extend(renames)
    current.made.extend(pending.made)
    current.flushed.extend(pending.flushed)


def _abandon(pending: PendingOutputs, start: int) -> None:
    """Remove the temporary outputs not yet installed, the outputs flushed early and the folders
    left empty."""
    for tmp, _ in reversed(pending.renames[start:]):
        _remove(tmp)
    for final in reversed(pending.flushed):
        _remove(final)
    _remove_empty(pending.made)


def make_folder(path) -> Path:
    """Create the folder ``path`` and its missing parents as outputs of the current transaction
    (removed again, when left empty, if the transaction fails); return ``path``."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise OutputPathError(f"{path}: is a file, expected a folder")
    _make_parent(path / "_")
    return path


def flush() -> None:
    """Install the outputs written so far in the current transaction, so that the command can
    read them back (e.g. a scene description and its parts before exporting them).

    They still count as the transaction's outputs: if it fails later, they are removed. Outside
    a transaction, nothing to do.
    """
    pending = _PENDING.get()
    if pending is None:
        return
    while pending.renames:
        tmp, final = pending.renames[0]
        _install(tmp, final)
        pending.renames.pop(0)
        pending.flushed.append(final)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_text(path, text: str) -> Path:
    """Write ``text`` (UTF-8, ``\\n`` line ends) to ``path`` atomically; return ``path``."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8", newline="\n")
    return Path(path)


def write_bytes(path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically; return ``path``."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def _suffix_ok(path: Path, suffixes) -> bool:
    name = path.name.lower()
    return any(name.endswith(s.lower()) for s in suffixes)


def _probe(folder: Path) -> str | None:
    """Why a file cannot be created in ``folder`` (None when it can): a real try, not ``os.access``."""
    try:
        fd, name = tempfile.mkstemp(prefix=".probe-", dir=folder)
    except OSError as exc:
        return exc.strerror or str(exc)
    os.close(fd)
    os.unlink(name)
    return None


def check_output_path(path, suffixes=None, what: str = "output") -> Path:
    """Check before any work starts that ``path`` can be written as an output file.

    Parameters
    ----------
    path : str or Path
        The output file.
    suffixes : iterable of str, optional
        The documented suffixes (e.g. ``(".las", ".laz")``); any other is refused. None: any.
    what : str
        How the message names the path (the option, e.g. ``"--pulses"``).

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    OutputPathError
        For a folder, a wrong suffix, a parent that is a file or cannot be created, or a place
        where no file can be created. Nothing is created on disk.
    """
    path = Path(path)
    if str(path) == "" or path.name in ("", ".", ".."):
        raise OutputPathError(f"{what} {path}: not a file name")
    if path.is_dir():
        raise OutputPathError(f"{what} {path}: is a folder, expected a file")
    if suffixes is not None and not _suffix_ok(path, suffixes):
        raise OutputPathError(f"{what} {path}: expected a name ending in {' or '.join(suffixes)}")
    _check_place(path, what)
    return path


def check_output_dir(path, what: str = "output folder") -> Path:
    """Check before any work starts that the folder ``path`` can be created or replaced.

    Raises
    ------
    OutputPathError
        When ``path`` is a file, or its nearest existing ancestor is not a writable folder.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise OutputPathError(f"{what} {path}: is a file, expected a folder")
    _check_place(path, what)
    return path


def _check_place(path: Path, what: str) -> None:
    ancestor = path.absolute().parent
    while not ancestor.exists():
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise OutputPathError(f"{what} {path}: {ancestor} is not a folder")
    why = _probe(ancestor)
    if why is not None:
        raise OutputPathError(f"{what} {path}: cannot write in {ancestor} ({why})")


def write_csv(path, frame, **to_csv) -> Path:
    """Write a pandas DataFrame with ``frame.to_csv(…, **to_csv)`` atomically; return ``path``."""
    with atomic_path(path) as tmp:
        frame.to_csv(tmp, **to_csv)
    return Path(path)


def save_figure(path, fig, **savefig) -> Path:
    """Save a matplotlib figure with ``fig.savefig(…, **savefig)`` atomically; return ``path``.

    The temporary name keeps the suffix, so the format follows ``path`` as with ``savefig``.
    """
    with atomic_path(path) as tmp:
        fig.savefig(tmp, **savefig)
    return Path(path)
