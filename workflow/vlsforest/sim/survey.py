"""Surveys: SURVEY.yaml parsing and the :class:`Survey` that a scanner and a platform make.

A survey is a scanner (a preset of :mod:`vlsforest.sim.scanner` with overrides) carried by a
platform. :func:`load_survey` reads SURVEY.yaml::

    scanner: riegl_vq780i              # preset name, or a mapping of flat scanner keys
                                       # (custom scanner, see scanner_from_dict, INPUT_KEYS)
    overrides: {prf_hz: 1.0e6, beam_divergence_fwhm_mrad: [1.6, 0.5], ...}   # optional
    platform:
      type: linear                     # default; or static (TLS)
      speed_mps: 51                    # default speed of the legs
      legs: [{start: [x, y, z], end: [x, y, z], active: true, speed_mps: 51}, ...]  # speed optional
    # platform: {type: static, positions: [{position: [x, y, z], heading_deg: 0, tilt_deg: 0}]}
    trajectory_noise: {position_sigma_m: 0.0, attitude_sigma_deg: 0.0, correlation_s: 1.0}
    seed: 0
    detector: {...}                    # kept as a plain dict, not validated here
    output: {...}                      # likewise

What the keys mean lives with the parts they describe: the legs' and scans' timing in
:mod:`vlsforest.sim.platform`, the frames, attitude and ``trajectory_noise`` in
:mod:`vlsforest.sim.trajectory`, the deflectors in :mod:`vlsforest.sim.deflector`, the pulses in
:mod:`vlsforest.sim.pulses`.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from vlsforest.errors import ConfigError
from vlsforest.sim.deflector import deflector_pattern, tls_grid
from vlsforest.sim.platform import Leg, ScanPosition, fly_legs, place_scans
from vlsforest.sim.pulses import PulseBatch, emit, emit_toward
from vlsforest.sim.scanner import (
    ScannerSettings,
    apply_overrides,
    emission_half_angle_deg,
    scanner_from_dict,
    scanner_from_preset,
    validate_scanner,
)
from vlsforest.sim.trajectory import Trajectory, TrajectoryNoise

__all__ = ["Survey", "load_survey", "load_survey_dict", "survey_from_dict"]

_TOP_KEYS = ("scanner", "overrides", "platform", "trajectory_noise", "seed", "detector", "output")


class Survey:
    """A parsed survey: scanner, platform, slots, pulses and trajectory.

    Build it with :func:`load_survey` or :func:`survey_from_dict`.

    Attributes
    ----------
    scanner : ScannerSettings
    detector : dict
        The ``detector`` section as given (not validated here).
    output : dict
        The ``output`` section as given (not validated here).
    seed : int
    platform_type : str
        ``linear`` or ``static``.
    speed_mps : float or None
        Platform speed (linear only).
    legs : list of Leg
        All legs, inactive ones included (linear only, else empty).
    positions : list of ScanPosition
        Scan positions (static only, else empty).
    noise : TrajectoryNoise
    base_dir : Path or None
        Directory for resolving relative paths in ``detector``/``output``.
    motion : Trajectory
        Position and attitude over the active legs / scans (with the noise realisation).
    n_slots : int
        Total number of pulse slots (emitted or not) over active legs / scans.
    """

    def __init__(self, scanner, platform_type, speed_mps, legs, positions, noise, seed, detector, output,
                 base_dir=None):
        self.scanner: ScannerSettings = scanner
        self.platform_type: str = platform_type
        self.speed_mps = speed_mps
        self.legs: list[Leg] = legs
        self.positions: list[ScanPosition] = positions
        self.noise: TrajectoryNoise = noise
        self.seed: int = seed
        self.detector: dict = detector
        self.output: dict = output
        self.base_dir = base_dir
        linear = platform_type == "linear"
        self._segs = [lg for lg in legs if lg.active] if linear else positions
        self.motion = Trajectory(self._segs, linear, noise, seed)
        self.n_slots: int = self.motion.n_slots
        self._pattern = deflector_pattern(scanner)

    @property
    def n_sources(self) -> int:
        """Number of flight lines / scan positions (the largest ``source_id``)."""
        return len(self._segs)

    @property
    def duration_s(self) -> float:
        """GPS time at the end of the last leg / scan."""
        if self.platform_type == "linear":
            last = self.legs[-1]
        else:
            last = self.positions[-1]
        return last.t_start + last.duration_s

    def source_slot_ranges(self) -> list[tuple[int, int, int]]:
        """``(source_id, first_slot, stop_slot)`` of every flight line / scan."""
        return [(int(s.source_id), int(s.slot_offset), int(s.slot_offset + s.n_slots)) for s in self._segs]

    def pulses(self, start: int, stop: int) -> PulseBatch:
        """The emitted pulses of the slots ``[start, stop)`` (:func:`vlsforest.sim.pulses.emit`).

        The result depends only on the slot indices, not on how a range is split into calls.
        """
        return emit(self.motion, self._pattern, start, stop)

    def pulses_toward(self, start: int, stop: int, lo, hi, tan_off: float):
        """The emitted slots of ``[start, stop)`` and the pulses among them whose beam cone can
        meet a box (:func:`vlsforest.sim.pulses.emit_toward`).

        Parameters
        ----------
        start, stop : int
            Slot range.
        lo, hi : array_like, shape (3,)
            The box; with a non-finite corner no pulse passes.
        tan_off : float
            Tangent of the cone's half angle.

        Returns
        -------
        slot : ndarray of int64
            Every emitted slot of the range.
        live : ndarray of int64
            Index into ``slot`` of the pulses that pass.
        batch : PulseBatch
            Those pulses.
        """
        return emit_toward(self.motion, self._pattern, start, stop, lo, hi, tan_off)

    def trajectory(self, rate_hz: float = 10.0, nominal: bool = False) -> pd.DataFrame:
        """Platform positions and attitude over the active legs / scans.

        Parameters
        ----------
        rate_hz : float
            Sampling rate; each active leg / scan is sampled from its start every
            ``1/rate_hz`` s, plus its end.
        nominal : bool
            Leave out the trajectory noise (by default it is included, as it is in the pulses).

        Returns
        -------
        pandas.DataFrame
            Columns ``gps_time, x, y, z, roll_deg, pitch_deg, heading_deg, source_id``;
            heading in [0, 360).
        """
        return self.motion.sample(rate_hz, nominal)

    def swath_width(self, ground_z: float) -> np.ndarray:
        """Across-track swath width on flat ground at height ``ground_z``, per active leg.

        Uses the mean platform height of each leg: ``2·h·tan(θ)`` with θ the emitted half
        angle (:func:`~vlsforest.sim.scanner.emission_half_angle_deg`; ``inf`` from 90° on).

        Returns
        -------
        ndarray, shape (n_active_legs,)
        """
        if self.platform_type != "linear":
            raise ValueError("swath_width is defined for linear (airborne) platforms only")
        theta = emission_half_angle_deg(self.scanner)
        out = []
        for lg in self._segs:
            h = 0.5 * (lg.start[2] + lg.end[2]) - ground_z
            if h <= 0:
                raise ValueError(f"leg {lg.source_id} is not above ground_z = {ground_z}")
            out.append(math.inf if theta >= 90.0 else 2.0 * h * math.tan(math.radians(theta)))
        return np.array(out)


# --------------------------------------------------------------------------- parsing


class _Loader(yaml.SafeLoader):
    """Safe YAML loader that rejects duplicate keys and reads ``1e6`` as a float."""

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            try:
                dup = key in seen
            except TypeError:
                dup = False
            if dup:
                raise ConfigError(f"line {key_node.start_mark.line + 1}: duplicate key {key!r}")
            try:
                seen.add(key)
            except TypeError:
                pass
        return super().construct_mapping(node, deep=deep)


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"),
)


def load_survey_dict(path) -> dict:
    """Read a SURVEY.yaml file into a plain mapping (not yet validated; see :func:`load_survey`).

    Raises
    ------
    ConfigError
        Missing/unreadable file, YAML syntax error (with its line) or an empty file.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"survey file not found: {path}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"cannot read survey file {path}: {exc}") from None
    try:
        data = yaml.load(text, Loader=_Loader)  # noqa: S506 (a SafeLoader subclass)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise ConfigError(f"{path}:{where}: YAML syntax error: {problem}") from None
    if data is None:
        raise ConfigError(f"{path}: the survey file is empty")
    return data


def load_survey(path) -> Survey:
    """Read and validate a SURVEY.yaml file.

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    Survey

    Raises
    ------
    ConfigError
        Missing/unreadable file, YAML syntax error (with its line) or an invalid value
        (naming the key path, e.g. ``platform.legs[2].end``).
    """
    path = Path(path)
    data = load_survey_dict(path)
    try:
        return survey_from_dict(data, base_dir=path.resolve().parent)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


def _real(v, key, *, positive=False, nonneg=False) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ConfigError(f"{key} must be a number (got {v!r})")
    v = float(v)
    if not math.isfinite(v):
        raise ConfigError(f"{key} must be finite (got {v!r})")
    if positive and not v > 0:
        raise ConfigError(f"{key} must be > 0 (got {v!r})")
    if nonneg and v < 0:
        raise ConfigError(f"{key} must be >= 0 (got {v!r})")
    return v


def _vec3(v, key) -> np.ndarray:
    if not isinstance(v, (list, tuple)) or len(v) != 3:
        raise ConfigError(f"{key} must be a list of three coordinates [x, y, z] (got {v!r})")
    return np.array([_real(x, f"{key}[{i}]") for i, x in enumerate(v)], dtype=np.float64)


def _mapping(v, key, allowed) -> dict:
    if not isinstance(v, dict):
        raise ConfigError(f"{key} must be a mapping (got {type(v).__name__})")
    for k in v:
        if k not in allowed:
            raise ConfigError(f"{key}.{k} is not a known key; allowed: {', '.join(allowed)}")
    return v


def _list(v, key) -> list:
    if not isinstance(v, list) or len(v) < 1:
        raise ConfigError(f"{key} must be a list with at least one entry (got {v!r})")
    return v


def _parse_linear(p: dict, prf: float):
    _mapping(p, "platform", ("type", "speed_mps", "legs"))
    if "speed_mps" not in p:
        raise ConfigError("platform.speed_mps is missing")
    if "legs" not in p:
        raise ConfigError("platform.legs is missing")
    speed = _real(p["speed_mps"], "platform.speed_mps", positive=True)
    raw = _list(p["legs"], "platform.legs")
    specs = []
    for i, entry in enumerate(raw):
        key = f"platform.legs[{i}]"
        _mapping(entry, key, ("start", "end", "active", "speed_mps"))
        for req in ("start", "end"):
            if req not in entry:
                raise ConfigError(f"{key}.{req} is missing")
        a = _vec3(entry["start"], f"{key}.start")
        b = _vec3(entry["end"], f"{key}.end")
        active = entry.get("active", True)
        if not isinstance(active, bool):
            raise ConfigError(f"{key}.active must be true or false (got {active!r})")
        leg_speed = _real(entry["speed_mps"], f"{key}.speed_mps", positive=True) if "speed_mps" in entry else speed
        if not float(np.linalg.norm(b - a)) > 0:
            raise ConfigError(f"{key} has zero length (start == end)")
        specs.append((a, b, active, leg_speed))
    source = sum(active for _, _, active, _ in specs)
    if source == 0:
        raise ConfigError("platform.legs has no active leg")
    if source > 65535:
        raise ConfigError("platform.legs has more than 65535 active legs (source_id is 16-bit)")
    legs = fly_legs(specs, prf)
    return speed, legs


def _parse_static(p: dict, scanner: ScannerSettings):
    _mapping(p, "platform", ("type", "positions"))
    if "positions" not in p:
        raise ConfigError("platform.positions is missing")
    raw = _list(p["positions"], "platform.positions")
    az, el = tls_grid(scanner.tls)
    specs = []
    for i, entry in enumerate(raw):
        key = f"platform.positions[{i}]"
        _mapping(entry, key, ("position", "heading_deg", "tilt_deg"))
        if "position" not in entry:
            raise ConfigError(f"{key}.position is missing")
        pos = _vec3(entry["position"], f"{key}.position")
        heading = _real(entry.get("heading_deg", 0.0), f"{key}.heading_deg")
        tilt = _real(entry.get("tilt_deg", 0.0), f"{key}.tilt_deg")
        if abs(tilt) > 90:
            raise ConfigError(f"{key}.tilt_deg must be within [-90, 90] (got {tilt!r})")
        specs.append((pos, heading, tilt))
    if len(specs) > 65535:
        raise ConfigError("platform.positions has more than 65535 entries (source_id is 16-bit)")
    return place_scans(specs, len(az) * len(el), scanner.emitter.prf_hz)


def survey_from_dict(d: dict, base_dir=None) -> Survey:
    """Validate a survey given as a dict (the parsed SURVEY.yaml).

    Parameters
    ----------
    d : dict
        The survey (see the module docstring).
    base_dir : str or Path, optional
        Directory the survey came from; kept as ``Survey.base_dir``.

    Returns
    -------
    Survey

    Raises
    ------
    ConfigError
        Naming the key path of the first invalid entry.
    """
    if not isinstance(d, dict):
        raise ConfigError(f"the survey must be a mapping of {', '.join(_TOP_KEYS)} (got {type(d).__name__})")
    for k in d:
        if k not in _TOP_KEYS:
            raise ConfigError(f"{k} is not a known survey key; allowed: {', '.join(_TOP_KEYS)}")
    for req in ("scanner", "platform"):
        if req not in d:
            raise ConfigError(f"{req} is missing")
    overrides = d.get("overrides")
    if overrides is not None and not isinstance(overrides, dict):
        raise ConfigError(f"overrides must be a mapping (got {type(overrides).__name__})")
    sc = d["scanner"]
    if isinstance(sc, ScannerSettings):  # programmatic use
        validate_scanner(sc, "scanner")
        scanner = apply_overrides(sc, overrides)
    elif isinstance(sc, dict):
        scanner = apply_overrides(scanner_from_dict(sc, "scanner"), overrides)
    else:
        scanner = scanner_from_preset(sc, overrides)

    p = d["platform"]
    if not isinstance(p, dict):
        raise ConfigError(f"platform must be a mapping (got {type(p).__name__})")
    ptype = p.get("type", "linear")
    if ptype not in ("linear", "static"):
        raise ConfigError(f"platform.type must be linear or static (got {ptype!r})")
    kind = scanner.deflector.kind
    if (ptype == "static") != (kind == "tls"):
        need = "static" if kind == "tls" else "linear"
        raise ConfigError(f"platform.type {ptype!r} does not fit the {kind} deflector of {scanner.name}; use {need}")
    if ptype == "linear":
        speed, legs = _parse_linear(p, scanner.emitter.prf_hz)
        positions = []
    else:
        speed, legs = None, []
        positions = _parse_static(p, scanner)

    tn = d.get("trajectory_noise")
    if tn is None:
        noise = TrajectoryNoise()
    else:
        _mapping(tn, "trajectory_noise", ("position_sigma_m", "attitude_sigma_deg", "correlation_s"))
        noise = TrajectoryNoise(
            _real(tn.get("position_sigma_m", 0.0), "trajectory_noise.position_sigma_m", nonneg=True),
            _real(tn.get("attitude_sigma_deg", 0.0), "trajectory_noise.attitude_sigma_deg", nonneg=True),
            _real(tn.get("correlation_s", 1.0), "trajectory_noise.correlation_s", positive=True),
        )

    seed = d.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ConfigError(f"seed must be a non-negative integer (got {seed!r})")

    sections = {}
    for key in ("detector", "output"):
        v = d.get(key)
        if v is None:
            v = {}
        if not isinstance(v, dict):
            raise ConfigError(f"{key} must be a mapping (got {type(v).__name__})")
        sections[key] = dict(v)

    return Survey(
        scanner=scanner,
        platform_type=ptype,
        speed_mps=speed,
        legs=legs,
        positions=positions,
        noise=noise,
        seed=seed,
        detector=sections["detector"],
        output=sections["output"],
        base_dir=Path(base_dir) if base_dir is not None else None,
    )
