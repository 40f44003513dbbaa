"""The diagnosis' trace cache: one plot's ray traces in memory, and on disk while a later stage needs them.

A trace of a default-forest plot holds ≈ 120 M sub-ray hits (≈ 3.5 GB). :class:`TraceCache`
keeps two in memory — the search's current baseline (:meth:`TraceCache.pin`) and the last other
one — and writes the traces a later stage will ask for again (:meth:`TraceCache.keep`) to a
spill folder when they leave memory, so that they are read back instead of traced again.
"""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import numpy as np


def _release_freed_memory():
    """Give freed heap pages back to the system (glibc only; elsewhere nothing happens).

    A trace gathers its hits from ≈ 20 000-pulse blocks of a few MB each; glibc serves such
    sizes from its heap once its adaptive mmap threshold has grown, and keeps the freed pages
    mapped after the blocks are joined, so the process would hold them for the rest of the run.
    """
    import ctypes
    import ctypes.util

    name = ctypes.util.find_library("c")
    try:
        trim = ctypes.CDLL(name).malloc_trim if name else None
    except (OSError, AttributeError):
        trim = None
    if trim is not None:
        trim(0)


def save_trace(folder: Path, trace: tuple) -> None:
    """Write a trace (pulses, hits) as one ``.npy`` file per array (key order kept)."""
    folder.mkdir(parents=True)
    order = {}
    for name, arrays in zip(("pulses", "hits"), trace):
        order[name] = list(arrays)
        for k, v in arrays.items():
            np.save(folder / f"{name}.{k}.npy", v, allow_pickle=False)
    (folder / "order.json").write_text(json.dumps(order))


def load_trace(folder: Path) -> tuple:
    """Read back what :func:`save_trace` wrote: the same arrays, dtypes and key order."""
    order = json.loads((folder / "order.json").read_text())
    return tuple({k: np.load(folder / f"{name}.{k}.npy", allow_pickle=False) for k in order[name]}
                 for name in ("pulses", "hits"))


class TraceCache:
    """The ray traces (pulses with hits, their hits) of one plot, by key.

    Parameters
    ----------
    name : str
        The plot's name (in the progress lines).
    log : callable
        Takes each progress line.
    spill_dir : Path, optional
        Where kept traces wait on disk; without it a trace that left memory is traced again.
    """

    def __init__(self, name: str, log, spill_dir: Path | None = None):
        self.name, self.log, self.spill_dir = name, log, spill_dir
        self.n_traced = 0             # traces made
        self.n_loaded = 0             # traces read back from disk
        self._held: dict = {}         # key → trace in memory
        self._pinned = None           # the key kept in memory until the next pin
        self._keep: set = set()       # keys of traces written to disk when evicted (a later stage reuses them)
        self._spilled: dict = {}      # key → folder of a trace on disk
        self._n_written = 0           # traces written so far (names their folders)

    def __contains__(self, key) -> bool:
        """Whether the trace of ``key`` is in memory."""
        return key in self._held

    def __len__(self) -> int:
        """The number of traces in memory."""
        return len(self._held)

    def pin(self, key) -> None:
        """Keep the trace of ``key`` (the search's baseline) in memory until the next pin."""
        self._pinned = key

    def keep(self, keys: set, spill: bool = True) -> None:
        """The traces of ``keys`` are this stage's: traces on disk that are not are deleted,
        and (with ``spill``) these are written to disk when they leave memory."""
        for k in [k for k in self._spilled if k not in keys]:
            shutil.rmtree(self._spilled.pop(k))
        self._keep = set(keys) if spill else set()

    def get(self, key, make, label: str) -> tuple:
        """The trace of ``key``: held, read back from disk, or made by ``make()`` (then counted).

        Before a trace is read or made, every trace in memory but the pinned one leaves it
        (kept ones to disk). ``label`` names the trace in the progress lines.
        """
        if key not in self._held:
            for k in [k for k in self._held if k != self._pinned]:
                self._evict(k)
            t0 = time.perf_counter()
            if key in self._spilled:
                self._held[key] = load_trace(self._spilled[key])
                self.n_loaded += 1
                self.log(f"  {self.name}: read {label} back from disk in "
                         f"{time.perf_counter() - t0:.1f} s (no new trace)")
                return self._held[key]
            self._held[key] = make()
            _release_freed_memory()
            self.n_traced += 1
            self.log(f"  {self.name}: traced {label} in {time.perf_counter() - t0:.1f} s "
                     f"({len(self._held[key][1]['pulse']):,} sub-ray hits)")
        return self._held[key]

    def _evict(self, key) -> None:
        """Drop a trace from memory; first write it to the spill folder if it is kept."""
        trace = self._held.pop(key)
        if key in self._keep and key not in self._spilled and self.spill_dir is not None:
            self._n_written += 1
            folder = self.spill_dir / f"{self.name}-{self._n_written}"
            try:
                save_trace(folder, trace)
            except OSError as exc:  # e.g. a full disk: the trace is made again when needed
                shutil.rmtree(folder, ignore_errors=True)
                self._keep.discard(key)
                self.log(f"  {self.name}: could not keep a trace on disk ({exc}); it is traced again if needed")
            else:
                self._spilled[key] = folder
