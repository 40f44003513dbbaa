"""The voxel-grid ray kernel of this checkout against the one of an earlier commit, on real rays.

Runs one simulation of a finished study (one worker), keeps every ``--every``-th batch of rays
that the simulation hands to the voxel grid, and traces those rays with the current kernel and
with ``workflow/vlsforest/sim/_voxelgrid.py`` as it was at ``--before``, interleaved, several
times. Prints the CPU seconds of both, their ratio and whether the hits are identical (they
must be: the kernel's speed-ups may not change a single hit).

Usage::

    python benchmarks/bench_voxelgrid_versions.py STUDY_DIR --plot P3 --methods fixed_0.02,scaled \
        --before 816f157

STUDY_DIR is a finished default study (``results/{plot}/{method}/scene``, ``results/{plot}/surveys``,
``results/{plot}/site.json``). Nothing is written outside a temporary folder.
"""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
KERNEL = "workflow/vlsforest/sim/_voxelgrid.py"


def _module_at(rev: str, tmp: Path):
    """The kernel module as it was at ``rev`` (compiled without numba's file cache)."""
    src = subprocess.run(["git", "-C", str(REPO), "show", f"{rev}:{KERNEL}"], check=True,
                         capture_output=True, text=True).stdout
    path = tmp / "_voxelgrid_before.py"
    path.write_text(src.replace("cache=True", "cache=False"))
    spec = importlib.util.spec_from_file_location("_voxelgrid_before", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _capture(study: Path, plot: str, method: str, scenario: str, every: int, tmp: Path):
    """Rays (origins, directions, tmax) of every ``every``-th grid call, and the grid."""
    from vlsforest import cli
    from vlsforest.sim import _voxelgrid as vg

    calls, state = [], {"n": 0, "grid": None}
    original = vg.VoxelGrid.trace

    def trace(self, o, d, tmax=None):
        state["n"] += 1
        if state["n"] % every == 0:
            calls.append((np.array(o), np.array(d), np.array(tmax)))
            state["grid"] = self
        return original(self, o, d, tmax)

    vg.VoxelGrid.trace = trace
    try:
        rc = cli.main(["simulate", str(study / f"results/{plot}/{method}/scene/scene.yaml"),
                       str(study / f"results/{plot}/surveys/{scenario}.yaml"), "-o", str(tmp / "sim.laz"),
                       "--seed", "0", "--workers", "1", "--region-from", str(study / f"results/{plot}/site.json"),
                       "--region-margin", "1"])
    finally:
        vg.VoxelGrid.trace = original
    if rc != 0 or not calls:
        raise SystemExit(f"{plot}/{method}/{scenario}: simulation failed or traced no voxel grid")
    o, d, t = (np.concatenate([c[k] for c in calls]) for k in range(3))
    return o, d, t, state["grid"], state["n"]


def _run(mod, g, o, d, t):
    m = len(o)
    out = (np.empty(m), np.empty(m, np.int8), np.empty(m, np.int64))
    lo = g.origin + g._mins * g.cell_size
    nx, ny, nz = (int(x) for x in g._dims)
    t0 = time.process_time()
    mod._trace_kernel_serial(o, d, t, lo, g.cell_size, nx, ny, nz, g.block_bits, g._nb[0], g._nb[1], g._wpb,
                             g._coarse, g._masks, g._prefix, g._base, g._cubes, *out)
    return time.process_time() - t0, out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("study", type=Path)
    ap.add_argument("--plot", default="P3")
    ap.add_argument("--methods", default="fixed_0.02,scaled")
    ap.add_argument("--scenario", default="uls")
    ap.add_argument("--before", required=True, help="git revision of the kernel to compare with")
    ap.add_argument("--every", type=int, default=20, help="keep every n-th batch of rays")
    ap.add_argument("--reps", type=int, default=8)
    args = ap.parse_args(argv)
    from vlsforest.sim import _voxelgrid as current

    with tempfile.TemporaryDirectory() as tmp:
        before = _module_at(args.before, Path(tmp))
        for method in args.methods.split(","):
            o, d, t, g, n_calls = _capture(args.study, args.plot, method, args.scenario, args.every, Path(tmp))
            for mod in (before, current):  # compile outside the timing
                _run(mod, g, o[:10], d[:10], t[:10])
            times = {"before": [], "now": []}
            outs = {}
            for _ in range(args.reps):
                for name, mod in (("before", before), ("now", current)):
                    s, outs[name] = _run(mod, g, o, d, t)
                    times[name].append(s)
            same = all(np.array_equal(a, b) for a, b in zip(outs["before"], outs["now"]))
            b, n = np.array(times["before"]), np.array(times["now"])
            print(f"{args.plot}/{method}/{args.scenario}: {len(o):,} rays from {n_calls // args.every} of "
                  f"{n_calls} grid calls, {g!r}")
            print(f"  kernel at {args.before}: median {np.median(b):.3f} s ({np.median(b) / len(o) * 1e6:.2f} us/ray)"
                  f"   now: median {np.median(n):.3f} s ({np.median(n) / len(o) * 1e6:.2f} us/ray)"
                  f"   ratio now/before (median of {args.reps} paired runs) {np.median(n / b):.3f}"
                  f"   hits identical: {same}")
            if not same:
                return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
