"""The simulation loop: pulses → sub-rays → nearest hits → energy → waveform → returns → LAS.

Work is split into fixed blocks of pulse slots (``block_slots``, default 20 000). The range
noise of a return is a function of the seed, its pulse slot and its return number alone
(:func:`~vlsforest.sim.waveform.range_noise`), so the output depends only on the scene, the
survey and the seed — not on the number of worker processes, the block size or the region
traced. Blocks run in worker processes (fork) because Embree holds the GIL; results are
gathered in block order.

Detector options (the SURVEY.yaml ``detector:`` mapping)::

    detector:
      mode: physical          # or helios_v1: defaults of the switches below
      peak_rule: physical     # physical | helios            (quirk 3, isolated echoes)
      two_way_time: false     # one-way time axis as HELIOS++ (quirk 1)
      dedupe_ranges: false    # drop a sub-ray whose range equals an earlier one (quirk 5)
      atmosphere_convention: physical   # physical | helios  (quirk 12)
      return_position: axis   # axis (HELIOS++) | weighted (energy-weighted sub-ray hits)
      box_test: cone          # cone | axis: a pulse is traced when its beam cone (cone) or
                              # its central ray (axis, HELIOS++) meets the scene's bounding box
      threshold_scope: window # window (HELIOS++ 2.x) | peak: where min_energy applies (helios rule)

``mode: helios_v1`` sets ``peak_rule: helios, atmosphere_convention: helios, box_test: axis``;
``mode: physical`` (default) sets ``peak_rule: physical, atmosphere_convention: physical,
box_test: cone``; both set ``threshold_scope: window``. HELIOS++ skips a pulse whose central ray
misses the scene's bounding box, although its outer sub-rays may hit the scene's edge (quirk
13). Neither mode drops duplicate ranges: HELIOS++ keys a pulse's sub-ray hits by their
double-precision range, so two keys are equal only for an exact geometric tie, while ranges
from Embree are single precision, whose rounding makes sub-rays that hit one face at ranges a
few 10⁻⁵ m apart equal. Dropping those removes energy HELIOS++ keeps and raises the
multiple-return share above HELIOS++'s (``benchmarks/bench_helios.py``, its ``agreement``
block). Under the helios rule ``threshold_scope`` says whether ``min_energy`` is the floor of
the peak and of every neighbour in its window (``window``: HELIOS++ 2.x's
``receivedEnergyMin_W``) or the threshold of the peak amplitude alone, the neighbours keeping
HELIOS++ 1.0.8's fixed floor (``peak``: a receiver's threshold, the meaning ``min_energy`` has
under the physical rule; see :mod:`vlsforest.sim.waveform`). The sub-ray rings sit where HELIOS++ puts them in both
modes; the beam's width is the scanner's ``beam_divergence_mrad`` (the 1/e² half angle, see
:mod:`vlsforest.sim.scanner`), so a real sensor's beam is given there, not by a detector switch.
"""

from __future__ import annotations

import os
import sys
import time
from dataclasses import dataclass, field

import numba
import numpy as np

from vlsforest._memory import release_freed_memory
from vlsforest.errors import ConfigError, InputDataError, VlsforestError
from vlsforest.sim.beam import cones_meet_box, subray_directions, subray_pattern, subray_rays32
from vlsforest.sim.waveform import (atmospheric_alpha, detect_embree, detect_returns, detect_traced,
                                    detection_constants, energy_constants, hit_energy, las_intensity,
                                    range_noise)
from vlsforest.sim.workers import WorkerDied, fork_map

_MODES = {
    "physical": dict(peak_rule="physical", two_way_time=False, dedupe_ranges=False,
                     atmosphere_convention="physical", return_position="axis", box_test="cone",
                     threshold_scope="window"),
    "helios_v1": dict(peak_rule="helios", two_way_time=False, dedupe_ranges=False,
                      atmosphere_convention="helios", return_position="axis", box_test="axis",
                      threshold_scope="window"),
}
_CHOICES = {
    "peak_rule": ("physical", "helios"),
    "atmosphere_convention": ("physical", "helios"),
    "return_position": ("axis", "weighted"),
    "box_test": ("cone", "axis"),
    "threshold_scope": ("window", "peak"),
}


@dataclass(frozen=True)
class DetectorOptions:
    """Resolved detector switches (see the module docstring)."""

    peak_rule: str = "physical"
    two_way_time: bool = False
    dedupe_ranges: bool = False
    atmosphere_convention: str = "physical"
    return_position: str = "axis"
    box_test: str = "cone"
    threshold_scope: str = "window"

    @classmethod
    def from_dict(cls, d: dict | None) -> "DetectorOptions":
        """Resolve a ``detector:`` mapping; unknown keys or values raise ConfigError."""
        d = dict(d or {})
        mode = d.pop("mode", "physical")
        if mode not in _MODES:
            raise ConfigError(f"detector.mode must be one of {sorted(_MODES)}, got {mode!r}")
        opts = dict(_MODES[mode])
        for k, v in d.items():
            if k not in opts:
                raise ConfigError(f"detector.{k} is not a detector option (known: mode, {', '.join(opts)})")
            if k in _CHOICES and v not in _CHOICES[k]:
                raise ConfigError(f"detector.{k} must be one of {list(_CHOICES[k])}, got {v!r}")
            if k in ("two_way_time", "dedupe_ranges") and not isinstance(v, bool):
                raise ConfigError(f"detector.{k} must be true or false, got {v!r}")
            opts[k] = v
        return cls(**opts)


@dataclass
class SimulationResult:
    """What a simulation produced.

    Attributes
    ----------
    points : dict of ndarray
        Per return: ``xyz`` (n, 3), ``intensity``, ``amplitude``, ``return_number``,
        ``number_of_returns``, ``gps_time``, ``scan_angle``, ``point_source_id``,
        ``object_id``, ``classification``, ``pulse`` (global pulse slot).
    pulses : dict of ndarray
        Per emitted pulse: ``slot``, ``gps_time``, ``origin``, ``direction``, ``scan_dir``,
        ``scan_angle``, ``source_id``, ``n_returns``.
    hits : dict of ndarray or None
        Per sub-ray hit (when requested): ``pulse`` (row in ``pulses``), ``subray``,
        ``range``, ``cos_inc``, ``part``.
    timings : dict
        Seconds spent in ``total``, and counts ``n_pulses``, ``n_rays``, ``n_points``.
    """

    points: dict
    pulses: dict
    hits: dict | None
    timings: dict = field(default_factory=dict)

    def hit_pulses(self) -> tuple[dict, dict]:
        """The pulses with at least one stored hit and the hits re-indexed to them.

        Enough for :func:`redetect` (pulses without hits return nothing) at a fraction of the
        memory of all emitted pulses.
        """
        if self.hits is None:
            raise InputDataError("the simulation kept no sub-ray hits (run it with keep_hits=True)")
        keep = np.zeros(len(self.pulses["slot"]), bool)
        keep[np.unique(self.hits["pulse"])] = True
        hits = dict(self.hits)
        hits["pulse"] = (np.cumsum(keep) - 1)[hits["pulse"]]
        return {k: v[keep] for k, v in self.pulses.items()}, hits


class _Job:
    """Everything a block needs; forked workers inherit it (:func:`~vlsforest.sim.workers.fork_map`)."""

    def __init__(self, scene, survey, seed, keep_hits, block_slots, keep_pulses=True, region=None,
                 hits_only=False):
        self.hits_only = bool(hits_only)
        keep_hits = keep_hits or self.hits_only
        self.keep_pulses = keep_pulses or keep_hits
        self.scene = scene
        self.survey = survey
        self.seed = int(seed)
        self.keep_hits = keep_hits
        self.block_slots = int(block_slots)
        sc = survey.scanner
        self.opts = DetectorOptions.from_dict(survey.detector)
        self.pattern = subray_pattern(sc.beam.sample_quality, sc.beam.divergence_mrad, sc.beam.orientation_deg)
        self.atm_alpha = (atmospheric_alpha(sc.emitter.wavelength_nm, sc.atmosphere.visibility_km,
                                            self.opts.atmosphere_convention)
                          if sc.atmosphere.enabled else 0.0)
        mats = [p.material for p in scene.parts]
        self.refl_pct = np.array([m.reflectance * 100.0 for m in mats] + [0.0])
        self.spec = np.array([m.specularity for m in mats] + [0.0])
        self.shin = np.array([m.shininess for m in mats] + [1.0])
        self.object_id = np.array([p.object_id for p in scene.parts] + [0], dtype=np.int32)
        self.classification = np.array([p.classification for p in scene.parts] + [0], dtype=np.uint8)
        self.labels = bool(getattr(scene, "has_labels", False))
        #: trace voxel grids with the single-threaded kernel (set by _run_blocks)
        self.serial = False
        self.max_offset = float(np.abs(self.pattern.offsets).max()) * np.sqrt(2.0)
        # without stored hits and with returns on the beam axis, detection runs fused with the
        # hit collection (detect_traced) instead of building the hit arrays
        self.fused = not keep_hits and self.opts.return_position == "axis"
        # and for pure Embree scenes without face labels straight from Embree's answer
        self.raw_embree = self._raw_embree()
        self.tan_off = float(np.tan(self.max_offset))
        self.range_min = float(sc.detector.range_min_m)
        self.energy_const = energy_constants(
            n_subrays=self.pattern.n, average_power_w=sc.emitter.average_power_w,
            receiver_diameter_m=sc.detector.receiver_diameter_m, optical_efficiency=sc.detector.optical_efficiency,
            range0=sc.detector.range_min_m, m2=sc.beam.quality_factor, atm_alpha=self.atm_alpha)
        self.detection_const = detection_constants(
            pulse_length_ns=sc.emitter.pulse_length_ns, bin_size_ns=sc.detector.bin_size_ns,
            window_size_ns=sc.detector.window_size_ns, min_energy=sc.detector.min_energy,
            max_returns=sc.detector.max_returns, peak_rule=self.opts.peak_rule,
            two_way_time=self.opts.two_way_time, dedupe_ranges=self.opts.dedupe_ranges,
            threshold_scope=self.opts.threshold_scope)
        if hasattr(scene, "bounds"):
            self.box_lo, self.box_hi = scene.bounds()
            if region is not None:
                self.box_lo[:2] = np.maximum(self.box_lo[:2], region[:2])
                self.box_hi[:2] = np.minimum(self.box_hi[:2], region[2:])

    def _raw_embree(self) -> bool:
        scene = self.scene
        return (self.fused and bool(getattr(scene, "uses_embree", False))
                and not getattr(scene, "has_grids", False) and not self.labels)


def _expected_rays(job: _Job, n_blocks: int, n_sample: int = 64) -> float:
    """Sub-rays the job will trace, estimated from the pulses of up to ``n_sample`` evenly
    spread blocks (the same beam-box test as the blocks themselves; deterministic)."""
    survey = job.survey
    if n_blocks <= 0 or survey.n_slots == 0:
        return 0.0
    blocks = np.unique(np.linspace(0, n_blocks - 1, min(n_sample, n_blocks)).round().astype(np.int64))
    slots = traced = 0
    for b in blocks:
        start = int(b) * job.block_slots
        stop = min(start + job.block_slots, survey.n_slots)
        if job.fused and not job.keep_pulses:
            traced += len(survey.pulses_toward(start, stop, job.box_lo, job.box_hi, job.tan_off)[2])
        else:
            traced += len(_live_rows(job, survey.pulses(start, stop)))
        slots += stop - start
    return traced / max(slots, 1) * survey.n_slots * job.pattern.n


def _run_block(job: _Job, b: int):
    start = b * job.block_slots
    stop = min(start + job.block_slots, job.survey.n_slots)
    if job.fused and not job.keep_pulses:
        # only the emitted slots and the frames of the pulses whose beam reaches the scene are needed
        slots, live, traced_batch = job.survey.pulses_toward(start, stop, job.box_lo, job.box_hi, job.tan_off)
        if len(slots) == 0:
            return _empty_block(job)
        points, n_live = _trace_fused(job, traced_batch)
        n_ret = np.zeros(len(slots), np.int16)
        n_ret[live] = n_live
        return points, dict(slot=slots, n_returns=n_ret), None, len(live) * job.pattern.n
    if job.hits_only:
        return _hit_pulses_block(job, job.survey.pulses(start, stop))
    return _trace_and_detect(job, job.survey.pulses(start, stop))


def _warm_up(job: _Job, n_blocks: int, max_blocks: int = 256) -> None:
    """Compile (or load from numba's cache) the workers' kernels once, in the parent.

    Forked workers inherit them instead of each compiling the same kernels at once (on a fresh
    checkout that cost ≈ 40 s of CPU per worker for the voxel-grid kernel alone). Runs the
    workers' serial code on the first block that traces anything (its result is discarded; the
    workers redo it) and one ray through each voxel grid.
    """
    for b in range(min(n_blocks, max_blocks)):
        if _run_block(job, b)[3] > 0:
            break
    for grid in getattr(job.scene, "grids", ()):
        lo, hi = grid.bounds
        grid.trace(np.array([0.5 * (lo + hi) + [0.0, 0.0, hi[2] - lo[2] + 1.0]]), np.array([[0.0, 0.0, -1.0]]),
                   serial=True)


def _cast(job: _Job, origin, direction, scan_dir):
    """Trace the sub-ray fans of pulses: (t, part, cos_inc[, label]) per sub-ray, pulse-major."""
    pat = job.pattern
    if getattr(job.scene, "uses_embree", False):  # float32 rays straight into Embree's frame
        o32, d32 = subray_rays32(origin, direction, scan_dir, pat, job.scene.shift)
        return job.scene.trace_local(o32, d32, with_labels=job.labels, serial=job.serial)
    dirs = subray_directions(direction, scan_dir, pat).reshape(-1, 3)
    origins = np.repeat(origin, pat.n, axis=0)
    return job.scene.trace(origins, dirs, with_labels=job.labels, serial=job.serial)


def _trace_fused(job: _Job, batch):
    """Trace every pulse of ``batch`` and detect its returns in one pass over the cast
    (:func:`detect_traced`); returns the points and the number of returns per pulse."""
    nl = len(batch)
    if nl == 0:
        return _empty_block(job)[0], np.zeros(0, np.int16)
    pat = job.pattern
    live = np.arange(nl, dtype=np.int64)
    consts = (pat.frac, job.refl_pct, job.spec, job.shin, job.energy_const, job.detection_const)
    if job.raw_embree:  # Embree's answer read in place: no range / part / |cos| arrays
        o32, d32 = subray_rays32(batch.origin, batch.direction, batch.scan_dir, pat, job.scene.shift)
        tfar, geom, ng, parts = job.scene.cast_embree(o32, d32)
        p, ranges, amp, ray, num, nof, n_ret = detect_embree(tfar, geom, ng, d32, parts, live, pat.n, nl,
                                                             job.range_min, *consts)
        return _assemble(job, batch.georeferenced(), p, ranges, amp, parts[geom[ray]], None, num, nof), n_ret
    traced = _cast(job, batch.origin, batch.direction, batch.scan_dir)
    t, part, cos_inc = traced[:3]
    p, ranges, amp, ray, num, nof, n_ret = detect_traced(t, part, cos_inc, live, pat.n, nl, job.range_min, *consts)
    label = traced[3][ray] if job.labels else None
    return _assemble(job, batch.georeferenced(), p, ranges, amp, part[ray], label, num, nof), n_ret


def _trace_and_detect(job: _Job, batch):
    m = len(batch)
    pat = job.pattern
    ns = pat.n
    if m == 0:
        return _empty_block(job)
    live = _live_rows(job, batch)
    nl = len(live)
    if job.fused:  # hits, energy, waveform and peaks in one pass over the cast
        points, n_live = _trace_fused(job, batch.subset(live))
        n_ret = np.zeros(m, np.int16)
        n_ret[live] = n_live
        return points, _pulse_table(job, batch.georeferenced(), n_ret), None, nl * ns
    hits, ptr = _block_hits(job, batch, live)
    # traced along the true beams; returns placed along the recorded (nominal) ones
    geo = batch.georeferenced()
    points, n_ret = _detect(job, geo, ptr, hits)
    return points, _pulse_table(job, geo, n_ret), (hits if job.keep_hits else None), nl * ns


def _pulse_geometry(batch, rows=slice(None)) -> dict:
    """The stored pulse table's geometry columns for ``rows`` of ``batch`` (see
    :class:`_StoredBatch` for the way back)."""
    return dict(slot=batch.slot[rows], gps_time=batch.gps_time[rows], origin=batch.origin[rows],
                direction=batch.direction[rows], scan_dir=batch.scan_dir[rows],
                scan_angle=batch.scan_angle_deg[rows], source_id=batch.source_id[rows])


def _pulse_table(job: _Job, batch, n_ret) -> dict:
    """A block's pulse table: the geometry (when the job keeps it), the slots and returns."""
    if job.keep_pulses:
        return dict(_pulse_geometry(batch), n_returns=n_ret)
    return dict(slot=batch.slot, n_returns=n_ret)


def _live_rows(job: _Job, batch) -> np.ndarray:
    """Rows of ``batch`` to trace: the pulses whose beam cone (``box_test: cone``) or central ray
    (``box_test: axis``, HELIOS++) meets the scene's bounding box."""
    if len(batch) == 0:
        return np.zeros(0, np.int64)
    offset = 0.0 if job.opts.box_test == "axis" else job.max_offset
    return np.flatnonzero(_beam_meets_box(batch.origin, batch.direction, job.box_lo, job.box_hi, offset))


def _no_hit_pulses(job: _Job):
    """A block result of :func:`trace_hits` without any hit."""
    _, pulses, hits, _ = _empty_block(job)
    pulses.pop("n_returns")
    hits["pulse"] = hits["pulse"].astype(np.int32)
    return None, pulses, hits, 0


def _block_hits(job: _Job, batch, live):
    """Trace the sub-ray fans of the pulses ``live`` of ``batch``: the valid hits (pulse-major,
    ``pulse`` = batch row) and their CSR offsets over all rows of the batch."""
    ns = job.pattern.n
    traced = _cast(job, batch.origin[live], batch.direction[live], batch.scan_dir[live])
    t, part, cos_inc = traced[:3]
    idx, hpulse, ptr = _collect_hits(t, job.range_min, ns, live.astype(np.int64), len(batch))
    hits = dict(pulse=hpulse, subray=(idx % ns).astype(np.int16), range=t[idx],
                cos_inc=cos_inc[idx].astype(np.float32), part=part[idx])
    if job.labels:
        hits["label"] = traced[3][idx]
    return hits, ptr


def _hit_pulses_block(job: _Job, batch):
    """Block result of :func:`trace_hits`: the pulses with hits and their hits, no detection.

    ``hits["pulse"]`` is the row in the block's kept pulses (int32).
    """
    live = _live_rows(job, batch)
    if len(live) == 0:
        return _no_hit_pulses(job)
    hits, ptr = _block_hits(job, batch, live)
    counts = np.diff(ptr)
    keep = np.flatnonzero(counts > 0)
    hits["pulse"] = np.repeat(np.arange(len(keep), dtype=np.int32), counts[keep])
    return None, _pulse_geometry(batch.georeferenced(), keep), hits, len(live) * job.pattern.n


@numba.njit(cache=True)
def _collect_hits(t, range_min, ns, live, m):
    """Indices of the valid sub-ray hits (pulse-major), their pulse rows and CSR offsets."""
    n = 0
    for i in range(t.shape[0]):
        if t[i] < np.inf and t[i] >= range_min:
            n += 1
    idx = np.empty(n, np.int64)
    pulse = np.empty(n, np.int64)
    ptr = np.zeros(m + 1, np.int64)
    k = 0
    for i in range(t.shape[0]):
        if t[i] < np.inf and t[i] >= range_min:
            idx[k] = i
            p = live[i // ns]
            pulse[k] = p
            ptr[p + 1] += 1
            k += 1
    for p in range(m):
        ptr[p + 1] += ptr[p]
    return idx, pulse, ptr


def _beam_meets_box(origin, direction, lo, hi, max_offset):
    """Whether the cone of half-angle ``max_offset`` around each central ray meets the box."""
    return cones_meet_box(origin, direction, lo, hi, np.tan(max_offset))


def _detect(job: _Job, batch, ptr, hits):
    """Energy, waveform, peaks, noise and positions for a batch with its sub-ray hits."""
    sc = job.survey.scanner
    pat = job.pattern
    hpart = hits["part"]
    energy = hit_energy(hits["range"], hits["subray"], hits["cos_inc"], hpart, pat.frac, job.refl_pct, job.spec,
                        job.shin, pat.n, average_power_w=sc.emitter.average_power_w,
                        receiver_diameter_m=sc.detector.receiver_diameter_m,
                        optical_efficiency=sc.detector.optical_efficiency, range0=sc.detector.range_min_m,
                        m2=sc.beam.quality_factor, atm_alpha=job.atm_alpha)
    o = job.opts
    det = detect_returns(ptr, hits["range"], energy, pulse_length_ns=sc.emitter.pulse_length_ns,
                         bin_size_ns=sc.detector.bin_size_ns, window_size_ns=sc.detector.window_size_ns,
                         min_energy=sc.detector.min_energy, max_returns=sc.detector.max_returns,
                         peak_rule=o.peak_rule, two_way_time=o.two_way_time,
                         dedupe_ranges=o.dedupe_ranges, threshold_scope=o.threshold_scope)
    label = hits["label"][det["hit"]] if "label" in hits else None
    weighted = None
    if o.return_position != "axis":
        def weighted(ranges):
            return _weighted_positions(job, batch, ptr, hits, energy, det, ranges)
    points = _assemble(job, batch, det["pulse"], det["range"], det["amplitude"], hpart[det["hit"]], label,
                       det["return_number"], det["number_of_returns"], weighted)
    return points, det["n_returns"]


def _assemble(job: _Job, batch, p, ranges, amp, part, label, ret_num, n_of_ret, weighted=None):
    """The point arrays of detected returns: range noise, positions and per-point attributes.

    ``p`` is the batch row of each return, ``part`` the scene part of its nearest sub-ray hit;
    ``weighted`` (ranges → xyz) replaces the position on the central beam axis.
    """
    sigma = job.survey.scanner.detector.range_noise_m
    if sigma > 0:
        ranges = ranges + range_noise(job.seed, batch.slot[p], ret_num, sigma)
    if weighted is None:
        xyz = batch.origin[p] + ranges[:, None] * batch.direction[p]
    else:
        xyz = weighted(ranges)
    amp32 = amp.astype(np.float32)  # the stored amplitude; the intensity follows it exactly
    points = dict(xyz=xyz, amplitude=amp32,
                  intensity=las_intensity(amp32),
                  return_number=np.minimum(ret_num, 15).astype(np.uint8),
                  number_of_returns=np.minimum(n_of_ret, 15).astype(np.uint8),
                  gps_time=batch.gps_time[p], scan_angle=batch.scan_angle_deg[p],
                  point_source_id=batch.source_id[p], object_id=job.object_id[part],
                  classification=job.classification[part], pulse=batch.slot[p])
    if label is not None:
        points["label"] = label
    return points


def _weighted_positions(job, batch, ptr, hits, energy, det, ranges):
    """Energy-weighted mean position of the sub-ray hits that belong to each return."""
    pat = job.pattern
    hp = hits["pulse"]
    dirs = _subray_dir(batch, pat, hp, hits["subray"])
    pos = batch.origin[hp] + hits["range"][:, None] * dirs
    # assign each hit to the return of its pulse nearest in range
    ret_of_pulse_start = np.zeros(len(batch) + 1, dtype=np.int64)
    np.cumsum(np.bincount(det["pulse"], minlength=len(batch)), out=ret_of_pulse_start[1:])
    out = np.empty((len(ranges), 3))
    acc = np.zeros((len(ranges), 3))
    wsum = np.zeros(len(ranges))
    has_ret = ret_of_pulse_start[hp + 1] > ret_of_pulse_start[hp]
    best = np.full(len(hp), -1, dtype=np.int64)
    bestd = np.full(len(hp), np.inf)
    nmax = int(np.max(np.diff(ret_of_pulse_start))) if len(ranges) else 0
    for k in range(nmax):
        r = ret_of_pulse_start[hp] + k
        ok = has_ret & (r < ret_of_pulse_start[hp + 1])
        dd = np.where(ok, np.abs(hits["range"] - det["range"][np.minimum(r, len(ranges) - 1)]), np.inf)
        upd = dd < bestd
        bestd[upd] = dd[upd]
        best[upd] = r[upd]
    sel = best >= 0
    np.add.at(acc, best[sel], pos[sel] * energy[sel, None])
    np.add.at(wsum, best[sel], energy[sel])
    p = det["pulse"]
    axis = batch.origin[p] + ranges[:, None] * batch.direction[p]
    good = wsum > 0
    out[good] = acc[good] / wsum[good, None]
    out[~good] = axis[~good]
    # range noise moves the point along the central beam direction
    shift = ranges - det["range"]
    out += shift[:, None] * batch.direction[p]
    return out


def _subray_dir(batch, pattern, pulse_idx, subray_idx):
    d = batch.direction[pulse_idx]
    e1 = batch.scan_dir[pulse_idx]
    e2 = np.cross(d, e1)
    tt = np.tan(pattern.offsets[subray_idx])
    v = d + tt[:, 0, None] * e1 + tt[:, 1, None] * e2
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _empty_block(job):
    pts = dict(xyz=np.zeros((0, 3)), amplitude=np.zeros(0, np.float32), intensity=np.zeros(0, np.uint16),
               return_number=np.zeros(0, np.uint8), number_of_returns=np.zeros(0, np.uint8),
               gps_time=np.zeros(0), scan_angle=np.zeros(0), point_source_id=np.zeros(0, np.uint16),
               object_id=np.zeros(0, np.int32), classification=np.zeros(0, np.uint8), pulse=np.zeros(0, np.int64))
    pulses = dict(slot=np.zeros(0, np.int64), gps_time=np.zeros(0), origin=np.zeros((0, 3)),
                  direction=np.zeros((0, 3)), scan_dir=np.zeros((0, 3)), scan_angle=np.zeros(0),
                  source_id=np.zeros(0, np.uint16), n_returns=np.zeros(0, np.int16))
    if not job.keep_pulses:
        pulses = dict(slot=pulses["slot"], n_returns=pulses["n_returns"])
    hits = dict(pulse=np.zeros(0, np.int64), subray=np.zeros(0, np.int16), range=np.zeros(0),
                cos_inc=np.zeros(0, np.float32), part=np.zeros(0, np.int32))
    if job.labels:
        pts["label"] = np.zeros(0, np.uint8)
        hits["label"] = np.zeros(0, np.uint8)
    return pts, pulses, (hits if job.keep_hits else None), 0


def _concat(dicts):
    return {k: np.concatenate([d[k] for d in dicts]) for k in dicts[0]}


def _check_region(region):
    if region is None:
        return None
    region = np.asarray(region, dtype=np.float64)
    if region.shape != (4,) or not (region[0] < region[2] and region[1] < region[3]):
        raise ConfigError(f"region must be (xmin, ymin, xmax, ymax) with min < max, got {region!r}")
    return region


def _run_blocks(job: _Job, workers, progress, t0):
    """Run every block of ``job`` (forked workers when more than one) and yield the block
    results in block order."""
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, (int, np.integer))
                                or workers < 1):
        raise ConfigError(f"workers must be an integer ≥ 1 (None: all CPUs), got {workers!r}")
    survey, scene = job.survey, job.scene
    n_blocks = -(-survey.n_slots // job.block_slots)
    if n_blocks == 0:  # a survey without pulse slots: one empty block of the job's kind
        yield _no_hit_pulses(job) if job.hits_only else _empty_block(job)
        return
    if getattr(scene, "needs_ray_estimate", False):
        # voxel lattices to Embree or to the grid, whichever traces this survey sooner
        scene.plan_for_rays(_expected_rays(job, n_blocks))
        job.raw_embree = job._raw_embree()
    if hasattr(scene, "prepare"):
        scene.prepare()  # build voxel grids and the Embree BVH once, before forking
    requested = workers or os.cpu_count() or 1
    workers = min(requested, max(n_blocks, 1))
    if workers <= 1 or n_blocks <= 1:
        # one CPU asked for: the voxel-grid kernel runs without threads too
        job.serial = requested <= 1
        it = (_run_block(job, b) for b in range(n_blocks))
    else:
        # numba's default (workqueue) threading layer is not fork-safe: the forked workers
        # (and the warm-up that compiles their kernels) trace serially
        job.serial = True
        _warm_up(job, n_blocks)
        it = fork_map(_run_block, job, range(n_blocks), workers)
    try:
        for k, r in enumerate(it):
            yield r
            if progress and (k % max(1, n_blocks // 10) == 0 or k == n_blocks - 1):
                tty = sys.stderr.isatty()
                print(f"{chr(13) if tty else ''}simulate: block {k + 1}/{n_blocks} ({100 * (k + 1) / n_blocks:.0f} %, "
                      f"{time.perf_counter() - t0:.0f} s)", end="" if tty else "\n", file=sys.stderr, flush=True)
    except WorkerDied:
        raise VlsforestError("a simulation worker process died (out of memory?); "
                             "try fewer workers (--workers 1)") from None
    finally:
        it.close()
    if progress and sys.stderr.isatty():
        print(file=sys.stderr)


def _concat_freeing(dicts):
    """Concatenate block dicts key by key, dropping each key's block arrays once joined (peak
    memory: the result plus one key's blocks, instead of twice the result)."""
    out = {}
    for k in list(dicts[0]):
        out[k] = np.concatenate([d.pop(k) for d in dicts])
        release_freed_memory()  # the blocks' arrays of this key, before the next key's result
    return out


def simulate(scene, survey, seed: int | None = None, workers: int | None = None, keep_hits: bool = False,
             block_slots: int = 20000, progress: bool = False, keep_pulses: bool = True,
             region=None) -> SimulationResult:
    """Run a survey over a scene.

    Parameters
    ----------
    scene : vlsforest.sim.scene.Scene
    survey : vlsforest.sim.survey.Survey
    seed : int, optional
        Seed of the range noise; defaults to the survey's ``seed``.
    workers : int, optional
        Worker processes, ≥ 1 (default None: number of CPUs, at most the number of blocks). With
        1 the survey runs in this process on one CPU (the voxel-grid kernel without threads too).
    keep_hits : bool
        Also return every sub-ray hit (for :func:`redetect`).
    keep_pulses : bool
        Keep each pulse's geometry (origin, directions, scan angle, source id) in
        ``result.pulses``; without it only ``slot`` and ``n_returns`` are kept (less memory and
        inter-process traffic).
    block_slots : int
        Pulse slots per block (the work unit of the worker processes; the result does not
        depend on it).
    region : (xmin, ymin, xmax, ymax), optional
        Trace only pulses whose beam reaches this horizontal region (the others are emitted
        and kept as zero-return pulses); geometry outside it still occludes and reflects.
    progress : bool
        Print progress to stderr.

    Returns
    -------
    SimulationResult
    """
    t0 = time.perf_counter()
    seed = survey.seed if seed is None else seed
    job = _Job(scene, survey, seed, keep_hits, block_slots, keep_pulses, _check_region(region))
    results = list(_run_blocks(job, workers, progress, t0))
    n_rays = int(sum(r[3] for r in results))
    hits = None
    if keep_hits:
        off = 0
        for r in results:  # each block's pulse indices, offset by the pulses of the blocks before it
            r[2]["pulse"] = r[2]["pulse"] + off
            off += len(r[1]["slot"])
        hits = _concat_freeing([r[2] for r in results])
    points = _concat_freeing([r[0] for r in results])
    pulses = _concat_freeing([r[1] for r in results])
    del results
    timings = dict(total=time.perf_counter() - t0, n_pulses=len(pulses["slot"]), n_rays=n_rays,
                   n_points=len(points["xyz"]))
    return SimulationResult(points, pulses, hits, timings)


def simulate_in_blocks(scene, survey, seed: int | None = None, workers: int | None = None,
                       block_slots: int = 20000, progress: bool = False, region=None):
    """Run a survey as :func:`simulate` does and yield its returns block by block.

    For a consumer that writes the returns as they come (:func:`vlsforest.sim.output.simulate_to_las`)
    and keeps neither the pulse table nor the hits: the blocks' points joined are
    ``simulate(...).points`` with the same arguments.

    Parameters
    ----------
    scene, survey, seed, workers, block_slots, progress, region
        As for :func:`simulate`.

    Yields
    ------
    points : dict of ndarray
        The block's returns (the keys of :attr:`SimulationResult.points`); one empty block for
        a survey without slots.
    n_pulses : int
        The block's emitted pulses.
    n_rays : int
        The block's traced sub-rays.
    """
    seed = survey.seed if seed is None else seed
    job = _Job(scene, survey, seed, False, block_slots, False, _check_region(region))
    for points, pulses, _, n_rays in _run_blocks(job, workers, progress, time.perf_counter()):
        yield points, len(pulses["slot"]), int(n_rays)


def trace_hits(scene, survey, seed: int | None = None, workers: int | None = None, block_slots: int = 20000,
               region=None, progress: bool = False) -> tuple[dict, dict]:
    """Trace a survey and keep only what :func:`redetect` needs: no detection, no points.

    Gives what ``simulate(..., keep_hits=True).hit_pulses()`` gives (``redetect`` on it
    returns the same points bit for bit), without building the points, the zero-hit pulses or
    a second copy of the hits: each block keeps only its pulses with hits, and the blocks are
    joined key by key. For fitting detection settings to a large recording (the diagnosis
    keeps such traces in memory).

    Parameters
    ----------
    scene, survey, seed, workers, block_slots, region, progress
        As in :func:`simulate`.

    Returns
    -------
    pulses : dict
        The pulse geometry of the pulses with at least one hit (``slot``, ``gps_time``,
        ``origin``, ``direction``, ``scan_dir``, ``scan_angle``, ``source_id``), in slot order.
    hits : dict
        Their sub-ray hits (``pulse`` — the row in ``pulses``, int32 unless the survey has
        2³¹ slots or more —, ``subray``, ``range``, ``cos_inc``, ``part``, [``label``]).
    """
    t0 = time.perf_counter()
    seed = survey.seed if seed is None else seed
    job = _Job(scene, survey, seed, True, block_slots, True, _check_region(region), hits_only=True)
    index = np.int32 if survey.n_slots < 2 ** 31 else np.int64
    pulse_parts, hit_parts, off = [], [], 0
    for _, pulses, hits, _ in _run_blocks(job, workers, progress, t0):
        hits["pulse"] = hits["pulse"].astype(index) + index(off)
        off += len(pulses["slot"])
        pulse_parts.append(pulses)
        hit_parts.append(hits)
    return _concat_freeing(pulse_parts), _concat_freeing(hit_parts)


class _StoredBatch:
    """A pulse batch rebuilt from a stored pulse table (for :func:`redetect`)."""

    def __init__(self, pulses: dict, sel):
        self.slot = pulses["slot"][sel]
        self.gps_time = pulses["gps_time"][sel]
        self.origin = pulses["origin"][sel]
        self.direction = pulses["direction"][sel]
        self.scan_dir = pulses["scan_dir"][sel]
        self.scan_angle_deg = pulses["scan_angle"][sel]
        self.source_id = pulses["source_id"][sel]

    def __len__(self):
        return len(self.slot)


def hit_offsets(pulses: dict, hits: dict) -> np.ndarray:
    """Where each stored pulse's sub-ray hits start in ``hits`` (for :func:`redetect`).

    Parameters
    ----------
    pulses, hits : dict
        As in :class:`SimulationResult`: pulses in ascending slot order, hits grouped by pulse
        in pulse order.

    Returns
    -------
    ndarray of int64, shape (n_pulses + 1,)
        Pulse ``i``'s hits are ``hits[...][ptr[i]:ptr[i + 1]]``.

    Raises
    ------
    InputDataError
        The pulses or hits are not in that order, or a hit names a pulse that is not stored.
    """
    if np.any(np.diff(pulses["slot"]) <= 0) or np.any(np.diff(hits["pulse"]) < 0):
        raise InputDataError("the stored pulses must be in ascending slot order and the hits grouped by pulse "
                             "in pulse order (as simulate and trace_hits give them)")
    n = len(hits["pulse"])
    if n and (int(hits["pulse"][0]) < 0 or int(hits["pulse"][-1]) >= len(pulses["slot"])):
        raise InputDataError(f"the stored hits name pulses outside 0…{len(pulses['slot']) - 1} "
                             "(the hits and pulses of different simulations?)")
    ptr = np.zeros(len(pulses["slot"]) + 1, dtype=np.int64)
    np.cumsum(np.bincount(hits["pulse"], minlength=len(pulses["slot"])), out=ptr[1:])
    return ptr


def redetect(scene_parts: dict, pulses: dict, hits: dict, survey, seed: int | None = None,
             block_slots: int = 20000, beam: dict | None = None,
             hit_ptr: np.ndarray | None = None) -> SimulationResult:
    """Re-run detection (energy, waveform, peaks, noise) on stored sub-ray hits — no tracing.

    The beam geometry (divergence, sample quality) must be the one the hits were traced
    with; detection settings (window, bins, pulse length, threshold, noise, max returns,
    reflectances) may differ. With unchanged settings and seed the result equals the
    original simulation bit for bit.

    Parameters
    ----------
    scene_parts : dict
        ``object_id``, ``classification``, ``reflectance``, ``specularity``, ``shininess``
        arrays per scene part (as stored by :func:`save_hits`).
    pulses, hits : dict
        As in :class:`SimulationResult`.
    survey : vlsforest.sim.survey.Survey
        Detection settings come from its scanner and ``detector:`` mapping.
    seed : int, optional
        Noise seed (default: the survey's).
    block_slots : int
        Pulse slots per block of the re-detection (the result does not depend on it).
    beam : dict, optional
        The beam geometry the hits were traced with (as :func:`vlsforest.sim.output.load_hits`
        returns it); any difference from the survey's scanner is a :class:`ConfigError`.
    hit_ptr : ndarray, optional
        :func:`hit_offsets` of ``pulses`` and ``hits``, computed here when not given (a caller
        that re-detects the same hits many times computes it once).
    """
    from types import SimpleNamespace

    if beam is not None:
        from vlsforest.sim.output import beam_mismatch

        diff = beam_mismatch(beam, survey.scanner)
        if diff:
            raise ConfigError(f"the survey's beam geometry differs from the one the hits were traced with "
                              f"({'; '.join(diff)}); detection needs the traced beam")

    t0 = time.perf_counter()
    seed = survey.seed if seed is None else seed
    fake_scene = SimpleNamespace(parts=[
        SimpleNamespace(material=SimpleNamespace(reflectance=r, specularity=s, shininess=h), object_id=o,
                        classification=c)
        for o, c, r, s, h in zip(scene_parts["object_id"], scene_parts["classification"],
                                 scene_parts["reflectance"], scene_parts["specularity"], scene_parts["shininess"])])
    job = _Job(fake_scene, survey, seed, False, block_slots)
    if len(hits["subray"]) and int(hits["subray"].max()) >= job.pattern.n:
        raise ConfigError(f"the hits were traced with more sub-rays than the survey's beam_sample_quality "
                          f"{survey.scanner.beam.sample_quality} gives ({job.pattern.n}); detection needs the "
                          "beam geometry the hits were traced with")
    blocks = pulses["slot"] // job.block_slots
    if hit_ptr is None:
        hit_ptr = hit_offsets(pulses, hits)
    elif len(hit_ptr) != len(pulses["slot"]) + 1 or (len(hit_ptr) and int(hit_ptr[-1]) != len(hits["pulse"])):
        raise InputDataError("hit_ptr is not the hit_offsets of these pulses and hits")
    pts, n_ret = [], []
    ub, first = np.unique(blocks, return_index=True)
    for b, r0, r1 in zip(ub, first, np.r_[first[1:], len(blocks)]):
        batch = _StoredBatch(pulses, slice(r0, r1))
        h0, h1 = hit_ptr[r0], hit_ptr[r1]
        h = {k: v[h0:h1] for k, v in hits.items()}
        h["pulse"] = h["pulse"] - r0
        ptr = hit_ptr[r0:r1 + 1] - h0
        p, n = _detect(job, batch, ptr, h)
        pts.append(p)
        n_ret.append(n)
    if not pts:
        pts = [_empty_block(job)[0]]
        n_ret = [np.zeros(0, np.int16)]
    points = _concat(pts)
    new_pulses = dict(pulses)
    new_pulses["n_returns"] = np.concatenate(n_ret)
    return SimulationResult(points, new_pulses, hits, dict(total=time.perf_counter() - t0,
                                                           n_pulses=len(pulses["slot"]), n_rays=0,
                                                           n_points=len(points["xyz"])))
