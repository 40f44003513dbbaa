# Per-tree metrics (the study's Table 4) of every simulated and reference target-tree cloud,
# heights above the target's segmented stem base (the same ground for simulation and reference).
# Each cloud's table is written by the job that extracts the cloud (rules sim_trees and
# extract_reference, `vlsforest extract … --metrics`); this file collects them.


rule collect_metrics:
    input:
        metric_tables(),
        targets=expand("results/{plot}/targets.csv", plot=PLOTS),
    output:
        report("results/summary/tree_metrics.csv", caption="../report/tree_metrics.rst", category="Tables"),
    log:
        "logs/summary/tree_metrics.log",
    benchmark:
        "logs/benchmarks/summary/tree_metrics.tsv"
    conda:
        "../../envs/vlsforest.yaml"
    resources:
        mem_mb=2000,
        runtime=10,
    params:
        tables=metric_tables(),
        library=command_hash("collect"),
    shell:
        "vlsforest collect metrics {params.tables} -o {output} > {log} 2>&1"
