# Example of a voxel method added as one rule file + one config entry
# (docs/tutorials/adding-a-method.md): PAD-scaled cubes whose *side* grows linearly with PAD (α = 1) instead of their face
# area (the study's α = 0.5). The method's function is in linear_pad.py beside this file.
# Config entry:
#
#   methods:
#     linear_pad: {kind: linear_pad}
#
# The rule writes the same output as the built-in `voxels` rule (results/{plot}/{method}/voxels.npz),
# so scenes, simulations, metrics, statistics and the report take the method up like any other.


rule voxels_linear_pad:
    input:
        crowns="results/{plot}/crowns.npz",
        targets="results/{plot}/targets.csv",
        pad="results/{plot}/pad/pad.vox",
    output:
        "results/{plot}/{method}/voxels.npz",
    log:
        "logs/voxels/{plot}_{method}.log",
    benchmark:
        "logs/benchmarks/voxels/{plot}_{method}.tsv"
    wildcard_constraints:
        method=methods_of_kind("linear_pad"),
    conda:
        "../../../envs/vlsforest.yaml"
    resources:
        mem_mb=4000,
        runtime=10,
    params:
        method=method_param,
        groups=json.dumps(PAD_GROUPS, sort_keys=True),
        min_pulses=config["pad"]["min_pulses"],
        default_group=config["pad"]["default_group"],
        seed=config["seed"],
        library=script_hash("methods/linear_pad.py"),
    script:
        "linear_pad.py"
