"""The ``linear_pad`` voxel method (example of a method added as a rule file): PAD-scaled cubes
whose side grows linearly with PAD (α = 1) instead of their face area (the study's α = 0.5).

Run by ``linear_pad.smk`` through Snakemake's ``script:`` directive; :func:`linear_pad_model`
is the method itself and can be used from Python like any built-in kind.
"""

import json
from pathlib import Path

import numpy as np

from vlsforest.io.csvfile import read_csv_table
from vlsforest.voxels import ModelInputs, PadGrid, scaled_model


def linear_pad_model(inputs, a0=0.25, alpha=1.0, groups=None):
    """PAD-scaled cubes with side a = a0 · (PAD / PADmax)^alpha (alpha = 1 by default)."""
    return scaled_model(inputs, a0=a0, alpha=alpha, shift="none", groups=groups)


def main(smk):
    with np.load(smk.input.crowns) as z:
        xyz, owner = z["xyz"], z["owner"]
    t = read_csv_table(smk.input.targets, "targets table", ("group",), ids=("tree_id",))
    inputs = ModelInputs(xyz, owner, dict(zip(t.tree_id.tolist(), t.group.astype(str))),
                         PadGrid.from_vox(smk.input.pad, smk.params.min_pulses), smk.params.seed,
                         smk.params.default_group)
    entry = {k: v for k, v in json.loads(smk.params.method).items() if k not in ("kind", "description")}
    model = linear_pad_model(inputs, groups=json.loads(smk.params.groups), **entry)
    model.save(smk.output[0])
    Path(smk.log[0]).parent.mkdir(parents=True, exist_ok=True)
    Path(smk.log[0]).write_text(f"linear_pad: {model.n_voxels} cubes\n")


if "snakemake" in globals():
    main(snakemake)  # noqa: F821 (set by Snakemake's script directive)
