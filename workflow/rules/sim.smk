# Survey planning and simulation per plot × method × scenario, and a summary table.


rule survey:
    input:
        scene="results/{plot}/{method}/scene/scene.yaml",
    output:
        survey="results/{plot}/{method}/{scenario}/survey.yaml",
    log:
        "logs/survey/{plot}_{method}_{scenario}.log",
    conda:
        "../../envs/vlsforest.yaml"
    resources:
        mem_mb=1000,
        runtime=5,
    params:
        scenario=scenario_param,
        seed=scenario_seed,
        library=SIM_HASH,
    shell:
        "python -m vlsforest.cli plan --scene {input.scene} --scenario-json {params.scenario:q} "
        "--seed {params.seed} -o {output.survey} > {log} 2>&1"


rule simulate:
    input:
        scene="results/{plot}/{method}/scene/scene.yaml",
        parts=expand("results/{{plot}}/{{method}}/scene/{part}", part=DEMO_PARTS),
        survey="results/{plot}/{method}/{scenario}/survey.yaml",
    output:
        laz="results/{plot}/{method}/{scenario}/sim.laz",
        pulses="results/{plot}/{method}/{scenario}/pulses.npz",
    log:
        "logs/simulate/{plot}_{method}_{scenario}.log",
    benchmark:
        "logs/benchmarks/simulate/{plot}_{method}_{scenario}.tsv"
    conda:
        "../../envs/vlsforest.yaml"
    # capped by --cores locally; on a cluster (no --cores) the profile's set-threads decides.
    # Not `workflow.cores`: that raises when no --cores is given (cluster runs).
    threads: 16
    resources:
        mem_mb=simulate_mem_mb,
        runtime=simulate_runtime,
    params:
        seed=scenario_seed,
        library=SIM_HASH,
    shell:
        "python -m vlsforest.cli simulate {input.scene} {input.survey} -o {output.laz} "
        "--pulses {output.pulses} --seed {params.seed} --workers {threads} > {log} 2>&1"


rule simulation_summary:
    input:
        laz=simulated_clouds(),
        pulses=pulse_tables(),
    output:
        csv="results/summary/simulations.csv",
    log:
        "logs/summary/simulations.log",
    localrule: True
    conda:
        "../../envs/vlsforest.yaml"
    resources:
        mem_mb=2000,
        runtime=10,
    params:
        library=SIM_HASH,
    shell:
        "python -m vlsforest.cli summarize-sims {input.laz} -o {output.csv} > {log} 2>&1"
