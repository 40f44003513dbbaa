"""``vlsforest plan --scene SCENE.yaml --scenario-json '{…}' -o SURVEY.yaml`` — flight planning."""

from __future__ import annotations

import json

import yaml

from vlsforest.commands import YAML, declare_outputs
from vlsforest.errors import ConfigError
from vlsforest.io.atomic import write_text
from vlsforest.io.yamlfile import read_yaml


def register(sub) -> None:
    """Add the ``plan`` sub-command."""
    p = sub.add_parser("plan", help="plan a survey (flight lines) covering a scene",
                       description="Write SURVEY.yaml with flight lines that cover the scene's ground plane "
                                   "(or its bounds), from a scenario: scanner, pattern, altitude, speed, "
                                   "line spacing (see vlsforest.sim.planning).")
    p.add_argument("--scene", help="SCENE.yaml whose extent to cover (patterns parallel / double_grid)")
    p.add_argument("--trajectory", help="trajectory CSV (gps_time, x, y, z, …, source_id) to re-fly "
                   "(pattern: trajectory)")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--scenario", help="scenario YAML file")
    src.add_argument("--scenario-json", help="scenario as a JSON object")
    p.add_argument("--seed", type=int, default=None, help="survey seed (noise)")
    p.add_argument("-o", "--output", required=True, help="SURVEY.yaml to write")
    p.set_defaults(func=run)
    declare_outputs(p, output=YAML)


def run(args) -> int:
    """Execute ``vlsforest plan``."""
    from pathlib import Path

    from vlsforest.sim.planning import plan_survey
    from vlsforest.sim.scene import Scene
    from vlsforest.sim.survey import survey_from_dict

    if args.scenario_json is not None:
        try:
            scenario = json.loads(args.scenario_json)
        except json.JSONDecodeError as exc:
            raise ConfigError(f"--scenario-json is not valid JSON: {exc}") from None
    else:
        scenario = read_yaml(args.scenario, "scenario")
    if not isinstance(scenario, dict):
        raise ConfigError("the scenario must be a mapping")
    if scenario.get("pattern") == "trajectory" or args.trajectory:
        from vlsforest.io.csvfile import read_csv_table
        from vlsforest.sim.planning import survey_from_trajectory

        if not args.trajectory:
            raise ConfigError("pattern 'trajectory' needs --trajectory CSV")
        tpath = Path(args.trajectory)
        traj = read_csv_table(tpath, "trajectory file")
        survey = survey_from_trajectory(scenario, traj, source=str(tpath))
    else:
        if not args.scene:
            raise ConfigError("--scene is required for patterns 'parallel' and 'double_grid'")
        ext, ground = Scene.from_yaml(args.scene).footprint()
        survey = plan_survey(scenario, ext, ground)
    if args.seed is not None:
        survey["seed"] = int(args.seed)
    survey_from_dict(survey)  # validate before writing
    out = Path(args.output)
    write_text(out, yaml.safe_dump(survey, sort_keys=False))
    return 0
