"""Benchmark: what first-touching freshly allocated memory costs on this machine.

The diagnosis' traces and the study's jobs allocate and free large arrays (a default-forest
trace holds ≈ 3.5 GB). On a virtual machine that hands freed guest memory back to its host
(Linux free page reporting, ``/sys/module/page_reporting``), touching such memory again costs
page faults served by the host, which shows as system time. This copies ``--gb`` GB into newly
allocated arrays ``--rounds`` times in one process (each round's arrays freed before the next)
and prints wall, user and system seconds per round and the ratio first / last round.

    python benchmarks/bench_fresh_memory.py --gb 7 --rounds 3

Needs ``--gb`` plus 0.5 GB of free memory.
"""

from __future__ import annotations

import argparse
import resource
import time
from pathlib import Path

import numpy as np


def _page_reporting() -> str:
    base = Path("/sys/module/page_reporting/parameters")
    if not base.is_dir():
        return "free page reporting: not present"
    vals = {p.name: p.read_text().strip() for p in sorted(base.iterdir()) if p.name in
            ("page_reporting_order", "min_free_ms", "reported_kib")}
    return "free page reporting: " + ", ".join(f"{k} {v}" for k, v in vals.items())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gb", type=float, default=7.0, help="GB copied into fresh arrays per round")
    ap.add_argument("--rounds", type=int, default=3)
    a = ap.parse_args(argv)
    print(_page_reporting())
    chunk = int(5e7)
    src = np.ones(chunk * 10, np.uint8)  # 0.5 GB source, touched once here
    parts = [src[k * chunk:(k + 1) * chunk] for k in range(10)]
    n = max(1, round(a.gb / 0.5))
    walls = []
    for r in range(a.rounds):
        r0 = resource.getrusage(resource.RUSAGE_SELF)
        t = time.perf_counter()
        out = [np.concatenate(parts) for _ in range(n)]  # n × 0.5 GB newly allocated and written
        wall = time.perf_counter() - t
        r1 = resource.getrusage(resource.RUSAGE_SELF)
        del out
        walls.append(wall)
        print(f"round {r + 1}: {n * 0.5:.1f} GB into fresh arrays in {wall:.2f} s "
              f"(user {r1.ru_utime - r0.ru_utime:.2f} s, system {r1.ru_stime - r0.ru_stime:.2f} s)")
    print(f"first / last round wall: {walls[0] / walls[-1]:.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
