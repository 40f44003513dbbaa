# Plant area density per 0.25 m cell from every TLS shot (vlsforest.pad). On the virtual forest
# the same job validates the estimate against the true plant area (the traversal runs once).


rule pad:
    input:
        unpack(plot_files),
    output:
        "results/{plot}/pad/pad.vox",
    log:
        "logs/pad/{plot}.log",
    benchmark:
        "logs/benchmarks/pad/{plot}.tsv"
    wildcard_constraints:
        plot="|".join(map(re.escape, [p for p in PLOTS if not is_virtual(p)])) or "(?!)",
    conda:
        "../../envs/vlsforest.yaml"
    resources:
        mem_mb=8000,
        runtime=30,
    params:
        tls_dir=lambda wc: _plot_path(wc.plot, "tls_dir"),
        args=pad_args,
        library=command_hash("pad"),
    shell:
        "vlsforest pad {params.tls_dir} {params.args} -o {output} > {log} 2>&1"


rule pad_virtual:
    input:
        forest="results/forest/plots/{plot}",
        truth="results/forest/truth/{plot}",
    output:
        vox="results/{plot}/pad/pad.vox",
        table="results/{plot}/pad/validation.csv",
        figure="results/{plot}/pad/validation.png",
    log:
        "logs/pad/{plot}.log",
    benchmark:
        "logs/benchmarks/pad/{plot}.tsv"
    wildcard_constraints:
        plot="|".join(map(re.escape, virtual_plots())) or "(?!)",
    conda:
        "../../envs/vlsforest.yaml"
    resources:
        mem_mb=8000,
        runtime=30,
    params:
        tls_dir=lambda wc: _plot_path(wc.plot, "tls_dir"),
        args=pad_args,
        library=command_hash("pad"),
    shell:
        "vlsforest pad {params.tls_dir} {params.args} -o {output.vox} "
        "--validate results/forest --plot {wildcards.plot} --table {output.table} --figure {output.figure} "
        "> {log} 2>&1"


rule pad_summary:
    input:
        expand("results/{plot}/pad/validation.csv", plot=virtual_plots()),
    output:
        csv=report("results/summary/pad_validation.csv", caption="../report/pad_validation.rst", category="PAD"),
        png=report("results/summary/pad_validation.png", caption="../report/pad_validation.rst", category="PAD"),
    log:
        "logs/summary/pad_validation.log",
    benchmark:
        "logs/benchmarks/summary/pad_validation.tsv"
    conda:
        "../../envs/vlsforest.yaml"
    resources:
        mem_mb=2000,
        runtime=10,
    params:
        library=command_hash("collect"),
    shell:
        "vlsforest collect pad {input} -o {output.csv} --figure {output.png} > {log} 2>&1"
