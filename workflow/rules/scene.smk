# Scene assembly per plot × method. Until the virtual forest lands, a plot of kind "demo" is the
# embedded demo tree (vlsforest.demo).


rule scene:
    output:
        scene="results/{plot}/{method}/scene/scene.yaml",
    log:
        "logs/scene/{plot}_{method}.log",
    conda:
        "../../envs/vlsforest.yaml"
    params:
        plot=plot_param,
        method=method_param,
        seed=config["seed"],
    resources:
        mem_mb=2000,
        runtime=10,
    shell:
        "vlsforest demo --plot-json '{params.plot}' --method-json '{params.method}' "
        "--seed {params.seed} -o {output.scene} > {log} 2>&1"
