"""Writing simulation results: LAS/LAZ points, the per-pulse table and the sub-ray hits.

- Points: LAS 1.4 point format 6 with the standard fields (xyz, intensity = the peak
  amplitude scaled as HELIOS++ does, :func:`vlsforest.sim.waveform.las_intensity`, return number, number of returns (both capped at
  15, the LAS 1.4 limit), GPS time, scan angle, point source id = flight line / scan position,
  classification) plus extra dimensions ``object_id`` (int32) and ``amplitude`` (float32).
- Pulses (``.npz`` or ``.csv``): one row per emitted pulse, zero-return pulses included:
  slot, gps_time, origin xyz, direction xyz, scan_dir xyz, scan_angle, source_id, n_returns.
- Hits (``.npz``): the pulse table, every sub-ray hit (pulse row, sub-ray, range, |cos|
  incidence, part) and the scene's part table, so :func:`vlsforest.sim.engine.redetect`
  can re-run detection without tracing.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vlsforest.errors import InputDataError
from vlsforest.io.las import PointCloud, write_las
from vlsforest.io.npz import save_npz

_PULSE_COLS = ("slot", "gps_time", "origin", "direction", "scan_dir", "scan_angle", "source_id", "n_returns")


def write_points(path, result) -> Path:
    """Write the returns of a :class:`SimulationResult` as LAS/LAZ."""
    p = result.points
    attrs = {k: p[k] for k in ("intensity", "return_number", "number_of_returns", "gps_time", "scan_angle",
                               "classification")}
    attrs["point_source_id"] = p["point_source_id"]
    attrs["object_id"] = p["object_id"].astype(np.int32)
    attrs["amplitude"] = p["amplitude"].astype(np.float32)
    if "label" in p:
        attrs["label"] = p["label"].astype(np.uint8)
    return write_las(path, PointCloud(p["xyz"], attrs))


def write_pulses(path, result) -> Path:
    """Write the per-pulse table (``.npz``, or ``.csv`` by extension)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    pu = result.pulses
    if path.suffix.lower() == ".csv":
        import pandas as pd

        cols = {"slot": pu["slot"], "gps_time": pu["gps_time"]}
        for name in ("origin", "direction", "scan_dir"):
            for i, ax in enumerate("xyz"):
                cols[f"{name}_{ax}"] = pu[name][:, i]
        cols.update(scan_angle=pu["scan_angle"], source_id=pu["source_id"], n_returns=pu["n_returns"])
        pd.DataFrame(cols).to_csv(path, index=False, float_format="%.9g")
    else:
        save_npz(path, {k: pu[k] for k in _PULSE_COLS})
    return path


def save_hits(path, result, scene, block_slots: int = 20000) -> Path:
    """Save pulses, sub-ray hits and the scene's part table for later re-detection."""
    if result.hits is None:
        raise InputDataError("the simulation kept no sub-ray hits (run it with keep_hits=True)")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    data = {f"pulse_{k}": result.pulses[k] for k in _PULSE_COLS}
    data.update({f"hit_{k}": v for k, v in result.hits.items()})
    data.update({f"part_{k}": v for k, v in scene.part_table().items()})
    data["block_slots"] = np.array(block_slots)
    save_npz(path, data)
    return path


def load_hits(path) -> tuple[dict, dict, dict, int]:
    """Load a file written by :func:`save_hits`: (parts, pulses, hits, block_slots)."""
    path = Path(path)
    if not path.is_file():
        raise InputDataError(f"{path}: no such file")
    try:
        z = np.load(path)
        keys = set(z.files)
        pulses = {k: z[f"pulse_{k}"] for k in _PULSE_COLS}
        hits = {k[4:]: z[k] for k in keys if k.startswith("hit_")}
        parts = {k[5:]: z[k] for k in keys if k.startswith("part_")}
        block = int(z["block_slots"])
    except (KeyError, ValueError, OSError) as exc:
        raise InputDataError(f"{path}: not a vlsforest hits file ({exc})") from None
    return parts, pulses, hits, block
