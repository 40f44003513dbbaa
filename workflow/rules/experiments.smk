# Experiments that test the cause of a finding that disagrees with the study
# (vlsforest.experiments; docs/findings.md). Each writes one JSON result under
# results/experiments/; an enabled experiment is part of the default target and its result goes
# into the findings (rule stats).


rule experiment_tls_step:
    output:
        "results/experiments/tls_step.json",
    log:
        "logs/experiments/tls_step.log",
    benchmark:
        "logs/benchmarks/experiments/tls_step.tsv"
    conda:
        "../../envs/vlsforest.yaml"
    resources:
        mem_mb=4000,
        runtime=60,
    params:
        settings=synth_param,
        plot=lambda wildcards: experiment_setting("tls_step", "plot", (virtual_plots() or [""])[0]),
        steps=lambda wildcards: " ".join(str(s) for s in experiment_setting("tls_step", "steps")),
        trees=lambda wildcards: (f"--trees {experiment_setting('tls_step', 'trees')}"
                                 if experiment_setting("tls_step", "trees") else ""),
        band=lambda wildcards: (f"--band {experiment_setting('tls_step', 'band_m')}"
                                if experiment_setting("tls_step", "band_m") else ""),
        # the fill of every configured fixed method's cell size
        cells=lambda wildcards: " ".join(f"{m['voxel_size']:g}" for m in config["methods"].values()
                                         if m["kind"] == "fixed"),
        library=command_hash("experiment"),
    shell:
        "vlsforest experiment tls-step --config-json {params.settings:q} --plot {params.plot} "
        "--steps {params.steps} {params.trees} {params.band} --cells {params.cells} -o {output} > {log} 2>&1"


rule experiment_recording_detector:
    output:
        "results/experiments/recording_detector.json",
    log:
        "logs/experiments/recording_detector.log",
    benchmark:
        "logs/benchmarks/experiments/recording_detector.tsv"
    conda:
        "../../envs/vlsforest.yaml"
    resources:
        mem_mb=8000,
        runtime=60,
    params:
        settings=synth_param,
        plot=lambda wildcards: experiment_setting("recording_detector", "plot", (virtual_plots() or [""])[0]),
        sensor=lambda wildcards: experiment_setting("recording_detector", "sensor"),
        variants=lambda wildcards: json.dumps(experiment_setting("recording_detector", "variants", {}), sort_keys=True),
        library=command_hash("experiment"),
    shell:
        "vlsforest experiment recording-detector --config-json {params.settings:q} --plot {params.plot} "
        "--sensor {params.sensor} --variants-json {params.variants:q} -o {output} > {log} 2>&1"


rule experiment_crown_outline:
    # takes the run's CPA errors apart (no simulation): reads what the manifest names
    input:
        lambda wildcards: manifest_paths(run_outputs_manifest(crown_outline_methods()),
                                         keep=lambda key: key != "metrics"),
    output:
        "results/experiments/crown_outline.json",
    log:
        "logs/experiments/crown_outline.log",
    benchmark:
        "logs/benchmarks/experiments/crown_outline.tsv"
    conda:
        "../../envs/vlsforest.yaml"
    resources:
        mem_mb=2000,
        runtime=10,
    params:
        inputs=lambda wildcards: json.dumps(run_outputs_manifest(crown_outline_methods()), sort_keys=True),
        methods=lambda wildcards: " ".join(crown_outline_methods()),
        scenarios=" ".join(SCENARIOS),
        library=command_hash("experiment"),
    shell:
        "vlsforest experiment crown-outline --inputs-json {params.inputs:q} --methods {params.methods} "
        "--scenarios {params.scenarios} -o {output} > {log} 2>&1"


rule experiment_shift_room:
    # relates the run's random-shift changes to the cube sizes (no simulation)
    input:
        lambda wildcards: manifest_paths(run_outputs_manifest(shift_room_methods()),
                                         keep=lambda key: key in ("targets", "metrics"))
        + [f"results/{plot}/{shift_room_methods()[0]}/voxels.npz" for plot in PLOTS],
    output:
        "results/experiments/shift_room.json",
    log:
        "logs/experiments/shift_room.log",
    benchmark:
        "logs/benchmarks/experiments/shift_room.tsv"
    conda:
        "../../envs/vlsforest.yaml"
    resources:
        mem_mb=2000,
        runtime=10,
    params:
        inputs=lambda wildcards: json.dumps(run_outputs_manifest(shift_room_methods()), sort_keys=True),
        base=lambda wildcards: shift_room_methods()[0],
        shifted=lambda wildcards: shift_room_methods()[1],
        scenarios=" ".join(SCENARIOS),
        library=command_hash("experiment"),
    shell:
        "vlsforest experiment shift-room --inputs-json {params.inputs:q} --base {params.base} "
        "--shifted {params.shifted} --scenarios {params.scenarios} -o {output} > {log} 2>&1"


rule experiment_cog_shift:
    # predicts the CoG shift's changes from the cubes the run's returns lie on, and splits the
    # simulated change into the cubes' displacement and what the pulses reach (no simulation)
    input:
        lambda wildcards: manifest_paths(run_outputs_manifest(cog_shift_methods()),
                                         keep=lambda key: key in ("targets", "voxels", "metrics", "trees")),
    output:
        "results/experiments/cog_shift.json",
    log:
        "logs/experiments/cog_shift.log",
    benchmark:
        "logs/benchmarks/experiments/cog_shift.tsv"
    conda:
        "../../envs/vlsforest.yaml"
    resources:
        mem_mb=2000,
        runtime=10,
    params:
        inputs=lambda wildcards: json.dumps(run_outputs_manifest(cog_shift_methods()), sort_keys=True),
        base=lambda wildcards: cog_shift_methods()[0],
        shifted=lambda wildcards: cog_shift_methods()[1],
        scenarios=" ".join(SCENARIOS),
        library=command_hash("experiment"),
    shell:
        "vlsforest experiment cog-shift --inputs-json {params.inputs:q} --base {params.base} "
        "--shifted {params.shifted} --scenarios {params.scenarios} -o {output} > {log} 2>&1"


rule experiment_cog_parts:
    # simulates the CoG shift's vertical and horizontal parts apart, with the run's surveys, seeds
    # and simulation region (two simulations per plot and scenario)
    input:
        lambda wildcards: manifest_paths(cog_parts_manifest()),
    output:
        "results/experiments/cog_parts.json",
    log:
        "logs/experiments/cog_parts.log",
    benchmark:
        "logs/benchmarks/experiments/cog_parts.tsv"
    conda:
        "../../envs/vlsforest.yaml"
    threads: 16
    resources:
        mem_mb=simulate_mem_mb,
        runtime=simulate_runtime,
    params:
        inputs=lambda wildcards: json.dumps(cog_parts_manifest(), sort_keys=True),
        base=lambda wildcards: cog_parts_methods()[0],
        shifted=lambda wildcards: cog_parts_methods()[1],
        scenarios=lambda wildcards: " ".join(experiment_scenarios("cog_parts")),
        seeds=lambda wildcards: json.dumps({sc: seed_of_scenario(sc) for sc in experiment_scenarios("cog_parts")},
                                           sort_keys=True),
        margin=config["simulation"]["region_margin_m"],
        library=command_hash("experiment"),
    shell:
        "vlsforest experiment cog-parts --inputs-json {params.inputs:q} --base {params.base} "
        "--shifted {params.shifted} --scenarios {params.scenarios} --seeds-json {params.seeds:q} "
        "--region-margin {params.margin} --workers {threads} -o {output} > {log} 2>&1"


rule experiment_reseed:
    # simulates one method again with each scenario's seed plus an offset, with the run's surveys
    # and simulation region (one simulation per plot and scenario): the run's own noise
    input:
        lambda wildcards: manifest_paths(reseed_manifest()),
    output:
        "results/experiments/reseed.json",
    log:
        "logs/experiments/reseed.log",
    benchmark:
        "logs/benchmarks/experiments/reseed.tsv"
    conda:
        "../../envs/vlsforest.yaml"
    threads: 16
    resources:
        mem_mb=simulate_mem_mb,
        runtime=simulate_runtime,
    params:
        inputs=lambda wildcards: json.dumps(reseed_manifest(), sort_keys=True),
        method=lambda wildcards: reseed_method(),
        scenarios=lambda wildcards: " ".join(experiment_scenarios("reseed")),
        seeds=lambda wildcards: json.dumps({sc: seed_of_scenario(sc) for sc in experiment_scenarios("reseed")},
                                           sort_keys=True),
        offset=lambda wildcards: experiment_setting("reseed", "seed_offset", 1),
        margin=config["simulation"]["region_margin_m"],
        library=command_hash("experiment"),
    shell:
        "vlsforest experiment reseed --inputs-json {params.inputs:q} --method {params.method} "
        "--scenarios {params.scenarios} --seeds-json {params.seeds:q} --seed-offset {params.offset} "
        "--region-margin {params.margin} --workers {threads} -o {output} > {log} 2>&1"
