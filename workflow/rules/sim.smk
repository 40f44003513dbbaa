# Simulation per plot × method × scenario, and a summary table.


rule survey:
    input:
        scene="results/{plot}/{method}/scene/scene.yaml",
    output:
        survey="results/{plot}/{method}/{scenario}/survey.yaml",
    log:
        "logs/survey/{plot}_{method}_{scenario}.log",
    conda:
        "../../envs/vlsforest.yaml"
    params:
        scenario=scenario_param,
        seed=config["seed"],
    resources:
        mem_mb=1000,
        runtime=5,
    shell:
        "vlsforest plan --scene {input.scene} --scenario-json '{params.scenario}' "
        "--seed {params.seed} -o {output.survey} > {log} 2>&1"


rule simulate:
    input:
        scene="results/{plot}/{method}/scene/scene.yaml",
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
    threads: workflow.cores
    resources:
        mem_mb=8000,
        runtime=120,
    params:
        seed=config["seed"],
    shell:
        "vlsforest simulate {input.scene} {input.survey} -o {output.laz} --pulses {output.pulses} "
        "--seed {params.seed} --workers {threads} > {log} 2>&1"


rule simulation_summary:
    input:
        laz=expand(
            "results/{plot}/{method}/{scenario}/sim.laz",
            plot=PLOTS,
            method=METHODS,
            scenario=SCENARIOS,
        ),
        pulses=expand(
            "results/{plot}/{method}/{scenario}/pulses.npz",
            plot=PLOTS,
            method=METHODS,
            scenario=SCENARIOS,
        ),
    output:
        csv="results/summary/simulations.csv",
    log:
        "logs/summary/simulations.log",
    conda:
        "../../envs/vlsforest.yaml"
    resources:
        mem_mb=2000,
        runtime=10,
    shell:
        "vlsforest summarize-sims {input.laz} -o {output.csv} > {log} 2>&1"
