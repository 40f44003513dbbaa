# Poisson stem meshes of the target trees (vlsforest.stems), one folder per plot with
# {tree_id}/stem.{ply,obj}, stem_points.laz and stem.json per target.


rule stems:
    input:
        unpack(plot_files),
        segment="results/{plot}/segment",
        targets="results/{plot}/targets.csv",
    output:
        directory("results/{plot}/stems"),
    log:
        "logs/stems/{plot}.log",
    benchmark:
        "logs/benchmarks/stems/{plot}.tsv"
    conda:
        "../../envs/vlsforest.yaml"
    resources:
        mem_mb=4000,
        runtime=30,
    params:
        scans=lambda wc: _plot_path(wc.plot, "scans"),
        settings=block_param("stems"),
        library=command_hash("stems"),
    shell:
        "vlsforest stems --segment {input.segment} --targets {input.targets} "
        "--scans {params.scans} --config-json {params.settings:q} -o {output} > {log} 2>&1"
