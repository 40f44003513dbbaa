# Shared helpers: config validation, wildcard constraints, target lists, parameter providers,
# the job environment (how shell commands find the vlsforest package), code hashes and the
# scheduler patch (on by default).
import json
import os
import re
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

#: species groups (leaf angle distribution, PADmax) used by PAD-scaled methods
PAD_GROUPS = config["pad"]["groups"]

#: methods whose voxels a built-in kind makes (others come from rule files in rules/methods/)
BUILTIN_KINDS = ("fixed", "scaled")


wildcard_constraints:
    plot="|".join(map(re.escape, PLOTS)),
    method="|".join(map(re.escape, METHODS)),
    scenario="|".join(map(re.escape, SCENARIOS)),
    source="|".join(map(re.escape, METHODS + ["reference"])),


# ---------------------------------------------------------------------------------------------
# Job environment. Shell commands call the installed `vlsforest` command, found on the PATH of
# the environment Snakemake runs in (e.g. the project's .venv, activated or put first on PATH by
# scripts/run-study.sh); nothing is changed.
# With --sdm conda (profiles/slurm) a rule's conda env holds the dependencies only: there, the
# source tree beside this file supplies the package (PYTHONPATH) and workflow/bin a `vlsforest`
# command that runs it with the env's Python (Snakemake puts the env's bin/ in front at job time).
# ---------------------------------------------------------------------------------------------
def conda_deployment():
    """Whether jobs run in the rules' conda envs (--sdm conda)."""
    from snakemake_interface_executor_plugins.settings import DeploymentMethod

    settings = getattr(workflow, "deployment_settings", None)
    return settings is not None and DeploymentMethod.CONDA in settings.deployment_method


def _prepend_env_path(name, entry):
    """Put ``entry`` first in the os.pathsep-separated variable ``name`` (once)."""
    parts = [p for p in os.environ.get(name, "").split(os.pathsep) if p]
    if not parts or parts[0] != entry:
        os.environ[name] = os.pathsep.join([entry] + [p for p in parts if p != entry])


def job_package_dir():
    """Folder of the vlsforest package the jobs run: the source tree with --sdm conda, else the
    package installed for the Python running Snakemake (found without importing it)."""
    import importlib.util

    if conda_deployment():
        return LIBRARY_DIR
    spec = importlib.util.find_spec("vlsforest")
    if spec is None or not spec.origin:
        raise WorkflowError(
            "the vlsforest package is not installed for this Python (bash scripts/bootstrap.sh, "
            "then run snakemake from .venv)"
        )
    return Path(spec.origin).parent


if conda_deployment():
    _prepend_env_path("PATH", str(Path(workflow.basedir, "workflow", "bin")))
    _prepend_env_path("PYTHONPATH", str(LIBRARY_DIR.parent))

JOB_PACKAGE_DIR = job_package_dir()


# ---------------------------------------------------------------------------------------------
# Code hashes. Snakemake reruns a job when its shell command, script or params change, but not
# when code inside an imported package changes. Every rule that runs library code therefore has
# a `library` param: a hash over the source files its command imports, transitively, as read
# from the code's import statements (vlsforest.workflow_support). No list of files to keep up to
# date: an edit of a module reruns exactly the rules whose commands import it.
# The hashed files are those of the package the jobs run (JOB_PACKAGE_DIR); the module is loaded
# by path, without importing the package.
# ---------------------------------------------------------------------------------------------
def load_module_file(name, path):
    """The Python module in the file ``path``, loaded as ``name`` (registered under that name,
    which dataclasses need; its parent package is not imported)."""
    import importlib.util
    import sys

    spec = importlib.util.spec_from_file_location(name, path)
    loaded = importlib.util.module_from_spec(spec)
    sys.modules[name] = loaded
    try:
        spec.loader.exec_module(loaded)
    except BaseException:
        del sys.modules[name]
        raise
    return loaded


_workflow_support = load_module_file("vlsforest_workflow_support", LIBRARY_DIR / "workflow_support.py")


# ---------------------------------------------------------------------------------------------
# Scanner settings. The schema takes a scenario's `overrides` as any mapping; its keys and values
# are checked here by the library that applies them (vlsforest.sim.scanner: its one list of
# scanner keys, INPUT_KEYS, and its value checks), so a misspelt or bad override stops the run
# before any job, naming the key. The module is loaded by path from the package the jobs run
# (it imports vlsforest.errors and numpy only, not the simulator). Where Snakemake's own Python
# cannot import those (a cluster's Snakemake with the jobs' software in conda environments), the
# jobs check the same settings when they start, with the same message.
# ---------------------------------------------------------------------------------------------
def check_scenario_scanners():
    """Raise a WorkflowError naming the scenario and key of the first invalid scanner override."""
    try:
        scanner = load_module_file("vlsforest_scanner_settings", JOB_PACKAGE_DIR / "sim" / "scanner.py")
    except ImportError:
        return
    for name, scenario in config["scenarios"].items():
        try:
            scanner.scanner_from_preset(scenario["scanner"], scenario.get("overrides"))
        except scanner.ConfigError as exc:
            msg = str(exc)
            where, msg = ((f"scenarios.{name}.overrides", msg[len("overrides."):]) if msg.startswith("overrides.")
                          else (f"scenarios.{name}", msg))
            raise WorkflowError(f"Invalid configuration at '{where}': {msg}") from None


check_scenario_scanners()


def command_hash(command):
    """Hash of the library code `vlsforest <command>` runs (a rule's `library` param)."""
    return _workflow_support.command_hash(command, JOB_PACKAGE_DIR)


def script_hash(script):
    """Hash of the library code the script `script` (relative to workflow/rules) imports."""
    return _workflow_support.script_hash(Path(workflow.basedir, "workflow", "rules", script), JOB_PACKAGE_DIR)


# ---------------------------------------------------------------------------------------------
# Plot inputs: the virtual forest (results/forest) or real data named in the config
# ---------------------------------------------------------------------------------------------
def is_virtual(plot):
    return config["plots"][plot].get("kind", "virtual") == "virtual"


def plot_files(wildcards):
    """Input files of a plot: the forest folder (virtual) or the real data files."""
    p = config["plots"][wildcards.plot]
    if is_virtual(wildcards.plot):
        return {"forest": f"results/forest/plots/{wildcards.plot}"}
    files = {"tls": p["tls"], "scans": p["scans"], "plot_json": p["plot_json"]}
    for sc in SCENARIOS:
        rec = config["scenarios"][sc].get("recording", sc)
        if rec in p:
            files[f"rec_{rec}"] = p[rec]
        if f"trajectory_{rec}" in p:
            files[f"traj_{rec}"] = p[f"trajectory_{rec}"]
    return files


def _plot_path(plot, what, rec=None):
    """Path of one input of a plot (what: tls_dir, scans, plot_json, recording, trajectory)."""
    p = config["plots"][plot]
    if is_virtual(plot):
        base = f"results/forest/plots/{plot}"
        return {
            "tls_dir": f"{base}/tls",
            "scans": f"{base}/tls/scans.csv",
            "plot_json": f"{base}/plot.json",
            "recording": f"{base}/{rec}.laz",
            "trajectory": f"{base}/trajectory_{rec}.csv",
        }[what]
    if what == "tls_dir":
        return str(Path(p["scans"]).parent)
    if what == "recording":
        return p[rec]
    if what == "trajectory":
        return p[f"trajectory_{rec}"]
    return p[what]


def tls_files(wildcards):
    """The plot's TLS scans (virtual: all LAZ files of the scan folder, known after synth)."""
    if is_virtual(wildcards.plot):
        return []
    return config["plots"][wildcards.plot]["tls"]


def tls_args(wildcards):
    """The TLS scans on the command line (virtual forest: every scan of the plot's folder)."""
    if is_virtual(wildcards.plot):
        return f"results/forest/plots/{wildcards.plot}/tls/scan_*.laz"
    return " ".join(map(str, config["plots"][wildcards.plot]["tls"]))


def builtin_methods():
    return [m for m in METHODS if config["methods"][m]["kind"] in BUILTIN_KINDS]


def has_rule(name):
    """Whether a rule of that name is defined (``rules.<name>`` raises otherwise)."""
    try:
        getattr(rules, name)
    except Exception:
        return False
    return True


def methods_of_kind(kind):
    """Wildcard pattern matching exactly the configured methods of ``kind`` (none: matches nothing)."""
    names = [m for m in METHODS if config["methods"][m]["kind"] == kind]
    return "|".join(map(re.escape, names)) or "(?!)"


def pad_args(wildcards):
    """PAD options from the config (only what the estimate itself depends on: not PADmax, which
    the scaled methods apply per species)."""
    p = config["pad"]
    return (
        f"--voxel-size {p['voxel_size']} --estimator {p['estimator']} --min-pulses {p['min_pulses']}"
    )


def recording_of(scenario):
    return config["scenarios"][scenario].get("recording", scenario)


# ---------------------------------------------------------------------------------------------
# Targets
# ---------------------------------------------------------------------------------------------
def metric_tables():
    """Per-tree metrics of every simulation and every reference."""
    return expand(
        "results/{plot}/{source}/{scenario}/metrics.csv",
        plot=PLOTS,
        source=METHODS + ["reference"],
        scenario=SCENARIOS,
    )


def voxel_models():
    return expand("results/{plot}/{method}/voxels.npz", plot=PLOTS, method=METHODS)


def timing_files():
    return expand(
        "results/{plot}/{method}/{scenario}/timing.json", plot=PLOTS, method=METHODS, scenario=SCENARIOS
    )


def unshifted_scaled_methods():
    """The configured scaled methods without a shift, in the config's order."""
    ms = config["methods"]
    return [m for m in METHODS if ms[m]["kind"] == "scaled" and ms[m].get("shift", "none") == "none"]


def side_view_methods():
    """The methods figure 13 shows: the first unshifted scaled method and the coarsest fixed one."""
    ms = config["methods"]
    fixed = sorted((m for m in METHODS if ms[m]["kind"] == "fixed"), key=lambda m: -float(ms[m]["voxel_size"]))
    return unshifted_scaled_methods()[:1] + fixed[:1]


def side_view_clouds():
    """Tree clouds figure 13 reads (scaled vs the coarsest fixed voxels, and the reference)."""
    sources = side_view_methods() + ["reference"]
    return expand("results/{plot}/{source}/{scenario}/trees.laz", plot=PLOTS, source=sources, scenario=SCENARIOS)


def side_view_args(wildcards=None):
    """The clouds of side_view_clouds() as `--tree-cloud PLOT/SOURCE/SCENARIO=PATH` options."""
    out = []
    for path in side_view_clouds():
        plot, source, scenario = path.split("/")[1:4]  # results/{plot}/{source}/{scenario}/trees.laz
        out.append(f"--tree-cloud {plot}/{source}/{scenario}={path}")
    return " ".join(out)


def virtual_plots():
    return [p for p in PLOTS if is_virtual(p)]


def final_outputs():
    """The default target: the summary tables, statistics, figures and findings."""
    out = [
        "results/summary/tree_metrics.csv",
        "results/summary/voxel_counts.csv",
        "results/summary/sim_times.csv",
        "results/summary/stats/findings.md",
        "results/summary/figures",
    ]
    if virtual_plots():
        out += ["results/summary/pad_validation.csv", "results/forest/truth/trees.csv"]
    out += expand("results/diagnosis/{scenario}.json", scenario=diagnosis_scenarios())
    out += list(enabled_experiments().values())
    return out


def synth_threads(wildcards=None):
    """Worker processes of one plot's synthesis: the local cores shared by the virtual plots, which
    are recorded side by side (2 cores, 6 plots: one each, and a finished plot's jobs take a core;
    one plot: both); 16 where no core count is given (a cluster: --max-threads caps it)."""
    try:
        cores = workflow.cores
    except WorkflowError:  # no --cores given
        cores = None
    n = max(1, len(virtual_plots()))
    if cores is None or cores >= 1 << 30:
        return 16
    return max(1, min(16, int(cores) // n))


def experiment_setting(name, key, default=None):
    """A setting of experiment ``name`` (config ``experiments.<name>.<key>``; the schema supplies
    the defaults it has), or ``default`` for a key without one."""
    return config["experiments"][name].get(key, default)


def run_outputs_manifest(methods):
    """The run's files that the analysis experiments read, by plot (the manifest of
    vlsforest.experiments.run_outputs): targets, reference tree clouds, and per method its voxel
    model, tree clouds and metrics per scenario."""
    out = {}
    for plot in PLOTS:
        out[plot] = {
            "targets": f"results/{plot}/targets.csv",
            "reference": {sc: f"results/{plot}/reference/{sc}/trees.laz" for sc in SCENARIOS},
            "methods": {m: {"voxels": f"results/{plot}/{m}/voxels.npz",
                            "trees": {sc: f"results/{plot}/{m}/{sc}/trees.laz" for sc in SCENARIOS},
                            "metrics": {sc: f"results/{plot}/{m}/{sc}/metrics.csv" for sc in SCENARIOS}}
                        for m in methods},
        }
    return out


#: the keys of a run-outputs manifest whose values are (or hold) paths
MANIFEST_KEYS = ("targets", "reference", "voxels", "trees", "metrics", "scene", "site", "surveys")


def manifest_paths(manifest, keep=lambda key: True):
    """Every path of a run-outputs manifest whose key (:data:`MANIFEST_KEYS`) ``keep`` accepts:
    the inputs of the job that reads it."""
    out = []

    def walk(node, key):
        if isinstance(node, str):
            if keep(key):
                out.append(node)
        else:
            for k, v in node.items():
                walk(v, k if k in MANIFEST_KEYS else key)

    walk(manifest, None)
    return out


def experiment_subset(name, key, known, what):
    """``experiments.<name>.<key>``: the names it lists, each checked against the configured
    ``known`` ones (a WorkflowError naming the key otherwise), or None where it lists none."""
    named = experiment_setting(name, key)
    if not named:
        return None
    unknown = [x for x in named if x not in known]
    if unknown:
        raise WorkflowError(f"Invalid configuration at 'experiments.{name}.{key}': "
                            f"{', '.join(map(repr, unknown))} is not a configured {what} ({', '.join(known)})")
    return list(named)


def crown_outline_methods():
    """The methods the crown-outline experiment takes apart: ``experiments.crown_outline.methods``,
    else every fixed method and the unshifted scaled ones."""
    return experiment_subset("crown_outline", "methods", METHODS, "method") or (
        [m for m in METHODS if config["methods"][m]["kind"] == "fixed"] + unshifted_scaled_methods())


def experiment_method(experiment, key, default):
    """``experiments.<experiment>.<key>``, else ``default``; a WorkflowError naming the key where
    that is no configured method."""
    m = experiment_setting(experiment, key) or default
    if m is None or m not in METHODS:
        raise WorkflowError(f"Invalid configuration at 'experiments.{experiment}.{key}': "
                            + (f"{m!r} is not a configured method" if m else "no such scaled method is configured"))
    return m


def shift_pair(experiment, shift):
    """The unshifted scaled method and its ``shift`` variant that ``experiment`` compares:
    ``experiments.<experiment>.base`` / ``shifted``, else the first of each kind configured."""
    ms = config["methods"]
    base = experiment_method(experiment, "base", (unshifted_scaled_methods() or [None])[0])
    shifted = experiment_method(experiment, "shifted", next(
        (m for m in METHODS if ms[m]["kind"] == "scaled" and ms[m].get("shift") == shift), None))
    return base, shifted


def shift_room_methods():
    """The unshifted scaled method and its random-shift variant (the shift-room experiment)."""
    return shift_pair("shift_room", "random")


def cog_shift_methods():
    """The unshifted scaled method and its CoG-shift variant (the CoG-shift experiment)."""
    return shift_pair("cog_shift", "cog")


def cog_parts_methods():
    """The unshifted scaled method and its CoG-shift variant (the CoG-parts experiment)."""
    return shift_pair("cog_parts", "cog")


def experiment_scenarios(name):
    """The scenarios experiment ``name`` simulates: ``experiments.<name>.scenarios``, else every
    scenario."""
    return experiment_subset(name, "scenarios", SCENARIOS, "scenario") or list(SCENARIOS)


def resimulation_manifest(methods, scene_method, scenarios):
    """The files an experiment that simulates the run's plots again reads, by plot: the
    run-outputs manifest of ``methods`` (their voxel models and metrics of ``scenarios``) with
    each plot's site and surveys and ``scene_method``'s scene folder."""
    out = {}
    for plot, entry in run_outputs_manifest(methods).items():
        ms = {m: {"voxels": e["voxels"], "metrics": {sc: e["metrics"][sc] for sc in scenarios}}
              for m, e in entry["methods"].items()}
        ms[scene_method]["scene"] = f"results/{plot}/{scene_method}/scene"
        out[plot] = {"targets": entry["targets"], "site": f"results/{plot}/site.json",
                     "surveys": {sc: f"results/{plot}/surveys/{sc}.yaml" for sc in scenarios}, "methods": ms}
    return out


def cog_parts_manifest():
    """The files the CoG-parts experiment reads (:func:`resimulation_manifest` of its two
    methods, with the unshifted method's scene)."""
    base, shifted = cog_parts_methods()
    return resimulation_manifest([base, shifted], base, experiment_scenarios("cog_parts"))


def reseed_method():
    """The method the reseed experiment simulates again: ``experiments.reseed.method``, else the
    first unshifted scaled method."""
    return experiment_method("reseed", "method", (unshifted_scaled_methods() or [None])[0])


def reseed_manifest():
    """The files the reseed experiment reads (:func:`resimulation_manifest` of its method)."""
    m = reseed_method()
    return resimulation_manifest([m], m, experiment_scenarios("reseed"))


def enabled_experiments():
    """The experiments the config enables, by name → their result file."""
    return {name: f"results/experiments/{name}.json"
            for name, block in config["experiments"].items() if block["enabled"]}


def study_param(wildcards=None):
    """The methods and scenarios blocks: the display order and the part each plays in the findings."""
    return json.dumps({"methods": config["methods"], "scenarios": config["scenarios"]})


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


def block_param(name):
    """A top-level config block as canonical JSON (tracked as a param)."""

    def get(wildcards=None):
        return json.dumps(config.get(name, {}), sort_keys=True)

    return get


def method_param(wildcards):
    """The method's config block (tracked as a param)."""
    return json.dumps(config["methods"][wildcards.method], sort_keys=True)


def method_groups(wildcards):
    """Species groups for PAD-scaled methods only (so a PADmax change reruns only those)."""
    m = config["methods"][wildcards.method]
    return json.dumps(PAD_GROUPS if m["kind"] == "scaled" else {}, sort_keys=True)


def method_pad(wildcards):
    """The plot's PAD grid, for PAD-scaled methods only."""
    m = config["methods"][wildcards.method]
    return [f"results/{wildcards.plot}/pad/pad.vox"] if m["kind"] == "scaled" else []


def method_pad_args(wildcards):
    m = config["methods"][wildcards.method]
    if m["kind"] != "scaled":
        return ""
    return f"--pad results/{wildcards.plot}/pad/pad.vox --min-pulses {config['pad']['min_pulses']}"


def scenario_recording(wildcards):
    return _plot_path(wildcards.plot, "recording", recording_of(wildcards.scenario))


def scenario_trajectory(wildcards):
    return _plot_path(wildcards.plot, "trajectory", recording_of(wildcards.scenario))


def scenario_radius(wildcards):
    return float(config["scenarios"][wildcards.scenario]["extraction_radius_m"])


def scenario_param(wildcards):
    """The scenario's config block (tracked as a param) for `vlsforest plan`, without `platform`
    (the part the scenario plays in the findings, which the flight does not use)."""
    block = {k: v for k, v in config["scenarios"][wildcards.scenario].items() if k != "platform"}
    return json.dumps(block, sort_keys=True)


def seed_of_scenario(scenario):
    """The scenario's own ``seed`` if it sets one, else the study's master ``seed``."""
    return int(config["scenarios"][scenario].get("seed", config["seed"]))


def scenario_seed(wildcards):
    """The seed of the ``{scenario}`` wildcard's simulations (:func:`seed_of_scenario`)."""
    return seed_of_scenario(wildcards.scenario)


# ---------------------------------------------------------------------------------------------
# Resources (portable: mem_mb, runtime in minutes); retried jobs get more
# ---------------------------------------------------------------------------------------------
def simulate_mem_mb(wildcards, attempt):
    """Memory of a simulation job: the tracer's BVH and pulse blocks, doubled per retry."""
    return 8000 * attempt


def simulate_runtime(wildcards, attempt):
    """Wall time (minutes) of a simulation job, doubled per retry."""
    return 120 * attempt


def diagnose_mem_mb(wildcards, attempt):
    """Memory of the diagnosis: one plot's trace held while the next is made (measured on the
    default study: largest process 10.8 GB, PSS of the job 10.1 GB), doubled per retry."""
    return 16000 * attempt


def diagnose_runtime(wildcards, attempt):
    """Wall time (minutes) of the diagnosis (default study: 22–27 min alone, 34 min beside the
    simulations), doubled per retry."""
    return 90 * attempt


# ---------------------------------------------------------------------------------------------
# Diagnosis (workflow/rules/diagnose.smk)
# ---------------------------------------------------------------------------------------------
def diagnosis_cfg():
    return config["diagnosis"]


def diagnosis_method():
    """The method whose scenes the diagnosis simulates: ``diagnosis.method``, else the first
    scaled method without a shift (the study's PAD-scaled cubes)."""
    d = diagnosis_cfg()
    if "method" in d:
        if d["method"] not in METHODS:
            raise WorkflowError(f"Invalid configuration at 'diagnosis.method': {d['method']!r} is not a "
                                f"configured method ({', '.join(METHODS)})")
        return d["method"]
    scaled = unshifted_scaled_methods()
    if not scaled:
        raise WorkflowError("Invalid configuration at 'diagnosis': 'method' is required: no scaled method "
                            "without a shift is configured")
    return scaled[0]


def diagnosis_scenarios():
    d = diagnosis_cfg()
    if not d["enabled"]:
        return []
    return [s for s in d.get("scenarios", SCENARIOS) if s in SCENARIOS]


def diagnosis_plots():
    return [p for p in (diagnosis_cfg().get("plots") or PLOTS) if p in PLOTS]


def diagnosis_inputs(wildcards):
    method = diagnosis_method()
    rec = recording_of(wildcards.scenario)
    out = {}
    for plot in diagnosis_plots():
        out[f"scene_{plot}"] = f"results/{plot}/{method}/scene"
        out[f"survey_{plot}"] = f"results/{plot}/surveys/{wildcards.scenario}.yaml"
        out[f"segment_{plot}"] = f"results/{plot}/segment"
        # a virtual plot's recording lies inside its folder of the forest (a directory output)
        out[f"real_{plot}"] = f"results/forest/plots/{plot}" if is_virtual(plot) else _plot_path(plot, "recording", rec)
    return out


def diagnosis_param(wildcards):
    """The sim-config of one scenario (everything the diagnosis reads), as JSON."""
    d = diagnosis_cfg()
    method = diagnosis_method()
    sc = config["scenarios"][wildcards.scenario]
    # the settings the config leaves out take the diagnosis' own defaults (vlsforest.diagnose.setup.SCHEMA)
    own = ("folds", "grid", "candidates", "beam_sample_quality", "realisations")
    setup = {
        "scenario": wildcards.scenario,
        "seed": config["seed"],
        **{k: d[k] for k in own if k in d},
        "plots": {
            plot: {
                "real": _plot_path(plot, "recording", recording_of(wildcards.scenario)),
                "scene": f"results/{plot}/{method}/scene/scene.yaml",
                "survey": f"results/{plot}/surveys/{wildcards.scenario}.yaml",
                "segment": f"results/{plot}/segment",
                "radius": sc["extraction_radius_m"],
                # absent: the library's default (vlsforest.diagnose.setup.REGION_MARGIN_M)
                **({"margin": d["region_margin_m"]} if "region_margin_m" in d else {}),
            }
            for plot in diagnosis_plots()
        },
    }
    return json.dumps({k: v for k, v in setup.items() if v is not None}, sort_keys=True)


# ---------------------------------------------------------------------------------------------
# The scheduler patch makes Snakemake's scheduler keep at most one pending re-evaluation timer
# (less CPU for Snakemake itself on long runs; results do not depend on it). It replaces a
# private Snakemake method, so it is applied only to the Snakemake it was written for
# (workflow/rules/scheduler_patch.py); VLSFOREST_SCHEDULER_PATCH=0 switches it off.
# ---------------------------------------------------------------------------------------------
_scheduler_patch = load_module_file(
    "vlsforest_scheduler_patch", Path(workflow.basedir, "workflow", "rules", "scheduler_patch.py")
)
_scheduler_patch.apply_if_enabled()
