# Shared helpers: config validation, wildcard constraints, target lists, parameter providers,
# and the job environment (how shell commands find the vlsforest package).
import hashlib
import json
import os
import re
import sys
from pathlib import Path

from snakemake.exceptions import WorkflowError
from snakemake.utils import validate


def _config_error(exc):
    """One-line message naming the offending key of a failed schema validation."""
    err = exc.__cause__ or exc.__context__  # the jsonschema ValidationError, if any
    path = getattr(err, "absolute_path", None)
    if path is None or not hasattr(err, "message"):
        return str(exc)
    where = ".".join(str(p) for p in path) or "(top level)"
    return f"Invalid configuration at '{where}': {err.message} (schema: config/schema.yaml)"


# Validate before anything else: a bad config stops here, naming the offending key, before the
# DAG is built or any job runs. Schema defaults (e.g. plots.*.ground_z) are filled in.
try:
    validate(config, "../../config/schema.yaml")
except WorkflowError as exc:
    raise WorkflowError(_config_error(exc)) from None

PLOTS = list(config["plots"])
METHODS = list(config["methods"])
SCENARIOS = list(config["scenarios"])

#: the library's source tree, versioned together with this workflow
LIBRARY_DIR = Path(workflow.basedir) / "workflow" / "vlsforest"

#: the parts ``vlsforest demo`` writes beside scene.yaml (declared outputs of rule scene)
DEMO_PARTS = ("stem.obj", "crown.csv")


wildcard_constraints:
    plot="|".join(map(re.escape, PLOTS)),
    method="|".join(map(re.escape, METHODS)),
    scenario="|".join(map(re.escape, SCENARIOS)),


# ---------------------------------------------------------------------------------------------
# Job environment. Shell commands call ``python -m vlsforest.cli``:
# - the interpreter running Snakemake (e.g. .venv/bin) goes first on PATH, so jobs find the
#   project's Python without an activated venv;
# - with --sdm conda, Snakemake puts the rule's conda env in front of that at job time, and the
#   source tree on PYTHONPATH supplies the vlsforest package itself (envs/vlsforest.yaml holds
#   only its dependencies).
# Both settings are re-made whenever the Snakefile is parsed (also inside cluster jobs).
# ---------------------------------------------------------------------------------------------
def _prepend_env_path(name, entry):
    """Put ``entry`` first in the os.pathsep-separated variable ``name`` (once)."""
    parts = [p for p in os.environ.get(name, "").split(os.pathsep) if p]
    if not parts or parts[0] != entry:
        os.environ[name] = os.pathsep.join([entry] + [p for p in parts if p != entry])


_prepend_env_path("PATH", os.path.dirname(sys.executable))
_prepend_env_path("PYTHONPATH", str(LIBRARY_DIR.parent))


def library_hash(*parts):
    """Short SHA-256 over library source files (paths and contents) below ``parts``.

    Rules get it as a param, naming the sub-packages/modules they run: Snakemake does not see
    code changes inside an imported package, and without this a library edit would leave
    stale results marked up to date. Naming only a rule's own modules keeps an edit of, say,
    the metrics from re-running the forest synthesis.
    """
    h = hashlib.sha256()
    for part in parts or ("",):
        root = LIBRARY_DIR / part
        files = [root] if root.is_file() else sorted(root.rglob("*")) if root.is_dir() else []
        for path in files:
            if (
                "__pycache__" in path.parts
                or not path.is_file()
                or path.suffix in (".pyc", ".nbi", ".nbc")
            ):
                continue
            h.update(path.relative_to(LIBRARY_DIR).as_posix().encode())
            h.update(b"\0")
            h.update(path.read_bytes())
            h.update(b"\0")
    return h.hexdigest()[:16]


#: the simulator stage's code: simulator, I/O, CLI, demo scene
SIM_HASH = library_hash("sim", "io", "commands", "cli.py", "demo.py", "errors.py")
#: the synthesis stage's code: the virtual forest plus the simulator it records with
SYNTH_HASH = library_hash("synth", "sim", "io", "commands", "cli.py", "errors.py")



# ---------------------------------------------------------------------------------------------
# Targets
# ---------------------------------------------------------------------------------------------
def simulated_clouds():
    """Every simulated cloud, results/{plot}/{method}/{scenario}/sim.laz."""
    return expand(
        "results/{plot}/{method}/{scenario}/sim.laz",
        plot=PLOTS,
        method=METHODS,
        scenario=SCENARIOS,
    )


def pulse_tables():
    """Every per-pulse table, results/{plot}/{method}/{scenario}/pulses.npz."""
    return expand(
        "results/{plot}/{method}/{scenario}/pulses.npz",
        plot=PLOTS,
        method=METHODS,
        scenario=SCENARIOS,
    )


def final_outputs():
    """The default target: the virtual forest, every simulated cloud, the simulation summary."""
    return ["results/forest"] + simulated_clouds() + ["results/summary/simulations.csv"]


def synth_param(wildcards=None):
    """The synthesis settings (seed, forest, tls, recordings blocks) as canonical JSON."""
    keys = ("seed", "forest", "tls", "recordings")
    return json.dumps({k: config[k] for k in keys if k in config}, sort_keys=True)


# ---------------------------------------------------------------------------------------------
# Params providers (whole config blocks as canonical JSON, so any new key is tracked)
# ---------------------------------------------------------------------------------------------
def plot_param(wildcards):
    """The plot's config block (tracked as a param)."""
    return json.dumps(config["plots"][wildcards.plot], sort_keys=True)


def method_param(wildcards):
    """The method's config block (tracked as a param)."""
    return json.dumps(config["methods"][wildcards.method], sort_keys=True)


def scenario_param(wildcards):
    """The scenario's config block (tracked as a param)."""
    return json.dumps(config["scenarios"][wildcards.scenario], sort_keys=True)


def scenario_seed(wildcards):
    """The scenario's own ``seed`` if it sets one, else the study's master ``seed``."""
    return int(config["scenarios"][wildcards.scenario].get("seed", config["seed"]))


# ---------------------------------------------------------------------------------------------
# Resources (portable: mem_mb, runtime in minutes); retried jobs get more
# ---------------------------------------------------------------------------------------------
def simulate_mem_mb(wildcards, attempt):
    """Memory of a simulation job: the tracer's BVH and pulse blocks, doubled per retry."""
    return 8000 * attempt


def simulate_runtime(wildcards, attempt):
    """Wall time (minutes) of a simulation job, doubled per retry."""
    return 120 * attempt
