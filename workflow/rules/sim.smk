# Survey per plot × scenario (re-flying the recorded trajectory), simulation per
# plot × method × scenario, and the simulated target-tree clouds with their metrics.


rule survey:
    input:
        unpack(plot_files),
    output:
        "results/{plot}/surveys/{scenario}.yaml",
    log:
        "logs/survey/{plot}_{scenario}.log",
    benchmark:
        "logs/benchmarks/survey/{plot}_{scenario}.tsv"
    conda:
        "../../envs/vlsforest.yaml"
    resources:
        mem_mb=1000,
        runtime=5,
    params:
        scenario=scenario_param,
        trajectory=scenario_trajectory,
        seed=scenario_seed,
        library=command_hash("plan"),
    shell:
        "vlsforest plan --trajectory {params.trajectory} --scenario-json {params.scenario:q} "
        "--seed {params.seed} -o {output} > {log} 2>&1"


rule simulate:
    input:
        scene="results/{plot}/{method}/scene",
        survey="results/{plot}/surveys/{scenario}.yaml",
        site="results/{plot}/site.json",
    output:
        laz="results/{plot}/{method}/{scenario}/sim.laz",
        timing="results/{plot}/{method}/{scenario}/timing.json",
    log:
        "logs/simulate/{plot}_{method}_{scenario}.log",
    benchmark:
        "logs/benchmarks/simulate/{plot}_{method}_{scenario}.tsv"
    conda:
        "../../envs/vlsforest.yaml"
    # the profiles' set-threads decide: one locally (profiles/default: jobs side by side), 8 on
    # SLURM; without a profile capped by --cores. Not `workflow.cores`: that raises when no
    # --cores is given (cluster runs).
    threads: 16
    resources:
        mem_mb=simulate_mem_mb,
        runtime=simulate_runtime,
    params:
        seed=scenario_seed,
        margin=config["simulation"]["region_margin_m"],
        library=command_hash("simulate"),
    shell:
        "vlsforest simulate {input.scene}/scene.yaml {input.survey} -o {output.laz} "
        "--timing {output.timing} --seed {params.seed} --workers {threads} "
        "--region-from {input.site} --region-margin {params.margin} 2>&1 "
        # progress: every 10 % of the blocks a line goes to the log and to the terminal,
        # prefixed with the job's plot/method/scenario (pipefail keeps the exit status)
        "| tee {log} | sed -u 's|^|[{wildcards.plot}/{wildcards.method}/{wildcards.scenario}] |' >&2"


rule sim_trees:
    # the target trees' points and their metrics in one job (one start-up and one read of the
    # simulated cloud instead of two jobs); the metrics are computed from trees.laz as written
    input:
        laz="results/{plot}/{method}/{scenario}/sim.laz",
        targets="results/{plot}/targets.csv",
    output:
        trees="results/{plot}/{method}/{scenario}/trees.laz",
        metrics="results/{plot}/{method}/{scenario}/metrics.csv",
    log:
        "logs/extract/{plot}_{method}_{scenario}.log",
    benchmark:
        "logs/benchmarks/extract/{plot}_{method}_{scenario}.tsv"
    conda:
        "../../envs/vlsforest.yaml"
    resources:
        mem_mb=4000,
        runtime=10,
    params:
        library=command_hash("extract"),
    shell:
        "vlsforest extract sim {input.laz} --targets {input.targets} -o {output.trees} "
        "--metrics {output.metrics} > {log} 2>&1"


rule sim_times:
    input:
        timing_files(),
    output:
        report("results/summary/sim_times.csv", caption="../report/sim_times.rst", category="Tables"),
    log:
        "logs/summary/sim_times.log",
    benchmark:
        "logs/benchmarks/summary/sim_times.tsv"
    conda:
        "../../envs/vlsforest.yaml"
    resources:
        mem_mb=1000,
        runtime=5,
    params:
        library=command_hash("collect"),
    shell:
        "vlsforest collect times {input} -o {output} > {log} 2>&1"
