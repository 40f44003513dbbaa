"""Flight planning: turn a scenario (sensor, altitude, speed, line spacing) and a plot extent
into a SURVEY mapping with legs that cover the plot.

- ``pattern: parallel`` (ALS): lines along y, ``line_spacing_m`` apart, centred on the plot,
  as many as needed for the swath (±scan angle at the altitude) to cover the plot, each
  running ``margin_m`` beyond the plot in both directions; connecting legs are inactive.
- ``pattern: double_grid`` (ULS): lines along x, then lines along y (a double grid),
  ``line_spacing_m`` apart, covering the plot plus ``margin_m``.

Lines are placed over the plot widened by ``cross_margin_m`` across track (default 0): a wide
scanner (±90°) also samples the plot from lines far beside it, which a real campaign over a
whole forest has.

Altitudes are above the given ground elevation. Every scenario value may be overridden.
"""

from __future__ import annotations

import math

import numpy as np

from vlsforest.errors import ConfigError

_KEYS = {"scanner", "overrides", "detector", "pattern", "altitude_m", "speed_mps", "line_spacing_m",
         "margin_m", "cross_margin_m", "n_lines", "seed", "trajectory_noise"}


def _lines(lo, hi, spacing, n_lines):
    centre = 0.5 * (lo + hi)
    if n_lines:
        k = np.arange(n_lines) - (n_lines - 1) / 2.0
    else:
        half = max(0.0, 0.5 * (hi - lo))
        m = int(math.ceil(half / spacing))
        k = np.arange(-m, m + 1, dtype=float)
    return centre + k * spacing


def plan_survey(scenario: dict, extent, ground_z: float, where: str = "scenario") -> dict:
    """Build a SURVEY mapping (as read by :func:`vlsforest.sim.survey.survey_from_dict`).

    Parameters
    ----------
    scenario : dict
        ``scanner`` (preset), ``pattern`` (``parallel`` | ``double_grid``), ``altitude_m``,
        ``speed_mps``, ``line_spacing_m``; optional ``overrides``, ``detector``,
        ``margin_m`` (default 20), ``n_lines`` (default: enough to cover), ``seed``,
        ``trajectory_noise``.
    extent : (xmin, ymin, xmax, ymax)
        Plot extent to cover.
    ground_z : float
        Ground elevation the altitude refers to.
    where : str
        Name used in error messages.

    Returns
    -------
    dict
    """
    unknown = set(scenario) - _KEYS
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {sorted(unknown)}")
    for key in ("scanner", "pattern", "altitude_m", "speed_mps", "line_spacing_m"):
        if key not in scenario:
            raise ConfigError(f"{where}.{key} is required")
    for key in ("margin_m", "cross_margin_m"):
        v = scenario.get(key, 0.0)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not v >= 0:
            raise ConfigError(f"{where}.{key} must be a number ≥ 0, got {v!r}")
    for key in ("altitude_m", "speed_mps", "line_spacing_m"):
        v = scenario[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0:
            raise ConfigError(f"{where}.{key} must be a positive number, got {v!r}")
    xmin, ymin, xmax, ymax = (float(v) for v in extent)
    z = float(ground_z) + float(scenario["altitude_m"])
    margin = float(scenario.get("margin_m", 20.0))
    cross = float(scenario.get("cross_margin_m", 0.0))
    spacing = float(scenario["line_spacing_m"])
    n_lines = int(scenario.get("n_lines", 0) or 0)
    legs = []
    pattern = scenario["pattern"]
    if pattern not in ("parallel", "double_grid"):
        raise ConfigError(f"{where}.pattern must be 'parallel' or 'double_grid', got {pattern!r}")
    xs = _lines(xmin - cross, xmax + cross, spacing, n_lines)
    for i, x in enumerate(xs):  # lines along y, alternating direction
        y0, y1 = (ymin - margin, ymax + margin) if i % 2 == 0 else (ymax + margin, ymin - margin)
        if legs:
            legs.append({"start": legs[-1]["end"], "end": [float(x), y0, z], "active": False})
        legs.append({"start": [float(x), y0, z], "end": [float(x), y1, z], "active": True})
    if pattern == "double_grid":
        ys = _lines(ymin - cross, ymax + cross, spacing, n_lines)
        for i, y in enumerate(ys):  # lines along x
            x0, x1 = (xmin - margin, xmax + margin) if i % 2 == 0 else (xmax + margin, xmin - margin)
            legs.append({"start": legs[-1]["end"], "end": [x0, float(y), z], "active": False})
            legs.append({"start": [x0, float(y), z], "end": [x1, float(y), z], "active": True})
    survey = {"scanner": scenario["scanner"], "platform": {"type": "linear",
                                                           "speed_mps": float(scenario["speed_mps"]), "legs": legs}}
    for key in ("overrides", "detector", "trajectory_noise", "seed"):
        if key in scenario:
            survey[key] = scenario[key]
    return survey
