"""Summarise the real Bretten per-tree metrics into the small parameter file the project ships.

The real table (``bretten_tree_metrics.csv``, pytreedb test data from Weiser et al. 2022) holds
one row per tree and sensor (ALS, ULS leaf-on/leaf-off, TLS, field inventory FI).  The project
must not ship that table, so :func:`summarise_bretten` reduces it to per-species statistics and a
few fitted allometric relations, written to ``vlsforest/synth/data/bretten_species.json`` by
``tools/summarise_bretten.py``.

Which sensor serves which quantity (the study's choices where the table allows them):

* height: ULS leaf-on (the study took tree height from ULS), ALS where no ULS leaf-on row exists;
* crown base height: TLS (as in the study), ULS leaf-on where no TLS value exists;
* crown projection area (convex) and crown radius: ULS leaf-on (the table has no TLS CPA),
  ALS as fallback;
* DBH: TLS, field inventory (FI) as fallback.

Rows with impossible values (negative CBH, as some FI rows carry; CBH above the height) are
dropped from the joint table.  The crown radius is the radius of a circle of the same area as
the convex CPA.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from vlsforest.errors import InputDataError

QUANTILE_LEVELS = (0.0, 0.05, 0.1, 0.25, 0.5, 0.75, 0.9, 0.95, 1.0)
_METRICS = ("height_m", "cbh_m", "cpa_convex_m2", "mean_crown_diameter_m", "dbh_cm")
_REQUIRED = ("id", "species", "source", "canopy_condition") + _METRICS
_MIN_TREES_JOINT = 20


def _sensor_key(source: str, condition) -> str:
    if source == "ULS":
        return "ULS_leaf_off" if condition == "leaf-off" else "ULS_leaf_on"
    return str(source)


def _stats(values: np.ndarray) -> dict:
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return {"count": 0}
    return {
        "count": int(v.size),
        "mean": round(float(v.mean()), 4),
        "sd": round(float(v.std(ddof=1)) if v.size > 1 else 0.0, 4),
        "quantiles": [round(float(q), 4) for q in np.quantile(v, QUANTILE_LEVELS)],
    }


def _loglinear(x: np.ndarray, y: np.ndarray) -> dict | None:
    ok = np.isfinite(x) & np.isfinite(y) & (x > 0) & (y > 0)
    if ok.sum() < 10:
        return None
    lx, ly = np.log(x[ok]), np.log(y[ok])
    b, a = np.polyfit(lx, ly, 1)
    resid = ly - (a + b * lx)
    return {
        "model": "ln(y) = a + b ln(height_m)",
        "a": round(float(a), 5),
        "b": round(float(b), 5),
        "resid_sd": round(float(resid.std(ddof=2)), 5),
        "n": int(ok.sum()),
        "x_range": [round(float(x[ok].min()), 3), round(float(x[ok].max()), 3)],
    }


def summarise_bretten(csv_path: str | Path) -> dict:
    """Reduce the real Bretten tree table to per-species statistics and relations.

    Parameters
    ----------
    csv_path : path
        ``bretten_tree_metrics.csv``.

    Returns
    -------
    dict
        JSON-serialisable summary: ``species`` maps the Latin name to ``key`` (snake case),
        ``by_sensor`` (per sensor and metric: count, mean, SD, quantiles at
        ``quantile_levels``), ``preferred`` (the sensor used per quantity) and ``joint`` (the
        per-tree table built from the preferred sensors: statistics of height, CBH, CPA, DBH,
        the CBH/height ratio, and log-linear fits of DBH and crown radius on height).

    Raises
    ------
    InputDataError
        The file is missing, unreadable, or lacks the needed columns.
    """
    import pandas as pd

    path = Path(csv_path)
    if not path.is_file():
        raise InputDataError(f"{path}: Bretten tree metrics table not found")
    try:
        raw = path.read_bytes()
        df = pd.read_csv(path)
    except Exception as exc:  # pragma: no cover - depends on the file
        raise InputDataError(f"{path}: cannot read CSV ({exc})") from exc
    missing = [c for c in _REQUIRED if c not in df.columns]
    if missing:
        raise InputDataError(f"{path}: missing columns {missing}")
    if len(df) == 0:
        raise InputDataError(f"{path}: table is empty")

    df = df.copy()
    df["sensor"] = [_sensor_key(s, c) for s, c in zip(df["source"], df["canopy_condition"])]
    # impossible CBH values (negative; some FI rows) are treated as missing
    df.loc[df["cbh_m"] < 0, "cbh_m"] = np.nan

    def pick(sub, col, order):
        for sensor in order:
            v = sub.loc[sub["sensor"] == sensor, col].dropna()
            if len(v):
                return float(v.iloc[0])
        return np.nan

    out_species = {}
    for name, sub in sorted(df.groupby("species"), key=lambda kv: kv[0]):
        by_sensor = {}
        for sensor, ss in sorted(sub.groupby("sensor"), key=lambda kv: kv[0]):
            entry = {"n_rows": int(len(ss))}
            for m in _METRICS:
                st = _stats(ss[m].to_numpy(dtype=float))
                if st["count"]:
                    entry[m] = st
            by_sensor[sensor] = entry
        rows = []
        for _tid, t in sub.groupby("id"):
            h = pick(t, "height_m", ("ULS_leaf_on", "ALS"))
            cbh = pick(t, "cbh_m", ("TLS", "ULS_leaf_on", "ALS"))
            cpa = pick(t, "cpa_convex_m2", ("ULS_leaf_on", "ALS"))
            dbh = pick(t, "dbh_cm", ("TLS", "FI"))
            if np.isfinite(h) and np.isfinite(cbh) and cbh >= h:
                cbh = np.nan
            rows.append((h, cbh, cpa, dbh))
        j = np.array(rows, dtype=float).reshape(-1, 4)
        h, cbh, cpa, dbh = j.T
        entry = {
            "key": name.lower().replace(".", "").replace(" ", "_"),
            "n_trees": int(sub["id"].nunique()),
            "by_sensor": by_sensor,
        }
        if np.isfinite(h).sum() >= _MIN_TREES_JOINT:
            radius = np.sqrt(cpa / np.pi)
            entry["joint"] = {
                "height_m": _stats(h),
                "cbh_m": _stats(cbh),
                "cpa_convex_m2": _stats(cpa),
                "dbh_cm": _stats(dbh),
                "cbh_ratio": _stats(cbh / h),
                "dbh_cm_on_height": _loglinear(h, dbh),
                "crown_radius_m_on_height": _loglinear(h, radius),
            }
        out_species[name] = entry

    return {
        "description": "Per-species summary of the real Bretten tree metrics (Weiser et al. 2022, "
        "pytreedb test data); regenerate with tools/summarise_bretten.py",
        "source_file": path.name,
        "source_sha256": hashlib.sha256(raw).hexdigest(),
        "quantile_levels": list(QUANTILE_LEVELS),
        "preferred": {
            "height_m": ["ULS_leaf_on", "ALS"],
            "cbh_m": ["TLS", "ULS_leaf_on", "ALS"],
            "cpa_convex_m2": ["ULS_leaf_on", "ALS"],
            "dbh_cm": ["TLS", "FI"],
        },
        "species": out_species,
    }
