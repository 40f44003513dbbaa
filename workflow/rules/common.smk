# Shared helpers: config validation, target lists, parameter providers.
import json
import re

from snakemake.utils import validate


validate(config, "../../config/schema.yaml")

PLOTS = list(config["plots"])
METHODS = list(config["methods"])
SCENARIOS = list(config["scenarios"])


wildcard_constraints:
    plot="|".join(map(re.escape, PLOTS)),
    method="|".join(map(re.escape, METHODS)),
    scenario="|".join(map(re.escape, SCENARIOS)),


def final_outputs():
    """Every simulated cloud and the simulation summary."""
    return expand(
        "results/{plot}/{method}/{scenario}/sim.laz",
        plot=PLOTS,
        method=METHODS,
        scenario=SCENARIOS,
    ) + ["results/summary/simulations.csv"]


def plot_param(wildcards):
    """The plot's config block (tracked as a param)."""
    return json.dumps(config["plots"][wildcards.plot], sort_keys=True)


def method_param(wildcards):
    """The method's config block (tracked as a param)."""
    return json.dumps(config["methods"][wildcards.method], sort_keys=True)


def scenario_param(wildcards):
    """The scenario's config block (tracked as a param)."""
    return json.dumps(config["scenarios"][wildcards.scenario], sort_keys=True)
