# vlsforest — virtual laser scanning of voxelised forests (Weiser et al. 2021, reproduced).
#
# Results path convention: results/{plot}/{method}/{scenario}/…  (scenes: results/{plot}/{method}/scene/)
# Logs under logs/, benchmark files under logs/benchmarks/. Jobs call `python -m vlsforest.cli`.
# Reruns: every config value a rule uses is a param, and so is a hash of the library sources
# (workflow/vlsforest): editing the library reruns the outputs (to keep results after a purely
# cosmetic edit: snakemake --cleanup-metadata <files>).
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


include: "workflow/rules/common.smk"
include: "workflow/rules/synth.smk"
include: "workflow/rules/scene.smk"
include: "workflow/rules/sim.smk"


rule all:
    default_target: True
    input:
        final_outputs(),
