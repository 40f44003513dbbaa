# Voxel models per plot × method (vlsforest.voxels). Built-in kinds (fixed, scaled) share this
# rule; a method added as a rule file under rules/methods/ writes the same output itself.


rule voxels:
    input:
        crowns="results/{plot}/crowns.npz",
        targets="results/{plot}/targets.csv",
        pad=method_pad,
    output:
        "results/{plot}/{method}/voxels.npz",
    log:
        "logs/voxels/{plot}_{method}.log",
    benchmark:
        "logs/benchmarks/voxels/{plot}_{method}.tsv"
    wildcard_constraints:
        method="|".join(map(re.escape, builtin_methods())) or "(?!)",
    conda:
        "../../envs/vlsforest.yaml"
    resources:
        mem_mb=8000,
        runtime=30,
    params:
        method=method_param,
        groups=method_groups,
        pad=method_pad_args,
        default_group=config["pad"]["default_group"],
        seed=config["seed"],
        library=command_hash("voxels"),
    shell:
        "vlsforest voxels {input.crowns} --method {wildcards.method} "
        "--method-json {params.method:q} --groups-json {params.groups:q} {params.pad} "
        "--targets {input.targets} --default-group {params.default_group} --seed {params.seed} "
        "-o {output} > {log} 2>&1"


rule voxel_counts:
    input:
        voxel_models(),
    output:
        report("results/summary/voxel_counts.csv", caption="../report/voxel_counts.rst", category="Tables"),
    log:
        "logs/summary/voxel_counts.log",
    benchmark:
        "logs/benchmarks/summary/voxel_counts.tsv"
    conda:
        "../../envs/vlsforest.yaml"
    resources:
        mem_mb=2000,
        runtime=10,
    params:
        library=command_hash("collect"),
    shell:
        "vlsforest collect voxels {input} -o {output} > {log} 2>&1"
