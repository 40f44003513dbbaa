"""Experiments that test the proposed cause of a finding that disagrees with the study.

Each experiment is one module with one ``run_…`` function that returns a JSON-able result, run
by ``vlsforest experiment <name>`` and by a workflow target (``workflow/rules/experiments.smk``);
:mod:`vlsforest.stats.findings` quotes the result beside the finding it explains.

* :mod:`~vlsforest.experiments.tls_step` — the TLS angular step and the 0.02 m / scaled voxel
  ratio (finding F2, Table 5's voxel rows);
* :mod:`~vlsforest.experiments.recording_detector` — the recordings' detector and their
  multiple-return share (finding D1, Table 5's penetration rows).
"""
