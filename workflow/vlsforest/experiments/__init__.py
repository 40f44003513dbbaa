"""Experiments that test the proposed cause of a finding that disagrees with the study.

Each experiment is one module with one ``run_…`` function that returns a JSON-able result, run
by ``vlsforest experiment <name>`` and by a workflow target (``workflow/rules/experiments.smk``);
:mod:`vlsforest.stats.findings` quotes the result beside the finding it explains.

* :mod:`~vlsforest.experiments.tls_step` — the TLS angular step and the 0.02 m / scaled voxel
  ratio (finding F2, Table 5's voxel rows);
* :mod:`~vlsforest.experiments.recording_detector` — the recordings' detector and their
  multiple-return share (finding D1, Table 5's penetration rows);
* :mod:`~vlsforest.experiments.crown_outline` — where the CPA and CBH errors come from (finding
  F1, Table 5's accuracy rows);
* :mod:`~vlsforest.experiments.shift_room` — the scaled cubes' size and what the random shift
  changes (finding F6);
* :mod:`~vlsforest.experiments.cog_shift` — what the CoG shift does to the cubes the returns come
  from (finding F4);
* :mod:`~vlsforest.experiments.cog_parts` — the CoG shift's vertical and horizontal parts,
  simulated apart (finding F4);
* :mod:`~vlsforest.experiments.reseed` — the run's own noise: one method simulated again with
  another seed (finding F6).

The last five read a finished run's files (:mod:`~vlsforest.experiments.run_outputs`); the CoG
parts and the reseed also simulate its plots again with its surveys
(:mod:`~vlsforest.experiments.resimulate`).
"""
