"""The study's configurations simulate the study as HELIOS++ 1.0.8 ran it."""

from pathlib import Path

import jsonschema
import pytest
import yaml

from vlsforest.sim.engine import DetectorOptions

ROOT = Path(__file__).resolve().parents[1]


def _load(name):
    return yaml.safe_load((ROOT / "config" / name).read_text())


@pytest.mark.parametrize("name", ["config.yaml", "quick.yaml"])
def test_study_scenarios_run_the_helios_v1_detector(name):
    scenarios = _load(name)["scenarios"]
    assert {"als", "uls"} <= set(scenarios)
    for key in ("als", "uls"):
        det = DetectorOptions.from_dict(scenarios[key].get("detector"))
        assert scenarios[key]["detector"] == {"mode": "helios_v1"}
        assert det.peak_rule == "helios" and not det.dedupe_ranges and det.atmosphere_convention == "helios"
    # the study's tuned windows (1.75 ns ALS, 1.5 ns ULS) stay with that rule
    assert scenarios["als"]["overrides"]["window_size_ns"] == 1.75
    assert scenarios["uls"]["overrides"]["window_size_ns"] == 1.5


def test_physical_detector_sensitivity_scenarios_validate_beside_the_study():
    extra = _load("physical-detector.yaml")["scenarios"]
    schema = yaml.safe_load((ROOT / "config" / "schema.yaml").read_text())
    for base in ("config.yaml", "quick.yaml"):
        cfg = _load(base)
        study = cfg["scenarios"]
        cfg["scenarios"] = {**study, **extra}
        jsonschema.validate(cfg, schema)
        for name, sc in extra.items():
            twin = study[name.removesuffix("_physical")]
            assert sc["detector"] == {"mode": "physical"}
            # the same survey as its study twin, the detector aside
            assert {k: v for k, v in sc.items() if k != "detector"} == \
                {k: v for k, v in twin.items() if k != "detector"}


def test_the_tests_quick_forest_settings_are_the_quick_study_s():
    """tests/conftest.py's QUICK_SYNTH (the settings the tests record the quick forest with,
    seed 0) are those of config/quick.yaml, so that such a recording is the quick study's forest."""
    from conftest import QUICK_SYNTH

    quick = _load("quick.yaml")
    assert quick["seed"] == 0
    # the blocks the workflow's synthesis reads besides the seed (workflow/rules/common.smk)
    assert {key: quick[key] for key in ("forest", "tls", "recordings") if key in quick} == QUICK_SYNTH


def test_the_default_config_plays_every_part_of_the_study():
    """Every method of config.yaml is one of the study's, both scenarios play its surveys, and the
    experiments scan a plot of the config."""
    from vlsforest.stats import StudyRoles

    cfg = _load("config.yaml")
    roles = StudyRoles.from_config(cfg["methods"], cfg["scenarios"])
    assert all(r.study for r in roles.methods) and len(roles.methods) == 7
    assert dict(roles.platforms) == {"als": "als", "uls": "uls"}
    for size in (0.25, 0.10, 0.05, 0.02):
        assert roles.method("fixed", size) is not None
    for shift in ("none", "random", "cog"):
        assert roles.method("scaled", shift=shift) is not None
    for name, block in cfg["experiments"].items():
        assert block["enabled"], name
        assert block.get("plot", next(iter(cfg["plots"]))) in cfg["plots"], name
    jsonschema.validate(cfg, yaml.safe_load((ROOT / "config" / "schema.yaml").read_text()))
