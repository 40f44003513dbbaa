"""The library of candidate physics: each a switch plus parameter(s) of the simulator.

A candidate's ids and parameters are those of the recording-physics YAML
(``vlsforest synth --recording-physics``), so any candidate can be hidden in "real" data and
modelled by the diagnosis with the same meaning. Baselines come from the survey being
diagnosed (the study's simulation setting: circular beam, no threshold, no noise, …).

========================  ======================  ===========  ==============  =====================
id                        parameter(s)            group        render          prior range
========================  ======================  ===========  ==============  =====================
``beam_divergence``       ``scale``               footprint    re-trace        0.5 – 4
``elliptical_footprint``  ``major_mrad``,         footprint    re-trace        aspect major/minor
                          ``minor_mrad`` (full                                 1 – 6 (searched)
                          angle at 50 % peak)
``detection_threshold``   ``min_energy``          link budget  stored hits     0 – 1e5 (amplitude)
``reflectance``           ``scale`` (all parts)   link budget  stored hits     0.2 – 2
``incidence_reflectance`` ``specularity``         link budget  stored hits     0 – 0.9 (Phong ks,
                          (shininess 10)                                       all parts)
``waveform_window``       ``window_ns``           dead zone    stored hits     0.5 – 6 ns
``max_returns``           ``n``                   dead zone    stored hits     1 – 7
``peak_rule``             ``physical``            dead zone    stored hits     0 (HELIOS++ 1.0.8
                                                                               rule) or 1 (physical)
``range_noise``           ``sigma_m``             noise        stored hits     0 – 0.25 m
``trajectory_noise``      ``position_sigma_m``    noise        re-trace        0 – 0.3 m
``tls_occlusion``         ``top_gain``            model input  re-trace        0 – 8
========================  ======================  ===========  ==============  =====================

``peak_rule`` is the detector's rule for a waveform peak: HELIOS++ 1.0.8 accepts a peak only
when every neighbour in its window is itself above the threshold, so an echo that does not
overlap earlier energy is dropped for windows of 6 bins or more (the study's 1.5 and 1.75 ns);
a physical detector reports it. Its parameter is 0 for the HELIOS++ rule and 1 for the physical
one (``detector.peak_rule`` of the survey).

``detection_threshold`` is a receiver's threshold on the peak amplitude (the recordings'
meaning): it sets ``detector.threshold_scope: peak``, so that under the helios rule the
neighbours of a peak keep HELIOS++ 1.0.8's fixed floor instead of having to reach the
threshold too (HELIOS++ 2.x's ``receivedEnergyMin_W``, which lets only echoes several times
the threshold through). The two candidates are then separable: switching the peak rule at a
fitted threshold adds the isolated echoes and leaves the weakest echo reported — the
``int_floor`` observable — where the threshold put it; with the threshold covering the window
the switch would also lower that floor by the window's factor, and the floor (the observable
measured most precisely across trees) would swamp the switch's signature.

``tls_occlusion`` is the one model-input candidate: the TLS sees the upper crown through the
lower one, so PAD is under-estimated there (Weiser et al. 2021, §4) and PAD-scaled cubes come out
too small. The correction multiplies each crown cube's PAD by ``1 + top_gain · ramp``, where
``ramp`` rises linearly from 0 at half the crown's height range to 1 at its top
(:func:`occlusion_corrected`); with the study's α = 0.5 the cube side grows by the square root of
that factor, capped at the cell. It applies to PAD-scaled voxel models only (the scaled methods);
cells the TLS never hit cannot be restored by it.

Groups are the declared look-alikes on tree metrics; within a group the diagnosis names the
observables that separate the members (:data:`TIE_BREAKERS`).

The footprint group splits the beam into its size and its shape. ``beam_divergence`` scales
the beam's solid angle and is applied after every other candidate (it scales whatever beam they
set); ``elliptical_footprint`` is searched along its aspect ratio at the solid angle of the beam
being simulated (:meth:`Candidate.current`: the survey's beam, or the one a fitted divergence
scale made), so its values are the whole beam and replace that scale (:func:`merge`). A
circle fitted first for the group and an ellipse fitted after it thus give the ellipse of the
fitted solid angle, not a second scaling of it.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np

from vlsforest.errors import ConfigError

from vlsforest.sim.scanner import datasheet_divergence, fwhm_to_1e2

#: a ``beam_divergence_mrad`` value (the HELIOS++ 1/e² half angle) → the full angle at 50 % peak
#: intensity: 2 / √(2 / ln 2) ≈ 1.177
_HALF_1E2_TO_FWHM = 2.0 / float(fwhm_to_1e2(1.0))


def _scanner(survey: dict):
    """The scanner a survey mapping (a preset and its ``overrides``) simulates."""
    from vlsforest.sim.scanner import scanner_from_preset

    return scanner_from_preset(survey["scanner"], survey.get("overrides"))


def _divergence(survey: dict) -> tuple[float, float]:
    """The survey's ``beam_divergence_mrad`` (major, minor; the HELIOS++ 1/e² half angle): its
    override, else the preset's."""
    major, minor = _scanner(survey).beam.divergence_mrad
    return float(major), float(minor)


#: candidates applied after all others: a scale of whatever beam the others set
_APPLIED_LAST = ("beam_divergence",)


def apply_all(survey: dict, assign: dict) -> tuple[dict, dict]:
    """``survey`` with every candidate of ``assign`` (id → values) applied, in the one order
    the diagnosis uses (by id, the divergence scale last), and their scene edits merged
    (reflectance scales multiply).

    Returns
    -------
    (dict, dict)
        The survey mapping and the scene edits (``reflectance_scale`` always present).
    """
    s, edits = survey, {"reflectance_scale": 1.0}
    for name in sorted(assign, key=lambda n: (n in _APPLIED_LAST, n)):
        s, e = CANDIDATES[name].apply(s, assign[name])
        edits["reflectance_scale"] *= e.pop("reflectance_scale", 1.0)
        edits.update(e)
    div = (s.get("overrides") or {}).get("beam_divergence_mrad")
    if isinstance(div, (list, tuple)):  # one beam reached two ways (a scale, an ellipse of aspect 1): one trace
        s = dict(s, overrides=dict(s["overrides"], beam_divergence_mrad=[float(f"{d:.12g}") for d in div]))
    return s, edits


@dataclass(frozen=True)
class Param:
    """One parameter of a candidate: bounds, a reference perturbation and a grid scale."""

    name: str
    lo: float
    hi: float
    delta: float            # reference perturbation (added, or a factor when log=True; from 0: added)
    log: bool = False
    integer: bool = False
    n_grid: int = 0         # grid points of its fit (0: the diagnosis' ``grid``); the reference step is one


@dataclass(frozen=True)
class Candidate:
    """A physics candidate (see the module table)."""

    name: str
    params: tuple
    group: str
    render: str             # "hits" (re-detection of stored sub-ray hits) or "trace"
    description: str
    keys: tuple = ()        # the values' names (the recording physics'), when not the searched parameters'
    #: its simulation is one draw of a random process with few independent samples over a plot
    #: (trajectory errors: smooth channels of GPS time); the recording is another draw, so its
    #: fitted value carries the scatter of both, which the diagnosis measures by simulating
    #: further draws (``"realisation": r`` among the values, see :meth:`apply`)
    realisations: bool = False

    @property
    def value_keys(self) -> tuple:
        """Names of the candidate's values (what :meth:`apply` takes and the report gives)."""
        return self.keys or tuple(p.name for p in self.params)

    def baseline(self, survey: dict) -> dict:
        """The values the survey already simulates."""
        det = _scanner(survey).detector
        div = _divergence(survey)
        tn = survey.get("trajectory_noise") or {}
        return {
            "beam_divergence": {"scale": 1.0},
            "elliptical_footprint": {"major_mrad": div[0] * _HALF_1E2_TO_FWHM,
                                     "minor_mrad": div[1] * _HALF_1E2_TO_FWHM},
            "detection_threshold": {"min_energy": float(det.min_energy)},
            "reflectance": {"scale": 1.0},
            "waveform_window": {"window_ns": float(det.window_size_ns)},
            "max_returns": {"n": float(det.max_returns or 7)},
            "peak_rule": {"physical": float(_peak_rule(survey) == "physical")},
            "range_noise": {"sigma_m": float(det.range_noise_m)},
            "trajectory_noise": {"position_sigma_m": float(tn.get("position_sigma_m", 0.0))},
            "incidence_reflectance": {"specularity": 0.0},
            "tls_occlusion": {"top_gain": 0.0},
        }[self.name]

    def current(self, survey: dict, base: dict) -> dict:
        """The values simulated with the candidates ``base`` (id → values) applied to ``survey``:
        its own entry there, else its baseline; for ``elliptical_footprint`` the beam ``base``
        makes (a fitted divergence scale included), so that its search starts from that beam."""
        if self.name in base:
            return dict(base[self.name])
        if self.name == "elliptical_footprint":
            major, minor = beam_fwhm(survey, base)
            return {"major_mrad": major, "minor_mrad": minor}
        return self.baseline(survey)

    def coords(self, values: dict) -> dict:
        """The searched parameters (:attr:`params`) of ``values``: the values themselves, but the
        aspect ratio major / minor for ``elliptical_footprint``."""
        if self.name == "elliptical_footprint":
            return {"aspect": values["major_mrad"] / values["minor_mrad"]}
        return {p.name: values[p.name] for p in self.params}

    def values(self, current: dict, coords: dict) -> dict:
        """The values at the searched parameters ``coords``, the rest as in ``current``; for
        ``elliptical_footprint`` the beam of ``current``'s solid angle (major · minor) with
        the aspect ratio ``coords["aspect"]``."""
        if self.name == "elliptical_footprint":
            area, k = current["major_mrad"] * current["minor_mrad"], float(coords["aspect"])
            return {"major_mrad": float(np.sqrt(area * k)), "minor_mrad": float(np.sqrt(area / k))}
        out = dict(current)
        out.update({k: float(v) for k, v in coords.items()})
        return out

    def bounds(self, survey: dict) -> dict:
        """Bounds per searched parameter (absolute units)."""
        return {p.name: (p.lo, p.hi) for p in self.params}

    def step_coords(self, current: dict, survey: dict) -> dict:
        """The searched parameters of :meth:`step`."""
        p = self.params[0]
        lo, hi = self.bounds(survey)[p.name]
        co = self.coords(current)
        c = co[p.name]
        v = (c * p.delta if c > 0 else p.delta) if p.log else c + p.delta
        co[p.name] = float(np.clip(v, lo, hi))
        if co[p.name] == c:
            co[p.name] = float(np.clip(c / p.delta if p.log else c - p.delta, lo, hi))
        return co

    def step(self, current: dict, survey: dict) -> dict:
        """``current`` with the first searched parameter moved by the reference perturbation
        (for the signature): multiplied by ``delta`` for log parameters (set to it from 0), else
        added; clipped to the bounds, and taken the other way when a bound blocks it. Returns
        values (as :meth:`apply` takes them)."""
        return self.values(current, self.step_coords(current, survey))

    def apply(self, survey: dict, values: dict) -> tuple[dict, dict]:
        """A copy of ``survey`` with the candidate set to ``values``; also the scene edits.

        For a candidate with :attr:`realisations`, ``values`` may hold ``"realisation": r``
        (an integer ≥ 1): the survey's seed is then replaced by one derived from it and ``r``,
        so its random process is drawn anew (0 or absent: the survey's own draw).

        Returns
        -------
        (dict, dict)
            The modified survey mapping and the edits of the scene this candidate needs (empty
            for survey-only candidates): ``reflectance_scale`` (factor on every part's
            reflectance), ``specularity`` (Phong ks of every part, shininess
            :data:`SHININESS`), ``top_gain`` (see :func:`occlusion_corrected`).
        """
        s = copy.deepcopy(survey)
        ov = dict(s.get("overrides") or {})
        edits = {}
        if self.name == "beam_divergence":
            div = _divergence(s)
            ov["beam_divergence_mrad"] = [div[0] * values["scale"], div[1] * values["scale"]]
        elif self.name == "elliptical_footprint":
            ov["beam_divergence_mrad"] = list(datasheet_divergence(fwhm_mrad=(values["major_mrad"],
                                                                               values["minor_mrad"])))
            ov["beam_orientation_deg"] = 0.0
        elif self.name == "detection_threshold":
            ov["min_energy"] = float(values["min_energy"])
            s["detector"] = dict(s.get("detector") or {}, threshold_scope="peak")
        elif self.name == "reflectance":
            edits["reflectance_scale"] = float(values["scale"])
        elif self.name == "incidence_reflectance":
            edits["specularity"] = float(values["specularity"])
        elif self.name == "tls_occlusion":
            edits["top_gain"] = float(values["top_gain"])
        elif self.name == "waveform_window":
            ov["window_size_ns"] = float(values["window_ns"])
        elif self.name == "max_returns":
            ov["max_returns"] = int(round(values["n"]))
        elif self.name == "range_noise":
            ov["range_noise_m"] = float(values["sigma_m"])
        elif self.name == "peak_rule":
            s["detector"] = dict(s.get("detector") or {},
                                 peak_rule="physical" if round(float(values["physical"])) else "helios")
        elif self.name == "trajectory_noise":
            tn = dict(s.get("trajectory_noise") or {})
            tn["position_sigma_m"] = float(values["position_sigma_m"])
            tn.setdefault("correlation_s", 2.0)
            s["trajectory_noise"] = tn
        r = values.get("realisation", 0)
        if r:  # another draw of the candidate's random process: a seed derived from the survey's
            if not self.realisations:
                raise ConfigError(f"{self.name}: draws no random realisation (got realisation={r!r})")
            s["seed"] = derived_seed([s.get("seed", 0), r], 0x5EED)
        s["overrides"] = ov
        return s, edits


CANDIDATES = {c.name: c for c in (
    Candidate("beam_divergence", (Param("scale", 0.5, 4.0, 1.7, log=True),), "footprint", "trace",
              "beam divergence (footprint size) differs from the simulated one"),
    Candidate("elliptical_footprint", (Param("aspect", 1.0, 6.0, 3.0, log=True, n_grid=5),), "footprint", "trace",
              "an elliptical beam (major × minor divergence at FWHM) instead of a circular one",
              keys=("major_mrad", "minor_mrad")),
    Candidate("detection_threshold", (Param("min_energy", 0.0, 1.0e5, 5000.0, log=True),), "link budget", "hits",
              "weak echoes below a minimum energy are not detected"),
    Candidate("reflectance", (Param("scale", 0.2, 2.0, 0.5, log=True),), "link budget", "hits",
              "target reflectance at the scanner wavelength differs (all parts scaled)"),
    Candidate("waveform_window", (Param("window_ns", 0.5, 6.0, 1.5),), "dead zone", "hits",
              "a longer peak-detection window (dead zone between echoes of a pulse)"),
    Candidate("max_returns", (Param("n", 1.0, 7.0, -2.0, integer=True),), "dead zone", "hits",
              "the receiver reports fewer returns per pulse"),
    Candidate("peak_rule", (Param("physical", 0.0, 1.0, 1.0, integer=True),), "dead zone", "hits",
              "the detector reports echoes that do not overlap earlier energy (a physical peak rule), "
              "which HELIOS++ 1.0.8's rule drops"),
    Candidate("range_noise", (Param("sigma_m", 0.0, 0.25, 0.05),), "noise", "hits",
              "random range error of each echo"),
    Candidate("trajectory_noise", (Param("position_sigma_m", 0.0, 0.3, 0.05),), "noise", "trace",
              "time-correlated position errors of the platform (GNSS/INS)", realisations=True),
    Candidate("incidence_reflectance", (Param("specularity", 0.0, 0.9, 0.3),), "link budget", "hits",
              "reflection depends on the incidence angle more than Lambert's law (Phong, cos-power lobe)"),
    Candidate("tls_occlusion", (Param("top_gain", 0.0, 8.0, 1.0),), "model input", "trace",
              "PAD under-estimated in the upper crown, where the TLS saw through the lower crown"),
)}

#: Phong shininess of the ``incidence_reflectance`` candidate (the recording physics' default)
SHININESS = 10.0

#: exponent α of the PAD-scaled cubes assumed by the ``tls_occlusion`` correction (the study's)
ALPHA_SCALED = 0.5


def occlusion_corrected(model, top_gain: float):
    """A PAD-scaled voxel model with the upper-crown PAD raised (the ``tls_occlusion`` candidate).

    Each cube's PAD is multiplied by ``g = 1 + top_gain · clip((z − zmid) / (ztop − zmid), 0, 1)``
    with ``zmid`` the middle and ``ztop`` the top of the model's cube centres (one model = one
    crown in the study's scenes); the cube side grows by ``g ** ALPHA_SCALED`` (a = a0 ·
    (PAD/PADmax)^α), capped at the cell size, and the centre is moved only as far as needed to
    keep the cube inside its cell.

    Parameters
    ----------
    model : vlsforest.io.voxel_model.VoxelModel
        A model with per-cube sizes (``half``) — fixed-size models have no PAD to correct.
    top_gain : float
        Relative PAD increase at the crown top (≥ 0).

    Returns
    -------
    VoxelModel
    """
    from vlsforest.io.voxel_model import VoxelModel

    if model.half is None:
        raise ConfigError("tls_occlusion corrects PAD-scaled cubes; this voxel model has fixed-size cubes")
    if not top_gain >= 0:
        raise ConfigError(f"tls_occlusion: top_gain must be ≥ 0, got {top_gain!r}")
    centre = model.centres()
    z = centre[:, 2]
    zmid, ztop = 0.5 * (z.min() + z.max()), z.max()
    ramp = np.clip((z - zmid) / (ztop - zmid), 0.0, 1.0) if ztop > zmid else np.zeros(len(z))
    g = 1.0 + top_gain * ramp
    half = np.minimum(model.half * g ** ALPHA_SCALED, 0.5 * model.size)
    lo = model.ijk * model.size
    centre = np.clip(centre, lo + half[:, None], lo + model.size - half[:, None])
    pad = None if model.pad is None else model.pad * g
    return VoxelModel(model.size, model.ijk, model.owner, half, centre, pad)


def derived_seed(entropy, key: int) -> int:
    """A survey seed (a non-negative 31-bit integer) derived from the integers ``entropy`` and the
    stream ``key``: the same inputs give the same seed, other inputs or keys an unrelated one."""
    seq = np.random.SeedSequence([int(e) for e in entropy], spawn_key=(int(key),))
    return int(seq.generate_state(1, np.uint32)[0] >> 1)


def merge(base: dict, name: str, values: dict) -> dict:
    """A copy of ``base`` (id → values) with candidate ``name`` set to ``values``.

    ``elliptical_footprint``'s values are the whole beam (its search starts from the beam of
    ``base``, see :meth:`Candidate.current`), so it replaces a ``beam_divergence`` scale there.
    """
    out = {k: dict(v) for k, v in base.items()
           if not (name == "elliptical_footprint" and k == "beam_divergence")}
    out[name] = dict(values)
    return out


def beam_fwhm(survey: dict, assign: dict) -> tuple[float, float]:
    """The beam (major, minor) of ``survey`` with ``assign`` applied, as full angles at 50 % peak
    intensity (mrad)."""
    major, minor = _divergence(apply_all(survey, assign)[0])
    return major * _HALF_1E2_TO_FWHM, minor * _HALF_1E2_TO_FWHM


def _peak_rule(survey: dict) -> str:
    """The peak rule the survey's detector runs (``"physical"`` or ``"helios"``)."""
    from vlsforest.sim.engine import DetectorOptions

    return DetectorOptions.from_dict(survey.get("detector")).peak_rule


def equivalent_circular_divergence(survey: dict, assign: dict) -> float:
    """FWHM divergence (mrad) of the circular beam with the same solid angle as the beam of
    ``survey`` with the candidates ``assign`` (id → values) applied: √(major · minor).

    The footprint group's members look alike on tree metrics when their beams have equal solid
    angles (the Gaussian beam's irradiance, hence which elements it detects, scales with
    1 / (major · minor)); when the group's separating observables do not separate an ellipse
    from a circle, this is the quantity the fitted member identifies.

    Parameters
    ----------
    survey : dict
        The survey mapping (``scanner`` and optional ``overrides``).
    assign : dict
        Candidate id → parameter values (e.g. ``{"beam_divergence": {"scale": 2.0}}``); the
        candidates are applied in the same order as the diagnosis' simulations.

    Returns
    -------
    float
    """
    major, minor = beam_fwhm(survey, assign)
    return float(np.sqrt(major * minor))


#: observables that separate the members of a group (named in the report when a group ties)
TIE_BREAKERS = {
    "footprint": ("crown_extent_ratio", "multi_pct_nadir", "multi_pct_offnadir"),
    "link budget": ("int_floor", "int_p01_rel", "int_p05_rel", "first_max"),
    "dead zone": ("interecho_floor", "interecho_p10", "interecho_short_pct", "rn3plus_share"),
    "noise": ("ground_sd_single", "ground_dz_single"),
}


def select(names=None) -> list[Candidate]:
    """Candidates by id (all by default); unknown ids raise ConfigError."""
    if names is None:
        return list(CANDIDATES.values())
    out = []
    for n in names:
        if n not in CANDIDATES:
            raise ConfigError(f"unknown physics candidate {n!r} (known: {', '.join(CANDIDATES)})")
        out.append(CANDIDATES[n])
    return out
