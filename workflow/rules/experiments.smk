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
