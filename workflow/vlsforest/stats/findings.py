"""The study's findings judged on a run's numbers, with the paper's tolerances, causes and experiments.

:func:`evaluate_findings` checks each qualitative finding of Weiser et al. (2021) and each row of
its Table 5 against the run's tables, by the rules and tolerances of :mod:`vlsforest.stats.claims`
(direction beyond a negligible effect with a 95 % bootstrap interval that excludes zero;
"nothing" as an interval within ± the negligible effect; stated sizes within their tolerance).
Which method or scenario plays which part comes from the configuration
(:class:`~vlsforest.stats.roles.StudyRoles`), never from its name.

A finding that disagrees names its cause only where an experiment tests it:

* ``D1`` compares the reference recordings' multiple-return shares with the study's real data;
  the Table 5 penetration rows then re-judge each method against the study's real shares
  instead of the recordings (the experiment of that cause, computed here);
* ``F2`` and the Table 5 voxel rows take the result of the TLS angular-step experiment
  (:mod:`vlsforest.experiments.tls_step`) when its file is given; so do ``F5`` (the
  experiment's fill of a fixed model smaller than the 0.25 m cell at both steps: how opaque that
  model is at the study's step, and the errors that predicts) and ``F3b`` (the fill of the fixed
  models per species group: whether their porosity contrast fades at the study's step) and ``F4``
  (the TLS points' centre of gravity in the 0.25 m cells at both steps: whether the CoG shift
  lowers the cubes at the study's step); ``F4`` also takes the CoG-shift experiment
  (:mod:`vlsforest.experiments.cog_shift`: the change the cubes the returns lie on predict);
* ``F1`` and the Table 5 accuracy rows take the crown-outline experiment
  (:mod:`vlsforest.experiments.crown_outline`: each model's CPA error split into its own outline,
  what the simulation does not see and the crown base), ``F6`` the shift-room experiment
  (:mod:`vlsforest.experiments.shift_room`: the cubes' size against what the random shift
  changes, over the trees) and the reseed experiment (:mod:`vlsforest.experiments.reseed`: the
  run's own noise, the unshifted model simulated again with another seed).

Everywhere else the cause column says that no experiment has tested a cause yet.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import pandas as pd

from vlsforest.stats import claims as cl
from vlsforest.stats.errors import block_rng, bootstrap_mean_ci
from vlsforest.stats.roles import StudyRoles, study_label
from vlsforest.stats.table5 import penetration_class
from vlsforest.stats.tables import REFERENCE, check_errors, scenario_order

__all__ = ["ALPHA", "CI_LEVEL", "N_BOOT", "Effect", "evaluate_findings", "findings_markdown", "findings_table"]

#: significance level where the paper's claim is about significance (F3)
ALPHA = 0.05
#: level of the bootstrap intervals of the mean effects
CI_LEVEL = 0.95
#: bootstrap resamples of each effect
N_BOOT = 2000
#: the TLS angular-step experiment's key of the study's 0.25 m cell (the scaled cubes' cell, which
#: its fill values are shares of); the experiment writes cell sizes as ``f"{size:g}"``
#: (vlsforest.experiments.tls_step.cell_key), which this layer does not import
_COARSE_KEY = "0.25"

#: the cause column of a disagreement that no experiment has tested
NO_EXPERIMENT = "not established: no experiment of this project tests a cause yet"


@dataclass(frozen=True)
class Effect:
    """Mean of per-tree values with its bootstrap interval."""

    mean: float
    lo: float
    hi: float
    n: int

    def text(self, unit: str, nd: int = 2) -> str:
        """``mean unit (95 % CI lo to hi, n trees)``."""
        return (f"{self.mean:+.{nd}f} {unit} (95 % CI {self.lo:+.{nd}f} to {self.hi:+.{nd}f}, "
                f"{self.n} trees)")


def _effect(values, seed: int, *names) -> Effect | None:
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    if len(v) < 2:
        return None
    lo, hi = bootstrap_mean_ci(v[:, None], block_rng(seed, "findings", *names), N_BOOT, CI_LEVEL)
    return Effect(float(v.mean()), float(lo[0]), float(hi[0]), len(v))


def _beyond(e: Effect, sign: int, margin: float) -> bool:
    """Mean beyond ``margin`` in direction ``sign`` and the interval excluding zero."""
    return bool(sign * e.mean > margin and (e.lo > 0 if sign > 0 else e.hi < 0))


def _within(e: Effect, margin: float) -> bool:
    """The whole interval within ± ``margin``."""
    return bool(e.lo >= -margin and e.hi <= margin)


def _fmt(x, nd=2) -> str:
    return "n/a" if x is None or not np.isfinite(x) else f"{x:.{nd}f}"


def _fmt_p(p) -> str:
    if p is None or not np.isfinite(p):
        return "n/a"
    return f"{p:.2g}" if p < 0.001 else f"{p:.3f}"


def _verdict(ok) -> str:
    if not ok:
        return "not testable"
    return "agrees" if all(ok) else "disagrees"


def _unit(metric: str) -> str:
    return {"multi_return_pct": "pp", "cpa": "m²"}.get(metric, "m")


class _Errors:
    """Per-tree lookups in a checked errors table."""

    def __init__(self, errors: pd.DataFrame):
        self.df = check_errors(errors)
        self._idx = {k: g for k, g in self.df.groupby(["method", "scenario", "metric"], sort=False)}

    def block(self, method, scenario, metric, group=None) -> pd.DataFrame:
        b = self._idx.get((method, scenario, metric))
        if b is None:
            return self.df.iloc[:0]
        return b if group is None else b[b["group"] == group]

    def paired(self, a, b, scenario, metric, col="sim"):
        """Per-tree ``col`` of methods a and b on their common trees, and the trees' reference."""
        def get(m):
            return self.block(m, scenario, metric).set_index(["plot", "tree_id"])[[col, "ref"]].astype(float)
        j = get(a).merge(get(b), left_index=True, right_index=True, suffixes=("_a", "_b")).dropna()
        return j[f"{col}_a"].to_numpy(), j[f"{col}_b"].to_numpy(), j["ref_a"].to_numpy()

    def abs_gap(self, a, b, metric, scenarios) -> np.ndarray:
        """Per tree that a and b share: the mean over ``scenarios`` of |a's error| − |b's error|."""
        def get(m, sc):
            return self.block(m, sc, metric).set_index(["plot", "tree_id"])["error"].astype(float).abs()
        parts = [pd.concat({"a": get(a, sc), "b": get(b, sc)}, axis=1).dropna() for sc in scenarios]
        parts = [j["a"] - j["b"] for j in parts if len(j)]
        if not parts:
            return np.zeros(0)
        return pd.concat(parts, axis=1).mean(axis=1).sort_index().to_numpy(float)


def _margin(metric: str, ref: np.ndarray) -> tuple[float, cl.Tolerance | None]:
    """The negligible effect of ``metric`` in its own unit (CPA: % of the mean reference)."""
    tol = cl.negligible(metric)
    if tol is None:
        return math.nan, None
    if tol.unit == "%":
        r = ref[np.isfinite(ref)]
        return (tol.value / 100.0 * float(np.mean(np.abs(r))) if len(r) else math.nan), tol
    return tol.value, tol


def _tolerance_text(*tols) -> str:
    seen = []
    for t in tols:
        if t is not None and t not in seen:
            seen.append(t)
    return "; ".join(f"{t.text()} ({t.source})" for t in seen)


def _row(fid, claim, ok, evidence, tolerance, cause="", experiment=""):
    verdict = _verdict(ok)
    if verdict == "disagrees" and not cause:
        cause = NO_EXPERIMENT
    if verdict != "disagrees":
        cause, experiment = "", experiment if verdict == "agrees" else ""
    return dict(id=fid, claim=claim, verdict=verdict, tolerance=tolerance, evidence=list(evidence), cause=cause,
                experiment=experiment)


def evaluate_findings(errors: pd.DataFrame, tests: pd.DataFrame, mr_tests: pd.DataFrame, t5: pd.DataFrame,
                      voxel_counts: pd.DataFrame, roles: StudyRoles, *, seed: int = 0,
                      experiments: Mapping | None = None) -> list[dict]:
    """Check the study's findings against a run's numbers.

    Parameters
    ----------
    errors, tests, mr_tests, t5 : pandas.DataFrame
        Outputs of :func:`~vlsforest.stats.errors.compute_errors`,
        :func:`~vlsforest.stats.significance.paired_tests`,
        :func:`~vlsforest.stats.significance.multireturn_ttest` and
        :func:`~vlsforest.stats.table5.table5`.
    voxel_counts : pandas.DataFrame
        ``plot, method, n_voxels``.
    roles : StudyRoles
        The part each configured method and scenario plays.
    seed : int
        Seed of the bootstrap intervals (each effect draws from its own generator).
    experiments : mapping, optional
        Experiment name → its result (e.g. ``{"tls_step": {...}}`` as
        :func:`vlsforest.experiments.tls_step.run_tls_step` writes it).

    Returns
    -------
    list of dict
        One per finding: ``id``, ``claim``, ``verdict`` (``"agrees"``, ``"disagrees"`` or
        ``"not testable"``), ``tolerance`` (with its source in the paper), ``evidence`` (lines
        of our numbers), ``cause`` and ``experiment`` (for a disagreement: the cause an
        experiment tests and what it showed, or that none has).
    """
    E = _Errors(errors)
    experiments = dict(experiments or {})
    scen = [s for s in scenario_order(E.df["scenario"], roles.scenario_names) if s in roles.platforms]
    methods = set(E.df["method"])

    def have(name):
        return name is not None and name in methods

    out = []
    coarse = roles.method("fixed", 0.25)
    fine = roles.method("fixed", 0.02)
    scaled = roles.method("scaled", shift="none")
    rand = roles.method("scaled", shift="random")
    cog = roles.method("scaled", shift="cog")

    # D1: the references' multiple-return shares against the study's real data
    ok, ev = [], []
    for sc in scen:
        plat = roles.platforms[sc]
        r = mr_tests[(mr_tests["method"] == REFERENCE) & (mr_tests["scenario"] == sc)]
        if r.empty:
            continue
        r = r.iloc[0]
        for g in ("conifer", "broadleaf"):
            ours, study = float(r[f"mean_{g}"]), cl.STUDY_REFERENCE_MULTI_RETURN[(plat, g)]
            if not np.isfinite(ours):
                continue
            good = abs(ours - study) <= cl.NEGLIGIBLE_MULTI_RETURN.value
            ok.append(good)
            ev.append(f"{sc} ({plat.upper()}) {g}: {ours:.1f} % vs the study's {study:.1f} % "
                      f"({ours - study:+.1f} pp)")
    d1_cause, d1_exp = _detector_cause(experiments.get("recording_detector"))
    out.append(_row("D1", "The reference recordings have the study's real multiple-return shares (ALS: conifer "
                          "73.4 %, broadleaf 55.9 %; ULS: 33.1 %, 28.1 %).", ok, ev,
                    _tolerance_text(cl.NEGLIGIBLE_MULTI_RETURN), d1_cause, d1_exp))
    d1_ok = out[-1]["verdict"] == "agrees"

    # F1: coarse fixed voxels overestimate CBH and underestimate CPA
    ok, ev, tols = [], [], []
    f1_missing = []  # (scenario, metric) of the parts that disagree
    if have(coarse):
        for sc in scen:
            for metric, sign, word in (("cbh", 1, "over"), ("cpa", -1, "under")):
                b = E.block(coarse, sc, metric)
                e = _effect(b["error"], seed, "F1", sc, metric)
                if e is None:
                    continue
                margin, tol = _margin(metric, b["ref"].to_numpy(float))
                tols.append(tol)
                good = _beyond(e, sign, margin)
                ok.append(good)
                if not good:
                    f1_missing.append((sc, metric))
                ev.append(f"{sc}: {metric.upper()} error {e.text(_unit(metric))}: "
                          f"{'an' if good else 'no'} {word}estimation beyond ±{_fmt(margin)} {_unit(metric)}")
    cause, experiment = (_outline_cause(experiments.get("crown_outline"), coarse, f1_missing)
                         if f1_missing else ("", ""))
    out.append(_row("F1", "0.25 m fixed voxels overestimate CBH and underestimate CPA.", ok, ev, _tolerance_text(*tols),
                    cause, experiment))

    # F2: scaled voxels as accurate as 0.02 m voxels (CBH, CPA) with ≈ 50× fewer voxels
    ok, ev, tols = [], [], []
    ratio_ok = None
    cause = experiment = ""
    if have(scaled) and have(fine):
        for sc in scen:
            for metric in ("cbh", "cpa"):
                a, b, ref = E.paired(scaled, fine, sc, metric, col="error")
                e = _effect(np.abs(a) - np.abs(b), seed, "F2", sc, metric)
                if e is None:
                    continue
                margin, tol = _margin(metric, ref)
                tols.append(tol)
                good = e.hi <= margin
                ok.append(good)
                ev.append(f"{sc}: |error| scaled − 0.02 m, {metric.upper()}: {e.text(_unit(metric))}: "
                          + (f"not worse than 0.02 m by more than {_fmt(margin)} {_unit(metric)}" if good else
                             f"the interval reaches beyond +{_fmt(margin)} {_unit(metric)}: not shown as accurate"))
        vc = voxel_counts.astype({"plot": str, "method": str})
        ps = set(vc.loc[vc["method"] == scaled, "plot"]) & set(vc.loc[vc["method"] == fine, "plot"])
        if ps:
            ns = float(vc.loc[(vc["method"] == scaled) & vc["plot"].isin(ps), "n_voxels"].sum())
            nf = float(vc.loc[(vc["method"] == fine) & vc["plot"].isin(ps), "n_voxels"].sum())
            ratio = nf / ns if ns > 0 else math.inf
            f = cl.APPROXIMATE_FACTOR.value
            ratio_ok = cl.VOXEL_RATIO / f <= ratio <= cl.VOXEL_RATIO * f
            ok.append(ratio_ok)
            tols.append(cl.APPROXIMATE_FACTOR)
            ev.append(f"voxels on {len(ps)} plot(s): 0.02 m {nf:.0f}, scaled {ns:.0f}: ratio {ratio:.1f}× "
                      f"(study ≈ {cl.VOXEL_RATIO:.0f}×; tolerated {cl.VOXEL_RATIO / f:.0f}–{cl.VOXEL_RATIO * f:.0f}×)")
    if ratio_ok is False:
        cause, experiment = _tls_step_cause(experiments.get("tls_step"), ratio)
    out.append(_row("F2", "Scaled voxels are as accurate (CBH, CPA) as 0.02 m fixed voxels with ≈ 50× fewer "
                          "voxels.", ok, ev, _tolerance_text(*tols), cause, experiment))

    # F3 / F3b: conifers have significantly more multiple returns (the paper's t-test)
    def mr_parts(ms, want_sig, fid):
        ok, ev = [], []
        for me in ms:
            for sc in scen:
                r = mr_tests[(mr_tests["method"] == me) & (mr_tests["scenario"] == sc)]
                if r.empty or not np.isfinite(r.iloc[0]["p"]):
                    continue
                r = r.iloc[0]
                sig = bool(r["diff"] > 0 and r["p"] < ALPHA)
                ok.append(sig == want_sig)
                ev.append(f"{me} {sc}: conifer {_fmt(r['mean_conifer'], 1)} % vs broadleaf "
                          f"{_fmt(r['mean_broadleaf'], 1)} %, t({int(r['df'])}) = {_fmt(r['t'])}, p = {_fmt_p(r['p'])}")
        return ok, ev

    sig_tol = f"the paper's own test: two-sample t, conifer vs broadleaf, p < {ALPHA:g}"
    ok, ev = mr_parts([REFERENCE] + ([scaled] if have(scaled) else []), True, "F3")
    if not have(scaled):
        ok = []  # the claim needs the scaled simulations as well
    out.append(_row("F3", "Conifers have significantly more multiple returns than broadleaf trees, in the "
                          "reference data and in the scaled-voxel simulations.", ok, ev, sig_tol))
    fixed = [r.name for r in roles.fixed_methods() if have(r.name)]
    ok, ev = mr_parts(fixed, False, "F3b")
    cause = experiment = ""
    failing = sorted({float(r.size) for r in roles.fixed_methods() if have(r.name)
                      and any(not o and e.startswith(f"{r.name} ") for o, e in zip(ok, ev))})
    if failing:
        cause, experiment = _group_fill_cause(experiments.get("tls_step"), failing)
    out.append(_row("F3b", "Fixed voxels do not reproduce this conifer–broadleaf difference.", ok, ev, sig_tol,
                    cause, experiment))

    # F4: the CoG shift lowers the percentiles, multiple returns, tree height and CPA (slightly)
    ok, ev = [], []
    f4_missing = []
    if have(scaled) and have(cog):
        for sc in scen:
            for metric in ("hmean", "multi_return_pct", "height", "cpa"):
                a, b, _ = E.paired(cog, scaled, sc, metric)
                e = _effect(a - b, seed, "F4", sc, metric)
                if e is None:
                    continue
                good = e.hi < 0
                ok.append(good)
                if not good:
                    f4_missing.append(f"{sc} {metric}")
                ev.append(f"{sc}: {metric} change CoG − scaled {e.text(_unit(metric))}: "
                          f"{'lower' if good else 'not lower'}")
    cause, experiment = (_cog_cause(experiments.get("tls_step"), experiments.get("cog_shift"), f4_missing,
                                    experiments.get("cog_parts"))
                         if f4_missing else ("", ""))
    out.append(_row("F4", "Shifting the scaled cubes to the centre of gravity lowers Hmean, the multiple-return "
                          "share, tree height and CPA slightly.", ok, ev,
                    "the 95 % CI of the mean change lies below zero; 'slightly' is not judged (the paper gives "
                    "it no size)", cause, experiment))

    # F5: large fixed voxels: Hmean and Hmin too high, Hsd too low
    ok, ev = [], []
    misses = []  # the parts that disagree: (cell size, scenario, metric, sign, mean error)
    means = {}   # (method, scenario, metric) -> mean error
    for r in roles.fixed_methods():
        if r.size < 0.1 - 1e-9 or not have(r.name):
            continue
        for sc in scen:
            for metric, sign in (("hmean", 1), ("hmin", 1), ("hsd", -1)):
                e = _effect(E.block(r.name, sc, metric)["error"], seed, "F5", r.name, sc, metric)
                if e is None:
                    continue
                means[(r.name, sc, metric)] = e.mean
                good = _beyond(e, sign, cl.NEGLIGIBLE_HEIGHT.value)
                ok.append(good)
                if not good:
                    misses.append((float(r.size), sc, metric, sign, e.mean))
                ev.append(f"{r.name} {sc}: {metric} error {e.text('m')}: "
                          f"{'too ' + ('high' if sign > 0 else 'low') if good else 'not too ' + ('high' if sign > 0 else 'low')}")
    cause = experiment = ""
    if misses:
        coarse_errors = {(sc, metric): means.get((coarse, sc, metric)) for _, sc, metric, _, _ in misses}
        cause, experiment = _fill_cause(experiments.get("tls_step"), misses, coarse_errors)
    out.append(_row("F5", "Large fixed voxels (0.25, 0.10 m) give too high Hmean and Hmin and too low Hsd.", ok, ev,
                    _tolerance_text(cl.NEGLIGIBLE_HEIGHT), cause, experiment))

    # F6: the random shift changes nothing
    ok, ev, tols = [], [], []
    f6_missing = []
    if have(scaled) and have(rand):
        for sc in scen:
            for metric in ("hmean", "multi_return_pct", "cbh", "cpa"):
                a, b, ref = E.paired(rand, scaled, sc, metric)
                e = _effect(a - b, seed, "F6", sc, metric)
                if e is None:
                    continue
                margin, tol = _margin(metric, ref)
                tols.append(tol)
                good = _within(e, margin)
                ok.append(good)
                if not good:
                    f6_missing.append((sc, metric, margin, e))
                ev.append(f"{sc}: {metric} change random − scaled {e.text(_unit(metric))}: "
                          f"{'within' if good else 'the interval reaches beyond'} ±{_fmt(margin)} {_unit(metric)}")
    cause, experiment = (_f6_cause(experiments.get("shift_room"), experiments.get("reseed"), f6_missing, seed)
                         if f6_missing else ("", ""))
    out.append(_row("F6", "The random shift of the scaled cubes changes nothing (Hmean, multiple returns, CBH, "
                          "CPA).", ok, ev, _tolerance_text(*tols), cause, experiment))

    # F7: 0.02 m voxels overestimate the ULS multiple-return share by ≈ 8 (conifer), ≈ 20 pp (broadleaf)
    ok, ev = [], []
    if have(fine):
        for sc in roles.scenarios_of("uls"):
            for g, study in cl.FINE_ULS_OVERESTIMATE.items():
                e = _effect(E.block(fine, sc, "multi_return_pct", g)["error"], seed, "F7", sc, g)
                if e is None:
                    continue
                good = abs(e.mean - study) <= cl.NEGLIGIBLE_MULTI_RETURN.value
                ok.append(good)
                ev.append(f"{sc} {g}: multiple-return error {e.text('pp', 1)} (study ≈ +{study:.0f} pp)")
    f7_cause = f7_exp = ""
    if not d1_ok and any(not o for o in ok):
        f7_cause, f7_exp = _recording_cause()
    out.append(_row("F7", "0.02 m fixed voxels overestimate the ULS multiple-return share by ≈ 8 (conifer) and "
                          "≈ 20 (broadleaf) percentage points.", ok, ev,
                    _tolerance_text(cl.NEGLIGIBLE_MULTI_RETURN), f7_cause, f7_exp))

    out += _table5_rows(t5, roles, mr_tests, scen, d1_ok, experiments, E, seed)
    return out


def _detector_cause(result) -> tuple[str, str]:
    """Cause and experiment of D1 from the recording-detector experiment's result (or its absence)."""
    if not result:
        return ("not established: the recordings' detector (energy threshold, peak rule) is the candidate",
                "recording-detector experiment not run: "
                "`snakemake --cores 2 results/experiments/recording_detector.json`")
    plat = result.get("sensor")
    rows = result.get("variants", [])
    parts, inside = [], []
    for g in ("conifer", "broadleaf"):
        vals = [r[g]["mean_pct"] for r in rows if np.isfinite(r[g]["mean_pct"])]
        study = cl.STUDY_REFERENCE_MULTI_RETURN.get((plat, g))
        if vals and study is not None:
            inside.append(min(vals) <= study <= max(vals))
    for r in rows:
        parts.append(f"{r['name']}: conifer {r['conifer']['mean_pct']:.1f} %, broadleaf {r['broadleaf']['mean_pct']:.1f} %")
    exp = (f"recording-detector experiment ({result.get('plot')}, {str(plat).upper()}, target trees): "
           + "; ".join(parts))
    if inside and all(inside):
        return ("the recordings' detector: with the detector varied and all else fixed the shares span the "
                "study's real values", exp)
    return ("not established: the detector variants tried do not reach the study's real shares", exp)


def _recording_cause() -> tuple[str, str]:
    return ("the reference recordings' multiple-return shares differ from the real sensors' (D1)",
            "each method's shares judged against the study's real shares instead (Table 5 rows, "
            "'against the study's real data')")


def _tls_step_cause(result, run_ratio: float | None = None) -> tuple[str, str]:
    """Cause and experiment of a voxel-ratio disagreement from the TLS angular-step experiment.

    The experiment's ratio at its coarsest and finest step gives a growth factor; where the run's
    own ratio is given, the text also says what it would become if the whole models grew by that
    factor (an extrapolation, stated as one).
    """
    cause = "the TLS angular step: 0.1° in the embedded forest's scans, 0.017° in the study's"
    if not result:
        return cause + " (untested in this run)", ("TLS angular-step experiment not run: "
                                                  "`snakemake --cores 2 results/experiments/tls_step.json`")
    rows = {float(r["step_deg"]): r for r in result.get("steps", [])}
    parts = [f"{s:g}°: {r['ratio']:.1f}×" for s, r in sorted(rows.items(), reverse=True)]
    text = _step_heading(result) + f"0.02 m / 0.25 m filled cells {', '.join(parts)}"
    if len(rows) >= 2:
        coarse, fine = rows[max(rows)]["ratio"], rows[min(rows)]["ratio"]
        if coarse and np.isfinite(coarse) and np.isfinite(fine):
            growth = fine / coarse
            text += f": {growth:.1f}× more fine cells per coarse cell at {min(rows):g}°"
            if run_ratio is not None and np.isfinite(run_ratio):
                text += (f"; the run's {run_ratio:.1f}× would be {run_ratio * growth:.0f}× if the whole models "
                         f"grew alike (study ≈ {cl.VOXEL_RATIO:.0f}×)")
    return cause, text


def _step_rows(result, field: str) -> dict:
    """The TLS angular-step experiment's steps by angle, those that hold ``field`` only."""
    return {float(r["step_deg"]): r for r in (result or {}).get("steps", []) if r.get(field)}


def _step_heading(result, trees: str | None = None) -> str:
    """The opening of an experiment text: ``TLS angular-step experiment (P3, 5 target trees,
    restricted field of view): `` (``trees``: another count of the trees, e.g. per group)."""
    trees = f"{result.get('n_trees')}" if trees is None else trees
    return f"TLS angular-step experiment ({result.get('plot')}, {trees} target trees, restricted field of view): "


def _step_untested(what: str) -> tuple[str, str]:
    """Cause and experiment of a row whose TLS angular-step experiment did not run (with ``what``)."""
    return ("not established: the TLS angular step is the candidate (untested in this run)",
            f"TLS angular-step experiment{what} not run: `snakemake --cores 2 results/experiments/tls_step.json`")


def _fill_cause(result, misses, coarse_errors) -> tuple[str, str]:
    """Cause and experiment of F5's disagreeing parts from the fill the TLS angular-step experiment
    measured at the embedded forest's and the study's step.

    The proposed cause: at the study's finer step a fixed model smaller than the 0.25 m cell fills
    more of the crown, so it is more opaque, nearer the 0.25 m model. The experiment gives the
    model's fill ``a`` at the run's step and ``b`` at the study's. A part's error at the study's
    step is predicted by moving its mean error towards the 0.25 m model's (whose fill is 1) in
    proportion to the fill gained: ``e + (b − a)/(1 − a)·(e_0.25 − e)`` (a linear interpolation in
    fill, stated as one). The cause holds for a part whose predicted error lies beyond the
    negligible effect in the claimed direction. The 0.25 m model fills its own cells at any step,
    so the step cannot explain its parts.

    Parameters
    ----------
    result : dict or None
        The experiment's result.
    misses : list of tuple
        ``(cell size, scenario, metric, sign, mean error)`` of each part that disagrees.
    coarse_errors : dict
        ``(scenario, metric)`` → the 0.25 m model's mean error (None where absent).
    """
    step_cause = "the TLS angular step: 0.1° in the embedded forest's scans, 0.017° in the study's"
    rows = _step_rows(result, "fill")
    if len(rows) < 2:
        return _step_untested(" with fill")
    coarse_step, fine_step = max(rows), min(rows)
    margin = cl.NEGLIGIBLE_HEIGHT.value
    fills, preds, explained, unexplained = [], [], [], []
    for size, sc, metric, sign, mean in misses:
        key = f"{float(size):g}"
        name = f"{key} m {sc} {metric}"
        a, b = rows[coarse_step]["fill"].get(key), rows[fine_step]["fill"].get(key)
        e_c = coarse_errors.get((sc, metric))
        if (key == _COARSE_KEY or a is None or b is None or e_c is None
                or not all(np.isfinite(v) for v in (a, b, e_c)) or a >= 1.0):
            unexplained.append(name)
            continue
        text = (f"{key} m cells fill {100 * a:.0f} % of the 0.25 m cells' volume at {coarse_step:g}°, "
                f"{100 * b:.0f} % at {fine_step:g}°")
        if text not in fills:
            fills.append(text)
        pred = mean + (b - a) / (1.0 - a) * (e_c - mean)
        good = bool(sign * pred > margin)
        preds.append(f"{name} {mean:+.2f} → {pred:+.2f} m")
        (explained if good else unexplained).append(name)
    text = _step_heading(result) + ("; ".join(fills) if fills else "no fill for these cell sizes")
    if preds:
        text += ("; mean errors moved towards the 0.25 m model's by the fill gained (a linear interpolation): "
                 + ", ".join(preds) + f" (negligible: ±{margin:g} m)")
    if explained:
        cause = (f"{step_cause}: at the study's step the finer fixed models fill more of the crown and are more "
                 f"opaque; the predicted errors of {', '.join(explained)} lie beyond the negligible effect as the "
                 f"study finds")
        if unexplained:
            cause += f"; not established for {', '.join(unexplained)}"
        return cause, text
    return ("not established: the experiment has no fill for these cell sizes" if not fills else
            f"not established: the fill gained at the study's step does not move {', '.join(unexplained)} "
            f"beyond the negligible effect"), text


def _cog_cause(result, shift_result, missing, parts_result=None) -> tuple[str, str]:
    """Cause and experiment of F4's disagreeing parts from the CoG-shift experiment and the TLS
    points' centre of gravity in the 0.25 m cells at the embedded forest's and the study's step.

    From the CoG-shift experiment (:mod:`vlsforest.experiments.cog_shift`), with 95 % intervals
    over the trees (t, n − 1 degrees of freedom): (1) the cubes a part's returns come from do not
    move down (``hmean``, ``height``) or in (``cpa``): the change the carried returns predict is
    not below zero (its interval reaches zero); (2) the change is too small to resolve: the
    predicted change lies below zero, the per-tree difference simulated − predicted is not
    significant (its interval holds zero), so the simulations follow the cubes, and only the
    simulated change's own interval reaches zero; (3) what the pulses reach: the simulated
    change departs from the prediction and the reached change (the shifted model's returns
    carried back to the unshifted cubes, less the unshifted model's returns) lies above zero:
    the shift changes which cubes and faces the pulses end on (with, where significant, the
    change of the share of returns on the columns' top cubes and of the cubes' cover seen from
    above). A part whose simulated change departs from the prediction without a reached change
    above zero stays unexplained by it. From the step experiment, (4) the TLS
    angular step: at the study's finer step the points' centre of gravity lies lower in the cells
    (and nearer the stem axis) than at ours; the step experiment supports it for the height parts
    when the vertical offset at the finest step lies below zero by more than twice its standard
    error and below the coarsest step's by more than twice their combined standard error; for
    ``cpa`` the same of the radial offset. The multiple-return share has no such link. From the
    CoG-parts experiment (:mod:`vlsforest.experiments.cog_parts`), for the parts the causes above
    leave: (5) the shift's two parts act against each other: the vertical part alone lowers the
    metric (95 % interval below zero) and the horizontal part alone raises it (above zero).
    """
    still = list(missing)
    causes, texts = [], []
    links = {"hmean": "z", "height": "z", "cpa": "radial"}
    if shift_result:
        summ = shift_result.get("summary") or {}
        still_moving, too_small, reached, parts = [], [], [], []
        for part in missing:
            sc, metric = part.split()[0], part.split()[-1]
            v = (summ.get(sc) or {}).get(metric) or {}
            p, sim, diff = v.get("predicted"), v.get("simulated"), _mean_interval(v.get("difference"))
            ci = _mean_interval(p)
            if ci is None:
                continue
            unit = _unit(metric)
            text = (f"{part} predicted {p['mean']:+.3f} {unit} (95 % CI {ci[0]:+.3f} to {ci[1]:+.3f}), "
                    f"simulated {sim['mean']:+.3f} {unit}")
            if diff is not None:
                text += f" (simulated − predicted 95 % CI {diff[0]:+.3f} to {diff[1]:+.3f})"
            reach = _mean_interval(v.get("reached"))
            if reach is not None:
                text += (f", reached {v['reached']['mean']:+.3f} {unit} "
                         f"(95 % CI {reach[0]:+.3f} to {reach[1]:+.3f})")
            parts.append(text)
            if ci[1] >= 0:
                still_moving.append(part)
            elif diff is not None and diff[0] <= 0 <= diff[1]:
                too_small.append(part)
            elif reach is not None and reach[0] > 0:
                reached.append(part)
        n = len(shift_result.get("trees", []))
        surf, every = shift_result.get("surface") or {}, shift_result.get("all_cubes") or {}
        share = ", ".join(f"{sc} {100 * v['mean']:.0f} %" for sc, v in (shift_result.get("on_cubes") or {}).items()
                          if np.isfinite(v.get("mean", math.nan)))
        texts.append(f"CoG-shift experiment ({n} target trees, the run's own files; the unshifted model's returns "
                     f"carried along with their cubes" + (f": {share} of them from a cube" if share else "")
                     + f"): the columns' top cubes move {100 * surf.get('mean', math.nan):+.1f} cm vertically, "
                     f"all cubes {100 * every.get('mean', math.nan):+.1f} cm (means over the trees)"
                     + ("; " + "; ".join(parts) if parts else "") + _reach_text(shift_result))
        if still_moving:
            causes.append("the cubes the returns come from: the CoG shift does not move the cubes these parts' "
                          "returns come from down or in beyond the trees' spread (the 95 % interval of the change "
                          f"they predict reaches zero; {', '.join(still_moving)})")
        if too_small:
            causes.append("a change smaller than the trees' spread resolves: the cubes these parts' returns come "
                          "from move down or in, the simulations follow them, and only the simulated change's own "
                          f"95 % interval still reaches zero ({', '.join(too_small)})")
        if reached:
            causes.append("what the pulses reach: the shifted model's own returns, carried back to where the "
                          "unshifted cubes lie, already raise these parts (the 95 % interval of the reached change "
                          f"lies above zero; {', '.join(reached)}): the shift changes which cubes and faces the "
                          "pulses end on, not only where the cubes lie"
                          + _reach_why(shift_result, sorted({p.split()[0] for p in reached})))
        still = [m for m in still if m not in still_moving and m not in too_small and m not in reached]
    rows = _step_rows(result, "cog_offset")
    if len(rows) >= 2:
        coarse_step, fine_step = max(rows), min(rows)
        a, b = rows[coarse_step]["cog_offset"], rows[fine_step]["cog_offset"]

        def lower(kind):
            m_a, se_a, m_b, se_b = a[f"{kind}_m"], a[f"{kind}_se_m"], b[f"{kind}_m"], b[f"{kind}_se_m"]
            if not all(np.isfinite(v) for v in (m_a, se_a, m_b, se_b)):
                return False
            return bool(m_b + 2 * se_b < 0 and m_b - m_a + 2 * math.hypot(se_a, se_b) < 0)

        by_step = [m for m in still if m.split()[-1] in links and lower(links[m.split()[-1]])]
        texts.append(_step_heading(result) + "the points' centre of gravity in the filled 0.25 m cells lies "
                     + "; ".join(f"{100 * r['cog_offset']['z_m']:+.1f} ± {100 * r['cog_offset']['z_se_m']:.1f} cm "
                                 f"vertically, {100 * r['cog_offset']['radial_m']:+.1f} ± "
                                 f"{100 * r['cog_offset']['radial_se_m']:.1f} cm radially at {s:g}° "
                                 f"({r['cog_offset']['n_cells']} cells)"
                                 for s, r in sorted(rows.items(), reverse=True))
                     + " (mean ± standard error; negative: low in the cell, towards the stem)")
        if by_step:
            causes.append(f"the TLS angular step: at the study's step the points' centre of gravity lies lower in "
                          f"the cells (or nearer the stem), so the CoG shift lowers (or draws in) the cubes: "
                          f"{', '.join(by_step)}")
            still = [m for m in still if m not in by_step]
    if parts_result and still:
        against, parts = [], []
        summ = parts_result.get("summary") or {}
        for part in still:
            sc, metric = part.split()[0], part.split()[-1]
            v = (summ.get(sc) or {}).get(metric) or {}
            ci = {k: _mean_interval(v.get(k)) for k in ("vertical", "horizontal", "whole")}
            if any(c is None for c in ci.values()):
                continue
            nd = 2 if metric == "multi_return_pct" else 3
            parts.append(f"{part}: " + ", ".join(
                f"{name} {v[k]['mean']:+.{nd}f} {_unit(metric)} (95 % CI {ci[k][0]:+.{nd}f} to {ci[k][1]:+.{nd}f})"
                for k, name in (("vertical", "vertical part alone"), ("horizontal", "horizontal part alone"),
                                ("whole", "whole shift"))))
            if ci["vertical"][1] < 0 < ci["horizontal"][0]:
                against.append(part)
        n = len(parts_result.get("trees", []))
        if parts:
            texts.append(f"CoG-parts experiment ({n} target trees; the unshifted cubes moved by only the vertical "
                         f"or only the horizontal component of their CoG displacement and simulated with the run's "
                         f"surveys, seeds and region): " + "; ".join(parts))
        if against:
            causes.append("the shift's two parts act against each other: moving the cubes only down (or up) lowers "
                          "these parts, moving them only sideways raises them (the 95 % intervals of the parts "
                          f"alone lie below and above zero; {', '.join(against)})")
            still = [m for m in still if m not in against]
    if not texts:
        return ("not established: the cubes the returns come from and the TLS angular step are the candidates "
                "(untested in this run)",
                "CoG-shift and TLS angular-step experiments not run: `snakemake --cores 2 "
                "results/experiments/cog_shift.json results/experiments/tls_step.json`")
    if still:
        causes.append(("not established for " if causes else "not established: neither the cubes the returns "
                       "come from nor the centre of gravity at the study's step explains ") + ", ".join(still))
    return "; ".join(causes), "; ".join(texts)


def _mean_interval(v):
    """The 95 % interval (t, n − 1 degrees of freedom) of a mean ``{mean, se, n}``; None without one."""
    from scipy.stats import t as student_t

    if not v or v.get("n", 0) < 2 or not np.isfinite(v.get("se", math.nan)):
        return None
    half = float(student_t.ppf(0.975, v["n"] - 1)) * v["se"]
    return v["mean"] - half, v["mean"] + half


def _above_zero(v) -> bool:
    """Whether a mean's 95 % interval lies above zero."""
    ci = _mean_interval(v)
    return ci is not None and ci[0] > 0


def _reach_text(shift_result) -> str:
    """The CoG-shift experiment's shares of returns on the columns' top cubes and the cubes'
    cover in vertical view, unshifted → shifted ('' where the result has neither)."""
    out = []
    shares = shift_result.get("top_share") or {}
    if shares:
        out.append("returns on the columns' top cubes " + ", ".join(
            f"{sc} {100 * v['base']['mean']:.0f} → {100 * v['shifted']['mean']:.0f} %" for sc, v in shares.items()))
    cover = shift_result.get("cover") or {}
    if cover:
        out.append(f"the cubes cover {cover['base_m2']['mean']:.1f} → {cover['shifted_m2']['mean']:.1f} m² in "
                   f"vertical view ({cover['change_pct']['mean']:+.0f} ± {cover['change_pct']['se']:.0f} %)")
    return ("; " + "; ".join(out) + " (unshifted → shifted, means over the trees)") if out else ""


def _reach_why(shift_result, scenarios) -> str:
    """What the CoG-shift experiment shows of where the shifted model's pulses end: more of them
    on the columns' top cubes, and the columns' cubes, moved apart, covering more of the crown
    seen from above (each only where its 95 % interval lies above zero)."""
    shares = shift_result.get("top_share") or {}
    up = [f"{sc} {100 * shares[sc]['change']['mean']:+.1f} pp" for sc in scenarios
          if sc in shares and _above_zero(shares[sc].get("change"))]
    cover = (shift_result.get("cover") or {}).get("change_pct")
    out = ""
    if up:
        out += f"; more of them end on the columns' top cubes ({', '.join(up)})"
    if _above_zero(cover):
        out += (f"{', and' if up else ';'} the columns' cubes, moved apart, cover more of the crown seen from "
                f"above ({cover['mean']:+.0f} %)")
    return out


def _group_fill_cause(result, sizes) -> tuple[str, str]:
    """Cause and experiment of F3b from the fill per species group at both TLS steps.

    The proposed cause: at the study's finer step the fixed models of both groups fill their
    crowns more alike, so the porosity contrast that gives conifers more multiple returns fades.
    The contrast of a cell size is the conifers' fill over the broadleaf trees'; the experiment
    supports the cause for a size whose contrast lies nearer 1 (in ratio) at the finest step.
    """
    rows = _step_rows(result, "fill")
    if len(rows) < 2 or not all({"conifer", "broadleaf"} <= set(r.get("groups", {})) for r in rows.values()):
        return _step_untested(" with conifer and broadleaf targets")
    coarse_step, fine_step = max(rows), min(rows)

    def contrast(step, key):
        g = rows[step]["groups"]
        c, b = g["conifer"]["fill"].get(key), g["broadleaf"]["fill"].get(key)
        return c / b if c is not None and b and np.isfinite(c) and np.isfinite(b) and c > 0 else math.nan

    parts, supported, untested, own_cells = [], [], [], []
    for size in sizes:
        key = f"{float(size):g}"
        if key == _COARSE_KEY:
            own_cells.append(f"{key} m")
            continue
        a, b = contrast(coarse_step, key), contrast(fine_step, key)
        if not (np.isfinite(a) and np.isfinite(b)):
            untested.append(f"{key} m")
            continue
        parts.append(f"{key} m: conifer / broadleaf fill {a:.2f} at {coarse_step:g}°, {b:.2f} at {fine_step:g}°")
        if abs(math.log(b)) < abs(math.log(a)):
            supported.append(f"{key} m")
    trees = ", ".join(f"{v['n_trees']} {g}" for g, v in sorted(rows[fine_step]["groups"].items()))
    text = _step_heading(result, trees) + ("; ".join(parts) if parts else "no fill contrast")
    rest = f"; {', '.join(untested + own_cells)}: not established" if untested or own_cells else ""
    if untested:
        text += f"; no fill per group for {', '.join(untested)}"
    if own_cells:
        text += f"; not testable by the step: {', '.join(own_cells)} (the 0.25 m model fills its own cells)"
    if parts and len(supported) == len(parts):
        return (f"the TLS angular step for {', '.join(supported)}: at the study's step the fixed models of conifers "
                f"and broadleaf trees fill their crowns more alike, so the porosity contrast behind the difference "
                f"fades{rest}", text)
    if supported:
        return (f"partly the TLS angular step: the groups' fill contrast fades at the study's step for "
                f"{', '.join(supported)} only{rest}", text)
    return ("not established: the groups' fill contrast does not fade at the study's step" if parts else
            "not established: the experiment has no fill per group for these cell sizes", text)


def _outline_untested() -> tuple[str, str]:
    return ("not established: the models' own crown outlines are the candidate (untested in this run)",
            "crown-outline experiment not run: `snakemake --cores 2 results/experiments/crown_outline.json`")


def _outline_heading(result) -> str:
    n = len({(r["plot"], r["tree_id"]) for r in result.get("trees", [])})
    return f"crown-outline experiment ({n} target trees, the run's own files): "


def _outline_cause(result, coarse, missing) -> tuple[str, str]:
    """Cause and experiment of F1's disagreeing parts from the crown-outline experiment.

    The experiment splits the coarse model's mean CPA error per scenario into the model's own
    outline against the reference's, what the simulation does not see of it, and the simulated
    crown base (:mod:`vlsforest.experiments.crown_outline`; the three add up to the error). The
    study's mechanism lowers the CPA (occlusion, a raised crown base); the cubes' outline raises
    it. For a CPA part that is no underestimation, the outline is the cause where it is wider than
    the reference's and larger than the two losses together. For a CBH part the experiment's split
    of the CBH error (the model's own crown base, what the simulation sees of it) is stated; it
    names no cause.
    """
    cpa = [sc for sc, m in missing if m == "cpa"]
    other = [f"{sc} {m.upper()}" for sc, m in missing if m != "cpa"]
    if not cpa:
        return NO_EXPERIMENT, ""
    if not result:
        return _outline_untested()
    summ = (result.get("summary") or {}).get(coarse, {})
    cbh_parts = []
    for sc, m in missing:
        c = (summ.get(sc) or {}).get("cbh")
        if m == "cbh" and c:
            cbh_parts.append(f"{sc}: CBH error {c['error']['mean']:+.2f} m = the model's own crown base "
                             f"{c['own_base']['mean']:+.2f}, seen {c['seen_base']['mean']:+.2f}")
    parts, explained, unexplained = [], [], []
    for sc in cpa:
        v = summ.get(sc)
        if not v:
            unexplained.append(sc)
            continue
        o, u, b, err = (v[k]["mean"] for k in ("outline", "unseen", "base", "error"))
        parts.append(f"{sc}: CPA error {err:+.2f} m² = the model's own outline {o:+.2f} (against the reference's "
                     f"{v['reference_m2']:.1f} m²), unseen {u:+.2f}, the simulated crown base {b:+.2f}")
        (explained if (o > 0 and o > -(u + b)) else unexplained).append(sc)
    exp = _outline_heading(result) + "; ".join(parts + cbh_parts) + " (means over the trees)"
    cause = ""
    if explained:
        cause = (f"the 0.25 m cubes widen the crown outline (each cube reaches up to a cell beyond the TLS points "
                 f"that filled it) by more than occlusion and the raised crown base remove ({', '.join(explained)})")
    if unexplained:
        cause = (cause + "; " if cause else "") + f"not established for {', '.join(unexplained)} CPA"
    if other:
        cause += f"; not established for {', '.join(other)}"
    return cause, exp


def _accuracy_outline_cause(result, t5, methods, gaps=()) -> tuple[str, str]:
    """Cause and experiment of a Table 5 accuracy-order disagreement from the crown-outline experiment.

    The CPA part of the accuracy follows the models' own outlines where the order of their mean
    absolute outline error (model outline − reference CPA, per tree) over ``methods`` is the order
    of their CPA MAE; the CBH part follows the models' own crown bases where the order of their
    mean absolute own-base error (the model's own CBH − the reference's, per tree) is the order of
    their CBH MAE. Where it does not, ``gaps`` test the trees' sampling noise: per other method
    ``(method, the study ranks methods[0] more accurate, Effect of |methods[0]'s CBH error| − |its|
    per tree)``; a gap against the study's order is noise where its 95 % interval holds zero.
    """
    if not result:
        return _outline_untested()
    trees = result.get("trees", [])
    cpa = _order_by_own(trees, t5, methods, "cpa_model", "cpa_ref", "cpa_mae_m2")
    if cpa is None:
        cause, exp = ("not established: the experiment has no outline for these methods",
                      _outline_heading(result) + "no outline of " + ", ".join(methods))
    else:
        same, own, mae = cpa
        exp = (_outline_heading(result) + "mean |own outline − reference CPA| "
               + ", ".join(f"{m} {v:.1f} m²" for m, v in own) + "; CPA MAE "
               + ", ".join(f"{m} {v:.1f} m²" for m, v in mae))
        cause = ("CPA: the models' own crown outlines set the order (each model's CPA error ranks as far as its "
                 "own outline lies from the reference's)" if same
                 else "not established: the CPA order does not follow the models' own outlines")
    cbh = _order_by_own(trees, t5, methods, "cbh_model", "cbh_ref", "cbh_mae_m")
    if cbh is None:
        return cause + "; CBH: not tested", exp
    same, own, mae = cbh
    exp += ("; mean |own crown base − reference CBH| " + ", ".join(f"{m} {v:.2f} m" for m, v in own)
            + "; CBH MAE " + ", ".join(f"{m} {v:.2f} m" for m, v in mae))
    if same:
        return cause + ("; CBH: the models' own crown bases set the order (each model's CBH error ranks as far as "
                        "its own crown base lies from the reference's)"), exp
    c, x = _cbh_gap_cause(methods[0], gaps)
    return cause + "; CBH: " + c, exp + ("; " + x if x else "")


def _cbh_gap_cause(me, gaps) -> tuple[str, str]:
    """The CBH part of an accuracy-order disagreement the crown bases leave: the trees' sampling noise?

    Each gap is ``(other method, the study ranks me more accurate, Effect of |me's CBH error| −
    |other's| per tree)``. A gap against the study's order whose 95 % interval holds zero is not
    told apart from no gap by the run's trees; where every gap against the order is such, the
    trees' sampling noise explains the CBH part.
    """
    tested = [(o, better, e) for o, better, e in gaps if e is not None]
    if not tested:
        return "not established: the CBH order does not follow the models' own crown bases", ""
    against = [(o, e) for o, better, e in tested if (e.mean > 0) == better and e.mean != 0]
    resolved = [o for o, e in against if not e.lo <= 0.0 <= e.hi]
    exp = ("CBH MAE gap over the target trees (paired bootstrap, per tree the mean over the scenarios): "
           + "; ".join(f"{me} − {o}: {e.text('m')}" for o, _, e in tested))
    if not against:
        return "in the study's order against " + ", ".join(o for o, _, _ in tested), exp
    if not resolved:
        return ("the trees' sampling noise: the CBH MAE gaps against the study's order ("
                + ", ".join(f"{me} − {o}" for o, _ in against)
                + ") are not told apart from zero (their 95 % intervals hold 0)"), exp
    return ("not established: the CBH order does not follow the models' own crown bases, and the trees resolve "
            + ", ".join(f"{me} − {o}" for o in resolved) + " beyond their sampling noise (a 95 % interval without 0)"), exp


def _order_by_own(trees, t5, methods, own_key, ref_key, mae_col):
    """Whether ``methods`` rank by their mean |own − reference| (per tree) as by ``t5[mae_col]``.

    Returns ``(same order, [(method, mean |own − ref|)] ascending, [(method, MAE)] ascending)``,
    or None when fewer than two methods have both.
    """
    own = {}
    for m in methods:
        v = [abs(r[own_key] - r[ref_key]) for r in trees if r["method"] == m and own_key in r]
        v = [x for x in v if np.isfinite(x)]
        if v:
            own[m] = float(np.mean(v))
    have = [m for m in methods if m in own and np.isfinite(t5.loc[m, mae_col])]
    if len(have) < 2:
        return None
    by_mae = sorted(have, key=lambda m: t5.loc[m, mae_col])
    by_own = sorted(have, key=lambda m: own[m])
    return by_mae == by_own, [(m, own[m]) for m in by_own], [(m, float(t5.loc[m, mae_col])) for m in by_mae]


def _f6_cause(shift_room, reseed, missing, seed: int) -> tuple[str, str]:
    """Cause and experiment of F6's disagreeing parts from the shift-room and reseed experiments.

    ``missing``: ``(scenario, metric, margin, effect)`` of each part whose change under the random
    shift reaches beyond the negligible effect. The shift-room experiment is asked first
    (:func:`_shift_room_parts`); the parts it leaves go to the reseed experiment
    (:func:`_reseed_parts`).
    """
    names = [f"{sc} {metric}" for sc, metric, _, _ in missing]
    if shift_room:
        room, left, exp = _shift_room_parts(shift_room, [(sc, metric) for sc, metric, _, _ in missing])
    else:
        room, left = [], names
        exp = "shift-room experiment not run: `snakemake --cores 2 results/experiments/shift_room.json`"
    noise, texts = [], []
    rest = [part for part, name in zip(missing, names) if name in left]
    if rest and reseed:
        noise, n, reseed_exp = _reseed_parts(reseed, rest, seed)
        exp += "; " + reseed_exp
    elif rest:
        exp += "; reseed experiment not run: `snakemake --cores 2 results/experiments/reseed.json`"
    unexplained = [n for n in left if n not in noise]
    if room:
        texts.append(f"the scaled cubes' size: the shift moves a cube within the room its cell leaves, and the "
                     f"change shrinks as the cubes grow ({', '.join(room)}); the study's cube sizes are not "
                     f"published, so whether its cubes left the shift less room is not tested")
    if noise:
        texts.append(f"the run's own noise ({', '.join(noise)}): simulated again with only its random draws changed, "
                     f"the unshifted model's metric moves on some trees so that its interval, too, reaches beyond the "
                     f"tolerance, while the shift's change is not told apart from zero: {n} trees cannot show "
                     f"\"no change\" within the tolerance of this metric")
    if unexplained:
        if shift_room or texts:
            texts.append(f"not established for {', '.join(unexplained)}")
        elif reseed:
            texts.append(f"not established for {', '.join(unexplained)}: the run's own noise does not explain it; "
                         f"the scaled cubes' size is the other candidate (untested in this run)")
        else:
            texts.append("not established: the scaled cubes' size is the candidate (untested in this run)")
    return "; ".join(texts), exp


def _shift_room_parts(result, missing) -> tuple[list, list, str]:
    """The parts of F6 the shift-room experiment explains, those it leaves, and its text.

    A part is explained by the cubes' size where, across the target trees, its change shrinks as
    the cubes grow: the least-squares slope of the change on the mean cube side has the opposite
    sign of the mean change and its 95 % interval (t, n − 2 degrees of freedom) excludes zero.
    """
    from scipy.stats import t as student_t

    summ = result.get("summary") or {}
    explained, unexplained, parts = [], [], []
    sides = {}
    for sc, metric in missing:
        v = (summ.get(sc) or {}).get(metric)
        if not v:
            unexplained.append(f"{sc} {metric}")
            continue
        f, mean = v["fit"], v["change"]["mean"]
        if f["n"] < 3 or not np.isfinite(f["slope_se"]):
            unexplained.append(f"{sc} {metric}")
            continue
        half = float(student_t.ppf(0.975, f["n"] - 2)) * f["slope_se"]
        lo, hi = f["slope"] - half, f["slope"] + half
        shrinks = np.sign(f["slope"]) == -np.sign(mean) and (lo > 0 or hi < 0)
        (explained if shrinks else unexplained).append(f"{sc} {metric}")
        unit = _unit(metric)
        groups = ", ".join(f"{g} {gv['fit']['r']:+.2f}" for g, gv in sorted(v["groups"].items())
                           if np.isfinite(gv["fit"]["r"]))
        parts.append(f"{sc} {metric}: r = {f['r']:+.2f} with the cube side ({groups or 'no group fit'}), "
                     f"{f['slope'] / 100:+.2f} {unit} per cm (95 % CI {lo / 100:+.2f} to {hi / 100:+.2f})")
        for g, gv in v["groups"].items():
            sides[g] = gv["side_m"]
    n = len({(r["plot"], r["tree_id"]) for r in result.get("trees", [])})
    exp = (f"shift-room experiment ({n} target trees, the run's own files): mean cube side "
           + ", ".join(f"{g} {sides[g]:.3f} m" for g in sorted(sides) if np.isfinite(sides[g]))
           + f" in a {result.get('cell_m', 0.25):g} m cell; " + "; ".join(parts))
    return explained, unexplained, exp


def _reseed_changes(result, scenario: str, metric: str) -> np.ndarray:
    """Per target tree of the reseed experiment: the ``change`` it wrote (reseeded − run; NaN where missing)."""
    return np.asarray([((row.get("scenarios") or {}).get(scenario) or {}).get("change", {}).get(metric, math.nan)
                       for row in result.get("trees", [])], float)


def _reseed_parts(result, missing, seed: int) -> tuple[list, int, str]:
    """The parts of F6 the run's own noise explains, the reseed experiment's tree count, its text.

    A part is explained by the noise where (1) the reseed experiment's change (the same model
    simulated again with another seed, reseeded − the run's, over the target trees) has a 95 %
    interval that itself reaches beyond the part's negligible effect: with that many trees the
    metric cannot show a change within the tolerance even where nothing but the random draws
    changed; and (2) the shift's own change is not told apart from zero (its interval holds 0).
    """
    explained, parts = [], []
    n = len(result.get("trees", []))
    for sc, metric, margin, e in missing:
        name, unit = f"{sc} {metric}", _unit(metric)
        change = _reseed_changes(result, sc, metric)
        e0 = _effect(change, seed, "F6", "reseed", sc, metric)
        if e0 is None or not np.isfinite(margin):
            parts.append(f"{name}: no reseeded values")
            continue
        noisy = not _within(e0, margin)
        if noisy and e.lo <= 0.0 <= e.hi:
            explained.append(name)
        moved = change[np.isfinite(change) & (change != 0.0)]
        parts.append(f"{name}: reseeded − run {e0.text(unit)}, "
                     f"{'reaching beyond' if noisy else 'within'} ±{_fmt(margin)} {unit}; "
                     f"{len(moved)} of {e0.n} trees changed"
                     + (f", by up to {_fmt(float(np.abs(moved).max()))} {unit}" if len(moved) else "")
                     + f"; the shift's change {e.text(unit)}")
    exp = (f"reseed experiment ({n} target trees, {result.get('method', 'the unshifted model')} simulated again "
           f"with the seed + {result.get('seed_offset', '?')}): " + "; ".join(parts))
    return explained, n, exp


def _table5_rows(t5, roles: StudyRoles, mr_tests, scen, d1_ok, experiments, E: _Errors, seed: int) -> list[dict]:
    t5 = t5.set_index("method") if "method" in t5.columns else t5
    parts = {}  # study key -> configured method name
    for key in cl.TABLE5:
        name = roles.method("fixed", key[1]) if key[0] == "fixed" else roles.method("scaled", shift=key[1])
        if name is not None:
            parts[key] = name
    present = {k: n for k, n in parts.items() if n in t5.index}
    voxel_level = {"few": 0, "many": 1, "very many": 2}
    accuracy_level = {"low": 0, "rather low": 1, "medium": 2, "high": 3}
    direction = {"strongly underestimated": "underestimated", "underestimated": "underestimated",
                 "realistic": "realistic", "overestimated": "overestimated"}
    out = []
    for key, (complexity, voxels, penetration, accuracy) in cl.TABLE5.items():
        label = study_label(*key)
        me = parts.get(key)
        claim = (f"Table 5, {label}: model generation {complexity}; voxels: {voxels or 'not stated'}; "
                 f"penetration {penetration}; CBH/CPA accuracy {accuracy}.")
        ok, ev = [], []
        cause = experiment = ""
        if me is not None and me in t5.index:
            r = t5.loc[me]
            if voxels is not None and np.isfinite(r["voxel_ratio"]):
                lv = voxel_level[voxels]
                bad = [present[o] for o in present if o != key and cl.TABLE5[o][1] is not None
                       and voxel_level[cl.TABLE5[o][1]] != lv and np.isfinite(t5.loc[present[o], "voxel_ratio"])
                       and np.sign(r["voxel_ratio"] - t5.loc[present[o], "voxel_ratio"])
                       != np.sign(lv - voxel_level[cl.TABLE5[o][1]])]
                ok.append(not bad)
                ev.append(f"{me}: voxels {r['n_voxels']:.0f} ({_fmt(r['voxel_ratio'], 1)}× the fewest)"
                          + (f"; out of the study's order against {', '.join(bad)}" if bad else ""))
                if bad and not cause:
                    cause, experiment = _tls_step_cause(experiments.get("tls_step"))
            pen_ok = None
            if np.isfinite(r["mr_bias_pp"]):
                ours, want = r["penetration"], direction[penetration]
                good = ours == want
                extra = ""
                coarse_next = present.get(("fixed", 0.10))
                if penetration == "strongly underestimated" and coarse_next is not None \
                        and np.isfinite(t5.loc[coarse_next, "mr_bias_pp"]):
                    stronger = r["mr_bias_pp"] < t5.loc[coarse_next, "mr_bias_pp"]
                    good = good and stronger
                    extra = f"; {'more' if stronger else 'not more'} negative than {coarse_next}"
                ok.append(bool(good))
                pen_ok = bool(good)
                ev.append(f"{me}: penetration {ours} (mean multiple-return error {_fmt(r['mr_bias_pp'], 1)} pp "
                          f"against the recordings{extra})")
                # the same judged against the study's real shares (the experiment of cause D1)
                study_bias = _bias_against_study(mr_tests, me, roles, scen)
                if np.isfinite(study_bias):
                    cls_study = penetration_class(study_bias)
                    ev.append(f"{me}: against the study's real data: {cls_study} "
                              f"(mean multiple-return error {study_bias:+.1f} pp)")
                    if not pen_ok and not d1_ok:
                        cause = cause or _recording_cause()[0]
                        experiment = (experiment + "; " if experiment else "") + (
                            f"judged against the study's real shares: penetration {cls_study}, "
                            f"{'as' if cls_study == want else 'not as'} the study states")
            if np.isfinite(r["accuracy_error_pct"]):
                la = accuracy_level[accuracy]
                bad = [present[o] for o in present if o != key and accuracy_level[cl.TABLE5[o][3]] != la
                       and np.isfinite(t5.loc[present[o], "accuracy_error_pct"])
                       and (r["accuracy_error_pct"] < t5.loc[present[o], "accuracy_error_pct"])
                       != (la > accuracy_level[cl.TABLE5[o][3]])]
                ok.append(not bad)
                ev.append(f"{me}: CBH/CPA error {_fmt(r['accuracy_error_pct'], 1)} % (CBH MAE {_fmt(r['cbh_mae_m'])} m, "
                          f"CPA MAE {_fmt(r['cpa_mae_m2'], 1)} m²)"
                          + (f"; out of the study's order against {', '.join(bad)}" if bad else ""))
                if bad:
                    gaps = [(o, la > accuracy_level[cl.TABLE5[k][3]],
                             _effect(E.abs_gap(me, o, "cbh", scen), seed, "T5", me, o, "cbh"))
                            for k, o in present.items() if o in bad]
                    c, x = _accuracy_outline_cause(experiments.get("crown_outline"), t5, [me] + bad, gaps)
                    cause = (cause + "; " if cause else "") + c
                    experiment = (experiment + "; " if experiment else "") + x
            ev.append("model generation complexity: not measured")
        tol = ("penetration: " + cl.REALISTIC_PENETRATION.text() + f" is realistic ({cl.REALISTIC_PENETRATION.source}); "
               "voxels and accuracy: the study's order of the methods")
        out.append(_row(f"T5:{label}", claim, ok, ev, tol, cause, experiment))
    return out


def _bias_against_study(mr_tests, method, roles: StudyRoles, scen) -> float:
    """Mean of (simulated group mean − the study's real share) over the platform scenarios and groups."""
    d = []
    for sc in scen:
        r = mr_tests[(mr_tests["method"] == method) & (mr_tests["scenario"] == sc)]
        if r.empty:
            continue
        r = r.iloc[0]
        for g in ("conifer", "broadleaf"):
            v = float(r[f"mean_{g}"])
            if np.isfinite(v):
                d.append(v - cl.STUDY_REFERENCE_MULTI_RETURN[(roles.platforms[sc], g)])
    return float(np.mean(d)) if d else math.nan


def findings_table(findings: list[dict]) -> pd.DataFrame:
    """The findings as a table (``findings.csv``): one row per finding, evidence joined by `` | ``."""
    cols = ["id", "claim", "verdict", "tolerance", "cause", "experiment", "evidence"]
    return pd.DataFrame([{**{k: f[k] for k in cols[:-1]}, "evidence": " | ".join(f["evidence"])}
                         for f in findings], columns=cols)


def findings_markdown(findings: list[dict]) -> str:
    """Render :func:`evaluate_findings` as Markdown (``findings.md``)."""
    n_ok = sum(f["verdict"] == "agrees" for f in findings)
    n_bad = sum(f["verdict"] == "disagrees" for f in findings)
    n_na = sum(f["verdict"] == "not testable" for f in findings)
    lines = [
        "# Findings of Weiser et al. (2021) checked against our numbers",
        "",
        f"{n_ok} agree, {n_bad} disagree, {n_na} not testable. Verdicts are computed from the tables in this "
        f"folder (errors.csv, tests.csv, multireturn_ttest.csv, table5.csv) by the paper's own claims: a direction "
        f"beyond the metric's negligible effect with a {CI_LEVEL:.0%} bootstrap interval that excludes zero, "
        f"'nothing' as an interval within ± the negligible effect, a stated size within its tolerance; each "
        f"tolerance and its source in the paper is given per finding. A disagreement names a cause only where "
        f"an experiment tests it.",
        "",
    ]
    sections = [("Data", [f for f in findings if f["id"].startswith("D")]),
                ("Qualitative findings", [f for f in findings if f["id"].startswith("F")]),
                ("Table 5", [f for f in findings if f["id"].startswith("T5:")])]
    for title, items in sections:
        if not items:
            continue
        lines += [f"## {title}", ""]
        for f in items:
            lines.append(f"- **{f['id']}** {f['claim']} — **{f['verdict']}**")
            if f.get("tolerance"):
                lines.append(f"  - tolerance: {f['tolerance']}")
            for e in f["evidence"]:
                lines.append(f"  - {e}")
            if f.get("cause"):
                lines.append(f"  - cause: {f['cause']}")
            if f.get("experiment"):
                lines.append(f"  - experiment: {f['experiment']}")
        lines.append("")
    return "\n".join(lines)
