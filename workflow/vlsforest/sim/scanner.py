"""Scanner settings, device presets, their validation and the beam divergence conventions.

A scanner is described by a frozen :class:`ScannerSettings`. Surveys name one of the
:data:`PRESETS` and may override any field except ``name`` and ``deflector``
(:func:`scanner_from_preset` validates the result and raises
:class:`~vlsforest.errors.ConfigError` naming the offending key).

``deflector`` names one of :data:`DEFLECTORS`; the patterns themselves (the beam direction of
each pulse slot) are :mod:`vlsforest.sim.deflector`. :func:`emission_half_angle_deg` gives the
emitted half angle of each pattern.

Beam divergence conventions
---------------------------
``beam_divergence_mrad`` is the value HELIOS++ takes as ``beamDivergence_rad`` (in mrad): the
simulator weights sub-rays with ``exp(−2 r²/w²)``, ``w = div·R``, so this value is the **1/e²
half angle** of the beam (the study entered its datasheet figures 0.25 and 0.5 mrad here,
which gives beams twice as wide as the datasheets'). A datasheet value goes into one of the
two input keys that name its convention, accepted wherever scanner settings are given:

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
from dataclasses import dataclass

import numpy as np

from vlsforest.errors import ConfigError

__all__ = [
    "DEFLECTORS",
    "DIVERGENCE_INPUTS",
    "PRESETS",
    "REAL_BEAMS",
    "ScannerSettings",
    "apply_overrides",
    "datasheet_divergence",
    "emission_half_angle_deg",
    "fwhm_to_1e2",
    "INPUT_KEYS",
    "scanner_from_dict",
    "scanner_from_preset",
    "validate_scanner",
]

#: the deflector kinds (:mod:`vlsforest.sim.deflector`)
DEFLECTORS = ("polygon", "rotating", "oscillating", "conic", "tls")

#: input keys that give a beam divergence in a datasheet convention (see the module docstring);
#: each is converted to ``beam_divergence_mrad`` (the HELIOS++ 1/e² half angle) on input
DIVERGENCE_INPUTS = ("beam_divergence_full_1e2_mrad", "beam_divergence_fwhm_mrad")


@dataclass(frozen=True, kw_only=True)
class ScannerSettings:
    """One laser scanner: device and survey settings.

    Angles are half angles unless stated otherwise. ``beam_divergence_mrad`` is in the HELIOS++
    convention, the 1/e² *half* angle (see the module docstring, "Beam divergence
    conventions"), ``(major, minor)``; a circular beam has equal values.

    Parameters
    ----------
    name : str
        Preset name (informational).
    deflector : str
        One of :data:`DEFLECTORS`.
    prf_hz : float
        Pulse repetition frequency: one slot every ``1/prf_hz`` seconds.
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
    beam_divergence_mrad : tuple of float
        ``(major, minor)`` divergence in the HELIOS++ convention: the 1/e² *half* angle.
    beam_orientation_deg : float
        Angle of the major axis from the scan direction.
    beam_sample_quality : int
        Number of sub-ray rings (HELIOS++ BSQ), 1..10.
    wavelength_nm, pulse_length_ns, bin_size_ns, window_size_ns : float
        Laser wavelength, pulse length, waveform bin size and peak-detection window.
    min_energy : float
        Detection threshold (0 = the simulator's default).
    range_noise_m : float
        Standard deviation of the Gaussian range noise per return (HELIOS++ ``accuracy_m``:
        the datasheet ranging accuracy).
    max_returns : int
        Maximum returns per pulse (0 = unlimited).
    range_min_m : float
        Minimum range: nearer hits are dropped.
    average_power_w, beam_quality_factor, optical_efficiency, receiver_diameter_m : float
        Energy-model constants (HELIOS++ defaults 4 W, 1, 0.99, 0.15 m).
    beam_exit_diameter_m : float
        Beam diameter at the exit aperture (used by the PAD beam section; 0 = a point source).
    visibility_km : float
        Atmospheric visibility; used only if ``atmosphere``.
    atmosphere : bool
        Apply atmospheric attenuation.
    tls_h_fov_deg : tuple of float
        (start, end) azimuth of a TLS scan.
    tls_v_fov_deg : tuple of float
        (min, max) elevation from horizontal of a TLS scan.
    tls_h_step_deg, tls_v_step_deg : float
        Angular steps of a TLS scan.
    """

    name: str
    deflector: str
    prf_hz: float
    scan_freq_hz: float
    scan_angle_deg: float
    max_scan_angle_deg: float
    beam_divergence_mrad: tuple[float, float]
    effective_max_scan_angle_deg: float | None = None
    beam_orientation_deg: float = 0.0
    beam_sample_quality: int = 3
    wavelength_nm: float = 1064.0
    pulse_length_ns: float = 4.0
    bin_size_ns: float = 0.25
    window_size_ns: float = 1.0
    min_energy: float = 0.0
    range_noise_m: float = 0.0
    max_returns: int = 0
    range_min_m: float = 0.0
    average_power_w: float = 4.0
    beam_quality_factor: float = 1.0
    optical_efficiency: float = 0.99
    receiver_diameter_m: float = 0.15
    beam_exit_diameter_m: float = 0.0
    visibility_km: float = 23.0
    atmosphere: bool = False
    tls_h_fov_deg: tuple[float, float] = (0.0, 360.0)
    tls_v_fov_deg: tuple[float, float] = (-40.0, 60.0)
    tls_h_step_deg: float = 0.017
    tls_v_step_deg: float = 0.017

    def __post_init__(self):
        # lists (e.g. from YAML) become tuples so that the settings stay hashable
        for key in ("beam_divergence_mrad", "tls_h_fov_deg", "tls_v_fov_deg"):
            v = getattr(self, key)
            if isinstance(v, list):
                object.__setattr__(self, key, tuple(v))
        if self.effective_max_scan_angle_deg is None:
            object.__setattr__(self, "effective_max_scan_angle_deg", self.max_scan_angle_deg)


#: value kinds of the overridable fields, used to check types
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
_FIELDS = tuple(f.name for f in dataclasses.fields(ScannerSettings))
_OVERRIDABLE = tuple(f for f in _FIELDS if f not in ("name", "deflector"))
#: every key a scanner mapping or overrides may hold: the fields and the datasheet divergences
INPUT_KEYS = _FIELDS + DIVERGENCE_INPUTS


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
        deflector="polygon",
        prf_hz=1_000_000.0,
        scan_freq_hz=250.0,
        scan_angle_deg=30.0,
        max_scan_angle_deg=45.0,
        effective_max_scan_angle_deg=30.0,
        beam_divergence_mrad=(0.25, 0.25),
        wavelength_nm=1064.0,
        window_size_ns=1.75,
        range_noise_m=0.02,
        range_min_m=100.0,
    ),
    # RIEGL miniVUX-1UAV: a 360° rotating mirror (field of view 360°), 100 kHz, 50 rotations/s;
    # the study's surveys keep ±90° of nadir (about half of the slots). beam_divergence_mrad
    # 0.5 circular as the study simulated it (HELIOS++ has no elliptical beam; the minor axis of
    # the real 1.6 × 0.5 mrad FWHM beam, REAL_BEAMS["riegl_minivux1uav"]). Ranging accuracy
    # 0.015 m (datasheet). range_min_m = 3 m: the datasheet minimum range.
    "riegl_minivux1uav": ScannerSettings(
        name="riegl_minivux1uav",
        deflector="rotating",
        prf_hz=100_000.0,
        scan_freq_hz=50.0,
        scan_angle_deg=90.0,
        max_scan_angle_deg=180.0,
        effective_max_scan_angle_deg=180.0,
        beam_divergence_mrad=(0.5, 0.5),
        wavelength_nm=905.0,
        window_size_ns=1.5,
        range_noise_m=0.015,
        range_min_m=3.0,
    ),
    # The same miniVUX settings as a HELIOS++ "rotating" (polygon) scanner entry of ±90° would
    # run them: every one of the 100 kHz slots is emitted and spread over ±90° (twice the pulses
    # per line of the real 360° mirror).
    "riegl_minivux1uav_helios1": ScannerSettings(
        name="riegl_minivux1uav_helios1",
        deflector="polygon",
        prf_hz=100_000.0,
        scan_freq_hz=50.0,
        scan_angle_deg=90.0,
        max_scan_angle_deg=90.0,
        beam_divergence_mrad=(0.5, 0.5),
        wavelength_nm=905.0,
        window_size_ns=1.5,
        range_noise_m=0.015,
        range_min_m=3.0,
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
        deflector="tls",
        prf_hz=300_000.0,
        scan_freq_hz=50.0,
        scan_angle_deg=50.0,
        max_scan_angle_deg=50.0,
        beam_divergence_mrad=(0.175, 0.175),
        beam_exit_diameter_m=0.007,
        wavelength_nm=1550.0,
        window_size_ns=1.0,
        range_noise_m=0.005,
        range_min_m=1.5,
        tls_h_fov_deg=(0.0, 360.0),
        tls_v_fov_deg=(-40.0, 60.0),
        tls_h_step_deg=0.017,
        tls_v_step_deg=0.017,
    ),
}


def emission_half_angle_deg(s: ScannerSettings) -> float:
    """The largest across-track angle at which the scanner emits, degrees.

    Polygon and rotating: ``min(effective_max_scan_angle_deg, scan_angle_deg)``; oscillating,
    conic: ``scan_angle_deg``; tls: the largest elevation of the grid from horizontal.
    """
    if s.deflector in ("polygon", "rotating"):
        return float(min(s.effective_max_scan_angle_deg, s.scan_angle_deg))
    if s.deflector == "tls":
        return float(max(abs(v) for v in s.tls_v_fov_deg))
    return float(s.scan_angle_deg)


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
    """Check the values of a scanner; raise :class:`ConfigError` naming the key.

    Parameters
    ----------
    s : ScannerSettings
        The settings to check.
    where : str
        Prefix for key names in messages (``overrides`` → ``overrides.prf_hz``).
    """

    def bad(key, msg):
        raise ConfigError(f"{where}.{key} {msg} (got {getattr(s, key)!r})")

    if s.deflector not in DEFLECTORS:
        raise ConfigError(f"scanner deflector must be one of {', '.join(DEFLECTORS)} (got {s.deflector!r})")
    for key in _OVERRIDABLE:
        v = getattr(s, key)
        vals = v if isinstance(v, tuple) else (v,)
        for x in vals:
            if _is_real(x) and not math.isfinite(x):
                bad(key, "must be finite")
    for key in ("prf_hz", "scan_freq_hz", "bin_size_ns", "pulse_length_ns", "wavelength_nm",
                "average_power_w", "receiver_diameter_m", "visibility_km"):
        if not getattr(s, key) > 0:
            bad(key, "must be > 0")
    for key in ("window_size_ns", "min_energy", "range_noise_m", "range_min_m", "max_returns"):
        if getattr(s, key) < 0:
            bad(key, "must be >= 0")
    if not 1 <= s.beam_sample_quality <= 10:
        bad("beam_sample_quality", "must be between 1 and 10")
    major, minor = s.beam_divergence_mrad
    if not (major > 0 and minor > 0):
        bad("beam_divergence_mrad", "must be > 0")
    if minor > major:
        bad("beam_divergence_mrad", "must be (major, minor) with minor <= major")
    if s.beam_quality_factor < 1:
        bad("beam_quality_factor", "must be >= 1 (M² of a real beam)")
    if not 0 < s.optical_efficiency <= 1:
        bad("optical_efficiency", "must be in (0, 1]")
    if s.deflector != "tls":
        limit = 180.0 if s.deflector == "rotating" else 90.0
        if not 0 < s.max_scan_angle_deg <= limit:
            bad("max_scan_angle_deg", f"must be in (0, {limit:g}] for a {s.deflector} deflector")
        if not 0 < s.effective_max_scan_angle_deg <= s.max_scan_angle_deg:
            bad("effective_max_scan_angle_deg", f"must be in (0, max_scan_angle_deg = {s.max_scan_angle_deg:g}]")
        if not 0 < s.scan_angle_deg <= s.effective_max_scan_angle_deg:
            bad("scan_angle_deg",
                f"must be in (0, effective_max_scan_angle_deg = {s.effective_max_scan_angle_deg:g}]")
    h0, h1 = s.tls_h_fov_deg
    if not (h1 > h0 and h1 - h0 <= 360.0):
        bad("tls_h_fov_deg", "must be (start, end) with start < end <= start + 360")
    v0, v1 = s.tls_v_fov_deg
    if not (-90.0 <= v0 < v1 <= 90.0):
        bad("tls_v_fov_deg", "must be (min, max) with -90 <= min < max <= 90")
    for key in ("tls_h_step_deg", "tls_v_step_deg"):
        if not getattr(s, key) > 0:
            bad(key, "must be > 0")


def scanner_from_preset(name: str, overrides: dict | None = None) -> ScannerSettings:
    """Build a scanner from a preset with optional overrides, and validate it.

    Parameters
    ----------
    name : str
        A key of :data:`PRESETS`.
    overrides : dict, optional
        Field values replacing the preset's (any field but ``name`` and ``deflector``).
        ``beam_divergence_mrad`` may be a number (circular beam) or ``[major, minor]``.

    Returns
    -------
    ScannerSettings

    Raises
    ------
    ConfigError
        Unknown preset (``scanner``), unknown override key, wrong type or value
        (``overrides.<key>``).
    """
    if not isinstance(name, str) or name not in PRESETS:
        raise ConfigError(f"scanner: unknown preset {name!r}; known presets: {', '.join(sorted(PRESETS))}")
    return apply_overrides(PRESETS[name], overrides)


def apply_overrides(base: ScannerSettings, overrides: dict | None) -> ScannerSettings:
    """Replace fields of ``base`` by ``overrides`` (not ``name``/``deflector``) and validate.

    Parameters
    ----------
    base : ScannerSettings
        A preset or custom scanner.
    overrides : dict, optional
        Field values; ``beam_divergence_mrad`` may be a number or ``[major, minor]``, or be
        given as ``beam_divergence_full_1e2_mrad`` or ``beam_divergence_fwhm_mrad`` (module
        docstring). A ``max_scan_angle_deg`` alone also caps the effective maximum.

    Returns
    -------
    ScannerSettings

    Raises
    ------
    ConfigError
        Naming ``overrides.<key>``.
    """
    if overrides is None:
        overrides = {}
    if not isinstance(overrides, dict):
        raise ConfigError(f"overrides must be a mapping of scanner fields (got {type(overrides).__name__})")
    clean = {}
    for key, value in overrides.items():
        if key in ("name", "deflector"):
            raise ConfigError(f"overrides.{key} cannot be overridden; choose another preset")
        if key not in _OVERRIDABLE + DIVERGENCE_INPUTS:
            raise ConfigError(
                f"overrides.{key} is not a scanner setting; allowed: {', '.join(_OVERRIDABLE + DIVERGENCE_INPUTS)}"
            )
        clean[key] = _coerce(key, value, _KINDS.get(key, "float"), "overrides")
    _resolve_divergence(clean, "overrides")
    if "max_scan_angle_deg" in clean and "effective_max_scan_angle_deg" not in clean:
        clean["effective_max_scan_angle_deg"] = min(clean["max_scan_angle_deg"], base.effective_max_scan_angle_deg)
    settings = dataclasses.replace(base, **clean)
    validate_scanner(settings, "overrides")
    return settings


def scanner_from_dict(d: dict, where: str = "scanner") -> ScannerSettings:
    """Build and validate a custom scanner from a mapping of :class:`ScannerSettings` fields.

    Required: ``deflector``, ``prf_hz``, a beam divergence (``beam_divergence_mrad``, the
    HELIOS++ 1/e² half angle, or one of the datasheet keys ``beam_divergence_full_1e2_mrad``,
    ``beam_divergence_fwhm_mrad``) and, except for ``tls``, ``scan_freq_hz`` and
    ``scan_angle_deg``. ``name`` defaults to ``"custom"``, ``max_scan_angle_deg`` to
    ``scan_angle_deg`` and ``effective_max_scan_angle_deg`` to ``max_scan_angle_deg``;
    everything else to the dataclass defaults.

    Parameters
    ----------
    d : dict
        The fields.
    where : str
        Key prefix for error messages.

    Returns
    -------
    ScannerSettings
    """
    if not isinstance(d, dict):
        raise ConfigError(f"{where} must be a preset name or a mapping of scanner fields (got {d!r})")
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
    settings = ScannerSettings(name=name, deflector=deflector, **vals)
    validate_scanner(settings, where)
    return settings
