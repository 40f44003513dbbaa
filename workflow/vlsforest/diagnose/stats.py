"""Statistics of the diagnosis: residual maps, global tests, signature projection, fits, held-out checks.

All statistics replicate over trees (never points). ``D`` is a trees × observables array of
real minus simulated values (NaN where an observable is missing for a tree).
"""

from __future__ import annotations

import numpy as np
from scipy import stats as sst


def weights(D: np.ndarray) -> np.ndarray:
    """Whitening weight per observable: 1 / across-tree variance of the residual (0 if unusable).

    The variance is the tree-to-tree spread around the mean residual (what a systematic effect
    does not explain), so that a systematic mismatch counts in units of that spread.
    """
    n = np.sum(np.isfinite(D), axis=0)
    X = np.where(np.isfinite(D), D, np.nan)
    w = np.zeros(D.shape[1])
    if D.size == 0:
        return w
    with np.errstate(invalid="ignore"):
        var = np.nanvar(X, axis=0, ddof=1)
    ok = (n >= 5) & np.isfinite(var) & (var > 0)
    w[ok] = 1.0 / var[ok]
    return w


def bh(p: np.ndarray) -> np.ndarray:
    """Benjamini–Hochberg adjusted p-values (NaN kept)."""
    p = np.asarray(p, float)
    q = np.full_like(p, np.nan)
    ok = np.isfinite(p)
    m = int(ok.sum())
    if m == 0:
        return q
    order = np.argsort(p[ok])
    ranked = p[ok][order] * m / np.arange(1, m + 1)
    ranked = np.minimum.accumulate(ranked[::-1])[::-1]
    out = np.empty(m)
    out[order] = np.minimum(ranked, 1.0)
    q[ok] = out
    return q


def holm(p: np.ndarray) -> np.ndarray:
    """Holm adjusted p-values (NaN kept)."""
    p = np.asarray(p, float)
    q = np.full_like(p, np.nan)
    ok = np.flatnonzero(np.isfinite(p))
    m = len(ok)
    order = ok[np.argsort(p[ok])]
    run = 0.0
    for k, i in enumerate(order):
        run = max(run, min(1.0, (m - k) * p[i]))
        q[i] = run
    return q


def locate(D: np.ndarray, n_boot: int = 2000, seed: int = 0) -> dict:
    """Per-observable residual summary and a global sign-flip permutation test.

    Returns
    -------
    dict
        ``mean``, ``ci_lo``, ``ci_hi`` (bootstrap 95 % over trees), ``p`` (Wilcoxon signed-rank),
        ``q`` (Benjamini–Hochberg), ``n`` per observable, and ``global_p`` (sign-flip permutation
        test of Σ t², the observables standardised by their across-tree spread).
    """
    rng = np.random.default_rng(seed)
    nt, nf = D.shape
    mean = np.full(nf, np.nan)
    lo = np.full(nf, np.nan)
    hi = np.full(nf, np.nan)
    p = np.full(nf, np.nan)
    n = np.sum(np.isfinite(D), axis=0)
    for j in range(nf):
        d = D[np.isfinite(D[:, j]), j]
        if len(d) < 5:
            continue
        mean[j] = d.mean()
        bs = d[rng.integers(0, len(d), (n_boot, len(d)))].mean(axis=1)
        lo[j], hi[j] = np.percentile(bs, [2.5, 97.5])
        if np.any(d != 0):
            p[j] = float(sst.wilcoxon(d, zero_method="zsplit").pvalue)
        else:
            p[j] = 1.0
    q = bh(p)
    use = n >= 5
    Z = np.where(np.isfinite(D), D, 0.0)[:, use]
    cnt = n[use].astype(float)
    sd = np.nanstd(np.where(np.isfinite(D), D, np.nan)[:, use], axis=0, ddof=1)
    sd[~(sd > 0)] = np.inf

    def stat(signs):
        m = (signs[:, None] * Z).sum(axis=0) / cnt
        return float(np.sum((m / (sd / np.sqrt(cnt))) ** 2))

    t_obs = stat(np.ones(nt))
    flips = rng.choice([-1.0, 1.0], size=(999, nt))
    null = np.array([stat(s) for s in flips])
    gp = float((1 + np.sum(null >= t_obs)) / (1 + len(null)))
    return {"mean": mean, "ci_lo": lo, "ci_hi": hi, "p": p, "q": q, "n": n, "global_p": gp}


def project(rbar: np.ndarray, J: np.ndarray, w: np.ndarray):
    """Least-squares amplitude of signature ``J`` in the mean residual ``rbar`` (weights ``w``).

    Returns
    -------
    (a, ev, cos)
        Amplitude (in units of the reference perturbation), explained fraction
        ``1 − ‖r̄ − aJ‖²_W / ‖r̄‖²_W`` (0 when the signature is empty) and the cosine
        between ``J`` and ``r̄`` in the weighted metric.
    """
    ok = np.isfinite(rbar) & np.isfinite(J) & (w > 0)
    r, j, ww = rbar[ok], J[ok], w[ok]
    jj = float(np.sum(ww * j * j))
    rr = float(np.sum(ww * r * r))
    if jj <= 0 or rr <= 0:
        return 0.0, 0.0, 0.0
    a = float(np.sum(ww * j * r)) / jj
    ev = 1.0 - float(np.sum(ww * (r - a * j) ** 2)) / rr
    return a, ev, float(np.sum(ww * j * r)) / np.sqrt(jj * rr)


def cosine(J1: np.ndarray, J2: np.ndarray, w: np.ndarray) -> float:
    """Cosine of two signatures in the weighted metric."""
    ok = np.isfinite(J1) & np.isfinite(J2) & (w > 0)
    a, b, ww = J1[ok], J2[ok], w[ok]
    den = np.sqrt(np.sum(ww * a * a) * np.sum(ww * b * b))
    return float(np.sum(ww * a * b) / den) if den > 0 else 0.0


def bias_loss(D: np.ndarray, w: np.ndarray, rows=None) -> float:
    """Weighted squared norm of the mean residual over ``rows`` (the fit's objective)."""
    X = D if rows is None else D[rows]
    with np.errstate(invalid="ignore"):
        m = np.nanmean(X, axis=0)
    ok = np.isfinite(m) & (w > 0)
    return float(np.sum(w[ok] * m[ok] ** 2))


def tree_loss(D: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Per-tree weighted mean square residual (the held-out error)."""
    ok = np.isfinite(D) & (w > 0)[None, :]
    num = np.sum(np.where(ok, w[None, :] * np.where(ok, D, 0.0) ** 2, 0.0), axis=1)
    cnt = ok.sum(axis=1)
    return np.where(cnt > 0, num / np.maximum(cnt, 1), np.nan)


def grid_minimum(x: np.ndarray, y: np.ndarray, lo: float, hi: float, log: bool = False) -> float:
    """Minimiser of a loss sampled on a grid: a parabola through the best point and its neighbours."""
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    order = np.argsort(x)
    x, y = x[order], y[order]
    ok = np.isfinite(y)
    x, y = x[ok], y[ok]
    if len(x) == 0:
        return float("nan")
    k = int(np.argmin(y))
    if 0 < k < len(x) - 1:
        t = np.log(x[k - 1:k + 2]) if log and np.all(x[k - 1:k + 2] > 0) else x[k - 1:k + 2]
        c = np.polyfit(t, y[k - 1:k + 2], 2)
        if c[0] > 0:
            v = -c[1] / (2 * c[0])
            v = float(np.clip(v, t[0], t[2]))
            v = float(np.exp(v)) if log and np.all(x[k - 1:k + 2] > 0) else v
            return float(np.clip(v, lo, hi))
    return float(x[k])


def mde(J: np.ndarray, D: np.ndarray, z: float = 2.8) -> float:
    """Minimum detectable amplitude (in units of the reference perturbation) of a signature.

    Matched filter on the mean residual of ``n`` trees with the across-tree spread ``s_j``:
    ``a_min = z / (√n · ‖J/s‖)``, z = 2.8 for α = 0.05 (two-sided) and 80 % power.
    """
    n = np.sum(np.isfinite(D), axis=0)
    sd = np.nanstd(np.where(np.isfinite(D), D, np.nan), axis=0, ddof=1)
    ok = np.isfinite(J) & (n >= 5) & (sd > 0)
    if not ok.any():
        return float("inf")
    s = np.sqrt(np.sum((J[ok] / sd[ok]) ** 2 * n[ok]))
    return float(z / s) if s > 0 else float("inf")


def paired_improvement(before: np.ndarray, after: np.ndarray) -> float:
    """One-sided paired Wilcoxon p-value that ``after`` < ``before`` (per tree)."""
    ok = np.isfinite(before) & np.isfinite(after)
    d = before[ok] - after[ok]
    if len(d) < 5 or not np.any(d != 0):
        return 1.0
    return float(sst.wilcoxon(d, alternative="greater", zero_method="zsplit").pvalue)


def worse_metrics(D0: np.ndarray, D1: np.ndarray, names, alpha: float = 0.05, margin: float = 0.1) -> list:
    """Observables whose absolute residual got significantly and relevantly larger.

    Significant: paired one-sided Wilcoxon per observable, Holm-corrected. Relevant: the mean
    increase of the absolute residual exceeds ``margin`` times the residual's spread across trees
    in ``D0``. Without the margin a change of a few per cent of the tree-to-tree spread, shared by
    every tree (e.g. a fitted value 1 % off the truth), would count as "worse".
    """
    p = np.full(D0.shape[1], np.nan)
    big = np.zeros(D0.shape[1], bool)
    for j in range(D0.shape[1]):
        ok = np.isfinite(D0[:, j]) & np.isfinite(D1[:, j])
        d = np.abs(D1[ok, j]) - np.abs(D0[ok, j])
        if ok.sum() >= 5 and np.any(d != 0):
            p[j] = float(sst.wilcoxon(d, alternative="greater", zero_method="zsplit").pvalue)
            big[j] = d.mean() > margin * np.std(D0[ok, j])
    q = holm(p)
    return [names[j] for j in range(len(names)) if np.isfinite(q[j]) and q[j] < alpha and big[j]]


def amplitude_test(D: np.ndarray, J: np.ndarray, w: np.ndarray):
    """Matched filter across trees: per-tree amplitude of ``J`` in each tree's residual.

    Returns
    -------
    (t, p)
        One-sample t statistic of the per-tree amplitudes and its two-sided p-value.
    """
    ok = np.isfinite(J) & (w > 0)
    a = []
    for d in D:
        m = ok & np.isfinite(d)
        jj = float(np.sum(w[m] * J[m] ** 2))
        if jj > 0 and m.sum() >= 3:
            a.append(float(np.sum(w[m] * J[m] * d[m])) / jj)
    a = np.asarray(a)
    if len(a) < 5 or not np.std(a) > 0:
        return 0.0, 1.0
    t = float(a.mean() / (a.std(ddof=1) / np.sqrt(len(a))))
    return t, float(2 * sst.t.sf(abs(t), len(a) - 1))


def information_weights(J: np.ndarray, D: np.ndarray, z0: float = 3.0) -> np.ndarray:
    """Per observable ``min(1, (z/z0)²)``, z = signature / standard error of the mean residual.

    Observables the candidate barely moves (relative to the across-tree spread) get little
    weight in its fit.
    """
    n = np.sum(np.isfinite(D), axis=0)
    sd = np.nanstd(np.where(np.isfinite(D), D, np.nan), axis=0, ddof=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        z = np.abs(J) / (sd / np.sqrt(np.maximum(n, 1)))
    z = np.where(np.isfinite(z), z, 0.0)
    return np.minimum(1.0, (z / z0) ** 2)


def chance_ev(m: int, k: int, alpha: float = 0.05) -> float:
    """Explained fraction that the best of ``k`` unrelated signatures exceeds with probability α.

    For a residual isotropic in the whitened metric of ``m`` observables, the explained
    fraction of a fixed direction is Beta(½, (m − 1)/2); Bonferroni over ``k`` candidates.
    """
    if m < 2 or k < 1:
        return 1.0
    return float(sst.beta.ppf(1.0 - alpha / k, 0.5, (m - 1) / 2.0))


def robust_fit(x: np.ndarray, Ds: list, w: np.ndarray, lo: float, hi: float, log: bool = False,
               rows=None) -> float:
    """Parameter value from per-observable zero crossings, combined by a weighted median.

    For each observable the mean residual (over ``rows``) is followed along the grid ``x``; where
    it changes sign, linear interpolation gives the value at which that observable alone would
    match (the crossing nearest the loss minimiser when there are several). The estimate is the
    median of these values weighted by ``w_j · range_j²`` (how strongly the parameter moves the
    observable), interpolated between neighbouring votes (:func:`weighted_median`; on the log
    scale for ``log``) so that it does not jump between two voters of near-equal weight.
    Observables that never cross — those whose residual is dominated by an error
    the candidate cannot remove, such as the voxel model's — do not vote, so they cannot pull
    the fit the way they pull a least-squares fit. Falls back to the least-squares grid minimum
    when fewer than three observables cross. :func:`crossing_votes` gives the votes and how far
    they disagree.
    """
    return crossing_votes(x, Ds, w, lo, hi, log, rows)[0]


def weighted_median(values: np.ndarray, weights: np.ndarray, log: bool = False) -> float:
    """Interpolated weighted median: 0.5 located between the values' centred cumulative weights.

    Each value sits at the middle of its weight, ``(C_i − w_i / 2) / Σ w`` (``C_i`` the cumulative
    weight up to and including it, in ascending order); the median is the linear interpolation
    of the values at 0.5 (of their logarithms for ``log``). Unlike the plain weighted median it
    moves continuously with the weights: two voters of equal weight give their midpoint rather
    than whichever one the rounding picks, and a voter holding a share ``s > ½`` of the weight
    keeps the estimate at most ``(1 − s) / s`` of the way toward a neighbouring vote (``1 − s``
    when there are only the two: 1/10 of the way for 90 %).
    """
    v = np.asarray(values, float)
    w = np.asarray(weights, float)
    keep = np.isfinite(v) & np.isfinite(w) & (w > 0)
    if not keep.any():
        raise ValueError("weighted median of no positively weighted value")
    v, w = v[keep], w[keep]
    k = np.argsort(v, kind="stable")
    v, w = v[k], w[k]
    t = np.log(v) if log else v
    centre = (np.cumsum(w) - 0.5 * w) / w.sum()
    m = float(np.interp(0.5, centre, t))
    return float(np.exp(m)) if log else m


def crossing_votes(x: np.ndarray, Ds: list, w: np.ndarray, lo: float, hi: float, log: bool = False,
                   rows=None, detail: bool = False):
    """:func:`robust_fit`'s estimate and its votes; with ``detail``, how far the votes disagree.

    Each crossing has a sampling variance ``v_j``: the standard error of the observable's mean
    residual there over the residual's slope along the grid (on the log scale for ``log``).
    The votes' disagreement beyond these is measured as in the particle physicists' combination
    of inconsistent measurements (Birge ratio / PDG scale factor): ``S² = Q / (k − 1)`` with
    ``Q = Σ (t_j − t̄)² / v_j`` about the inverse-variance mean ``t̄`` of the ``k`` crossings ``t_j``.
    ``S² ≫ 1`` says the observables carry systematic errors of their own (the reconstruction's,
    which scale with each observable's across-tree spread, so the weights stay as they are);
    the estimate then has an SD beyond sampling of ``√(max(0, S² − 1) / Σ 1/v_j)``.

    Returns
    -------
    value : float
        The estimate (as :func:`robust_fit`).
    votes : dict
        Observable index → (crossing, weight) of every observable that voted; empty when fewer
        than three crossed and the least-squares grid minimum was taken instead.
    spread : dict, only with ``detail``
        ``scale_factor`` (S), ``systematic_sd`` (the SD beyond sampling; on the log scale for
        ``log``), ``sampling_var`` (observable index → ``v_j``) and ``bias_shift`` (observable
        index → how far its crossing moves, on the same scale, for a bias of one across-tree SD
        in its residual; see :func:`bias_allowance`); empty without votes.
    """
    x = np.asarray(x, float)
    order = np.argsort(x)
    x = x[order]
    with np.errstate(invalid="ignore", divide="ignore"):
        sub = [D if rows is None else D[rows] for D in Ds]
        M = np.array([np.nanmean(D, axis=0) for D in sub])[order]
        SD = np.array([np.nanstd(D, axis=0, ddof=1) for D in sub])[order] if detail else None  # across trees
        S = (SD / np.sqrt(np.maximum(np.array([np.sum(np.isfinite(D), axis=0) for D in sub])[order], 1))
             if detail else None)  # standard error of each mean residual
    loss = [bias_loss(D, w, rows) for D in Ds]
    x_ls = grid_minimum(np.asarray(x), np.asarray(loss)[order], lo, hi, log)
    logt = log and bool(np.all(x > 0))
    t = np.log(x) if logt else x
    votes, var, shift = {}, {}, {}
    for j in range(M.shape[1]):
        m = M[:, j]
        if w[j] <= 0 or not np.isfinite(m).all():
            continue
        cross = np.flatnonzero((m[:-1] == 0) | (np.sign(m[:-1]) != np.sign(m[1:])))
        if len(cross) == 0:
            continue
        cand = []
        for i in cross:
            if m[i] == m[i + 1]:
                cand.append((x[i], np.inf, np.inf))  # flat at zero: no slope, so no finite variance or shift
                continue
            f = m[i] / (m[i] - m[i + 1])
            v = b = np.inf
            if detail:
                dtdm = abs((t[i + 1] - t[i]) / (m[i + 1] - m[i]))
                se, sd = (1 - f) * S[i, j] + f * S[i + 1, j], (1 - f) * SD[i, j] + f * SD[i + 1, j]
                v = float((se * dtdm) ** 2) if np.isfinite(se) else np.inf
                b = float(sd * dtdm) if np.isfinite(sd) else np.inf
            cand.append((x[i] + (x[i + 1] - x[i]) * f, v, b))
        r, v, b = min(cand, key=lambda c: abs(c[0] - x_ls))
        votes[j] = (float(r), float(w[j] * float(m.max() - m.min()) ** 2))
        var[j], shift[j] = v, b
    if len(votes) < 3:
        return (x_ls, {}, {}) if detail else (x_ls, {})
    roots = np.array([r for r, _ in votes.values()])
    wts = np.array([q for _, q in votes.values()])
    # voters whose residual is exactly 0 all along the grid weigh nothing; with no other voter
    # the least-squares grid minimum stands
    value = float(np.clip(weighted_median(roots, wts, logt), lo, hi)) if np.any(wts > 0) else x_ls
    if not detail:
        return value, votes
    v = np.array([var[j] for j in votes])
    ok = np.isfinite(v) & (v > 0)
    scale, sys_sd = float("nan"), 0.0
    if ok.sum() >= 2:
        tr = np.log(roots[ok]) if logt else roots[ok]
        a = 1.0 / v[ok]
        Q = float(np.sum(a * (tr - np.sum(a * tr) / np.sum(a)) ** 2))
        scale = float(np.sqrt(Q / (ok.sum() - 1)))
        sys_sd = float(np.sqrt(max(0.0, scale ** 2 - 1.0) / np.sum(a)))
    return value, votes, {"scale_factor": scale, "systematic_sd": sys_sd,
                          "sampling_var": {j: float(vj) for j, vj in zip(votes, v)},
                          "bias_shift": {j: shift[j] for j in votes}}


def bias_scale(D: np.ndarray, cols) -> float:
    """The typical bias of an observable, in units of its across-tree SD, from residuals ``D``.

    ``β² = mean_k (z_k² − 1 / n_k)`` over the columns ``cols``, ``z_k`` being column k's mean
    residual over its across-tree SD and ``1 / n_k`` what sampling alone gives ``z_k²`` on
    average (``n_k`` trees); 0 when sampling accounts for it all, NaN without a usable column.
    Fed with the residuals a fit leaves in the observables it did not use, this measures the
    systematic errors (the voxel reconstruction's) that the fit's own observables carry too but
    cannot show, having been fitted to them.
    """
    z2 = []
    for k in cols:
        d = D[:, k]
        d = d[np.isfinite(d)]
        if len(d) < 3:
            continue
        sd = float(d.std(ddof=1))
        if sd > 0:
            z2.append((float(d.mean()) / sd) ** 2 - 1.0 / len(d))
    return float(np.sqrt(max(0.0, float(np.mean(z2))))) if z2 else float("nan")


def bias_allowance(beta: float, shares: dict, shift: dict) -> float:
    """The SD an estimate gets when each of its voters carries an independent bias of ``beta``
    across-tree SDs: ``β · √(Σ a_j² s_j²)``, ``a_j`` the voters' weight shares and ``s_j`` their
    crossings' shift per across-tree SD (``bias_shift`` of :func:`crossing_votes`). A fit that
    rests on one observable gets that observable's whole bias; one spread over many gets less.
    """
    terms = [(shares[j] * shift[j]) ** 2 for j in shares if j in shift and np.isfinite(shift[j])]
    return float(beta * np.sqrt(sum(terms))) if terms and np.isfinite(beta) else 0.0
