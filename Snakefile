# vlsforest — virtual laser scanning of voxelised forests (Weiser et al. 2021, reproduced).
#
# Results path convention: results/{plot}/{method}/{scenario}/…  (scenes: results/{plot}/{method}/scene/)
# Logs under logs/, benchmark files under logs/benchmarks/.
# Run:  bash scripts/run-study.sh            (default target, embedded default data)
#       snakemake --cores 2 --configfile config/quick.yaml
from snakemake.utils import min_version

min_version("9.0")


configfile: "config/config.yaml"


include: "workflow/rules/common.smk"
include: "workflow/rules/scene.smk"
include: "workflow/rules/sim.smk"


rule all:
    default_target: True
    input:
        final_outputs(),
