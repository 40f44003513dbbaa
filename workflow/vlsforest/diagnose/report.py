"""The diagnosis' report: the search's result as the JSON contract and a verdict in words.

The contract of the report: ``significant_mismatch``, ``mismatches``, ``effects``, ``accepted``,
plus the verdict in words, the group/tie-breaker reasoning, the fitted values with bootstrap
CIs, the minimum detectable effect per candidate and the cost; ``model`` (the accepted
candidates' values, as simulated: for a random process draw 0's fit,
``realisation_scatter.draw0_fit``, while its effect's ``parameters`` hold the estimate matched
with the mean of the draws) and ``beam_fwhm_mrad`` (the beam they make, major and minor
divergence at FWHM).
"""

from __future__ import annotations

import numpy as np

from vlsforest.diagnose import library as lib
from vlsforest.diagnose.features import FEATURES, STRATUM
from vlsforest.diagnose.search import ALPHA


def _nanstd(x):
    x = x[np.isfinite(x)]
    return float(x.std(ddof=1)) if len(x) > 1 else None


def clean(o):
    """``o`` as plain JSON values: string keys, lists, floats (non-finite ones as None), ints, bools."""
    if isinstance(o, dict):
        return {str(k): clean(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [clean(v) for v in o]
    if isinstance(o, (np.floating, float)):
        return None if not np.isfinite(o) else float(o)
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, np.bool_):
        return bool(o)
    return o


def mismatches(loc: dict) -> list:
    """The observables that differ (BH q < α), most significant first, each with its words."""
    mism = []
    for j, f in enumerate(FEATURES):
        if np.isfinite(loc["q"][j]) and loc["q"][j] < ALPHA:
            mism.append({"metric": f, "stratum": STRATUM[f], "mean_residual": float(loc["mean"][j]),
                         "ci95": [float(loc["ci_lo"][j]), float(loc["ci_hi"][j])], "q": float(loc["q"][j]),
                         "n_trees": int(loc["n"][j]),
                         "text": f"{f} ({STRATUM[f]}): real − simulated = {loc['mean'][j]:+.3g} "
                                 f"[{loc['ci_lo'][j]:+.3g}, {loc['ci_hi'][j]:+.3g}], q = {loc['q'][j]:.2g}"})
    mism.sort(key=lambda m: m["q"])
    return mism


def _notes(found: dict) -> dict:
    """Per accepted effect, what the verdict adds after its value: the beams an unseparated
    footprint group stands for, the beam an identified ellipse makes, the observable a fit rests
    on. Also completes the text of a footprint tie that was not separated."""
    effects, rounds, beam = found["effects"], found["rounds"], found["beam_fwhm_mrad"]
    note = {}
    for e in effects:  # a footprint fit: the solid angle every member of the group would fit
        if "equivalent_circular_fwhm_mrad" not in e:
            continue
        tie, eq = rounds[e["stage"] - 1]["tie"], e["equivalent_circular_fwhm_mrad"]
        if tie is not None and not tie["resolved"] and tie["winner"] == e["name"]:
            tie["text"] += (f"; it fits a beam of the solid angle of a {eq:.3g} mrad (FWHM) circle, i.e. any "
                            f"beam with major × minor = {eq * eq:.3g} mrad² (the members' aspect ratios are "
                            f"not identified)")
            note[e["name"]] = (f" (for the footprint group: a beam of major × minor = {eq * eq:.3g} mrad² "
                               f"at FWHM; ellipse and circle not separated)")
    if "elliptical_footprint" in found["accepted"]:  # its aspect identified: the group stands for this beam
        note.pop("beam_divergence", None)
        note["elliptical_footprint"] = f" (the beam: {beam[0]:.3g} × {beam[1]:.3g} mrad at FWHM)"
    for e in effects:  # a fit that rests on one observable says so, with the value without it
        if e.get("accepted") and e.get("rests_on"):
            note[e["name"]] = note.get(e["name"], "") + "".join(
                f" ({par}: {r['observable']} carries {100 * r['weight_share']:.0f} % of the fit's weight; "
                f"{r['without_it']:.3g} without it)" for par, r in e["rests_on"].items())
    return note


def verdict(found: dict, effects: list, note: dict) -> str:
    """The verdict in words: no mismatch, a mismatch not attributable, or the accepted effects
    with their first searched parameter's value and CI, the notes and the observables that got
    worse."""
    accepted = found["accepted"]
    if not found["significant"]:
        return "no significant mismatch"
    if not accepted:
        return "mismatch found, not attributable"

    def fitted(e):  # the first searched parameter's value and CI
        c = lib.CANDIDATES[e["name"]]
        par = c.params[0].name
        x, (lo, hi) = c.coords(e["parameters"])[par], e["ci95"][par]
        return f" [{par} = {x:.3g}, 95 % CI {lo:.3g}–{hi:.3g}]"

    eff_of = {e["name"]: e for e in effects if e.get("accepted")}
    out = "mismatch explained by " + " + ".join(a + fitted(eff_of[a]) + note.get(a, "") for a in accepted)
    worse = sorted({m for e in effects if e.get("accepted") for m in e.get("worse_metrics", [])})
    if worse:
        out += f" (held-out {', '.join(worse)} got worse: the voxel model's own error compensated there)"
    return out


def assemble(setup, found: dict, cost: dict, oracle: dict | None = None) -> dict:
    """The report mapping of a search's result (:func:`.search.search`).

    Parameters
    ----------
    setup : setup.Setup
        Its ``scenario`` and plots' names label the report.
    found : dict
        The search's result (its ties' texts are completed here).
    cost : dict
        ``traced_simulations``, ``traces_read_back`` and ``seconds`` of the diagnosis.
    oracle : dict, optional
        A benchmark's comparison with the hidden truth (:func:`.truth.told_truth`).
    """
    rounds, loc, D0, final_D = found["rounds"], found["loc"], found["D0"], found["final_D"]
    effects = list(found["effects"])
    for r in (rounds[0]["ranking"] if rounds else []):  # the candidates of the first round not fitted
        if r["name"] not in {e["name"] for e in effects}:
            effects.append({"name": r["name"], "group": r["group"], "parameters": {},
                            "explained_fraction": r["explained_fraction"], "heldout_error_before": None,
                            "heldout_error_after": None, "p_value": None, "accepted": False,
                            "stage": None})
    beam = found["beam_fwhm_mrad"]
    rep = {
        "scenario": setup.scenario,
        "metric": "diagonal",  # explained fractions weigh each observable by 1 / its across-tree variance
        "plots": [p.name for p in setup.plots],
        "n_trees": found["n_trees"],
        "significant_mismatch": found["significant"],
        "global_p": loc["global_p"],
        "mismatches": mismatches(loc),
        "effects": effects,
        "accepted": found["accepted"],
        "model": found["model"],
        "beam_fwhm_mrad": [float(beam[0]), float(beam[1])],
        "verdict": verdict(found, effects, _notes(found)),
        "rounds": rounds,
        "minimum_detectable_effect": {r["name"]: r["mde"] for r in rounds[0]["ranking"]} if rounds else {},
        "residual_after": {f: (float(np.nanmean(final_D[:, j])) if np.isfinite(final_D[:, j]).any() else None)
                           for j, f in enumerate(FEATURES)},
        "residual_before": {f: (float(loc["mean"][j]) if np.isfinite(loc["mean"][j]) else None)
                            for j, f in enumerate(FEATURES)},
        "residual_sd": {f: _nanstd(D0[:, j]) for j, f in enumerate(FEATURES)},
        "oracle": oracle,
        "cost": cost,
    }
    return clean(rep)
