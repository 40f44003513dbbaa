# Scene assembly per plot × method. Until the virtual forest lands, a plot of kind "demo" is the
# embedded demo tree (vlsforest.demo): scene.yaml plus its parts (DEMO_PARTS) in one folder.


rule scene:
    output:
        scene="results/{plot}/{method}/scene/scene.yaml",
        parts=expand("results/{{plot}}/{{method}}/scene/{part}", part=DEMO_PARTS),
    log:
        "logs/scene/{plot}_{method}.log",
    benchmark:
        "logs/benchmarks/scene/{plot}_{method}.tsv"
    conda:
        "../../envs/vlsforest.yaml"
    resources:
        mem_mb=2000,
        runtime=10,
    params:
        plot=plot_param,
        method=method_param,
        seed=config["seed"],
        library=SIM_HASH,
    shell:
        "python -m vlsforest.cli demo --plot-json {params.plot:q} --method-json {params.method:q} "
        "--seed {params.seed} -o {output.scene} > {log} 2>&1"
