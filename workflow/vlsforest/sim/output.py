"""Writing simulation results: LAS/LAZ points, the per-pulse table and the sub-ray hits.

- Points: LAS 1.4 point format 6 with the standard fields (xyz, intensity = the peak
  amplitude scaled as HELIOS++ does, :func:`vlsforest.sim.waveform.las_intensity`, return number, number of returns (both capped at
  15, the LAS 1.4 limit), GPS time, scan angle, point source id = flight line / scan position,
  classification) plus extra dimensions ``object_id`` (int32) and ``amplitude`` (float32).
- Pulses (``.npz`` or ``.csv``): one row per emitted pulse, zero-return pulses included:
  slot, gps_time, origin xyz, direction xyz, scan_dir xyz, scan_angle, source_id, n_returns.
- Hits (``.npz``): the pulse table, every sub-ray hit (pulse row, sub-ray, range, |cos|
  incidence, part), the scene's part table and the beam geometry the hits were traced with
  (divergence, orientation, sample quality), so :func:`vlsforest.sim.engine.redetect`
  can re-run detection without tracing, and refuses a survey with another beam.

Every file is written whole or not at all (:mod:`vlsforest.io.atomic`); the loaders validate
every array (:func:`vlsforest.io.npz.load_npz`).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from vlsforest.errors import InputDataError
from vlsforest.io.atomic import atomic_path
from vlsforest.io.las import LasPieces, PointCloud, write_las
from vlsforest.io.npz import ArraySpec, load_npz, save_npz
from vlsforest.sim.engine import simulate_in_blocks

_PULSE_COLS = ("slot", "gps_time", "origin", "direction", "scan_dir", "scan_angle", "source_id", "n_returns")
#: the documented suffixes of the outputs
POINTS_SUFFIXES = (".las", ".laz")
PULSES_SUFFIXES = (".npz", ".csv")
HITS_SUFFIXES = (".npz",)
#: the arrays of a pulse table ("p": one row per pulse)
PULSE_SPEC = {"slot": ArraySpec("iu", ("p",)), "gps_time": ArraySpec("f", ("p",)),
              "origin": ArraySpec("f", ("p", 3)), "direction": ArraySpec("f", ("p", 3)),
              "scan_dir": ArraySpec("f", ("p", 3)), "scan_angle": ArraySpec("f", ("p",)),
              "source_id": ArraySpec("iu", ("p",)), "n_returns": ArraySpec("iu", ("p",))}
#: the beam geometry stored with the hits: detection needs the one the hits were traced with
BEAM_SPEC = {"beam_divergence_mrad": ArraySpec("f", (2,)), "beam_orientation_deg": ArraySpec("f", ()),
             "beam_sample_quality": ArraySpec("iu", ())}
#: the arrays of a hits file ("p": pulses, "h": sub-ray hits, "s": scene parts)
HITS_SPEC = {**{f"pulse_{k}": v for k, v in PULSE_SPEC.items()},
             "hit_pulse": ArraySpec("iu", ("h",)), "hit_subray": ArraySpec("iu", ("h",)),
             "hit_range": ArraySpec("f", ("h",)), "hit_cos_inc": ArraySpec("f", ("h",)),
             "hit_part": ArraySpec("iu", ("h",)), "hit_label": ArraySpec("iu", ("h",), required=False),
             "part_object_id": ArraySpec("iu", ("s",)), "part_classification": ArraySpec("iu", ("s",)),
             "part_reflectance": ArraySpec("f", ("s",)), "part_specularity": ArraySpec("f", ("s",)),
             "part_shininess": ArraySpec("f", ("s",)), "block_slots": ArraySpec("iu", ()), **BEAM_SPEC}


def beam_geometry(scanner) -> dict:
    """The beam geometry of a scanner that sub-ray hits depend on, as stored in a hits file.

    Parameters
    ----------
    scanner : vlsforest.sim.scanner.ScannerSettings
        The survey's scanner.

    Returns
    -------
    dict
        ``beam_divergence_mrad`` (major, minor), ``beam_orientation_deg``, ``beam_sample_quality``.
    """
    beam = scanner.beam
    return {"beam_divergence_mrad": np.asarray(beam.divergence_mrad, dtype=np.float64).reshape(2),
            "beam_orientation_deg": np.float64(beam.orientation_deg),
            "beam_sample_quality": np.int64(beam.sample_quality)}


def beam_mismatch(stored: dict, scanner) -> list[str]:
    """The beam geometry keys on which a scanner differs from the stored geometry (empty: none).

    Each entry reads ``key stored → survey``.
    """
    now = beam_geometry(scanner)
    return [f"{k} {np.asarray(stored[k]).tolist()} → {np.asarray(now[k]).tolist()}"
            for k in BEAM_SPEC if not np.allclose(np.asarray(stored[k], float), np.asarray(now[k], float),
                                                  rtol=1e-12, atol=0.0)]


def _las_attrs(p: dict) -> dict:
    """A simulation's returns as the attributes of a LAS file (the order of its fields)."""
    attrs = {k: p[k] for k in ("intensity", "return_number", "number_of_returns", "gps_time", "scan_angle",
                               "classification")}
    attrs["point_source_id"] = p["point_source_id"]
    attrs["object_id"] = p["object_id"].astype(np.int32)
    attrs["amplitude"] = p["amplitude"].astype(np.float32)
    if "label" in p:
        attrs["label"] = p["label"].astype(np.uint8)
    return attrs


def write_points(path, result) -> Path:
    """Write the returns of a :class:`SimulationResult` as LAS/LAZ."""
    return write_las(path, PointCloud(result.points["xyz"], _las_attrs(result.points)))


def simulate_to_las(scene, survey, path, seed: int | None = None, workers: int | None = None,
                    block_slots: int = 20000, progress: bool = False, region=None) -> dict:
    """Run a survey and write its returns as LAS/LAZ, block by block.

    The file holds the bytes ``write_points(path, simulate(scene, survey, ...))`` writes, without
    the run ever holding its returns as one cloud or any pulse table: each block's returns are
    packed into point records as they arrive (:class:`vlsforest.io.las.LasPieces`, 62 bytes a
    return), and beyond 128 MB of them the earlier blocks wait in an unnamed temporary file in
    the output's folder until the write, so a long survey's returns add at most about that
    much to the simulation's own memory.

    Parameters
    ----------
    scene, survey, seed, workers, block_slots, progress, region
        As for :func:`vlsforest.sim.engine.simulate`.
    path : str or Path
        The LAS/LAZ file (written whole or not at all).

    Returns
    -------
    dict
        The timings and counts of :attr:`SimulationResult.timings`: ``total`` (seconds of the
        simulation, the write not included), ``n_pulses``, ``n_rays``, ``n_points``.
    """
    t0 = time.perf_counter()
    pieces = LasPieces(path)
    n_pulses = n_rays = 0
    for points, pulses, rays in simulate_in_blocks(scene, survey, seed=seed, workers=workers,
                                                   block_slots=block_slots, progress=progress, region=region):
        pieces.add(PointCloud(points.pop("xyz"), _las_attrs(points)))
        n_pulses, n_rays = n_pulses + pulses, n_rays + rays
    timings = dict(total=time.perf_counter() - t0, n_pulses=n_pulses, n_rays=n_rays, n_points=pieces.n_points)
    pieces.write()
    return timings


def write_pulses(path, result) -> Path:
    """Write the per-pulse table (``.npz``, or ``.csv`` by extension)."""
    path = Path(path)
    if path.suffix.lower() not in PULSES_SUFFIXES:
        raise InputDataError(f"{path}: a pulse table is written as {' or '.join(PULSES_SUFFIXES)}")
    pu = result.pulses
    if path.suffix.lower() == ".csv":
        import pandas as pd

        cols = {"slot": pu["slot"], "gps_time": pu["gps_time"]}
        for name in ("origin", "direction", "scan_dir"):
            for i, ax in enumerate("xyz"):
                cols[f"{name}_{ax}"] = pu[name][:, i]
        cols.update(scan_angle=pu["scan_angle"], source_id=pu["source_id"], n_returns=pu["n_returns"])
        with atomic_path(path) as tmp:
            pd.DataFrame(cols).to_csv(tmp, index=False, float_format="%.9g")
    else:
        save_npz(path, {k: pu[k] for k in _PULSE_COLS})
    return path


def save_hits(path, result, scene, scanner, block_slots: int = 20000) -> Path:
    """Save pulses, sub-ray hits, the scene's part table and the beam geometry for re-detection.

    Parameters
    ----------
    path : str or Path
        The ``.npz`` to write.
    result : SimulationResult
        A result kept with ``keep_hits=True``.
    scene : vlsforest.sim.scene.Scene
        The scene traced (its part table is stored).
    scanner : vlsforest.sim.scanner.ScannerSettings
        The scanner traced with (its beam geometry is stored, :func:`beam_geometry`).
    block_slots : int
        The tracing block size (noise streams depend on it).
    """
    if result.hits is None:
        raise InputDataError("the simulation kept no sub-ray hits (run it with keep_hits=True)")
    path = Path(path)
    data = {f"pulse_{k}": result.pulses[k] for k in _PULSE_COLS}
    data.update({f"hit_{k}": v for k, v in result.hits.items()})
    data.update({f"part_{k}": v for k, v in scene.part_table().items()})
    data["block_slots"] = np.array(block_slots)
    data.update(beam_geometry(scanner))
    save_npz(path, data)
    return path


def load_hits(path) -> tuple[dict, dict, dict, int, dict]:
    """Load and validate a file written by :func:`save_hits`.

    Returns
    -------
    tuple
        ``(parts, pulses, hits, block_slots, beam)``; ``beam`` as :func:`beam_geometry` gives it.

    Raises
    ------
    InputDataError
        For a file that is not a complete hits file (:func:`vlsforest.io.npz.load_npz`), or
        whose hits point at pulses, sub-rays or parts it does not hold.
    """
    path = Path(path)
    z = load_npz(path, HITS_SPEC, "hits")
    pulses = {k: z[f"pulse_{k}"] for k in _PULSE_COLS}
    hits = {k[4:]: v for k, v in z.items() if k.startswith("hit_")}
    parts = {k[5:]: v for k, v in z.items() if k.startswith("part_")}
    beam = {k: z[k] for k in BEAM_SPEC}
    n_pulses, n_parts = len(pulses["slot"]), len(parts["object_id"])
    for name, n in (("pulse", n_pulses), ("part", n_parts)):
        h = hits[name]
        if len(h) and (int(h.min()) < 0 or int(h.max()) >= n):
            raise InputDataError(f"{path}: array 'hit_{name}' refers to rows outside the {n} stored {name}s")
    if int(z["block_slots"]) < 1:
        raise InputDataError(f"{path}: array 'block_slots' must be ≥ 1, got {int(z['block_slots'])}")
    return parts, pulses, hits, int(z["block_slots"]), beam


def load_pulses(path) -> dict:
    """Load and validate a pulse table written by :func:`write_pulses` (``.npz`` or ``.csv``).

    Raises
    ------
    InputDataError
        For a file that is not a complete pulse table; the message names the file and column.
    """
    path = Path(path)
    if path.suffix.lower() != ".csv":
        z = load_npz(path, PULSE_SPEC, "pulses")
        return {k: z[k] for k in _PULSE_COLS}
    import pandas as pd

    if not path.is_file():
        raise InputDataError(f"{path}: no such pulses file")
    try:
        df = pd.read_csv(path)
    except Exception as exc:  # empty, binary or ragged text
        raise InputDataError(f"{path}: not a pulse table ({' '.join(str(exc).split())})") from None
    out = {}
    for k in _PULSE_COLS:
        cols = [f"{k}_{ax}" for ax in "xyz"] if PULSE_SPEC[k].shape == ("p", 3) else [k]
        missing = [c for c in cols if c not in df.columns]
        if missing:
            raise InputDataError(f"{path}: the pulse table lacks the column(s) {', '.join(missing)}")
        vals = df[cols].to_numpy()
        if vals.dtype.kind not in "fiu" or not np.isfinite(vals.astype(float)).all():
            raise InputDataError(f"{path}: column {cols[0]!r} holds non-numeric, NaN or infinite values")
        out[k] = vals if len(cols) == 3 else vals[:, 0]
    return out
