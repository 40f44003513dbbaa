"""Flight planning: turn a scenario (sensor, altitude, speed, line spacing) and a plot extent
into a SURVEY mapping with legs that cover the plot.

- ``pattern: parallel`` (ALS): lines along y, ``line_spacing_m`` apart, centred on the plot,
  as many as needed for the swath (±scan angle at the altitude) to cover the plot, each
  running ``margin_m`` beyond the plot in both directions; connecting legs are inactive.
- ``pattern: double_grid`` (ULS): lines along x, then lines along y (a double grid),
  ``line_spacing_m`` apart, covering the plot plus ``margin_m``.
- ``pattern: trajectory``: emulate a recorded flight (the study's scenarios "emulate the real
  trajectories"): one straight active leg per flight line of a trajectory CSV (``gps_time, x, y,
  z, …, source_id``) from its first to its last sample, inactive legs between lines, each line
  flown at its own recorded speed (:func:`survey_from_trajectory`).

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
         "margin_m", "cross_margin_m", "n_lines", "line_offset_m", "seed", "trajectory_noise",
         "recording", "extraction_radius_m"}  # the last two are for the workflow, not the flight


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
        ``margin_m`` (default 20), ``n_lines`` (default: enough to cover), ``line_offset_m``
        (default 0: the lines sit symmetrically about the plot's centre; otherwise the whole
        pattern is shifted across track by this), ``seed``, ``trajectory_noise``.
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
    shift = scenario.get("line_offset_m", 0.0)
    if isinstance(shift, bool) or not isinstance(shift, (int, float)) or not math.isfinite(shift):
        raise ConfigError(f"{where}.line_offset_m must be a number, got {shift!r}")
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
    if pattern == "trajectory":
        raise ConfigError(f"{where}.pattern 'trajectory' needs a trajectory file (vlsforest plan --trajectory)")
    if pattern not in ("parallel", "double_grid"):
        raise ConfigError(f"{where}.pattern must be 'parallel', 'double_grid' or 'trajectory', got {pattern!r}")
    xs = _lines(xmin - cross, xmax + cross, spacing, n_lines) + float(shift)
    for i, x in enumerate(xs):  # lines along y, alternating direction
        y0, y1 = (ymin - margin, ymax + margin) if i % 2 == 0 else (ymax + margin, ymin - margin)
        if legs:
            legs.append({"start": legs[-1]["end"], "end": [float(x), y0, z], "active": False})
        legs.append({"start": [float(x), y0, z], "end": [float(x), y1, z], "active": True})
    if pattern == "double_grid":
        ys = _lines(ymin - cross, ymax + cross, spacing, n_lines) + float(shift)
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


def survey_from_trajectory(scenario: dict, trajectory, where: str = "scenario", source: str = "trajectory") -> dict:
    """A SURVEY mapping that re-flies a recorded trajectory, one straight leg per flight line.

    Parameters
    ----------
    scenario : dict
        ``scanner`` and optional ``overrides``, ``detector``, ``seed``, ``trajectory_noise``
        (flight-geometry keys are ignored: the trajectory gives them).
    trajectory : DataFrame
        Columns ``gps_time, x, y, z, source_id`` (one row per trajectory sample).
    where, source : str
        Names for error messages (config key, trajectory file).

    Returns
    -------
    dict
    """
    if "scanner" not in scenario:
        raise ConfigError(f"{where}.scanner is required")
    need = {"gps_time", "x", "y", "z", "source_id"}
    cols = set(getattr(trajectory, "columns", ()))
    if not need <= cols:
        from vlsforest.errors import InputDataError

        raise InputDataError(f"{source}: trajectory needs columns {sorted(need)}, has {sorted(cols)}")
    t = trajectory.sort_values(["source_id", "gps_time"], kind="stable")
    vals = t[["gps_time", "x", "y", "z"]].to_numpy(float)
    if len(t) < 2 or not np.isfinite(vals).all():
        from vlsforest.errors import InputDataError

        raise InputDataError(f"{source}: trajectory needs ≥ 2 finite samples")
    legs, speeds = [], []
    for sid, g in t.groupby("source_id", sort=True):
        a = g[["gps_time", "x", "y", "z"]].to_numpy(float)
        if len(a) < 2 or a[-1, 0] <= a[0, 0]:
            continue
        start, end = a[0, 1:].tolist(), a[-1, 1:].tolist()
        dist = float(np.linalg.norm(a[-1, 1:] - a[0, 1:]))
        if dist <= 0:
            continue
        speeds.append(float(dist / (a[-1, 0] - a[0, 0])))
        if legs:
            legs.append({"start": legs[-1]["end"], "end": start, "active": False})
        legs.append({"start": start, "end": end, "active": True, "speed_mps": speeds[-1]})
    if not legs:
        from vlsforest.errors import InputDataError

        raise InputDataError(f"{source}: no flight line with two distinct samples")
    survey = {"scanner": scenario["scanner"],
              "platform": {"type": "linear", "speed_mps": float(np.median(speeds)), "legs": legs}}
    # the platform speed (the median line speed) is used by the transit legs between lines only
    for key in ("overrides", "detector", "trajectory_noise", "seed"):
        if key in scenario:
            survey[key] = scenario[key]
    return survey
