# The embedded virtual Bretten forest: trees, plots, TLS scans and "real" ALS/ULS recordings
# (vlsforest.synth), one job per plot: a plot's downstream jobs start as soon as its recordings
# are written, beside the synthesis of the other plots (the plots are independent: own seeds; the
# same bytes as one `vlsforest synth` call for the whole forest). Everything downstream reads
# results/forest/plots/{plot}/; only validation steps read results/forest/truth/.


rule synth_plot:
    output:
        plot=directory("results/forest/plots/{plot}"),
        truth=directory("results/forest/truth/{plot}"),
    log:
        "logs/synth/{plot}.log",
    benchmark:
        "logs/benchmarks/synth/{plot}.tsv"
    wildcard_constraints:
        plot="|".join(map(re.escape, virtual_plots())) or "(?!)",
    conda:
        "../../envs/vlsforest.yaml"
    threads: synth_threads
    resources:
        mem_mb=8000,
        runtime=30,
    params:
        settings=synth_param,
        library=command_hash("synth"),
    shell:
        "vlsforest synth --config-json {params.settings:q} --plots {wildcards.plot} --part "
        "--workers {threads} -o results/forest > {log} 2>&1"


# the forest's truth table and settings, from the plots' truth folders (the same bytes as one call)
rule forest_truth:
    input:
        expand("results/forest/truth/{plot}", plot=virtual_plots()),
    output:
        trees="results/forest/truth/trees.csv",
        settings="results/forest/truth/synth_settings.yaml",
        physics="results/forest/truth/recording_physics.yaml",
    log:
        "logs/synth/forest_truth.log",
    benchmark:
        "logs/benchmarks/synth/forest_truth.tsv"
    conda:
        "../../envs/vlsforest.yaml"
    params:
        library=command_hash("collect"),
    shell:
        "vlsforest collect truth {input} -o {output.trees} > {log} 2>&1"
