# Reference tree clouds: the real ALS/ULS points within the scenario's radius of each target's
# TLS points (the study: 0.5 m ALS, 0.3 m ULS), all returns kept, and their per-tree metrics
# (written in the same job, from the file as written).


rule extract_reference:
    input:
        unpack(plot_files),
        segment="results/{plot}/segment",
        targets="results/{plot}/targets.csv",
    output:
        trees="results/{plot}/reference/{scenario}/trees.laz",
        metrics="results/{plot}/reference/{scenario}/metrics.csv",
    log:
        "logs/extract/{plot}_reference_{scenario}.log",
    benchmark:
        "logs/benchmarks/extract/{plot}_reference_{scenario}.tsv"
    conda:
        "../../envs/vlsforest.yaml"
    resources:
        mem_mb=4000,
        runtime=10,
    params:
        recording=scenario_recording,
        radius=scenario_radius,
        library=command_hash("extract"),
    shell:
        "vlsforest extract reference {params.recording} --segment {input.segment} "
        "--targets {input.targets} --radius {params.radius} -o {output.trees} --metrics {output.metrics} > {log} 2>&1"
