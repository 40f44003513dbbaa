#!/usr/bin/env python
"""Regenerate ``workflow/vlsforest/synth/data/bretten_species.json`` from the real Bretten CSV.

Usage::

    python tools/summarise_bretten.py [path/to/bretten_tree_metrics.csv] [-o out.json]

Defaults: the CSV in ``../shared/data/real/`` next to the repository, and the shipped JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DEFAULT_CSV = REPO.parent / "shared" / "data" / "real" / "bretten_tree_metrics.csv"
DEFAULT_OUT = REPO / "workflow" / "vlsforest" / "synth" / "data" / "bretten_species.json"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("csv", nargs="?", default=str(DEFAULT_CSV))
    ap.add_argument("-o", "--out", default=str(DEFAULT_OUT))
    args = ap.parse_args(argv)
    from vlsforest.errors import VlsforestError
    from vlsforest.synth._summarise import summarise_bretten

    try:
        summary = summarise_bretten(args.csv)
    except VlsforestError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.write_text(json.dumps(summary, indent=1, sort_keys=False) + "\n")
    print(f"wrote {out} ({out.stat().st_size} bytes, {len(summary['species'])} species)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
