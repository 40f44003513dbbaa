# The embedded virtual Bretten forest: trees, plots, TLS scans and "real" ALS/ULS recordings
# (vlsforest.synth). Everything downstream reads results/forest/plots/; only validation steps
# may read results/forest/truth/.


rule synth:
    output:
        forest=directory("results/forest"),
    log:
        "logs/synth/synth.log",
    benchmark:
        "logs/benchmarks/synth.tsv"
    conda:
        "../../envs/vlsforest.yaml"
    threads: 16
    resources:
        mem_mb=12000,
        runtime=60,
    params:
        settings=synth_param,
        library=SYNTH_HASH,
    shell:
        "python -m vlsforest.cli synth --config-json {params.settings:q} --workers {threads} "
        "-o {output.forest} > {log} 2>&1"
