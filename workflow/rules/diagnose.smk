# Physics diagnosis (vlsforest.diagnose): where do the simulations of one voxel method differ from
# the real recordings, which physics left out of the simulation explains it, fitted and checked
# on held-out trees. Configured by the `diagnosis:` block (off when absent or enabled: false).
# results/diagnosis/{scenario}.sim.yaml keeps the set-up, to rerun `vlsforest diagnose` by hand.


rule diagnose:
    input:
        unpack(diagnosis_inputs),
    output:
        setup="results/diagnosis/{scenario}.sim.yaml",
        json=report("results/diagnosis/{scenario}.json", caption="../report/diagnosis.rst", category="Diagnosis"),
        figure=report("results/diagnosis/{scenario}.png", caption="../report/diagnosis.rst", category="Diagnosis"),
    log:
        "logs/diagnose/{scenario}.log",
    benchmark:
        "logs/benchmarks/diagnose_{scenario}.tsv"
    conda:
        "../../envs/vlsforest.yaml"
    threads: 2
    resources:
        mem_mb=diagnose_mem_mb,
        disk_mb=16000,  # a stage's traces wait beside the report for the next stage (≤ 4 × ≈ 3.5 GB on the default forest)
        runtime=diagnose_runtime,
    params:
        setup=diagnosis_param,
        library=command_hash("diagnose"),
    shell:
        "vlsforest diagnose --real results/forest/plots --sim-config-json {params.setup:q} "
        "--write-sim-config {output.setup} --scenario {wildcards.scenario} -o {output.json} "
        "--figure {output.figure} --workers {threads} > {log} 2>&1"
