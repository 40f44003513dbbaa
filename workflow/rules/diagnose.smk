# Physics diagnosis (vlsforest.diagnose): where do the simulations of one voxel method differ from
# the real recordings, which physics left out of the simulation explains it, fitted and checked
# on held-out trees. Configured by the `diagnosis:` block (off when absent or enabled: false).


def diagnosis_cfg():
    return config.get("diagnosis") or {}


def diagnosis_scenarios():
    d = diagnosis_cfg()
    if not d.get("enabled", False):
        return []
    return [s for s in d.get("scenarios", SCENARIOS) if s in SCENARIOS]


def diagnosis_plots():
    return [p for p in (diagnosis_cfg().get("plots") or PLOTS) if p in PLOTS]


def diagnosis_inputs(wildcards):
    method = diagnosis_cfg().get("method", "scaled")
    rec = recording_of(wildcards.scenario)
    out = {}
    for plot in diagnosis_plots():
        out[f"scene_{plot}"] = f"results/{plot}/{method}/scene"
        out[f"survey_{plot}"] = f"results/{plot}/surveys/{wildcards.scenario}.yaml"
        out[f"segment_{plot}"] = f"results/{plot}/segment"
        # a virtual plot's recording lies inside the forest folder (a directory output)
        out[f"real_{plot}"] = "results/forest" if is_virtual(plot) else _plot_path(plot, "recording", rec)
    return out


def diagnosis_param(wildcards):
    """The sim-config of one scenario (everything the diagnosis reads, as one mapping)."""
    d = diagnosis_cfg()
    method = d.get("method", "scaled")
    sc = config["scenarios"][wildcards.scenario]
    return {
        "scenario": wildcards.scenario,
        "seed": config["seed"],
        "folds": d.get("folds", 3),
        "grid": d.get("grid", 7),
        "candidates": d.get("candidates") or None,
        "plots": {
            plot: {
                "real": _plot_path(plot, "recording", recording_of(wildcards.scenario)),
                "scene": f"results/{plot}/{method}/scene/scene.yaml",
                "survey": f"results/{plot}/surveys/{wildcards.scenario}.yaml",
                "segment": f"results/{plot}/segment",
                "radius": sc.get("extraction_radius_m", 0.5),
                "margin": config["simulation"]["region_margin_m"],
            }
            for plot in diagnosis_plots()
        },
    }


rule diagnosis_setup:
    output:
        "results/diagnosis/{scenario}.sim.yaml",
    params:
        setup=diagnosis_param,
    run:
        import yaml

        setup = {k: v for k, v in params.setup.items() if v is not None}
        Path(output[0]).parent.mkdir(parents=True, exist_ok=True)
        Path(output[0]).write_text(yaml.safe_dump(setup, sort_keys=True))


rule diagnose:
    input:
        unpack(diagnosis_inputs),
        setup="results/diagnosis/{scenario}.sim.yaml",
    output:
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
        mem_mb=12000,
        runtime=60,
    params:
        library=DIAGNOSE_HASH,
    shell:
        "python -m vlsforest.cli diagnose --real results/forest/plots --sim-config {input.setup} "
        "--scenario {wildcards.scenario} -o {output.json} --figure {output.figure} > {log} 2>&1"
