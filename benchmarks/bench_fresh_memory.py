"""Benchmark: what re-touching freed memory costs on this machine, with and without
``vlsforest._memory.keep_freed_memory`` (which every ``vlsforest`` command applies).

The diagnosis' traces and the study's jobs allocate and free large arrays (a default-forest
trace holds ≈ 3.5 GB). On a virtual machine that hands freed guest memory back to its host
(Linux free page reporting, ``/sys/module/page_reporting``), touching such memory again costs
page faults served by the host, which shows as system time. Each setting runs in its own
process: ``--rounds`` times it copies ``--gb`` GB into newly allocated arrays, frees them and
waits ``--pause`` s (long enough for the kernel to report the freed pages). It prints wall and
system seconds per round and the ratios of the two settings.

    python benchmarks/bench_fresh_memory.py --gb 4 --rounds 3

Needs ``--gb`` plus 0.5 GB of free memory.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "workflow"))

from vlsforest._memory import keep_freed_memory, plain_environ  # noqa: E402


def _page_reporting() -> str:
    base = Path("/sys/module/page_reporting/parameters")
    if not base.is_dir():
        return "free page reporting: not present"
    vals = {p.name: p.read_text().strip() for p in sorted(base.iterdir()) if p.name in
            ("page_reporting_order", "min_free_ms")}
    return "free page reporting: " + ", ".join(f"{k} {v}" for k, v in vals.items())


def _rounds(gb: float, rounds: int, pause: float, keep: bool) -> list[tuple[float, float]]:
    """Run the rounds in this process; return (wall, system) seconds per round."""
    if keep and not keep_freed_memory():
        raise SystemExit("keep_freed_memory did not apply (not glibc, or MALLOC_* set)")
    chunk = int(5e7)
    src = np.ones(chunk * 10, np.uint8)  # 0.5 GB source, touched once here
    parts = [src[k * chunk:(k + 1) * chunk] for k in range(10)]
    n = max(1, round(gb / 0.5))
    out = []
    for _ in range(rounds):
        r0 = resource.getrusage(resource.RUSAGE_SELF)
        t = time.perf_counter()
        arrays = [np.concatenate(parts) for _ in range(n)]  # n × 0.5 GB newly allocated and written
        wall = time.perf_counter() - t
        r1 = resource.getrusage(resource.RUSAGE_SELF)
        del arrays
        out.append((wall, r1.ru_stime - r0.ru_stime))
        time.sleep(pause)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gb", type=float, default=4.0, help="GB copied into fresh arrays per round")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--pause", type=float, default=6.0, help="seconds between rounds")
    ap.add_argument("--child", choices=("default", "keep"), help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.child:
        print(json.dumps(_rounds(a.gb, a.rounds, a.pause, a.child == "keep")))
        return 0
    print(_page_reporting())
    env = plain_environ()
    res = {}
    for mode in ("default", "keep"):
        proc = subprocess.run([sys.executable, __file__, "--child", mode, "--gb", str(a.gb), "--rounds",
                               str(a.rounds), "--pause", str(a.pause)], env=env, capture_output=True,
                              text=True, check=True)
        res[mode] = json.loads(proc.stdout)
        for r, (wall, sys_s) in enumerate(res[mode]):
            print(f"{mode:>7}, round {r + 1}: {a.gb:.1f} GB into fresh arrays in {wall:.2f} s (system {sys_s:.2f} s)")
    for label, sl in (("first round", slice(0, 1)), ("later rounds", slice(1, None))):
        d, k = (sum(w for w, _ in res[m][sl]) for m in ("default", "keep"))
        if k > 0:
            print(f"{label}: default / keep wall {d / k:.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
