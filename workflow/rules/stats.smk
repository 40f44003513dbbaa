# Sim-vs-reference statistics, the study's figures and the findings (vlsforest.stats,
# vlsforest.report). `snakemake --report results/report.html` gathers them into one HTML.


rule stats:
    input:
        unpack(lambda wildcards: enabled_experiments()),
        metrics="results/summary/tree_metrics.csv",
        voxels="results/summary/voxel_counts.csv",
        times="results/summary/sim_times.csv",
    output:
        findings=report("results/summary/stats/findings.md", caption="../report/findings.rst", category="Findings"),
        findings_table="results/summary/stats/findings.csv",
        errors=report("results/summary/stats/errors.csv", caption="../report/errors.rst", category="Tables"),
        summary=report(
            "results/summary/stats/summary_by_species.csv", caption="../report/summary_by_species.rst", category="Tables"
        ),
        tests=report("results/summary/stats/tests.csv", caption="../report/tests.rst", category="Tables"),
        mr=report("results/summary/stats/multireturn_ttest.csv", caption="../report/multireturn_ttest.rst", category="Tables"),
        table5=report("results/summary/stats/table5.csv", caption="../report/table5.rst", category="Tables"),
    log:
        "logs/stats/stats.log",
    benchmark:
        "logs/benchmarks/stats/stats.tsv"
    conda:
        "../../envs/vlsforest.yaml"
    resources:
        mem_mb=4000,
        runtime=10,
    params:
        seed=config["seed"],
        study=study_param,
        experiments=lambda wildcards, input: " ".join(
            f"--experiment {name}={getattr(input, name)}" for name in enabled_experiments()
        ),
        library=command_hash("stats"),
    shell:
        "vlsforest stats --metrics {input.metrics} --voxel-counts {input.voxels} "
        "--sim-times {input.times} --study-json {params.study:q} {params.experiments} --seed {params.seed} "
        "--out-errors {output.errors} --out-summary {output.summary} --out-tests {output.tests} "
        "--out-multireturn {output.mr} --out-table5 {output.table5} --out-findings {output.findings} "
        "--out-findings-table {output.findings_table} > {log} 2>&1"


rule figures:
    input:
        metrics="results/summary/tree_metrics.csv",
        errors="results/summary/stats/errors.csv",
        voxels="results/summary/voxel_counts.csv",
        sims=side_view_clouds(),
    output:
        report(directory("results/summary/figures"), patterns=["{name}.png"], caption="../report/figures.rst",
               category="Figures"),
    log:
        "logs/stats/figures.log",
    benchmark:
        "logs/benchmarks/stats/figures.tsv"
    conda:
        "../../envs/vlsforest.yaml"
    resources:
        mem_mb=4000,
        runtime=10,
    params:
        clouds=side_view_args,
        library=command_hash("report"),
    shell:
        "vlsforest report figures --metrics {input.metrics} --errors {input.errors} "
        "--voxel-counts {input.voxels} {params.clouds} -o {output} > {log} 2>&1"
