# Scene assembly per plot × method (vlsforest.scene): ground plane, target stem meshes, voxel
# crowns and surrounding trees, object ids per target stem and crown; HELIOS++ XML beside it.


rule scene:
    input:
        voxels="results/{plot}/{method}/voxels.npz",
        targets="results/{plot}/targets.csv",
        site="results/{plot}/site.json",
        stems="results/{plot}/stems",
    output:
        directory("results/{plot}/{method}/scene"),
    log:
        "logs/scene/{plot}_{method}.log",
    benchmark:
        "logs/benchmarks/scene/{plot}_{method}.tsv"
    conda:
        "../../envs/vlsforest.yaml"
    resources:
        mem_mb=4000,
        runtime=10,
    params:
        reflectance=lambda wc: json.dumps(config["scene"]["reflectance"], sort_keys=True),
        helios=lambda wc: f"--helios results/{wc.plot}/{wc.method}/scene/helios" if config["scene"]["helios_export"] else "",
        library=command_hash("scene"),
    shell:
        "vlsforest scene build --voxels {input.voxels} --targets {input.targets} "
        "--site {input.site} --stems {input.stems} --reflectance-json {params.reflectance:q} "
        "--method {wildcards.method} {params.helios} -o {output}/scene.yaml > {log} 2>&1"
