"""Recordings of the virtual forest: multi-scan TLS, and "real" ALS and ULS with fuller physics.

What a field campaign would deliver, made by scanning the leaf-level truth geometry with our
own simulator. The recordings record the sensors as they are: the datasheet beams
(:data:`~vlsforest.sim.scanner.REAL_BEAMS`: the VQ-780i's 0.25 mrad and the miniVUX's elliptical
1.6 × 0.5 mrad at 50 % peak intensity), the presets' datasheet ranging accuracy and a physical
detector (``detector: {mode: physical, threshold_scope: peak}``), plus the recording physics
(:data:`DEFAULT_RECORDING_PHYSICS`, replaceable with ``--recording-physics FILE``): 37 sub-rays,
an energy threshold on the peak amplitude, at most 5–7 returns and small trajectory noise. Its keys are the
physics-candidate ids of the diagnosis stage, per sensor::

    als:
      beam_sample_quality: 4                 # 37 sub-rays
      elliptical_footprint: {major_mrad: 0.25, minor_mrad: 0.25, convention: 1/e2}
      detection_threshold: {min_energy: 60}  # peak amplitude units of the energy model
      trajectory_noise: {position_sigma_m: 0.05, attitude_sigma_deg: 0.006, correlation_s: 2.0}
      max_returns: {n: 7}
    uls:
      elliptical_footprint: {major_mrad: 1.6, minor_mrad: 0.5, convention: fwhm, orientation_deg: 0}
      …
    tls: {}

``elliptical_footprint`` gives the beam as datasheet full angles, at 50 % peak intensity
(``convention: fwhm``, the default) or at 1/e² (``convention: 1/e2``). Every key is optional;
a missing key leaves the scanner preset's value (the study's simulation setting). Unknown keys
are an error. Further candidates (``beam_divergence`` ``{scale}``, ``range_noise``
``{sigma_m}``, ``waveform_window`` ``{window_ns}``, ``peak_rule`` ``{physical}`` (0: the
HELIOS++ 1.0.8 rule), ``incidence_reflectance`` ``{specularity, shininess}``, ``reflectance``
``{foliage, wood, ground}``) are accepted too.

Scene of a plot: the rough ground as a mesh (object id 1, class 2) and per tree two mesh parts,
wood (object id ``10·tree_id + 1``) and foliage (``10·tree_id + 2``), both labelled per face
with the organ (0 stem, 1 branch, 2 foliage). The delivered clouds carry no object ids or
labels; those go to ``truth/``.
"""

from __future__ import annotations

import copy
import json
import multiprocessing
import sys
import time
import zlib
from concurrent.futures import FIRST_EXCEPTION, ProcessPoolExecutor, wait
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from vlsforest.errors import ConfigError, InputDataError
from vlsforest.io.atomic import adopt_outputs, collect_outputs, make_folder, output_transaction, write_csv, write_text
from vlsforest.io.yamlfile import read_yaml
from vlsforest.io.las import PointCloud, write_las
from vlsforest.domain.labels import GROUND_ID
from vlsforest.io.mesh import TriangleMesh, write_mesh
from vlsforest.sim.engine import simulate
from vlsforest.io.npz import save_npz
from vlsforest.sim.planning import plan_survey
from vlsforest.sim.scanner import PRESETS, REAL_BEAMS, datasheet_divergence
from vlsforest.sim.scene import Material, Scene
from vlsforest.sim.survey import survey_from_dict

WOOD, FOLIAGE = 1, 2
#: the airborne recordings trace the pulses that reach the plot ± this (m; :func:`recording_region`)
RECORDING_PAD_M = 3.0

DEFAULT_RECORDING_PHYSICS = {
    "als": {
        "beam_sample_quality": 4,
        "elliptical_footprint": {"major_mrad": REAL_BEAMS["riegl_vq780i"]["full_1e2_mrad"][0],
                                 "minor_mrad": REAL_BEAMS["riegl_vq780i"]["full_1e2_mrad"][1],
                                 "convention": "1/e2", "orientation_deg": 0.0},
        # Detection thresholds in peak amplitude units of the energy model (a full-footprint hit
        # on foliage is ≈ 400 at the ALS's 700 m and ≈ 40 000 at the ULS's 70 m; the divergence
        # cancels from it): a real receiver loses the weakest partial hits, and the recordings'
        # multiple-return shares are compared with the real Bretten targets' in the report.
        "detection_threshold": {"min_energy": 60.0},
        # GNSS/INS errors of a manned survey: ~5 cm position, 0.006° attitude (7 cm at 700 m)
        "trajectory_noise": {"position_sigma_m": 0.05, "attitude_sigma_deg": 0.006, "correlation_s": 2.0},
        "max_returns": {"n": 7},
    },
    "uls": {
        "beam_sample_quality": 4,
        "elliptical_footprint": {"major_mrad": REAL_BEAMS["riegl_minivux1uav"]["fwhm_mrad"][0],
                                 "minor_mrad": REAL_BEAMS["riegl_minivux1uav"]["fwhm_mrad"][1],
                                 "convention": "fwhm", "orientation_deg": 0.0},
        "detection_threshold": {"min_energy": 10000.0},
        "trajectory_noise": {"position_sigma_m": 0.03, "attitude_sigma_deg": 0.005, "correlation_s": 2.0},
        "max_returns": {"n": 5},
    },
    "tls": {},
}

#: candidate id → allowed parameter names
_CANDIDATES = {
    "beam_sample_quality": None,
    "elliptical_footprint": {"major_mrad", "minor_mrad", "convention", "orientation_deg"},
    "beam_divergence": {"scale"},
    "detection_threshold": {"min_energy"},
    "waveform_window": {"window_ns"},
    "range_noise": {"sigma_m"},
    "trajectory_noise": {"position_sigma_m", "attitude_sigma_deg", "correlation_s"},
    "incidence_reflectance": {"specularity", "shininess"},
    "reflectance": {"foliage", "wood", "ground"},
    "max_returns": {"n"},
    "peak_rule": {"physical"},
}

#: the candidates whose effect is detection alone (receiver, ranging noise, materials): a trace of
#: a recording serves every variant made of them (:func:`vlsforest.sim.redetect`)
DETECTION_CANDIDATES = frozenset({"detection_threshold", "waveform_window", "range_noise", "max_returns",
                                  "peak_rule", "reflectance", "incidence_reflectance"})

#: reflectance (fraction) at the scanner wavelengths: 1064 nm (ALS), 905 nm (ULS), 1550 nm (TLS)
REFLECTANCE = {
    "als": {"foliage": 0.45, "wood": 0.35, "ground": 0.3},
    "uls": {"foliage": 0.45, "wood": 0.35, "ground": 0.3},
    "tls": {"foliage": 0.25, "wood": 0.35, "ground": 0.25},
}

#: TLS campaign defaults (VZ-400-like). The angular step is much coarser than the study's
#: 0.017° so that the default forest records in minutes; it still gives ~1.7 cm spacing at
#: 10 m. One ray per shot: the 0.3 mrad beam is 3–9 mm wide at 10–30 m, far below the step.
DEFAULT_TLS = {
    "n_positions": 6,          # 5–8 positions on an ellipse around the targets
    "ring_margin_m": 8.0,      # ellipse = targets' bounding ellipse + this margin
    "height_m": 1.5,           # scanner height above ground
    "h_fov_deg": 80.0,         # horizontal field of view, centred on the targets
    "v_fov_deg": [-40.0, 60.0],
    "step_deg": 0.1,
    "beam_sample_quality": 1,
    "tilted_min_height_m": 25.0,  # plots whose tallest target exceeds this get tilted scans
    "n_tilted": 2,
    "tilt_deg": 40.0,
    "clearance_m": 2.0,        # a position keeps this far from stems and from crowns reaching down to it
    "head_clearance_m": 2.0,   # and no plant surface this close to the scanner head (1.5 m minimum range + 0.5)
}

#: ALS / ULS campaign settings of the study (Table 3); altitude above ground by plot
DEFAULT_CAMPAIGN = {
    # ALS: a block of parallel lines 175 m apart whose swaths (±30° at ≈ 700 m: ≈ 810 m) overlap
    # by ≈ 76 %, as in the study; 7 lines hold every strip that reaches a plot, and the block is
    # not centred on the plot but shifted by a seeded offset in [0, spacing) (random_line_offset),
    # as a campaign planned over the whole area is. The mean over offsets is the campaign's
    # density, PRF_eff / (speed · spacing).
    "als": {"scanner": "riegl_vq780i", "pattern": "parallel", "speed_mps": 51.0, "line_spacing_m": 175.0,
            "n_lines": 7, "random_line_offset": True, "margin_m": 25.0, "overrides": {"scan_freq_hz": 225.0},
            "altitude_m": {"P1": 687, "P2": 725, "P3": 710, "P4": 710, "P5": 658, "P6": 658, "default": 700}},
    # speed_mps: a number, or by plot a number or one per repeat (the first `repeats` are flown;
    # P2's second grid flew at 4 m/s)
    "uls": {"scanner": "riegl_minivux1uav", "pattern": "double_grid",
            "speed_mps": {"P2": [5.0, 4.0], "default": 5.0}, "line_spacing_m": 28.0,
            "margin_m": 15.0, "cross_margin_m": 60.0, "repeats": 2, "overrides": {},
            "altitude_m": {"P1": 68, "P2": 64, "P3": 72, "P4": 72, "P5": 71, "P6": 71, "default": 70}},
}


# ---------------------------------------------------------------------------------- physics
def validate_recording_physics(phys, where: str = "recording_physics") -> dict:
    """Check a recording-physics mapping (see the module docstring); return a deep copy."""
    if not isinstance(phys, dict):
        raise ConfigError(f"{where} must be a mapping with keys als, uls, tls")
    out = {}
    for sensor, block in phys.items():
        if sensor not in ("als", "uls", "tls"):
            raise ConfigError(f"{where}.{sensor}: unknown sensor (als, uls, tls)")
        if block is None:
            block = {}
        if not isinstance(block, dict):
            raise ConfigError(f"{where}.{sensor} must be a mapping")
        for key, val in block.items():
            if key not in _CANDIDATES:
                raise ConfigError(f"{where}.{sensor}.{key}: unknown physics candidate (known: {', '.join(_CANDIDATES)})")
            allowed = _CANDIDATES[key]
            if allowed is None:
                if isinstance(val, bool) or not isinstance(val, int) or not 1 <= val <= 10:
                    raise ConfigError(f"{where}.{sensor}.{key} must be an integer 1–10")
                continue
            if not isinstance(val, dict):
                raise ConfigError(f"{where}.{sensor}.{key} must be a mapping of {sorted(allowed)}")
            for p, v in val.items():
                if p not in allowed:
                    raise ConfigError(f"{where}.{sensor}.{key}.{p}: unknown parameter (known: {sorted(allowed)})")
                if p == "convention":
                    if v not in ("fwhm", "1/e2"):
                        raise ConfigError(f"{where}.{sensor}.{key}.convention must be 'fwhm' or '1/e2'")
                elif isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or v < 0:
                    raise ConfigError(f"{where}.{sensor}.{key}.{p} must be a non-negative number, got {v!r}")
        out[sensor] = copy.deepcopy(block)
    return out


def load_recording_physics(path) -> dict:
    """Read and validate a recording-physics YAML file."""
    data = read_yaml(path, "recording-physics", empty={})
    return validate_recording_physics(data, where=str(path))


def physics_overrides(block: dict, base_divergence) -> tuple[dict, dict | None]:
    """Scanner overrides and trajectory noise for one sensor's physics block.

    ``base_divergence`` is the preset's ``beam_divergence_mrad`` (the HELIOS++ 1/e² half angle),
    which a ``beam_divergence`` scale multiplies when no ``elliptical_footprint`` sets the beam.
    """
    ov: dict = {}
    if "beam_sample_quality" in block:
        ov["beam_sample_quality"] = int(block["beam_sample_quality"])
    div = np.asarray(base_divergence, dtype=float)
    if "elliptical_footprint" in block:
        e = block["elliptical_footprint"]
        if "major_mrad" not in e or "minor_mrad" not in e:
            raise ConfigError("elliptical_footprint needs major_mrad and minor_mrad")
        major, minor = float(e["major_mrad"]), float(e["minor_mrad"])
        key = "fwhm_mrad" if e.get("convention", "fwhm") == "fwhm" else "full_1e2_mrad"
        div = np.array(datasheet_divergence(**{key: (major, minor)}))
        ov["beam_orientation_deg"] = float(e.get("orientation_deg", 0.0))
    if "beam_divergence" in block:
        div = div * float(block["beam_divergence"].get("scale", 1.0))
    if "elliptical_footprint" in block or "beam_divergence" in block:
        ov["beam_divergence_mrad"] = [float(div[0]), float(div[1])]
    if "detection_threshold" in block:
        ov["min_energy"] = float(block["detection_threshold"].get("min_energy", 0.0))
    if "waveform_window" in block:
        ov["window_size_ns"] = float(block["waveform_window"]["window_ns"])
    if "range_noise" in block:
        ov["range_noise_m"] = float(block["range_noise"].get("sigma_m", 0.0))
    if "max_returns" in block:
        ov["max_returns"] = int(block["max_returns"].get("n", 0))
    traj = None
    if "trajectory_noise" in block:
        t = block["trajectory_noise"]
        traj = {"position_sigma_m": float(t.get("position_sigma_m", 0.0)),
                "attitude_sigma_deg": float(t.get("attitude_sigma_deg", 0.0)),
                "correlation_s": float(t.get("correlation_s", 1.0))}
    return ov, traj


# ---------------------------------------------------------------------------------- scenes
def plot_scene(plot, geometries: dict, sensor: str, physics: dict | None = None) -> Scene:
    """The truth scene of a plot for one sensor: rough ground mesh + trees (wood, foliage).

    Geometry first, then the sensor's materials by :func:`restyle_for` (the one place that maps
    parts to materials), so scenes of other sensors can share the geometry and its BVH.
    """
    sc = Scene()
    xmin, ymin, xmax, ymax = _scene_extent(plot)
    g = plot.ground.mesh((xmin, ymin, xmax, ymax), spacing=1.0)
    sc.add_mesh(GROUND_ID, g.vertices, g.faces, classification=2, name="ground",
                face_labels=np.full(len(g.faces), 255, dtype=np.uint8))
    for tid in sorted(geometries):
        geo = geometries[tid]
        wood = geo.organ != 2
        for grp, sel in ((WOOD, wood), (FOLIAGE, ~wood)):
            if sel.any():
                f = geo.faces[sel]
                used, inv = np.unique(f, return_inverse=True)
                sc.add_mesh(10 * tid + grp, geo.vertices[used], inv.reshape(-1, 3), classification=5,
                            name=f"tree {tid}", face_labels=geo.organ[sel].astype(np.uint8))
    return restyle_for(sc, sensor, physics)


def _sensor_materials(sensor: str, physics: dict | None):
    physics = physics or {}
    refl = dict(REFLECTANCE[sensor])
    refl.update(physics.get("reflectance", {}))
    ks = physics.get("incidence_reflectance", {})
    return refl, float(ks.get("specularity", 0.0)), float(ks.get("shininess", 10.0))


def restyle_for(scene: Scene, sensor: str, physics: dict | None) -> Scene:
    """The same plot scene with the materials of a sensor (geometry and BVH shared)."""
    refl, spec, shin = _sensor_materials(sensor, physics)
    mats = {}
    for p in scene.parts:
        kind = "ground" if p.object_id == GROUND_ID else ("wood" if p.object_id % 10 == WOOD else "foliage")
        mats[p.object_id] = Material(refl[kind], spec, shin)
    return scene.restyled(mats)


def _scene_extent(plot):
    xs = [t.x for t in plot.trees]
    ys = [t.y for t in plot.trees]
    pad = 12.0
    xmin, ymin, xmax, ymax = plot.extent
    return (min(xmin, min(xs)) - pad, min(ymin, min(ys)) - pad, max(xmax, max(xs)) + pad, max(ymax, max(ys)) + pad)


# ---------------------------------------------------------------------------------- TLS
def tls_clearance(plot, x: float, y: float, cfg: dict) -> float:
    """How far (m) a scanner at ``(x, y)`` stands clear of the trees (negative: too close).

    A field crew sets the scanner up where it sees out: at least ``clearance_m`` from every stem
    surface, and outside the lower crown of trees whose crown comes down to the scanner (crown
    base below scanner height + 1 m; crown radius taken as 0.6 × the radius of the crown
    projection, the lower crown being narrower than its widest part).
    """
    best = np.inf
    h = float(cfg["height_m"])
    for t in plot.trees:
        d = float(np.hypot(t.x - x, t.y - y))
        best = min(best, d - 0.5 * t.params.dbh - cfg["clearance_m"])
        if t.params.cbh < h + 1.0:
            best = min(best, d - 0.6 * np.sqrt(t.params.cpa / np.pi) - 0.5 * cfg["clearance_m"])
    return best


class _HeadClearance:
    """Distance from a scanner head to the nearest plant surface (vertices and face centroids)."""

    def __init__(self, plot, geometries: dict, cfg: dict):
        from scipy.spatial import cKDTree

        self.h = float(cfg["height_m"])
        self.need = float(cfg["head_clearance_m"])
        top = float(np.max(plot.ground.z(np.array([t.x for t in plot.trees] or [0.0]),
                                         np.array([t.y for t in plot.trees] or [0.0])))) + self.h + self.need + 1.0
        pts = []
        for g in geometries.values():
            v = np.asarray(g.vertices, float)
            low = v[:, 2] <= top
            if not low.any():
                continue
            f = np.asarray(g.faces)
            f = f[low[f].any(axis=1)]
            pts += [v[low], v[f].mean(axis=1)]
        self.tree = cKDTree(np.vstack(pts)) if pts else None
        self.plot = plot

    def __call__(self, x: float, y: float) -> float:
        if self.tree is None:
            return np.inf
        z = float(self.plot.ground.z(np.array([x]), np.array([y]))[0]) + self.h
        d, _ = self.tree.query([x, y, z], k=1)
        return float(d) - self.need


def tls_positions(plot, cfg: dict, geometries: dict | None = None) -> list[dict]:
    """Scan positions on an ellipse around the targets (+ tilted extra scans for tall trees).

    Position ``k`` starts at angle ``2πk/n + π/n`` on the ellipse; where it stands too close to a
    tree (:func:`tls_clearance`, and, given the trees' ``geometries``, a plant surface closer to
    the scanner head than ``head_clearance_m``) it moves along the ellipse (up to ±0.4 of the
    spacing, 1° steps) and, failing that, onto an ellipse up to 6 m smaller or larger, to the
    first clear spot (or the clearest one when none is clear).
    """
    head = _HeadClearance(plot, geometries, cfg) if geometries else None
    targets = [t for t in plot.trees if t.target]
    tx = np.array([t.x for t in targets])
    ty = np.array([t.y for t in targets])
    cx, cy = float(tx.mean()), float(ty.mean())
    ax = float(np.abs(tx - cx).max()) + cfg["ring_margin_m"]
    ay = float(np.abs(ty - cy).max()) + cfg["ring_margin_m"]
    n = int(cfg["n_positions"])
    span = np.radians(np.arange(0.0, 0.4 * 360.0 / n + 1e-9, 1.0))
    shifts = np.r_[0.0, np.ravel(np.column_stack([span[1:], -span[1:]]))]
    out = []
    for k in range(n):
        phi0 = 2 * np.pi * k / n + np.pi / n
        best = None
        for dr in (0.0, -1.0, 1.0, -2.0, 2.0, -3.0, 3.0, -4.0, 4.0, -5.0, 5.0, -6.0, 6.0):
            for dphi in shifts:
                phi = phi0 + dphi
                xy = (cx + (ax + dr) * np.cos(phi), cy + (ay + dr) * np.sin(phi))
                c = tls_clearance(plot, *xy, cfg)
                if head is not None:
                    c = min(c, head(*xy))
                if best is None or c > best[0]:
                    best = (c, xy)
                if c >= 0:
                    break
            if best[0] >= 0:
                break
        x, y = best[1]
        z = float(plot.ground.z(np.array([x]), np.array([y]))[0]) + cfg["height_m"]
        heading = float(np.degrees(np.arctan2(cx - x, cy - y)) % 360.0)  # compass azimuth towards the centre
        out.append({"position": [float(x), float(y), z], "heading_deg": heading, "tilt_deg": 0.0})
    tallest = max(t.params.height for t in targets)
    if tallest > cfg["tilted_min_height_m"]:
        for k in range(int(cfg["n_tilted"])):
            base = dict(out[(k * n) // max(int(cfg["n_tilted"]), 1)])
            base["tilt_deg"] = float(cfg["tilt_deg"])
            out.append(base)
    return out


def tls_survey(pos: dict, cfg: dict, physics: dict, seed: int) -> dict:
    """Survey mapping of one TLS scan of the recordings (the VZ-400, static).

    Parameters
    ----------
    pos : dict
        The scan position as :func:`tls_positions` gives it (``position``, ``heading_deg``,
        ``tilt_deg``).
    cfg : dict
        The ``tls`` block of :func:`synth_settings`; its ``h_fov_deg`` (centred on the heading),
        ``v_fov_deg``, ``step_deg`` (horizontal and vertical) and ``beam_sample_quality`` are read.
    physics : dict
        The TLS block of the recording physics (:func:`physics_overrides`; its peak rule sets the
        detector).
    seed : int
        The scan's seed.

    Returns
    -------
    dict
        A mapping for :func:`vlsforest.sim.survey.survey_from_dict`.
    """
    half = cfg["h_fov_deg"] / 2.0
    ov = {"tls_h_fov_deg": [-half, half], "tls_v_fov_deg": list(cfg["v_fov_deg"]),
          "tls_h_step_deg": cfg["step_deg"], "tls_v_step_deg": cfg["step_deg"],
          "beam_sample_quality": int(cfg["beam_sample_quality"])}
    pov, _ = physics_overrides(physics, PRESETS["riegl_vz400"].beam.divergence_mrad)
    ov.update(pov)
    return {"scanner": "riegl_vz400", "overrides": ov, "seed": seed,
            "platform": {"type": "static", "positions": [pos]}, "detector": _detector(physics)}


def _detector(physics: dict) -> dict:
    """The recordings' detector: physical, or HELIOS++ 1.0.8's peak rule where the physics asks.

    Its ``detection_threshold`` is a receiver's threshold on the peak amplitude under either
    rule (``threshold_scope: peak``, :mod:`vlsforest.sim.engine`), as the diagnosis' candidate
    of that name models it.
    """
    det = {"mode": "physical", "threshold_scope": "peak"}
    if "peak_rule" in physics and not round(float(physics["peak_rule"].get("physical", 1))):
        det["peak_rule"] = "helios"
    return det


# ---------------------------------------------------------------------------------- airborne
def airborne_survey(plot, sensor: str, campaign: dict, physics: dict, seed: int) -> list[dict]:
    """Survey mapping(s) of the "real" ALS or ULS campaign over a plot (ULS: repeated grids)."""
    c = dict(campaign)
    alt = c.pop("altitude_m")
    alt = alt.get(plot.name, alt.get("default")) if isinstance(alt, dict) else alt
    repeats = int(c.pop("repeats", 1))
    if c.pop("random_line_offset", False):
        rng = np.random.default_rng([int(seed), zlib.crc32(f"{plot.name}/{sensor}".encode())])
        c["line_offset_m"] = float(rng.uniform(0.0, float(c["line_spacing_m"])))
    speed = c.pop("speed_mps")
    speed = speed.get(plot.name, speed.get("default")) if isinstance(speed, dict) else speed
    speeds = [float(v) for v in speed] if isinstance(speed, (list, tuple)) else [float(speed)] * repeats
    if len(speeds) < repeats:
        raise ConfigError(f"recordings.{sensor}.speed_mps: {len(speeds)} speed(s) for {repeats} repeats of {plot.name}")
    base_div = PRESETS[c["scanner"]].beam.divergence_mrad
    pov, traj = physics_overrides(physics, base_div)
    ov = dict(c.pop("overrides", {}) or {})
    ov.update(pov)
    c["overrides"] = ov
    c["altitude_m"] = float(alt)
    c["detector"] = _detector(physics)
    if traj:
        c["trajectory_noise"] = traj
    surveys = []
    for r in range(repeats):
        ext = list(plot.extent)
        if r % 2 == 1:  # a second grid shifted by half a line spacing
            s = c["line_spacing_m"] / 2.0
            ext = [ext[0] + s, ext[1] + s, ext[2] + s, ext[3] + s]
        d = plan_survey(dict(c, speed_mps=speeds[r]), ext, plot.ground_z(), where=f"recordings.{sensor}")
        d["seed"] = int(seed) + 7919 * r
        surveys.append(d)
    return surveys


# ---------------------------------------------------------------------------------- main
def _log(msg, quiet):
    if not quiet:
        print(f"synth: {msg}", file=sys.stderr, flush=True)


def _write_cloud(path, res, gps_offset=0.0, extra_attrs=None):
    p = res.points
    attrs = {k: p[k] for k in ("intensity", "return_number", "number_of_returns", "scan_angle", "classification")}
    attrs["gps_time"] = p["gps_time"] + gps_offset
    attrs["point_source_id"] = p["point_source_id"]
    if extra_attrs:
        attrs.update(extra_attrs)
    write_las(path, PointCloud(p["xyz"], attrs))


def _truth_labels(path, res):
    oid = res.points["object_id"].astype(np.int64)
    tree = np.where(oid >= 10, oid // 10, 0).astype(np.int32)
    organ = res.points.get("label", np.full(len(oid), 255, np.uint8)).astype(np.uint8)
    save_npz(path, {"tree_id": tree, "organ": organ})


def record_plot(plot, geometries: dict, out: Path, physics: dict, tls_cfg: dict, campaign: dict, seed: int,
                workers=None, quiet=False, sensors=("tls", "als", "uls")) -> dict:
    """Record one plot: TLS scans, ALS and ULS; write clouds, scan table, trajectories, truth."""
    pdir = out / "plots" / plot.name
    tdir = out / "truth" / plot.name
    timings = {}
    base = plot_scene(plot, geometries, "tls", physics.get("tls", {}))  # one BVH for all sensors
    if "tls" in sensors:
        t0 = time.perf_counter()
        scene = base
        rows = []
        gps = 0.0
        for k, pos in enumerate(tls_positions(plot, tls_cfg, geometries), start=1):
            sv = tls_survey(pos, tls_cfg, physics.get("tls", {}), seed + 101 * k)
            survey = survey_from_dict(sv)
            res = simulate(scene, survey, workers=workers, keep_pulses=False)
            # one scan = one source id: the scan number
            res.points["point_source_id"] = np.full(len(res.points["xyz"]), k, np.uint16)
            _write_cloud(pdir / "tls" / f"scan_{k}.laz", res, gps_offset=gps)
            _truth_labels(tdir / "tls" / f"scan_{k}_labels.npz", res)
            write_text(pdir / "tls" / f"scan_{k}.survey.yaml", yaml.safe_dump(sv, sort_keys=False))
            grid, beam, prf = survey.scanner.tls, survey.scanner.beam, survey.scanner.emitter.prf_hz
            rows.append({"scan_id": k, "x": pos["position"][0], "y": pos["position"][1], "z": pos["position"][2],
                         "heading_deg": pos["heading_deg"], "tilt_deg": pos["tilt_deg"],
                         "h_fov_start_deg": grid.h_fov_deg[0], "h_fov_end_deg": grid.h_fov_deg[1],
                         "v_fov_min_deg": grid.v_fov_deg[0], "v_fov_max_deg": grid.v_fov_deg[1],
                         "h_step_deg": grid.h_step_deg, "v_step_deg": grid.v_step_deg, "prf_hz": prf,
                         "beam_divergence_full_1e2_mrad": 2.0 * beam.divergence_mrad[0],
                         "beam_exit_diameter_m": beam.exit_diameter_m, "gps_time_start": gps,
                         "n_shots": survey.n_slots, "n_points": len(res.points["xyz"])})
            gps += survey.n_slots / prf + 1.0
            _log(f"{plot.name} TLS scan {k}: {survey.n_slots} shots, {len(res.points['xyz'])} points "
                 f"({res.timings['total']:.1f} s)", quiet)
        write_csv(pdir / "tls" / "scans.csv", pd.DataFrame(rows), index=False, float_format="%.12g")
        timings["tls_s"] = time.perf_counter() - t0
    for sensor in ("als", "uls"):
        if sensor not in sensors:
            continue
        t0 = time.perf_counter()
        scene = restyle_for(base, sensor, physics.get(sensor, {}))
        clouds, trajs = [], []
        gps = 0.0
        for r, sv in enumerate(airborne_survey(plot, sensor, campaign[sensor], physics.get(sensor, {}), seed)):
            survey = survey_from_dict(sv)
            # pulses are traced where they reach the plot (+ a small pad): the recording covers
            # the plot, the trees around it still occlude and reflect
            res = simulate(scene, survey, workers=workers, keep_pulses=False, region=recording_region(plot))
            res.points["gps_time"] = res.points["gps_time"] + gps
            res.points["point_source_id"] = (res.points["point_source_id"].astype(np.int64) + 100 * r).astype(np.uint16)
            tr = survey.trajectory()
            tr["gps_time"] += gps
            tr["source_id"] = tr["source_id"].astype(np.int64) + 100 * r
            trajs.append(tr)
            clouds.append(res)
            gps += survey.duration_s + 10.0
        merged = _merge_results(clouds)
        _write_cloud(pdir / f"{sensor}.laz", merged)
        _truth_labels(tdir / f"{sensor}_labels.npz", merged)
        write_csv(pdir / f"trajectory_{sensor}.csv", pd.concat(trajs), index=False, float_format="%.9g")
        timings[f"{sensor}_s"] = time.perf_counter() - t0
        _log(f"{plot.name} {sensor.upper()}: {len(merged.points['xyz'])} points "
             f"({timings[f'{sensor}_s']:.1f} s)", quiet)
    return timings


def recording_region(plot, pad: float = RECORDING_PAD_M) -> tuple[float, float, float, float]:
    """Where the airborne recordings trace their pulses: the plot's extent grown by ``pad`` (m).

    Returns
    -------
    (xmin, ymin, xmax, ymax)
        The ``region`` of :func:`vlsforest.sim.engine.simulate`.
    """
    xmin, ymin, xmax, ymax = plot.extent
    return (xmin - pad, ymin - pad, xmax + pad, ymax + pad)


def _merge_results(results):
    from vlsforest.sim.engine import SimulationResult

    pts = {k: np.concatenate([r.points[k] for r in results]) for k in results[0].points}
    return SimulationResult(pts, {}, None, {})


def write_plot_info(plot, out: Path) -> None:
    """``plots/{plot}/plot.json``: what the field campaign knows (extent, ground, target stems)."""
    pdir = out / "plots" / plot.name
    make_folder(pdir)
    info = {"plot": plot.name, "extent": [float(v) for v in plot.extent], "ground_z": float(plot.ground_z()),
            "area_ha": float(plot.area_ha()),
            "targets": [{"tree_id": int(t.tree_id), "species": t.species, "x": float(t.x), "y": float(t.y)}
                        for t in plot.trees if t.target]}
    write_text(pdir / "plot.json", json.dumps(info, indent=2) + "\n")


def write_truth_stems(geometries: dict, plot, out: Path) -> None:
    """Closed stem meshes of the target trees (truth for mesh validation)."""
    for t in plot.trees:
        if t.target:
            sm = geometries[t.tree_id].stem_mesh
            write_mesh(out / "truth" / plot.name / "stems" / f"{t.tree_id}.ply", TriangleMesh(sm.vertices, sm.faces))


def synth_settings(cfg: dict | None) -> dict:
    """Resolve the synth settings of a workflow config: ``forest``, ``tls``, ``recordings`` blocks.

    ``forest`` may be a full forest block (see :mod:`vlsforest.synth.forest`) or
    ``{preset: default | quick}``; ``tls`` and ``recordings.{als,uls}`` override the defaults
    key by key.
    """
    from vlsforest.synth import forest as _forest

    cfg = dict(cfg or {})
    fc = cfg.get("forest", {"preset": "default"})
    if not isinstance(fc, dict):
        raise ConfigError("forest must be a mapping")
    if "preset" in fc:
        presets = {"default": _forest.DEFAULT_FOREST, "quick": _forest.QUICK_FOREST}
        if fc["preset"] not in presets:
            raise ConfigError(f"forest.preset must be one of {sorted(presets)}, got {fc['preset']!r}")
        base = copy.deepcopy(presets[fc["preset"]])
        base.update({k: v for k, v in fc.items() if k != "preset"})
        fc = base
    tls = dict(DEFAULT_TLS)
    for k, v in (cfg.get("tls") or {}).items():
        if k not in DEFAULT_TLS:
            raise ConfigError(f"tls.{k}: unknown key (known: {', '.join(DEFAULT_TLS)})")
        tls[k] = v
    if isinstance(tls["n_positions"], bool) or not isinstance(tls["n_positions"], int) or tls["n_positions"] < 1:
        raise ConfigError(f"tls.n_positions must be an integer ≥ 1, got {tls['n_positions']!r}")
    if not tls["step_deg"] > 0:
        raise ConfigError(f"tls.step_deg must be > 0, got {tls['step_deg']!r}")
    hc = tls["head_clearance_m"]
    if isinstance(hc, bool) or not isinstance(hc, (int, float)) or not hc >= 0:
        raise ConfigError(f"tls.head_clearance_m must be a number ≥ 0, got {hc!r}")
    camp = copy.deepcopy(DEFAULT_CAMPAIGN)
    for sensor, block in (cfg.get("recordings") or {}).items():
        if sensor not in camp:
            raise ConfigError(f"recordings.{sensor}: unknown sensor (als, uls)")
        camp[sensor].update(block or {})
    return {"forest": fc, "tls": tls, "recordings": camp}


#: at most this many plots are recorded at once (each holds its leaf-level scene, up to ≈ 4 GB)
MAX_PLOTS_AT_ONCE = 2


def _plot_processes(workers, n_plots: int) -> int:
    """Number of plots recorded side by side with ``workers`` CPUs (1: one after the other)."""
    if workers is None or int(workers) < 2 or n_plots < 2:
        return 1
    return min(int(workers), n_plots, MAX_PLOTS_AT_ONCE)


def _synth_plot(plot, workers, out: Path, physics: dict, tls_cfg: dict, campaign: dict, seed: int,
                quiet: bool, forest_files: dict):
    """Grow, describe and record one plot; returns its truth table and timings."""
    from vlsforest.synth.forest import generate_plot_trees, truth_table

    t0 = time.perf_counter()
    geoms = generate_plot_trees(plot)
    _log(f"{plot.name}: {len(geoms)} trees, {sum(g.n_triangles for g in geoms.values()):,} triangles "
         f"({time.perf_counter() - t0:.1f} s)", quiet)
    write_plot_info(plot, out)
    write_truth_stems(geoms, plot, out)
    tt = truth_table([plot], geoms)
    make_folder(out / "truth" / plot.name)  # also for a plot without targets
    write_csv(out / "truth" / plot.name / "trees.csv", tt, index=False, float_format="%.6f")
    for name, text in forest_files.items():  # the plot's truth folder holds what rebuilds it
        write_text(out / "truth" / plot.name / name, text)
    tm = record_plot(plot, geoms, out, physics, tls_cfg, campaign, seed, workers=workers, quiet=quiet)
    tm["total_s"] = time.perf_counter() - t0
    return tt, tm


def _synth_plot_apart(plot, workers, *args):
    """:func:`_synth_plot` in a worker process; also returns the plot's outputs, still under their
    temporary names, for the parent to install with the rest of the forest
    (:func:`vlsforest.io.atomic.adopt_outputs`)."""
    with collect_outputs() as outputs:
        tt, tm = _synth_plot(plot, workers, *args)
    return tt, tm, outputs


#: forest-level truth files (``truth/``); every plot's truth folder holds a copy of the two YAML files
FOREST_TRUTH_FILES = ("trees.csv", "recording_physics.yaml", "synth_settings.yaml")


def synthesize(cfg: dict | None, out_dir, seed: int = 0, physics: dict | None = None, plots=None,
               workers=None, quiet: bool = False, part: bool = False) -> dict:
    """Build the virtual forest and record it (the ``vlsforest synth`` command).

    Parameters
    ----------
    cfg : dict
        Workflow config (its ``forest``, ``tls``, ``recordings`` blocks; see :func:`synth_settings`).
    out_dir : path
        Output folder (``plots/``, ``truth/``).
    seed : int
        Master seed: same seed → byte-identical outputs.
    physics : dict, optional
        Recording physics (default :data:`DEFAULT_RECORDING_PHYSICS`).
    plots : list of str, optional
        Plot names to build (default all).
    part : bool
        Write only the plots' own folders (``plots/{plot}/``, ``truth/{plot}/``), not the
        forest-level ``truth/`` files: one workflow job per plot, several writing into the same
        folder; :func:`gather_truth` writes those files afterwards, the same bytes as one call for
        all the plots. Needs ``plots``.

    Returns
    -------
    dict
        Timings per plot and stage.

    Notes
    -----
    The outputs appear together when every plot is recorded, and none when one fails or the
    call is interrupted (:func:`vlsforest.io.atomic.output_transaction`; plots recorded side by
    side hand their files to it, :func:`vlsforest.io.atomic.collect_outputs`).
    """
    with output_transaction():
        return _synthesize(cfg, out_dir, seed, physics, plots, workers, quiet, part)


def _synthesize(cfg, out_dir, seed, physics, plots, workers, quiet, part) -> dict:
    """The work of :func:`synthesize`, inside its transaction."""
    from vlsforest.synth.forest import forest_from_config

    st = synth_settings(cfg)
    physics = validate_recording_physics(DEFAULT_RECORDING_PHYSICS if physics is None else physics)
    layouts = forest_from_config(st["forest"], seed)
    names = [p.name for p in layouts]
    if plots:
        unknown = [p for p in plots if p not in names]
        if unknown:
            raise ConfigError(f"--plots: unknown plot(s) {unknown} (known: {names})")
        layouts = [p for p in layouts if p.name in plots]
    if part and not plots:
        raise ConfigError("part: name the plots to record (--plots)")
    out = Path(out_dir)
    make_folder(out / "truth")
    files = {"recording_physics.yaml": yaml.safe_dump(physics, sort_keys=True),
             "synth_settings.yaml": yaml.safe_dump({"seed": int(seed), **st}, sort_keys=True)}
    if not part:
        for name, text in files.items():
            write_text(out / "truth" / name, text)
    args = (out, physics, st["tls"], st["recordings"], seed, quiet, files)
    n_proc = _plot_processes(workers, len(layouts))
    if n_proc > 1:
        # two plots at a time, each recorded with all the workers: growing the trees, the TLS
        # scans and writing the clouds run on one CPU, and while one plot does that the other's
        # ULS recording takes the idle core (one plot at a time leaves a core idle for long
        # stretches). Spawned, not forked: a fork after the caller has built an Embree scene
        # (whose task threads the child does not inherit) hangs in the child's first build.
        # The plots are independent (own seeds) and collected in plot order: the same bytes
        # as one after the other.
        # Each plot's files join this call's outputs: installed together at its end, or removed
        # together when a plot fails.
        order = sorted(range(len(layouts)), key=lambda i: -len(layouts[i].trees))  # largest first
        jobs = {}
        try:
            with ProcessPoolExecutor(n_proc, mp_context=multiprocessing.get_context("spawn")) as pool:
                try:
                    for i in order:
                        jobs[i] = pool.submit(_synth_plot_apart, layouts[i], workers, *args)
                    wait(jobs.values(), return_when=FIRST_EXCEPTION)
                finally:  # after a failure or an interrupt, start no further plot
                    for job in jobs.values():
                        job.cancel()
        finally:  # the pool has ended: every plot recorded so far hands over its files
            for i in sorted(jobs):
                if jobs[i].done() and not jobs[i].cancelled() and jobs[i].exception() is None:
                    adopt_outputs(jobs[i].result()[2])
        for i in range(len(layouts)):  # the first failure in plot order (not a plot cancelled after it)
            if not jobs[i].cancelled() and jobs[i].exception() is not None:
                jobs[i].result()
        done = [jobs[i].result()[:2] for i in range(len(layouts))]
    else:
        done = [_synth_plot(plot, workers, *args) for plot in layouts]
    truth = [tt for tt, _ in done]
    timings = {plot.name: tm for plot, (_, tm) in zip(layouts, done)}
    if not part:
        table = pd.concat(truth, ignore_index=True)
        write_csv(out / "truth" / "trees.csv", table, index=False, float_format="%.6f")
    return timings


def gather_truth(plot_truth_dirs, out_csv) -> list[str]:
    """Write the forest-level truth files from plots recorded one by one (``synthesize(part=True)``).

    Parameters
    ----------
    plot_truth_dirs : list of path
        The plots' truth folders (``DIR/truth/{plot}``), each with ``trees.csv``,
        ``synth_settings.yaml`` and ``recording_physics.yaml``.
    out_csv : path
        The forest's ``truth/trees.csv``; the two YAML files are written beside it.

    Returns
    -------
    list of str
        The plots, in the forest's order (the order of ``trees.csv``).

    Raises
    ------
    InputDataError
        A file is missing, or the plots were recorded with different settings or physics.
    """
    from vlsforest.synth.forest import layouts_from_settings

    dirs = [Path(d) for d in plot_truth_dirs]
    if not dirs:
        raise InputDataError("no plot truth folder to gather")
    texts = {}
    for d in dirs:
        for name in FOREST_TRUTH_FILES:
            if not (d / name).is_file():
                raise InputDataError(f"{d / name}: no such file (a plot recorded by vlsforest synth --part)")
        for name in FOREST_TRUTH_FILES[1:]:
            text = (d / name).read_text()
            if texts.setdefault(name, (d, text))[1] != text:
                raise InputDataError(f"{d / name} differs from {texts[name][0] / name}: the plots were "
                                     "recorded with different settings; re-record them together")
    order = [p.name for p in layouts_from_settings(texts["synth_settings.yaml"][0] / "synth_settings.yaml")]
    by_name = {d.name: d for d in dirs}
    unknown = sorted(set(by_name) - set(order))
    if unknown or len(by_name) != len(dirs):
        raise InputDataError(f"plot truth folders {unknown or [str(d) for d in dirs]}: not the plots of one "
                             f"forest (its plots: {order})")
    names = [n for n in order if n in by_name]
    out_csv = Path(out_csv)
    # the plots' tables one after the other, header once: the bytes of one call for all plots
    lines = []
    for i, n in enumerate(names):
        rows = (by_name[n] / "trees.csv").read_text().splitlines(keepends=True)
        if i and rows[:1] != lines[:1]:
            raise InputDataError(f"{by_name[n] / 'trees.csv'}: columns differ from {by_name[names[0]] / 'trees.csv'}")
        lines += rows if i == 0 else rows[1:]
    write_text(out_csv, "".join(lines))
    for name in FOREST_TRUTH_FILES[1:]:
        write_text(out_csv.parent / name, texts[name][1])
    return names
