"""The embedded default forest: the real ALS-vs-ULS disagreement (issue 3) and the segmentation's accuracy (issue 4), slow.

Builds, with the workflow, the reference tree clouds of the 30 target trees from the default
virtual forest's "real" ALS and ULS recordings (synth, segmentation, TLS-guided extraction
with the study's 0.5 m / 0.3 m radii, Table 4 metrics: ≈ 20 min on 2 cores) and checks that
ULS − ALS has the signs of the real Bretten comparison (1,016 trees): ULS height above ALS,
ULS crown base lower, ULS crown projection area smaller, in the mean and in the median.

Marked ``slow`` (left out of CI): ``bash scripts/run-slow-tests.sh`` runs these tests and records
each one's outcome and seconds in ``benchmarks/results/slow_tests.jsonl``.

Set ``VLSFOREST_DEFAULT_RESULTS`` to a working directory where the default config already ran
(at least up to ``results/{plot}/reference/{als,uls}/metrics.csv``) to check those files
instead of building them. The segmentation test reads the same run's ``results/{plot}/segment``
folders and the forest's truth labels.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from wfrun import REPO, snakemake_cli

pytestmark = pytest.mark.slow

DEFAULT = REPO / "config" / "config.yaml"
NO_DIAGNOSIS = REPO / "config" / "no-diagnosis.yaml"


@pytest.fixture(scope="module")
def default_run(tmp_path_factory):
    """Working directory of a default-config run up to the reference metrics of every plot."""
    plots = list(yaml.safe_load(DEFAULT.read_text())["plots"])
    targets = [f"results/{p}/reference/{s}/metrics.csv" for p in plots for s in ("als", "uls")]
    given = os.environ.get("VLSFOREST_DEFAULT_RESULTS")
    if given:
        work = Path(given)
    else:
        work = tmp_path_factory.mktemp("default")
        proc = snakemake_cli("--cores", 2, "--configfile", DEFAULT, NO_DIAGNOSIS, "--", *targets, cwd=work,
                             timeout=3600)
        assert proc.returncode == 0, proc.stderr[-4000:]
    return work, targets


@pytest.fixture(scope="module")
def reference_metrics(default_run):
    work, targets = default_run
    frames = []
    for t in targets:
        d = pd.read_csv(work / t)
        d["scenario"] = Path(t).parent.name
        frames.append(d)
    return pd.concat(frames, ignore_index=True)


def test_uls_minus_als_has_the_real_signs(reference_metrics):
    m = reference_metrics
    wide = m.pivot_table(index="tree_id", columns="scenario", values=["height", "cbh", "cpa", "n_points"])
    assert len(wide) == 30 and (wide["n_points"] > 100).all().all()
    diff = {k: wide[(k, "uls")] - wide[(k, "als")] for k in ("height", "cbh", "cpa")}
    # real Bretten ULS − ALS: height +0.18 / +0.24 m, CBH −1.89 / −0.90 m, CPA −1.55 / −1.57 m² (mean / median)
    assert diff["height"].mean() > 0
    assert diff["cbh"].mean() < 0 and diff["cbh"].median() < 0
    assert diff["cpa"].mean() < 0 and diff["cpa"].median() < 0
    # the CBH sign is not carried by a few trees: most trees get a lower or equal ULS crown base
    assert (diff["cbh"] <= 0).sum() >= 20
    # no reference tree's crown base sits on the ground (ground returns are not tree points)
    assert (wide["cbh"] > 1.0).all().all()


@pytest.mark.xfail(strict=True, reason="the TLS reach (docs: limitations): for 10 of the 15 spruce "
                   "targets the TLS never reaches the top 0.7–3.5 m, so neither reference cloud holds the top and "
                   "the median ULS − ALS height is a coin flip (−0.004 m) instead of the real +0.24 m")
def test_uls_minus_als_median_height_has_the_real_sign(reference_metrics):
    m = reference_metrics
    wide = m.pivot_table(index="tree_id", columns="scenario", values="height")
    assert (wide["uls"] - wide["als"]).median() > 0


def test_segmentation_of_the_targets_meets_the_issue_bar(default_run):
    """Issue 4 on the default forest: targets found with F1 ≥ 0.95 (within 0.5 m), mean target
    point IoU ≥ 0.90 over the 30 targets, median DBH error ≤ 2 cm."""
    from vlsforest.io.las import read_las
    from vlsforest.segment import match_stems

    work, _ = default_run
    truth_all = pd.read_csv(work / "results" / "forest" / "truth" / "trees.csv")
    ious, dbh_err, n_targets, n_found, n_fp = [], [], 0, 0, 0
    for plot in yaml.safe_load(DEFAULT.read_text())["plots"]:
        # the rule passes the scans as the shell glob scan_*.laz orders them
        scans = sorted((work / "results" / "forest" / "plots" / plot / "tls").glob("scan_*.laz"))
        lab = np.concatenate([np.load(work / "results" / "forest" / "truth" / plot / "tls" / f"{p.stem}_labels.npz")["tree_id"]
                              for p in scans])
        seg = work / "results" / plot / "segment"
        tid = read_las(seg / "segmented.laz", require=("tree_id",)).attrs["tree_id"].astype(np.int64)
        assert len(tid) == len(lab)
        trees = pd.read_csv(seg / "trees.csv")
        truth = truth_all[truth_all["plot"] == plot].reset_index(drop=True)
        targets = truth[truth["target"]].reset_index(drop=True)
        pairs = match_stems(trees[["x", "y"]].to_numpy(), targets[["x", "y"]].to_numpy(), 0.5)
        n_targets += len(targets)
        n_found += len(pairs)
        for f, t in pairs:
            T, P = lab == targets["tree_id"][t], tid == trees["tree_id"][f]
            ious.append((T & P).sum() / (T | P).sum())
        all_pairs = match_stems(trees[["x", "y"]].to_numpy(), truth[["x", "y"]].to_numpy(), 0.5)
        dbh_err += [trees["dbh"][f] - truth["dbh"][t] for f, t in all_pairs]
        # a false positive: a found stem that matches no true stem and stands within 5 m of a target
        other = np.setdiff1d(np.arange(len(trees)), [f for f, _ in all_pairs])
        d = np.hypot(trees["x"].to_numpy()[other, None] - targets["x"].to_numpy()[None],
                     trees["y"].to_numpy()[other, None] - targets["y"].to_numpy()[None])
        n_fp += int((d.min(axis=1) < 5.0).sum()) if len(other) else 0
    assert n_targets == 30
    assert 2 * n_found / (2 * n_found + n_fp + n_targets - n_found) >= 0.95
    assert np.mean(ious) >= 0.90, np.round(ious, 3)
    assert np.median(np.abs(dbh_err)) <= 0.02


def test_no_plant_surface_inside_a_scanners_minimum_range(default_run):
    """Every TLS position of the default forest keeps its head ≥ head_clearance_m (2 m) from every
    plant surface, so that no shot is blocked unseen inside the VZ-400's 1.5 m minimum range (a
    scanner 0.9 m from a small tree's foliage once cost a beech crown 80 % of its estimated PAD)."""
    from vlsforest.synth.forest import forest_from_config, generate_plot_trees
    from vlsforest.synth.record import _HeadClearance

    work, _ = default_run
    forest = work / "results" / "forest"
    st = yaml.safe_load((forest / "truth" / "synth_settings.yaml").read_text())
    for plot in forest_from_config(st["forest"], int(st.get("seed", 0))):
        head = _HeadClearance(plot, generate_plot_trees(plot), st["tls"])
        scans = pd.read_csv(forest / "plots" / plot.name / "tls" / "scans.csv")
        for _, row in scans.iterrows():
            assert head(row["x"], row["y"]) >= -1e-9, (plot.name, int(row["scan_id"]))
