"""The diagnosis' search: locate a sim-vs-real mismatch, attribute it, fit the winner, check on held-out trees.

Steps (see docs/diagnosis.md):

1. **Locate** — per tree, real minus simulated observables (:mod:`.features`); per observable the
   mean residual with a bootstrap CI, Wilcoxon p and Benjamini–Hochberg q; a global sign-flip
   permutation test. ``significant_mismatch`` = global p < α or any q < α.
2. **Attribute** — each candidate's signature ``J_k`` = mean change of the observables when its
   parameter moves by a reference step (common random numbers: same pulses, same seed);
   projection of the mean residual on ``J_k`` (weights: 1 / mean square residual per
   observable) gives an amplitude and an explained fraction; physically impossible signs score 0;
   a penalty per parameter ranks simpler candidates first at equal fit. The leader must explain
   more than a signature unrelated to the residual would by chance (the 1 − α/K quantile of
   Beta(½, (m − 1)/2) for m observables and K candidates) and pass a matched-filter test
   across trees (Bonferroni over candidates). Members of a declared
   group (or signatures with |cos| > 0.9) that score within 0.1 of each other tie; the tie is
   broken on the group's separating observables and the report names them — or, when those do
   not separate the members either (explained fractions within 0.05), the report says so and the
   simplest member is fitted on behalf of the group.
3. **Model** — the winner's parameter(s) are fitted on a grid (one simulation per grid point,
   shared by all folds; several parameters by coordinate search; the ellipse along its aspect
   ratio at the solid angle of the beam simulated so far): each observable whose
   mean residual changes sign along the grid votes for its crossing, and the weighted median of
   the votes, interpolated between neighbouring votes, is the estimate
   (:func:`.stats.robust_fit`; observables dominated by errors the
   candidate cannot remove do not vote); k-fold across trees: each fold's value is fitted on
   the other trees and simulated for the held-out ones. The effect is accepted when the held-out per-tree error drops
   significantly (one-sided paired Wilcoxon); observables that get significantly worse (Holm)
   are named in the report and the verdict. For an accepted candidate whose simulation is one
   draw of a random process with few independent samples over a plot (trajectory noise:
   :attr:`.library.Candidate.realisations`), further draws are simulated at the fitted value and
   each is fitted as if it were the recording: the estimate is matched with the draws' mean
   amplitude instead of draw 0's alone (the simulation's draw then adds little scatter), and
   the scatter that remains — the recording's own draw's — widens the CI. So do the voters'
   own systematic errors: the larger of their disagreement beyond their sampling variances
   (:func:`.stats.crossing_votes`) and the bias allowance, which gives each voter a bias as
   large, in across-tree SDs, as those the fit leaves in the observables it did not use
   (:func:`.stats.bias_scale`; it covers a fit that rests on one observable, whose bias no
   disagreement shows); ``ci95_trees`` is the bootstrap over trees alone.
   Then a second effect is sought the same way on top of the first.

The search works on a study (:class:`.simulation.Study`, or any object with its ``sim``,
``residual``, ``pin``, ``keep``, ``has_trace``, ``real`` and ``survey``); :mod:`.report` puts
its result into words.
"""

from __future__ import annotations

import numpy as np

from vlsforest.diagnose import library as lib
from vlsforest.diagnose import stats as st
from vlsforest.diagnose.features import FEATURES
from vlsforest.errors import InputDataError

ALPHA = 0.05
PENALTY = 0.05          # explained-fraction penalty per parameter
TIE_MARGIN = 0.10       # scores closer than this tie within a group
TIE_RESOLVE = 0.05      # a tie is broken only if the separating observables differ by this much
DOMINANT_VOTE = 0.5     # a fit whose one observable carries more of the weight "rests on" it (reported)
MIN_EV = 0.05           # a candidate must explain at least this share of the mean residual
#                         (the reconstruction error of the voxel model is always there beside it)
MAX_EFFECTS = 2         # effects accepted one after another at most (stages of the attribution)

_merge = lib.merge


def _grid(par: lib.Param, lo: float, hi: float, base: float, n: int) -> np.ndarray:
    if par.integer:
        g = np.arange(int(np.ceil(lo)), int(np.floor(hi)) + 1, dtype=float)
        if len(g) > n:
            g = np.unique(np.round(np.linspace(lo, hi, n)))
        return g
    if par.log and lo > 0:
        g = np.geomspace(lo, hi, n)
    elif par.log and lo == 0:  # a wide prior from 0: zero, then log-spaced
        g = np.r_[0.0, np.geomspace(hi / 1000.0, hi, n - 1)]
    else:
        g = np.linspace(lo, hi, n)
    return np.unique(np.r_[g, base])


# ------------------------------------------------------------------------------------ the steps
def _attribute(study, base: dict, cands: list, D0: np.ndarray, w: np.ndarray, last: bool = True):
    """Signatures, projections, scores and groups of every candidate (relative to ``base``).

    Unless this is the ``last`` stage, the candidates' traces go to disk when they leave memory:
    when the stage accepts a stored-hit effect (threshold, window, noise, …), the next stage's
    signatures render the same traces again with the new baseline, and read them back instead of
    tracing them.
    """
    rbar = np.nanmean(D0, axis=0)
    project = st.project
    S0 = study.sim(base).reindex(study.real.index).to_numpy(float)
    steps = {c.name: c.step(c.current(study.survey, base), study.survey) for c in cands}
    study.keep([_merge(base, c.name, steps[c.name]) for c in cands], spill=not last)
    # simulate the candidates whose trace is still held first: a trace-side candidate traced last
    # in the previous round is not traced again after the others evicted it (same results)
    for c in sorted(cands, key=lambda c: not study.has_trace(_merge(base, c.name, steps[c.name]))):
        study.sim(_merge(base, c.name, steps[c.name]))
    rows, sigs = [], {}
    for c in cands:
        cur = c.coords(c.current(study.survey, base))
        p0 = c.params[0]
        lo = c.bounds(study.survey)[p0.name][0]
        pert = steps[c.name]
        S1 = study.sim(_merge(base, c.name, pert)).reindex(study.real.index).to_numpy(float)
        J = np.nanmean(S1 - S0, axis=0)  # common random numbers: same pulses and seed
        sigs[c.name] = J
        a, ev, cos = project(rbar, J, w)
        step = c.coords(pert)[p0.name] - cur[p0.name]
        implied = cur[p0.name] + a * step
        possible = bool(implied >= lo - 1e-9)  # below the lower bound: a physically impossible sign
        score = (ev if possible else 0.0) - PENALTY * len(c.params)
        t, p = st.amplitude_test(D0, J, w)
        rows.append({"name": c.name, "group": c.group, "amplitude": a, "explained_fraction": max(ev, 0.0),
                     "t": t, "p_matched": min(1.0, p * len(cands)),
                     "possible_sign": bool(possible), "implied": implied, "score": score,
                     "mde": st.mde(J, D0) * abs(step), "step": step})
    # significant (matched filter, Bonferroni over candidates) and physically possible first
    ranked = sorted(rows, key=lambda r: (not (r["p_matched"] < ALPHA and r["possible_sign"]), -r["score"]))
    names = [r["name"] for r in ranked]
    cosm = {(a, b): st.cosine(sigs[a], sigs[b], w) for a in names for b in names}
    return ranked, sigs, cosm


def tie_break(ranked, sigs, cosm, D0, w):
    """Resolve a tie between the leader and look-alikes on the group's separating observables."""
    lead = ranked[0]
    rivals = [r for r in ranked[1:] if (r["group"] == lead["group"] or abs(cosm[(lead["name"], r["name"])]) > 0.9)
              and lead["score"] - r["score"] < TIE_MARGIN and r["score"] > 0]
    if not rivals:
        return ranked, None
    # the separating observables of every group in the tie: a look-alike from another group is
    # told apart by its own group's observables as much as by the leader's
    groups = list(dict.fromkeys([lead["group"]] + [r["group"] for r in rivals]))
    tb = tuple(dict.fromkeys(f for g in groups for f in lib.TIE_BREAKERS.get(g, ())))
    idx = [FEATURES.index(f) for f in tb]
    mask = np.zeros(len(FEATURES))
    mask[idx] = 1.0
    rbar = np.nanmean(D0, axis=0)
    scored = []
    for r in [lead] + rivals:
        _, ev, _ = st.project(rbar, sigs[r["name"]], w * mask)
        scored.append((ev, r["name"]))
    scored.sort(key=lambda x: -x[0])
    resolved = len(scored) < 2 or scored[0][0] - scored[1][0] >= TIE_RESOLVE
    if resolved:
        winner = scored[0][1]
    else:  # the separating observables do not separate: the simplest member speaks for the group
        winner = min((n for _, n in scored), key=lambda n: (len(lib.CANDIDATES[n].value_keys), n != lead["name"]))
    where = (f"{lead['group']} group" if len(groups) == 1 else
             "tie of look-alikes from the " + " and ".join(groups) + " groups")
    note = {"group": lead["group"], "groups": groups, "members": [n for _, n in scored], "tie_breakers": list(tb),
            "explained_on_tie_breakers": {n: round(float(e), 3) for e, n in scored}, "winner": winner,
            "resolved": bool(resolved),
            "text": (f"{winner} wins the {where} on {', '.join(tb)}" if resolved else
                     f"the {where} ({', '.join(n for _, n in scored)}) is not separated by "
                     f"{', '.join(tb)}; the simplest member, {winner}, is fitted for the group")}
    if winner != lead["name"]:
        ranked = [r for r in ranked if r["name"] == winner] + [r for r in ranked if r["name"] != winner]
    return ranked, note


def fit(study, base: dict, cand: lib.Candidate, w: np.ndarray, folds: np.ndarray, n_grid: int,
         rng: np.random.Generator):
    """Grid fit of a candidate (coordinate search over its searched parameters, from the values
    ``base`` simulates).

    Returns the all-tree and per-fold values (as :meth:`Candidate.apply` takes them) and a
    mapping with ``votes`` (per searched
    parameter: observable → its crossing and its share of the weight; empty where the
    least-squares grid minimum was taken), ``rests_on`` (for a parameter whose fit rests on one
    observable, more than :data:`DOMINANT_VOTE` of the weight: that observable, its share and
    the value fitted without it), ``between_observables`` (per parameter: the crossings'
    ``scale_factor`` S — their disagreement beyond sampling, ≈ 1 when they agree — and the
    estimate's ``systematic_sd`` beyond sampling, on the log scale where ``log_scale``; the
    bias allowance's entries are added by :func:`_systematic_ci`), ``ci95_trees`` (the first
    searched parameter's 95 % CI from the bootstrap over trees; :func:`_systematic_ci` widens
    it), ``curve`` (the first parameter's grid and residuals, for :func:`_realisation_scatter`)
    and ``voters`` (the first parameter's voters' weight shares and bias shifts and every
    parameter's voters, for :func:`_systematic_ci`); the last two are not for the report."""
    start = cand.current(study.survey, base)
    cur = cand.coords(start)
    bounds = cand.bounds(study.survey)
    k = int(folds.max()) + 1
    per_fold = [dict(cur) for _ in range(k)]
    allv = dict(cur)
    curves, votes, rests_on, spread, used = {}, {}, {}, {}, set()
    for par in cand.params:
        lo, hi = bounds[par.name]
        if par.n_grid:  # its own grid, through the reference step (simulated for the signature)
            g = np.unique(np.r_[_grid(par, lo, hi, cur[par.name], par.n_grid),
                                cand.step_coords(start, study.survey)[par.name]])
        else:
            g = _grid(par, lo, hi, cur[par.name], n_grid if par is cand.params[0] else max(n_grid - 2, 3))
        Ds = []
        for v in g:
            val = dict(allv)
            val[par.name] = float(v)
            Ds.append(study.residual(_merge(base, cand.name, cand.values(start, val))))
        curves[par.name] = (g, Ds)
        lg = par.log and lo > 0
        allv[par.name], v, spread[par.name] = st.crossing_votes(g, Ds, w, lo, hi, lg, detail=True)
        total = sum(q for _, q in v.values())
        used |= set(v)
        if par is cand.params[0]:  # its voters' weight shares and bias shifts, for the bias allowance
            voters = {"shares": {j: q / total for j, (_, q) in v.items()} if total > 0 else {},
                      "bias_shift": spread[par.name].get("bias_shift", {})}
        votes[par.name] = {FEATURES[j]: {"crossing": r, "weight_share": q / total if total > 0 else 0.0}
                           for j, (r, q) in sorted(v.items(), key=lambda kv: -kv[1][1])}
        top = max(v, key=lambda j: v[j][1]) if total > 0 else None
        if top is not None and v[top][1] > DOMINANT_VOTE * total:  # the fit rests on one observable
            w_out = w.copy()
            w_out[top] = 0.0
            rests_on[par.name] = {"observable": FEATURES[top], "weight_share": v[top][1] / total,
                                  "without_it": st.robust_fit(g, Ds, w_out, lo, hi, lg)}
        for f in range(k):
            per_fold[f][par.name] = st.robust_fit(g, Ds, w, lo, hi, lg, rows=folds != f)
        if par.integer:
            allv[par.name] = float(round(allv[par.name]))
            for f in range(k):
                per_fold[f][par.name] = float(round(per_fold[f][par.name]))
    # bootstrap CI over trees of the (first) parameter from the grid curve
    par = cand.params[0]
    g, Ds = curves[par.name]
    lo, hi = bounds[par.name]
    n = len(folds)
    boot = []
    for _ in range(300):
        rows = rng.integers(0, n, n)
        boot.append(st.robust_fit(g, Ds, w, lo, hi, par.log and lo > 0, rows=rows))
    ci_trees = [float(np.percentile(boot, 2.5)), float(np.percentile(boot, 97.5))]
    between = {q.name: {"scale_factor": spread[q.name]["scale_factor"],
                        "systematic_sd": spread[q.name]["systematic_sd"],
                        "log_scale": bool(q.log and bounds[q.name][0] > 0)}
               for q in cand.params if spread.get(q.name)}
    return (cand.values(start, allv), [cand.values(start, v) for v in per_fold],
            {"votes": votes, "rests_on": rests_on, "between_observables": between,
             "ci95_trees": {par.name: ci_trees}, "curve": curves[par.name], "voters": dict(voters, used=used)})


def _systematic_ci(cand: lib.Candidate, survey: dict, allv: dict, fit_info: dict, voters: dict,
                   D_left: np.ndarray, w: np.ndarray) -> list:
    """The first searched parameter's 95 % CI: the bootstrap over trees (``ci95_trees``) widened,
    in quadrature, by the SD the voters' systematic errors give the estimate — the larger of two
    estimates of it. One is the votes' disagreement beyond sampling (``systematic_sd``,
    :func:`.stats.crossing_votes`), which sees such errors only where several voters of
    comparable precision disagree. The other is the bias allowance
    (:func:`.stats.bias_allowance`): the voters are taken to carry biases as large, in
    across-tree SDs, as those the fit leaves in the observables it did not use (``D_left``, the
    held-out residuals; β from :func:`.stats.bias_scale`), which also covers a fit that rests on
    one observable. Records ``bias_scale``, ``bias_sd`` and ``n_unused`` in
    ``fit_info["between_observables"]``."""
    par = cand.params[0]
    lo, hi = cand.bounds(survey)[par.name]
    log = bool(par.log and lo > 0)
    rest = [k for k in range(len(FEATURES)) if w[k] > 0 and k not in voters["used"]]
    beta = st.bias_scale(D_left, rest)
    sd = st.bias_allowance(beta, voters["shares"], voters["bias_shift"])
    row = fit_info["between_observables"].setdefault(par.name, {"scale_factor": None, "systematic_sd": 0.0,
                                                                 "log_scale": log})
    row.update(bias_scale=beta, bias_sd=sd, n_unused=len(rest))
    return _widened(fit_info["ci95_trees"][par.name], cand.coords(allv)[par.name], max(sd, row["systematic_sd"]),
                    log, lo, hi)


def _widened(ci: list, x: float, sd: float, log: bool, lo: float, hi: float) -> list:
    """``ci`` about ``x`` with ``± 1.96 sd`` added in quadrature on each side (on the log scale
    for ``log``), within the bounds."""
    if not sd > 0:
        return list(ci)
    to, back = (np.log, np.exp) if log and x > 0 and ci[0] > 0 else (float, float)
    t, a, b = to(x), to(ci[0]), to(ci[1])
    return [float(max(lo, back(t - np.hypot(max(t - a, 0.0), 1.96 * sd)))),
            float(min(hi, back(t + np.hypot(max(b - t, 0.0), 1.96 * sd))))]


def _realisation_scatter(study, base: dict, cand: lib.Candidate, allv: dict, curve: tuple,
                         w: np.ndarray, n: int) -> dict:
    """The scatter of a random candidate's fit between draws of its process, and the fit
    averaged over the draws.

    Draws 1 … ``n`` of the process are simulated at the fitted value ``x`` (``allv``); each is
    taken as if it were the recording and fitted on the all-tree grid ``curve`` (draw 0's
    simulations) the way the diagnosis fits (:func:`.stats.robust_fit`, weights ``w``). Draw r
    fits at ``x · a_r / a_0``, ``a`` being the draws' amplitudes (how strongly each moves the
    observables), so ``c = (1, x_1 / x, …, x_n / x)`` are ``n + 1`` draws' amplitudes up to one
    factor, and their relative SD (``ddof = 1``) is that of one draw (``relative_sd_one_draw``).
    Using draw 0 as one of the samples keeps this from depending on whether draw 0 happened to be
    a weak or a strong one.

    Draw 0's fit ``x`` matches the recording's draw with the simulation's draw 0: it is
    ``σ · a_real / a_0`` and carries both draws' scatter. Matched with the mean amplitude of
    the ``n + 1`` simulated draws instead, the estimate is ``x / mean(c)`` (``fitted_mean``):
    the simulation's part of the scatter shrinks by ``√(n + 1)``, the recording's own draw stays,
    so its relative SD is ``relative_sd_one_draw · √(1 + 1 / (n + 1))`` (``relative_sd``; the
    fit of draw 0 alone had ``√2`` times that of one draw). ``draw0_fit`` keeps ``x``, the value
    draw 0 needs to reproduce the recording, which the diagnosis goes on simulating.
    """
    par = cand.params[0]
    g, Ds = curve
    lo, hi = cand.bounds(study.survey)[par.name]
    x = cand.coords(allv)[par.name]
    vals = []
    for r in range(1, n + 1):
        Dr = study.residual(_merge(base, cand.name, dict(allv, realisation=r)))
        # draw r's simulation as the recording: (real − sim_0(g)) − (real − sim_r(x)) = sim_r(x) − sim_0(g)
        vals.append(st.robust_fit(g, [D - Dr for D in Ds], w, lo, hi, par.log and lo > 0))
    c = np.r_[1.0, np.asarray(vals) / x] if x > 0 else np.array([np.nan])
    ok = len(c) > 1 and np.isfinite(c).all() and np.mean(c) > 0
    one = float(np.std(c, ddof=1) / np.mean(c)) if ok else float("nan")
    mean_x = float(np.clip(x / np.mean(c), lo, hi)) if ok else float(x)
    return {"n": n, "fitted": [float(v) for v in vals], "draw0_fit": float(x),
            "mean_amplitude": float(np.mean(c)) if ok else float("nan"), "fitted_mean": mean_x,
            "relative_sd_one_draw": one, "relative_sd": float(one * np.sqrt(1.0 + 1.0 / len(c)))}



def _nanmean(x):
    x = x[np.isfinite(x)]
    return float(x.mean()) if len(x) else None


def search(study, cands: list, setup, log) -> dict:
    """Steps 1–3 (see the module docstring) on ``study`` with the candidates ``cands``.

    Parameters
    ----------
    study : simulation.Study
    cands : list of library.Candidate
    setup : setup.Setup
        Its ``seed`` (folds, bootstraps), ``folds``, ``grid`` and ``realisations``.
    log : callable
        Takes each progress line.

    Returns
    -------
    dict
        ``D0`` (the residuals as given, trees × observables), ``w`` (the observables' weights),
        ``loc`` (:func:`.stats.locate` of ``D0``), ``n_trees``, ``significant``, ``rounds`` (per
        stage the ranking, the tie and the chance explained fraction), ``effects`` (the fitted
        candidates, in stage order), ``accepted`` (their names), ``model`` (the accepted values,
        as simulated), ``final_D`` (the held-out residuals after the last accepted effect) and
        ``beam_fwhm_mrad`` (the beam the model simulates).
    """
    rng = np.random.default_rng(setup.seed)
    base: dict = {}
    study.pin(base)
    D0 = study.residual(base)
    have = np.isfinite(study.real.to_numpy(float)).any(axis=1)
    n_trees = int(have.sum())
    if n_trees < 10:
        raise InputDataError(f"only {n_trees} trees with enough real points; the diagnosis needs ≥ 10")
    w = st.weights(D0)
    loc = st.locate(D0, seed=setup.seed)
    n_differ = sum(1 for j in range(len(FEATURES)) if np.isfinite(loc["q"][j]) and loc["q"][j] < ALPHA)
    significant = bool(loc["global_p"] < ALPHA or n_differ)
    log(f"{n_trees} trees; global p = {loc['global_p']:.3g}; {n_differ} observables differ (BH q < {ALPHA})")
    # folds across trees (fixed by the seed)
    order = rng.permutation(len(D0))
    folds = np.empty(len(D0), int)
    folds[order] = np.arange(len(D0)) % setup.folds

    effects, accepted, rounds = [], [], []
    current_D = D0
    final_D = D0  # the held-out residuals after the last accepted effect
    remaining = list(cands)
    for stage in range(MAX_EFFECTS if significant else 0):
        last = stage + 1 >= MAX_EFFECTS or len(remaining) < 2
        ranked, sigs, cosm = _attribute(study, base, remaining, current_D, w, last=last)
        ranked, tie = tie_break(ranked, sigs, cosm, current_D, w)
        rounds.append({"stage": stage + 1, "ranking": [{k: (round(v, 4) if isinstance(v, float) else v)
                                                         for k, v in r.items()} for r in ranked],
                       "tie": tie})
        lead = ranked[0]
        log(f"stage {stage + 1}: " + ", ".join(f"{r['name']} {r['explained_fraction']:.2f}" for r in ranked[:4]))
        ev_crit = st.chance_ev(int(np.sum(np.isfinite(np.nanmean(current_D, axis=0)) & (w > 0))), len(remaining))
        rounds[-1]["chance_explained_fraction"] = ev_crit
        if (lead["explained_fraction"] < max(MIN_EV, ev_crit) or not lead["possible_sign"]
                or lead["p_matched"] >= ALPHA):
            break
        cand = lib.CANDIDATES[lead["name"]]
        # fit on the observables the candidate informs: weights scaled by the squared
        # signal-to-noise of its signature (reconstruction errors elsewhere do not pull the fit)
        wfit = w * st.information_weights(sigs[cand.name], current_D)
        allv, per_fold, fit_info = fit(study, base, cand, wfit, folds, setup.grid, rng)
        curve, voters = fit_info.pop("curve"), fit_info.pop("voters")
        # held-out: each fold simulated at the value fitted without it
        D_after = np.full_like(current_D, np.nan)
        for f, val in enumerate(per_fold):
            Df = study.residual(_merge(base, cand.name, val))
            D_after[folds == f] = Df[folds == f]
        ci = _systematic_ci(cand, study.survey, allv, fit_info, voters, D_after, w)
        before = st.tree_loss(current_D, w)
        after = st.tree_loss(D_after, w)
        p = st.paired_improvement(before, after)
        worse = st.worse_metrics(current_D, D_after, FEATURES)
        eb, ea = float(np.nanmean(before)), float(np.nanmean(after))
        # accepted on the held-out total error; observables that got significantly worse are
        # reported (the voxel model's own error there was compensating the missing physics)
        ok = p < ALPHA and ea < eb
        at_bound = any(np.isclose(cand.coords(allv)[q.name], b, rtol=1e-3) for q in cand.params
                       for b in cand.bounds(study.survey)[q.name])
        change = {f: {"before": _nanmean(current_D[:, j]), "after": _nanmean(D_after[:, j])}
                  for j, f in enumerate(FEATURES)}
        effects.append({"name": cand.name, "group": cand.group, "parameters": {k: float(v) for k, v in allv.items()},
                        "ci95": {cand.params[0].name: ci}, "baseline": cand.current(study.survey, base),
                        "explained_fraction": float(lead["explained_fraction"]),
                        "heldout_error_before": eb, "heldout_error_after": ea, "p_value": p,
                        "worse_metrics": worse, "heldout_mean_residual": change,
                        "at_prior_bound": bool(at_bound), "accepted": bool(ok),
                        "per_fold": per_fold, **fit_info, "stage": stage + 1})
        if cand.group == "footprint":  # what every member of the group would fit: the solid angle
            effects[-1]["equivalent_circular_fwhm_mrad"] = lib.equivalent_circular_divergence(
                study.survey, _merge(base, cand.name, allv))
        log(f"  fitted {cand.name} = {allv} (CI {ci}); held-out error {eb:.3f} → {ea:.3f}, p = {p:.3g}"
            f"{'; worse: ' + ', '.join(worse) if worse else ''} → {'accepted' if ok else 'rejected'}")
        if ok and cand.realisations and setup.realisations > 0:
            sc = _realisation_scatter(study, base, cand, allv, curve, wfit, setup.realisations)
            pn = cand.params[0].name
            blo, bhi = cand.bounds(study.survey)[pn]
            if np.isfinite(sc["relative_sd"]):
                # the estimate matched with the draws' mean amplitude; the CI so far (draw 0's, of
                # which every fit scales alike) moved with it and widened by the scatter that
                # remains (the recording's draw and the mean of the simulated ones), in quadrature
                x, k = sc["fitted_mean"], sc["fitted_mean"] / sc["draw0_fit"]
                effects[-1]["parameters"] = {kk: float(v) for kk, v in
                                             cand.values(cand.current(study.survey, base), {pn: x}).items()}
                moved = [float(np.clip(v * k, blo, bhi)) for v in ci]
                effects[-1]["ci95"] = {pn: _widened(moved, x, sc["relative_sd"] * x, False, blo, bhi)}
            effects[-1]["realisation_scatter"] = sc
            log(f"  {sc['n']} further draws of its process fit {', '.join(f'{v:.3g}' for v in sc['fitted'])}; "
                f"matched with the draws' mean {pn} = {sc['fitted_mean']:.3g} (draw 0 alone: {sc['draw0_fit']:.3g}, "
                f"relative SD {sc['relative_sd']:.2f}); CI {effects[-1]['ci95'][pn]}")
        if not ok:
            break
        accepted.append(cand.name)
        final_D = D_after
        base = _merge(base, cand.name, allv)
        remaining = [c for c in remaining if c.name != cand.name]
        if last:  # no further stage needs the residuals of the all-tree fit (no simulation of it)
            break
        study.pin(base)
        current_D = study.residual(base)
    return {"D0": D0, "w": w, "loc": loc, "n_trees": n_trees, "significant": significant, "rounds": rounds,
            "effects": effects, "accepted": accepted, "model": base, "final_D": final_D,
            "beam_fwhm_mrad": lib.beam_fwhm(study.survey, base)}  # the beam the accepted effects simulate
