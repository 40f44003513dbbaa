"""The diagnosis' set-up: plots, scenario, candidates and settings, read from a sim-config.

The sim-config's keys, their types, bounds and defaults are one JSON schema, :data:`SCHEMA`
(draft 2020-12). :func:`load_setup` validates a sim-config against it and fills in its
defaults; by hand it adds only what a schema cannot say: the scenario comes from the command
line or from the file, and a plot's real recording defaults to a file under ``--real``.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from pathlib import Path

from vlsforest.diagnose.library import CANDIDATES
from vlsforest.errors import ConfigError
from vlsforest.io.yamlfile import read_yaml

#: default of a plot's ``margin`` (m): the diagnosis traces the pulses that enter the trees'
#: observed region ± this; the workflow's ``diagnosis.region_margin_m`` falls back to it too
REGION_MARGIN_M = 1.0

#: a scenario or recording name (as the workflow's ``scenarios`` keys: it names files)
_NAME = "^[A-Za-z0-9][A-Za-z0-9_.-]*$"

#: the sim-config's schema: every key, its type, bounds and default
SCHEMA = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "vlsforest diagnose sim-config",
    "type": "object",
    "additionalProperties": False,
    "required": ["plots"],
    "properties": {
        "scenario": {"type": "string", "pattern": _NAME,
                     "description": "the scenario's name (--scenario overrides it): labels the report and names "
                                    "the default recording"},
        "recording": {"type": "string", "pattern": _NAME,
                      "description": "file name of the real recording per plot (default: the scenario)"},
        "seed": {"type": "integer", "minimum": 0, "default": 0},
        "folds": {"type": "integer", "minimum": 2, "default": 3, "description": "k-fold across trees"},
        "grid": {"type": "integer", "minimum": 3, "maximum": 15, "default": 7,
                 "description": "grid points of the first searched parameter's fit"},
        "workers": {"type": "integer", "minimum": 1, "default": 2,
                    "description": "worker processes of the ray traces"},
        "candidates": {"type": "array", "minItems": 1, "items": {"enum": list(CANDIDATES)},
                       "description": "the physics candidates (default: the whole library)"},
        "beam_sample_quality": {"type": "integer", "minimum": 1, "maximum": 8,
                                "description": "sub-ray rings of the diagnosis' simulations (default: the "
                                               "survey's)"},
        "realisations": {"type": "integer", "minimum": 0, "maximum": 20, "default": 3,
                         "description": "further draws of an accepted random candidate's process"},
        "plots": {
            "type": "object",
            "minProperties": 1,
            "additionalProperties": {
                "type": "object",
                "additionalProperties": False,
                "required": ["scene", "survey", "segment", "radius"],
                "properties": {
                    "real": {"type": "string", "description": "the real recording (default: "
                                                              "<--real DIR>/<plot>/<recording>.laz)"},
                    "scene": {"type": "string"},
                    "survey": {"type": "string"},
                    "segment": {"type": "string", "description": "segmentation folder (trees.csv, trees/*.laz)"},
                    "radius": {"type": "number", "exclusiveMinimum": 0,
                               "description": "extraction radius around the TLS tree points (m)"},
                    "margin": {"type": "number", "minimum": 0, "default": REGION_MARGIN_M,
                               "description": "pulses are traced where they enter the observed region ± this (m)"},
                },
            },
        },
    },
}

#: the top-level defaults of :data:`SCHEMA`
DEFAULTS = {k: v["default"] for k, v in SCHEMA["properties"].items() if "default" in v}


@dataclass
class PlotInput:
    """What the diagnosis needs of one plot."""

    name: str
    real: Path
    scene: Path
    survey: Path
    segment: Path
    radius: float
    margin: float = REGION_MARGIN_M


@dataclass
class Setup:
    """A diagnosis set-up: plots, scenario, candidates and settings (see :func:`load_setup`)."""

    scenario: str
    plots: list
    candidates: list = field(default_factory=lambda: list(CANDIDATES))
    folds: int = DEFAULTS["folds"]
    seed: int = DEFAULTS["seed"]
    workers: int = DEFAULTS["workers"]
    grid: int = DEFAULTS["grid"]
    #: whether ``candidates`` was given (else: the whole library, less what the scenes cannot model)
    candidates_given: bool = False
    #: sub-ray rings of the diagnosis' own simulations (None: the survey's). Footprint fits are
    #: biased when the simulation samples the beam more coarsely than the real beam is (fewer
    #: sub-rays split fewer echoes, so a wider beam is fitted); see docs/diagnosis.md
    beam_sample_quality: int | None = None
    #: further draws of a random candidate's process simulated at its fitted value, whose
    #: scatter widens its CI (one trace each; 0: no draws, the CI holds the trees' bootstrap and
    #: the observables' disagreement only)
    realisations: int = DEFAULTS["realisations"]


def _where(path) -> str:
    """A JSON-schema error path as a key path (``plots.Q1.radius``, ``candidates[0]``)."""
    out = ""
    for p in path:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out


def _with_defaults(d: dict, schema: dict) -> dict:
    """``d`` with the defaults of ``schema``'s properties filled in, at every depth."""
    props = schema.get("properties", {})
    for k, sub in props.items():
        if k not in d and "default" in sub:
            d[k] = copy.deepcopy(sub["default"])
    extra = schema.get("additionalProperties")
    for k, v in d.items():
        sub = props.get(k, extra if isinstance(extra, dict) else None)
        if sub is not None and isinstance(v, dict):
            _with_defaults(v, sub)
    return d


def load_setup(path, real_dir=None, scenario=None) -> Setup:
    """Read a sim-config YAML (or take the same as a mapping) and check it against :data:`SCHEMA`.

    Format::

        scenario: uls                 # the scenario's name (the CLI's --scenario overrides it)
        recording: uls                # file name of the real recording per plot (default: scenario)
        seed: 0
        folds: 3                      # k-fold across trees
        grid: 7                       # grid points of the fit
        workers: 2                    # worker processes of the ray traces
        candidates: [range_noise, …]  # default: the whole library
        beam_sample_quality: 4        # sub-ray rings of the diagnosis' simulations (default: the
                                      # survey's); finer than the study's for footprint fits
        realisations: 3               # further draws of an accepted trajectory-noise fit's process
                                      # (one trace each) whose scatter widens its CI; 0: none
        plots:
          Q1:
            real: …/Q1/uls.laz        # default: <--real DIR>/<plot>/<recording>.laz
            scene: results/Q1/scaled/scene/scene.yaml
            survey: results/Q1/surveys/uls.yaml
            segment: results/Q1/segment     # segmentation folder (trees.csv, trees/*.laz)
            radius: 0.3               # extraction radius around the TLS tree points (m)
            margin: 1                 # pulses are traced where they enter the observed region
                                      # (the trees' points ± radius and the ground columns under
                                      # their crowns) ± this (m; default 1,
                                      # :data:`REGION_MARGIN_M`)

    The scenario is a name (the workflow's ``{scenario}``): the platform and scanner are those
    of each plot's survey. Relative paths are taken from the current directory.

    Raises
    ------
    ConfigError
        One line naming the file and the key: a value the schema rejects, no scenario, or a plot
        without ``real`` when no ``real_dir`` is given.
    """
    import jsonschema

    if isinstance(path, dict):
        d, path = path, "sim-config"
    else:
        path = Path(path)
        d = read_yaml(path, "sim-config", empty={})
    if not isinstance(d, dict):
        raise ConfigError(f"{path}: must be a mapping")
    d = copy.deepcopy(d)
    if scenario is not None:
        d["scenario"] = scenario
    err = jsonschema.exceptions.best_match(jsonschema.Draft202012Validator(SCHEMA).iter_errors(d))
    if err is not None:
        where = _where(err.absolute_path)
        raise ConfigError(f"{path}: {where + ': ' if where else ''}{' '.join(err.message.split())}")
    d = _with_defaults(d, SCHEMA)
    if "scenario" not in d:
        raise ConfigError(f"{path}: no scenario (give --scenario NAME or 'scenario' in the sim-config)")
    rec = d.get("recording", d["scenario"])
    out = []
    for name, p in d["plots"].items():
        real = p.get("real")
        if real is None:
            if real_dir is None:
                raise ConfigError(f"{path}: plots.{name}.real is missing and no --real DIR was given")
            real = Path(real_dir) / str(name) / f"{rec}.laz"
        out.append(PlotInput(str(name), Path(real), Path(p["scene"]), Path(p["survey"]), Path(p["segment"]),
                             float(p["radius"]), float(p["margin"])))
    return Setup(d["scenario"], out, list(d.get("candidates") or CANDIDATES), int(d["folds"]), int(d["seed"]),
                 int(d["workers"]), int(d["grid"]), candidates_given=bool(d.get("candidates")),
                 beam_sample_quality=None if d.get("beam_sample_quality") is None else int(d["beam_sample_quality"]),
                 realisations=int(d["realisations"]))
