# vlsforest — virtual laser scanning of voxelised forests (Weiser et al. 2021, reproduced).
#
# Results path convention: results/{plot}/{method}/{scenario}/…  (per plot: segment/, stems/, pad/,
# targets.csv, site.json, crowns.npz, surveys/; per method: voxels.npz, scene/; references under
# results/{plot}/reference/{scenario}/; summaries under results/summary/)
# Logs under logs/, benchmark files under logs/benchmarks/. Jobs call the `vlsforest` command.
# Reruns: every config value a rule uses is a param, and so is a hash of the library code the
# rule's command imports (workflow/vlsforest, followed through its import statements): editing a
# module reruns the rules that import it (to keep results after a purely cosmetic edit:
# snakemake --cleanup-metadata <files>).
# Run:  bash scripts/run-study.sh            (default target, embedded default data)
#       snakemake --cores 2 --configfile config/quick.yaml
# Config: config/config.yaml of the working directory if it has one, else this repository's.
# --configfile FILE replaces it entirely (it is not merged into it: a plot, method or scenario of
# the default config does not creep into another study); --config KEY=VALUE is merged over it.
# The result is validated against config/schema.yaml before any job runs.
from pathlib import Path

from snakemake.utils import min_version

min_version("9.0")


DEFAULT_CONFIG = "config/config.yaml"
if not Path(DEFAULT_CONFIG).is_file():
    DEFAULT_CONFIG = str(Path(workflow.basedir, DEFAULT_CONFIG))

if not workflow.overwrite_configfiles:

    configfile: DEFAULT_CONFIG


report: "workflow/report/workflow.rst"


include: "workflow/rules/common.smk"
include: "workflow/rules/synth.smk"
include: "workflow/rules/segment.smk"
include: "workflow/rules/stems.smk"
include: "workflow/rules/extract.smk"
include: "workflow/rules/pad.smk"
include: "workflow/rules/voxels.smk"
include: "workflow/rules/scene.smk"
include: "workflow/rules/sim.smk"
include: "workflow/rules/metrics.smk"
include: "workflow/rules/stats.smk"
include: "workflow/rules/diagnose.smk"
include: "workflow/rules/experiments.smk"


# Voxel methods added as rule files (docs/tutorials/adding-a-method.md): every rules/methods/*.smk
for _method_rules in sorted(Path(workflow.basedir, "workflow", "rules", "methods").glob("*.smk")):

    include: _method_rules


# every configured method needs a kind that something builds: built in, or a rule voxels_<kind>
for _name, _entry in config["methods"].items():
    if _entry["kind"] not in BUILTIN_KINDS and not has_rule(f"voxels_{_entry['kind']}"):
        raise WorkflowError(
            f"Invalid configuration at 'methods.{_name}.kind': unknown kind {_entry['kind']!r} "
            f"(built in: {', '.join(BUILTIN_KINDS)}; or add workflow/rules/methods/<kind>.smk "
            f"with a rule voxels_<kind>)"
        )

# the diagnosis simulates one configured method on configured scenarios
_diag = diagnosis_cfg()
if _diag["enabled"]:
    diagnosis_method()  # raises for a method that is not configured (or none to default to)
    for _pl in _diag.get("plots", []):
        if _pl not in config["plots"]:
            raise WorkflowError(
                f"Invalid configuration at 'diagnosis.plots': {_pl!r} is not a configured plot "
                f"({', '.join(config['plots'])})"
            )
    for _sc in _diag.get("scenarios", []):
        if _sc not in config["scenarios"]:
            raise WorkflowError(
                f"Invalid configuration at 'diagnosis.scenarios': {_sc!r} is not a configured scenario "
                f"({', '.join(config['scenarios'])})"
            )


rule all:
    default_target: True
    input:
        final_outputs(),
