# TLS processing per plot: tree segmentation (vlsforest.segment), then the targets named in the
# plot's field description matched to segmented trees, the site (ground elevation, extent) and
# the crown points that voxel models are made of.


rule segment:
    input:
        unpack(plot_files),
    output:
        directory("results/{plot}/segment"),
    log:
        "logs/segment/{plot}.log",
    benchmark:
        "logs/benchmarks/segment/{plot}.tsv"
    conda:
        "../../envs/vlsforest.yaml"
    resources:
        mem_mb=8000,
        runtime=30,
    params:
        tls=tls_args,
        settings=block_param("segment"),
        library=command_hash("segment"),
    shell:
        "vlsforest segment {params.tls} --config-json {params.settings:q} -o {output} > {log} 2>&1"


rule targets:
    input:
        unpack(plot_files),
        segment="results/{plot}/segment",
    output:
        targets="results/{plot}/targets.csv",
        site="results/{plot}/site.json",
    log:
        "logs/targets/{plot}.log",
    benchmark:
        "logs/benchmarks/targets/{plot}.tsv"
    conda:
        "../../envs/vlsforest.yaml"
    resources:
        mem_mb=4000,
        runtime=10,
    params:
        plot_json=lambda wc: _plot_path(wc.plot, "plot_json"),
        library=command_hash("scene"),
    shell:
        "vlsforest scene targets {input.segment} --plot-json {params.plot_json} "
        "-o {output.targets} > {log} 2>&1"


rule crowns:
    input:
        segment="results/{plot}/segment",
        stems="results/{plot}/stems",
        targets="results/{plot}/targets.csv",
    output:
        "results/{plot}/crowns.npz",
    log:
        "logs/crowns/{plot}.log",
    benchmark:
        "logs/benchmarks/crowns/{plot}.tsv"
    conda:
        "../../envs/vlsforest.yaml"
    resources:
        mem_mb=4000,
        runtime=10,
    params:
        library=command_hash("scene"),
    shell:
        "vlsforest scene crowns {input.segment} --stems {input.stems} "
        "--targets {input.targets} -o {output} > {log} 2>&1"
