"""Scanner settings, device presets, their validation and the beam divergence conventions.

A scanner is a frozen :class:`ScannerSettings` made of one record per part of the device, as
HELIOS++ separates them:

==============  ======================  ==========================================================
field           record                  holds
==============  ======================  ==========================================================
``emitter``     :class:`Emitter`        the laser: pulse rate, wavelength, pulse length, power
``deflector``   :class:`Deflector`      the beam deflector: kind, line rate, scan angles
``beam``        :class:`Beam`           the beam: divergence, orientation, sub-ray sampling, M²,
                                        exit diameter
``detector``    :class:`Detector`       the receiver and its full-waveform detection: aperture,
                                        efficiency, bins, window, threshold, returns, range limits
``atmosphere``  :class:`Atmosphere`     atmospheric attenuation
``tls``         :class:`TlsGrid`        the angular grid of a terrestrial scan
==============  ======================  ==========================================================

Survey files, presets' overrides and custom scanners give the settings as one flat mapping
(``prf_hz: 1.0e6``, ``window_size_ns: 1.75``, ...). :data:`INPUT_KEYS` lists those keys, and
:data:`FLAT_KEYS` says which record field each one sets; :meth:`ScannerSettings.flat` and
:meth:`ScannerSettings.replaced` convert between the two. Surveys name one of the
:data:`PRESETS` and may override any key except ``name`` and ``deflector``
(:func:`scanner_from_preset` validates the result and raises
:class:`~vlsforest.errors.ConfigError` naming the offending key).

``deflector`` names one of :data:`DEFLECTORS`; the patterns themselves (the beam direction of
each pulse slot) are :mod:`vlsforest.sim.deflector`. :func:`emission_half_angle_deg` gives the
emitted half angle of each pattern.

Beam divergence conventions
---------------------------
``beam_divergence_mrad`` (:attr:`Beam.divergence_mrad`) is the value HELIOS++ takes as
``beamDivergence_rad`` (in mrad): the simulator weights sub-rays with ``exp(−2 r²/w²)``,
``w = div·R``, so this value is the **1/e² half angle** of the beam (the study entered its
datasheet figures 0.25 and 0.5 mrad here, which gives beams twice as wide as the datasheets').
A datasheet value goes into one of the two input keys that name its convention, accepted
wherever scanner settings are given:

``beam_divergence_full_1e2_mrad``
    Full angle at 1/e² of the peak intensity (RIEGL's convention for the VQ-780i, VZ-400):
    stored as half of it.
``beam_divergence_fwhm_mrad``
    Full angle at 50 % of the peak intensity (RIEGL's for the miniVUX-1UAV): stored as
    ``fwhm_to_1e2(θ) / 2``.

:data:`REAL_BEAMS` holds the datasheet beams of the preset devices in these terms.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from vlsforest.errors import ConfigError

__all__ = [
    "DEFLECTORS",
    "DIVERGENCE_INPUTS",
    "FLAT_KEYS",
    "INPUT_KEYS",
    "PARTS",
    "PRESETS",
    "REAL_BEAMS",
    "Atmosphere",
    "Beam",
    "Deflector",
    "Detector",
    "Emitter",
    "ScannerSettings",
    "TlsGrid",
    "apply_overrides",
    "datasheet_divergence",
    "emission_half_angle_deg",
    "fwhm_to_1e2",
    "input_key",
    "scanner_from_dict",
    "scanner_from_preset",
    "validate_scanner",
]

#: the deflector kinds (:mod:`vlsforest.sim.deflector`)
DEFLECTORS = ("polygon", "rotating", "oscillating", "conic", "tls")

#: input keys that give a beam divergence in a datasheet convention (see the module docstring);
#: each is converted to ``beam_divergence_mrad`` (the HELIOS++ 1/e² half angle) on input
DIVERGENCE_INPUTS = ("beam_divergence_full_1e2_mrad", "beam_divergence_fwhm_mrad")


def _tuple_fields(obj, names) -> None:
    """Lists (e.g. from YAML) become tuples, so that the settings stay hashable."""
    for name in names:
        v = getattr(obj, name)
        if isinstance(v, list):
            object.__setattr__(obj, name, tuple(v))


@dataclass(frozen=True, kw_only=True)
class Emitter:
    """The laser source.

    Parameters
    ----------
    prf_hz : float
        Pulse repetition frequency: one slot every ``1/prf_hz`` seconds.
    wavelength_nm : float
        Laser wavelength (used by the atmospheric attenuation).
    pulse_length_ns : float
        Pulse length (the waveform's pulse shape).
    average_power_w : float
        Average emitted power of the energy model (HELIOS++ default 4 W).
    """

    prf_hz: float
    wavelength_nm: float = 1064.0
    pulse_length_ns: float = 4.0
    average_power_w: float = 4.0


@dataclass(frozen=True, kw_only=True)
class Deflector:
    """The beam deflector. Angles are half angles.

    Parameters
    ----------
    kind : str
        One of :data:`DEFLECTORS`.
    scan_freq_hz : float
        Lines per second (conic: rotations per second; tls: unused).
    scan_angle_deg : float
        Survey half scan angle (conic: cone half angle; tls: unused).
    max_scan_angle_deg : float
        Device maximum: polygon: the mirror's half sweep; rotating: 180 (a full turn) or less;
        oscillating/conic: largest allowed survey angle; tls: unused.
    effective_max_scan_angle_deg : float, optional
        Device limit of the emitted half angle (polygon, rotating): pulses beyond it are not
        emitted. Defaults to ``max_scan_angle_deg``.
    """

    kind: str
    scan_freq_hz: float
    scan_angle_deg: float
    max_scan_angle_deg: float
    effective_max_scan_angle_deg: float | None = None

    def __post_init__(self):
        if self.effective_max_scan_angle_deg is None:
            object.__setattr__(self, "effective_max_scan_angle_deg", self.max_scan_angle_deg)


@dataclass(frozen=True, kw_only=True)
class Beam:
    """The laser beam.

    Parameters
    ----------
    divergence_mrad : tuple of float
        ``(major, minor)`` divergence in the HELIOS++ convention: the 1/e² *half* angle (see
        the module docstring, "Beam divergence conventions"); a circular beam has equal values.
    orientation_deg : float
        Angle of the major axis from the scan direction.
    sample_quality : int
        Number of sub-ray rings (HELIOS++ BSQ), 1..10.
    quality_factor : float
        Beam quality factor M² of the energy model (HELIOS++ default 1).
    exit_diameter_m : float
        Beam diameter at the exit aperture (used by the PAD beam section; 0 = a point source).
    """

    divergence_mrad: tuple[float, float]
    orientation_deg: float = 0.0
    sample_quality: int = 3
    quality_factor: float = 1.0
    exit_diameter_m: float = 0.0

    def __post_init__(self):
        _tuple_fields(self, ("divergence_mrad",))


@dataclass(frozen=True, kw_only=True)
class Detector:
    """The receiver and its full-waveform detection (the survey's ``detector:`` block, by
    contrast, chooses the detection model: :class:`~vlsforest.sim.engine.DetectorOptions`).

    Parameters
    ----------
    bin_size_ns, window_size_ns : float
        Waveform bin size and peak-detection window.
    min_energy : float
        Detection threshold (0 = the simulator's default).
    max_returns : int
        Maximum returns per pulse (0 = unlimited).
    range_min_m : float
        Minimum range: nearer hits are dropped.
    range_noise_m : float
        Standard deviation of the Gaussian range noise per return (HELIOS++ ``accuracy_m``:
        the datasheet ranging accuracy).
    optical_efficiency, receiver_diameter_m : float
        Energy-model constants (HELIOS++ defaults 0.99, 0.15 m).
    """

    bin_size_ns: float = 0.25
    window_size_ns: float = 1.0
    min_energy: float = 0.0
    max_returns: int = 0
    range_min_m: float = 0.0
    range_noise_m: float = 0.0
    optical_efficiency: float = 0.99
    receiver_diameter_m: float = 0.15


@dataclass(frozen=True, kw_only=True)
class Atmosphere:
    """Atmospheric attenuation.

    Parameters
    ----------
    enabled : bool
        Apply it.
    visibility_km : float
        Atmospheric visibility; used only if ``enabled``.
    """

    enabled: bool = False
    visibility_km: float = 23.0


@dataclass(frozen=True, kw_only=True)
class TlsGrid:
    """The angular grid of a terrestrial (``tls``) scan.

    Parameters
    ----------
    h_fov_deg : tuple of float
        (start, end) azimuth.
    v_fov_deg : tuple of float
        (min, max) elevation from horizontal.
    h_step_deg, v_step_deg : float
        Angular steps.
    """

    h_fov_deg: tuple[float, float] = (0.0, 360.0)
    v_fov_deg: tuple[float, float] = (-40.0, 60.0)
    h_step_deg: float = 0.017
    v_step_deg: float = 0.017

    def __post_init__(self):
        _tuple_fields(self, ("h_fov_deg", "v_fov_deg"))


#: the records of a :class:`ScannerSettings`: field name → record class
PARTS = {"emitter": Emitter, "deflector": Deflector, "beam": Beam, "detector": Detector,
         "atmosphere": Atmosphere, "tls": TlsGrid}

#: every flat key of a scanner mapping (survey files, overrides, custom scanners) → the
#: ``(record, field)`` of :class:`ScannerSettings` it sets; ``name`` is the settings' own field
FLAT_KEYS: dict[str, tuple[str, str]] = {
    "prf_hz": ("emitter", "prf_hz"),
    "wavelength_nm": ("emitter", "wavelength_nm"),
    "pulse_length_ns": ("emitter", "pulse_length_ns"),
    "average_power_w": ("emitter", "average_power_w"),
    "deflector": ("deflector", "kind"),
    "scan_freq_hz": ("deflector", "scan_freq_hz"),
    "scan_angle_deg": ("deflector", "scan_angle_deg"),
    "max_scan_angle_deg": ("deflector", "max_scan_angle_deg"),
    "effective_max_scan_angle_deg": ("deflector", "effective_max_scan_angle_deg"),
    "beam_divergence_mrad": ("beam", "divergence_mrad"),
    "beam_orientation_deg": ("beam", "orientation_deg"),
    "beam_sample_quality": ("beam", "sample_quality"),
    "beam_quality_factor": ("beam", "quality_factor"),
    "beam_exit_diameter_m": ("beam", "exit_diameter_m"),
    "bin_size_ns": ("detector", "bin_size_ns"),
    "window_size_ns": ("detector", "window_size_ns"),
    "min_energy": ("detector", "min_energy"),
    "max_returns": ("detector", "max_returns"),
    "range_min_m": ("detector", "range_min_m"),
    "range_noise_m": ("detector", "range_noise_m"),
    "optical_efficiency": ("detector", "optical_efficiency"),
    "receiver_diameter_m": ("detector", "receiver_diameter_m"),
    "atmosphere": ("atmosphere", "enabled"),
    "visibility_km": ("atmosphere", "visibility_km"),
    "tls_h_fov_deg": ("tls", "h_fov_deg"),
    "tls_v_fov_deg": ("tls", "v_fov_deg"),
    "tls_h_step_deg": ("tls", "h_step_deg"),
    "tls_v_step_deg": ("tls", "v_step_deg"),
}

_KEY_OF = {where: key for key, where in FLAT_KEYS.items()}


def input_key(part: str, name: str) -> str:
    """The flat key (as survey files write it) of the field ``name`` of the record ``part``.

    Examples
    --------
    >>> input_key("detector", "window_size_ns")
    'window_size_ns'
    >>> input_key("beam", "divergence_mrad")
    'beam_divergence_mrad'
    """
    return _KEY_OF[(part, name)]


@dataclass(frozen=True, kw_only=True)
class ScannerSettings:
    """One laser scanner: device and survey settings, one record per part of the device (see
    the module docstring; :data:`FLAT_KEYS` maps the flat input keys onto them).

    Parameters
    ----------
    name : str
        Preset name (informational).
    emitter : Emitter
    deflector : Deflector
    beam : Beam
    detector : Detector, optional
        Default: the :class:`Detector` defaults.
    atmosphere : Atmosphere, optional
        Default: none.
    tls : TlsGrid, optional
        Default: the :class:`TlsGrid` defaults (used only by a ``tls`` deflector).
    """

    name: str
    emitter: Emitter
    deflector: Deflector
    beam: Beam
    detector: Detector = field(default_factory=Detector)
    atmosphere: Atmosphere = field(default_factory=Atmosphere)
    tls: TlsGrid = field(default_factory=TlsGrid)

    @classmethod
    def from_flat(cls, name: str = "custom", **flat) -> ScannerSettings:
        """Settings from flat keys (:data:`FLAT_KEYS`), each record's defaults for the rest.

        The keys are not validated (:func:`scanner_from_dict` does that for input).

        Raises
        ------
        TypeError
            For a key that is not in :data:`FLAT_KEYS` or a required one that is missing.
        """
        parts: dict[str, dict] = {p: {} for p in PARTS}
        for key, value in flat.items():
            if key not in FLAT_KEYS:
                raise TypeError(f"{key!r} is not a scanner key")
            part, attr = FLAT_KEYS[key]
            parts[part][attr] = value
        return cls(name=name, **{p: PARTS[p](**kw) for p, kw in parts.items()})

    def flat(self) -> dict:
        """The settings as flat keys: ``name`` and every key of :data:`FLAT_KEYS`."""
        return {"name": self.name} | {key: getattr(getattr(self, part), name)
                                      for key, (part, name) in FLAT_KEYS.items()}

    def replaced(self, **flat) -> ScannerSettings:
        """A copy with the values of the flat keys ``flat`` (:data:`FLAT_KEYS`, ``name``)
        replaced; not validated (:func:`apply_overrides` validates).

        Raises
        ------
        TypeError
            For a key that is not a scanner key.
        """
        changes: dict[str, dict] = {}
        top = {}
        for key, value in flat.items():
            if key == "name":
                top["name"] = value
                continue
            if key not in FLAT_KEYS:
                raise TypeError(f"{key!r} is not a scanner key")
            part, name = FLAT_KEYS[key]
            changes.setdefault(part, {})[name] = value
        for part, kw in changes.items():
            top[part] = dataclasses.replace(getattr(self, part), **kw)
        return dataclasses.replace(self, **top)


#: value kinds of the input keys, used to check types (the others are floats)
_KINDS = {
    "beam_sample_quality": "int",
    "max_returns": "int",
    "atmosphere": "bool",
    "beam_divergence_mrad": "pair_or_scalar",
    "beam_divergence_full_1e2_mrad": "pair_or_scalar",
    "beam_divergence_fwhm_mrad": "pair_or_scalar",
    "tls_h_fov_deg": "pair",
    "tls_v_fov_deg": "pair",
}
#: the keys an override may set: all but the preset's identity
_OVERRIDABLE = tuple(k for k in FLAT_KEYS if k != "deflector") + DIVERGENCE_INPUTS
#: every key a scanner mapping or overrides may hold: the flat keys, ``name`` and the
#: datasheet divergences
INPUT_KEYS = ("name",) + tuple(FLAT_KEYS) + DIVERGENCE_INPUTS


def _resolve_divergence(vals: dict, where: str) -> dict:
    """Replace a datasheet divergence key of ``vals`` by ``beam_divergence_mrad`` (in place)."""
    given = [k for k in ("beam_divergence_mrad",) + DIVERGENCE_INPUTS if k in vals]
    if len(given) > 1:
        raise ConfigError(f"{where}: give the beam divergence once, not as {' and '.join(given)}")
    if given and given[0] in DIVERGENCE_INPUTS:
        key = given[0]
        value = vals.pop(key)
        if not all(v > 0 for v in value):
            raise ConfigError(f"{where}.{key} must be > 0 (got {value!r})")
        kw = {"full_1e2_mrad" if key == "beam_divergence_full_1e2_mrad" else "fwhm_mrad": value}
        vals["beam_divergence_mrad"] = datasheet_divergence(**kw)
    return vals


def fwhm_to_1e2(angle):
    """Convert a Gaussian beam's full width at half maximum into its full width at 1/e².

    For an intensity profile ``exp(−2 r²/w²)`` the half maximum lies at
    ``r = w·sqrt(ln 2 / 2)``, so ``FWHM = w·sqrt(2 ln 2)`` and the 1/e² full width
    ``2w = FWHM · 2/sqrt(2 ln 2) ≈ 1.699 · FWHM``.

    Parameters
    ----------
    angle : float or array_like
        FWHM (any unit).

    Returns
    -------
    float or ndarray
        The 1/e² full width, same unit.
    """
    factor = 2.0 / math.sqrt(2.0 * math.log(2.0))
    if np.isscalar(angle):
        return float(angle) * factor
    return np.asarray(angle, dtype=np.float64) * factor


def datasheet_divergence(full_1e2_mrad=None, fwhm_mrad=None) -> tuple[float, float]:
    """The ``beam_divergence_mrad`` value (HELIOS++ 1/e² half angle) of a datasheet beam.

    Exactly one of the arguments is given, each a number (circular beam) or ``(major, minor)``.

    Parameters
    ----------
    full_1e2_mrad : float or (float, float), optional
        Full divergence at 1/e² of the peak intensity.
    fwhm_mrad : float or (float, float), optional
        Full divergence at 50 % of the peak intensity.

    Returns
    -------
    (float, float)
        ``(major, minor)`` 1/e² half angles, mrad.

    Examples
    --------
    >>> datasheet_divergence(full_1e2_mrad=0.25)
    (0.125, 0.125)
    """
    if (full_1e2_mrad is None) == (fwhm_mrad is None):
        raise ConfigError("give exactly one of beam_divergence_full_1e2_mrad and beam_divergence_fwhm_mrad")
    v = full_1e2_mrad if fwhm_mrad is None else fwhm_to_1e2(fwhm_mrad)
    pair = np.broadcast_to(np.asarray(v, dtype=np.float64), (2,))
    return (float(pair[0]) / 2.0, float(pair[1]) / 2.0)


#: the datasheet beams of the preset devices, as ``{convention key: value}`` accepted by
#: :func:`datasheet_divergence` (without the ``beam_divergence_`` prefix and ``_mrad`` suffix):
#: RIEGL VQ-780i 0.25 mrad and VZ-400 0.35 mrad full angle at 1/e²; miniVUX-1UAV
#: 1.6 × 0.5 mrad at 50 % peak intensity (≈ 2.72 × 0.85 mrad full angle at 1/e²)
REAL_BEAMS = {
    "riegl_vq780i": {"full_1e2_mrad": (0.25, 0.25)},
    "riegl_minivux1uav": {"fwhm_mrad": (1.6, 0.5)},
    "riegl_vz400": {"full_1e2_mrad": (0.35, 0.35)},
}


PRESETS: dict[str, ScannerSettings] = {
    # RIEGL VQ-780i as the study ran it in HELIOS++ 1.0.8 (scanner entry riegl_vq_780i): a
    # polygon mirror sweeping the device's ±45° of which ±30° is the effective field of view,
    # so 2/3 of the 1 MHz PRF is emitted (the datasheet's effective measurement rate at 60°);
    # 250 lines/s (the simulation table; the real campaign flew 225). beam_divergence_mrad 0.25
    # as the study entered the datasheet value into HELIOS++ (a 1/e² half angle there; the
    # real beam is REAL_BEAMS["riegl_vq780i"]). Ranging accuracy 0.02 m (HELIOS++ accuracy_m,
    # the datasheet's). range_min_m = 100 m: the datasheet minimum range and the HELIOS++
    # rangeMin; it drops nothing at 658–725 m and enters the beam-width term
    # w(R) ∝ sqrt(R0² + R²) only. max_returns = 0 (unlimited) as in that HELIOS++ entry; the
    # real device reports at most 5 targets per pulse at 1 MHz (override max_returns: 5).
    "riegl_vq780i": ScannerSettings(
        name="riegl_vq780i",
        emitter=Emitter(prf_hz=1_000_000.0, wavelength_nm=1064.0),
        deflector=Deflector(kind="polygon", scan_freq_hz=250.0, scan_angle_deg=30.0, max_scan_angle_deg=45.0,
                            effective_max_scan_angle_deg=30.0),
        beam=Beam(divergence_mrad=(0.25, 0.25)),
        detector=Detector(window_size_ns=1.75, range_noise_m=0.02, range_min_m=100.0),
    ),
    # RIEGL miniVUX-1UAV: a 360° rotating mirror (field of view 360°), 100 kHz, 50 rotations/s;
    # the study's surveys keep ±90° of nadir (about half of the slots). beam_divergence_mrad
    # 0.5 circular as the study simulated it (HELIOS++ has no elliptical beam; the minor axis of
    # the real 1.6 × 0.5 mrad FWHM beam, REAL_BEAMS["riegl_minivux1uav"]). Ranging accuracy
    # 0.015 m (datasheet). range_min_m = 3 m: the datasheet minimum range.
    "riegl_minivux1uav": ScannerSettings(
        name="riegl_minivux1uav",
        emitter=Emitter(prf_hz=100_000.0, wavelength_nm=905.0),
        deflector=Deflector(kind="rotating", scan_freq_hz=50.0, scan_angle_deg=90.0, max_scan_angle_deg=180.0,
                            effective_max_scan_angle_deg=180.0),
        beam=Beam(divergence_mrad=(0.5, 0.5)),
        detector=Detector(window_size_ns=1.5, range_noise_m=0.015, range_min_m=3.0),
    ),
    # The same miniVUX settings as a HELIOS++ "rotating" (polygon) scanner entry of ±90° would
    # run them: every one of the 100 kHz slots is emitted and spread over ±90° (twice the pulses
    # per line of the real 360° mirror).
    "riegl_minivux1uav_helios1": ScannerSettings(
        name="riegl_minivux1uav_helios1",
        emitter=Emitter(prf_hz=100_000.0, wavelength_nm=905.0),
        deflector=Deflector(kind="polygon", scan_freq_hz=50.0, scan_angle_deg=90.0, max_scan_angle_deg=90.0),
        beam=Beam(divergence_mrad=(0.5, 0.5)),
        detector=Detector(window_size_ns=1.5, range_noise_m=0.015, range_min_m=3.0),
    ),
    # RIEGL VZ-400 as used for the study's TLS: 1550 nm, 0.35 mrad full angle at 1/e² (stored
    # as the 0.175 mrad half angle) and a 7 mm exit diameter (the datasheet; AMAPVox's VZ-400
    # entry), 300 kHz, 0.017° steps, 100° vertical FOV (−40° … +60°), full panorama. At 0.017°
    # one scan has 21 177 × 5 883 ≈ 1.25e8 slots (≈ 7 min at 300 kHz); the data generator
    # overrides the steps for speed. Ranging accuracy 0.005 m (datasheet). window_size_ns = 1 ns:
    # the HELIOS++ default (pulse length / 4). range_min_m = 1.5 m: the datasheet minimum range.
    # scan_freq_hz, scan angles: unused for tls.
    "riegl_vz400": ScannerSettings(
        name="riegl_vz400",
        emitter=Emitter(prf_hz=300_000.0, wavelength_nm=1550.0),
        deflector=Deflector(kind="tls", scan_freq_hz=50.0, scan_angle_deg=50.0, max_scan_angle_deg=50.0),
        beam=Beam(divergence_mrad=(0.175, 0.175), exit_diameter_m=0.007),
        detector=Detector(window_size_ns=1.0, range_noise_m=0.005, range_min_m=1.5),
        tls=TlsGrid(h_fov_deg=(0.0, 360.0), v_fov_deg=(-40.0, 60.0), h_step_deg=0.017, v_step_deg=0.017),
    ),
}


def emission_half_angle_deg(s: ScannerSettings) -> float:
    """The largest across-track angle at which the scanner emits, degrees.

    Polygon and rotating: ``min(effective_max_scan_angle_deg, scan_angle_deg)``; oscillating,
    conic: ``scan_angle_deg``; tls: the largest elevation of the grid from horizontal.
    """
    d = s.deflector
    if d.kind in ("polygon", "rotating"):
        return float(min(d.effective_max_scan_angle_deg, d.scan_angle_deg))
    if d.kind == "tls":
        return float(max(abs(v) for v in s.tls.v_fov_deg))
    return float(d.scan_angle_deg)


# --------------------------------------------------------------------------- validation


def _is_real(v) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))


def _coerce(key: str, value, kind: str, where: str):
    """Check the type of one override value and return it in canonical form."""
    label = f"{where}.{key}"
    if kind == "int":
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
            if isinstance(value, (float, np.floating)) and math.isfinite(value) and float(value).is_integer():
                return int(value)
            raise ConfigError(f"{label} must be an integer (got {value!r})")
        return int(value)
    if kind == "bool":
        if not isinstance(value, (bool, np.bool_)):
            raise ConfigError(f"{label} must be true or false (got {value!r})")
        return bool(value)
    if kind in ("pair", "pair_or_scalar"):
        if kind == "pair_or_scalar" and _is_real(value):
            return (float(value), float(value))
        if not isinstance(value, (list, tuple)) or len(value) != 2 or not all(_is_real(v) for v in value):
            what = "a number or a list of two numbers" if kind == "pair_or_scalar" else "a list of two numbers"
            raise ConfigError(f"{label} must be {what} (got {value!r})")
        return (float(value[0]), float(value[1]))
    # float
    if not _is_real(value):
        raise ConfigError(f"{label} must be a number (got {value!r})")
    return float(value)


def validate_scanner(s: ScannerSettings, where: str = "overrides") -> None:
    """Check the values of a scanner; raise :class:`ConfigError` naming the flat key.

    Parameters
    ----------
    s : ScannerSettings
        The settings to check.
    where : str
        Prefix for key names in messages (``overrides`` → ``overrides.prf_hz``).
    """
    v = s.flat()

    def bad(key, msg):
        raise ConfigError(f"{where}.{key} {msg} (got {v[key]!r})")

    if v["deflector"] not in DEFLECTORS:
        raise ConfigError(f"scanner deflector must be one of {', '.join(DEFLECTORS)} (got {v['deflector']!r})")
    for key in _OVERRIDABLE:
        if key in DIVERGENCE_INPUTS:
            continue
        vals = v[key] if isinstance(v[key], tuple) else (v[key],)
        for x in vals:
            if _is_real(x) and not math.isfinite(x):
                bad(key, "must be finite")
    for key in ("prf_hz", "scan_freq_hz", "bin_size_ns", "pulse_length_ns", "wavelength_nm",
                "average_power_w", "receiver_diameter_m", "visibility_km"):
        if not v[key] > 0:
            bad(key, "must be > 0")
    for key in ("window_size_ns", "min_energy", "range_noise_m", "range_min_m", "max_returns"):
        if v[key] < 0:
            bad(key, "must be >= 0")
    if not 1 <= v["beam_sample_quality"] <= 10:
        bad("beam_sample_quality", "must be between 1 and 10")
    major, minor = v["beam_divergence_mrad"]
    if not (major > 0 and minor > 0):
        bad("beam_divergence_mrad", "must be > 0")
    if minor > major:
        bad("beam_divergence_mrad", "must be (major, minor) with minor <= major")
    if v["beam_quality_factor"] < 1:
        bad("beam_quality_factor", "must be >= 1 (M² of a real beam)")
    if not 0 < v["optical_efficiency"] <= 1:
        bad("optical_efficiency", "must be in (0, 1]")
    if v["deflector"] != "tls":
        limit = 180.0 if v["deflector"] == "rotating" else 90.0
        if not 0 < v["max_scan_angle_deg"] <= limit:
            bad("max_scan_angle_deg", f"must be in (0, {limit:g}] for a {v['deflector']} deflector")
        if not 0 < v["effective_max_scan_angle_deg"] <= v["max_scan_angle_deg"]:
            bad("effective_max_scan_angle_deg", f"must be in (0, max_scan_angle_deg = {v['max_scan_angle_deg']:g}]")
        if not 0 < v["scan_angle_deg"] <= v["effective_max_scan_angle_deg"]:
            bad("scan_angle_deg",
                f"must be in (0, effective_max_scan_angle_deg = {v['effective_max_scan_angle_deg']:g}]")
    h0, h1 = v["tls_h_fov_deg"]
    if not (h1 > h0 and h1 - h0 <= 360.0):
        bad("tls_h_fov_deg", "must be (start, end) with start < end <= start + 360")
    v0, v1 = v["tls_v_fov_deg"]
    if not (-90.0 <= v0 < v1 <= 90.0):
        bad("tls_v_fov_deg", "must be (min, max) with -90 <= min < max <= 90")
    for key in ("tls_h_step_deg", "tls_v_step_deg"):
        if not v[key] > 0:
            bad(key, "must be > 0")


def scanner_from_preset(name: str, overrides: dict | None = None, where: str = "overrides") -> ScannerSettings:
    """Build a scanner from a preset with optional overrides, and validate it.

    Parameters
    ----------
    name : str
        A key of :data:`PRESETS`.
    overrides : dict, optional
        Flat keys (:data:`INPUT_KEYS`) whose values replace the preset's (any but ``name`` and
        ``deflector``). ``beam_divergence_mrad`` may be a number (circular beam) or
        ``[major, minor]``.
    where : str
        Prefix for key names in messages (``overrides`` → ``overrides.prf_hz``).

    Returns
    -------
    ScannerSettings

    Raises
    ------
    ConfigError
        Unknown preset (``scanner``), unknown override key, wrong type or value
        (``<where>.<key>``).
    """
    if not isinstance(name, str) or name not in PRESETS:
        raise ConfigError(f"scanner: unknown preset {name!r}; known presets: {', '.join(sorted(PRESETS))}")
    return apply_overrides(PRESETS[name], overrides, where)


def apply_overrides(base: ScannerSettings, overrides: dict | None, where: str = "overrides") -> ScannerSettings:
    """Replace values of ``base`` by ``overrides`` (flat keys, not ``name``/``deflector``) and
    validate.

    Parameters
    ----------
    base : ScannerSettings
        A preset or custom scanner.
    overrides : dict, optional
        Flat keys (:data:`INPUT_KEYS`) and values; ``beam_divergence_mrad`` may be a number or
        ``[major, minor]``, or be given as ``beam_divergence_full_1e2_mrad`` or
        ``beam_divergence_fwhm_mrad`` (module docstring). A ``max_scan_angle_deg`` alone also
        caps the effective maximum.
    where : str
        Prefix for key names in messages (``overrides`` → ``overrides.prf_hz``).

    Returns
    -------
    ScannerSettings

    Raises
    ------
    ConfigError
        Naming ``<where>.<key>``.
    """
    if overrides is None:
        overrides = {}
    if not isinstance(overrides, dict):
        raise ConfigError(f"{where} must be a mapping of scanner settings (got {type(overrides).__name__})")
    clean = {}
    for key, value in overrides.items():
        if key in ("name", "deflector"):
            raise ConfigError(f"{where}.{key} cannot be overridden; choose another preset")
        if key not in _OVERRIDABLE:
            raise ConfigError(f"{where}.{key} is not a scanner setting; allowed: {', '.join(_OVERRIDABLE)}")
        clean[key] = _coerce(key, value, _KINDS.get(key, "float"), where)
    _resolve_divergence(clean, where)
    if "max_scan_angle_deg" in clean and "effective_max_scan_angle_deg" not in clean:
        clean["effective_max_scan_angle_deg"] = min(clean["max_scan_angle_deg"],
                                                    base.deflector.effective_max_scan_angle_deg)
    settings = base.replaced(**clean)
    validate_scanner(settings, where)
    return settings


def scanner_from_dict(d: dict, where: str = "scanner") -> ScannerSettings:
    """Build and validate a custom scanner from a mapping of flat keys (:data:`INPUT_KEYS`).

    Required: ``deflector``, ``prf_hz``, a beam divergence (``beam_divergence_mrad``, the
    HELIOS++ 1/e² half angle, or one of the datasheet keys ``beam_divergence_full_1e2_mrad``,
    ``beam_divergence_fwhm_mrad``) and, except for ``tls``, ``scan_freq_hz`` and
    ``scan_angle_deg``. ``name`` defaults to ``"custom"``, ``max_scan_angle_deg`` to
    ``scan_angle_deg`` and ``effective_max_scan_angle_deg`` to ``max_scan_angle_deg``;
    everything else to the records' defaults.

    Parameters
    ----------
    d : dict
        The flat keys and values.
    where : str
        Key prefix for error messages.

    Returns
    -------
    ScannerSettings
    """
    if not isinstance(d, dict):
        raise ConfigError(f"{where} must be a preset name or a mapping of scanner settings (got {d!r})")
    for key in d:
        if key not in INPUT_KEYS:
            raise ConfigError(f"{where}.{key} is not a scanner setting; allowed: {', '.join(INPUT_KEYS)}")
    deflector = d.get("deflector")
    if deflector not in DEFLECTORS:
        raise ConfigError(f"{where}.deflector must be one of {', '.join(DEFLECTORS)} (got {deflector!r})")
    name = d.get("name", "custom")
    if not isinstance(name, str):
        raise ConfigError(f"{where}.name must be a string (got {name!r})")
    required = ["prf_hz"]
    if deflector != "tls":
        required += ["scan_freq_hz", "scan_angle_deg"]
    for key in required:
        if key not in d:
            raise ConfigError(f"{where}.{key} is missing")
    if not any(k in d for k in ("beam_divergence_mrad",) + DIVERGENCE_INPUTS):
        raise ConfigError(f"{where}.beam_divergence_mrad is missing (or give beam_divergence_full_1e2_mrad "
                          "or beam_divergence_fwhm_mrad)")
    vals = {k: _coerce(k, v, _KINDS.get(k, "float"), where) for k, v in d.items() if k not in ("name", "deflector")}
    _resolve_divergence(vals, where)
    vals.setdefault("scan_freq_hz", 1.0)
    vals.setdefault("scan_angle_deg", 1.0)
    vals.setdefault("max_scan_angle_deg", vals["scan_angle_deg"])
    settings = ScannerSettings.from_flat(name=name, deflector=deflector, **vals)
    validate_scanner(settings, where)
    return settings
