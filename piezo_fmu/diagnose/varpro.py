"""Variable projection: the parameters that enter linearly, solved exactly for given dynamics.

For fixed dynamics (amplifier, operators, the linear chain, the sampling lags) the displacement
and the sensor voltage are linear in the PI weights, the channel offsets and the drift
polynomial, and bilinear in the sensor sensitivity. :func:`solve_linear` finds them by bounded
linear least squares on small Gram matrices (every partial sum of the weights kept positive, so
the model stays invertible); :func:`residuals` is the weighted residual the nonlinear searches of
:mod:`.fit` minimise.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.linalg import cho_factor, cho_solve, solve_triangular
from scipy.optimize import lsq_linear

from . import workers
from .engine import at_samples, chain, drift_curvature, leak, predict, replay, saturate, shift
from .model_io import Device, Params

__all__ = ["residuals", "solve_linear"]

S_ROUNDS = 200     # most alternations of the sensor gain with the weights per solve
S_TOL = 1e-9       # relative change of the sensor gain at which the alternation stops
# ridge on the KP cells' weights, relative to each column's squared norm: directions of the cells'
# weights the training rows determine to less than this share of a column's norm are held small.
# At 1e-9 only exactly collinear columns were held: cells whose weights cancel on the training rows
# drew a step where held-out data alone cross their thresholds (rig-d22-154, a loop shape beside a
# leakage: one held-out block whose step from 23.9 to 51.5 V no training row repeats went from
# 0.008 to 0.35 um rms while every other block improved 3 x, and the shape failed; at 1e-6 that
# block 0.013 um and the shape passes). Set 2026-12-05 (stop 74) from 1e-6, 1e-5 and 1e-4 on the
# cases 1e-4 changed: 1e-4 also bent the screening of true shapes (rig-d22-167's finer loop
# screened worse than the loop without cells) and drew a false drift and a false mode beside
# rig-d22-138's creep and 164's shape; 1e-5 still the mode. 1e-6 kept the gains without them
CELL_RIDGE = 1e-6
AS_ROUNDS = 8      # active-set rounds of the bounded solve before it falls back to bvls


# the saturation's Gauss-Newton steps start from the current weights unless these drive the
# stroke beyond DEEP_SAT x the saturation level somewhere: x = h / (1 + |h| / y_sat) within 10 %
# of its rail, where the linearisation says nothing. Weights fitted for other dynamics could sit
# there (rig-145: h 2e6 against y_sat 9.8e3 after the lag was swapped for a current limit; the
# steps from there swung the cost between 3e6 and 2e9, against 1.1e4 from no sag, and the
# screening never saw the limit)
DEEP_SAT = 10.0


def _columns(p, rp, lin_w, h0=None):
    """Columns (per weight) of the free stroke, plus the known part from saturation (linearised at
    the stroke ``h0`` of the weights ``lin_w``, computed when not given), at every internal step."""
    z = rp.z
    cols = np.empty((z.shape[0] + 1, z.shape[1]))
    if math.isfinite(p.y_sat) and lin_w is not None:
        h0 = lin_w @ z if h0 is None else h0
        gp = 1.0 / (1.0 + np.abs(h0) / p.y_sat) ** 2
        np.multiply(z, gp, out=cols[:-1])
        cols[-1] = saturate(h0, p.y_sat) - gp * h0
    else:
        cols[:-1] = z
        cols[-1] = 0.0
    return cols


def _normal(ch, rec, dev, p, cols, nw, extra, rows):
    """Gram matrix and right side of channel ``ch``'s normal equations on ``rec``: the design's rows
    are ``cols`` through the channel's chain (the weights and the saturation's known part), then
    the offset and ``extra`` terms (``x``: the drift's rate and curvature; ``us``: a load
    pick-off's drift in the force)."""
    lag = p.lag_x if ch == "x" else p.lag_us
    cmat = np.empty((nw + 2 + extra, rec.n))
    cmat[:nw + 1] = shift(at_samples(rec, chain(cols, ch, dev, p, rec.h)), lag)
    cmat[nw + 1] = 1.0
    if ch == "x":
        if extra >= 1:
            tl = shift(rec.t, lag)
            cmat[nw + 2] = tl
        if extra >= 2:
            cmat[nw + 3] = drift_curvature(tl, p.drift_tau)
    else:
        for j in range(extra):              # the drift's rate and curvature terms in the force
            term = rec.t if j == 0 else drift_curvature(rec.t, p.drift_tau)
            cmat[nw + 2 + j] = shift(leak(dev.k_load * term, p.tau_leak, rec.dt), lag)
    return _gram(cmat, rec, rows), _gram_vec(cmat, getattr(rec, ch), rec, rows)


def solve_linear(recs, dev: Device, p: Params, lam: dict, *, drift_terms=0, fit_sensor_gain=True,
                 replays=None, gn_iter=2, rows="train", want_residuals=True):
    """Fit the PI weights (and the KP cells' weights), offsets, drift and sensor gain for fixed
    dynamics; update ``p`` in place.

    Minimises ``sum_c lam[c] * ||y_c - model_c||^2`` over the training rows with every partial sum
    of the weights >= a small positive bound (the model stays invertible; concave loading curves
    allowed). ``drift_terms``: 0 (offset only), 1 (+ rate) or 2 (+ curvature). The sensor gain
    (bilinear with the weights) is alternated with them; strain saturation is handled by
    Gauss-Newton steps from the current weights. Everything after the design matrices works on
    their small Gram matrices. Returns the weighted residual vector (training rows).
    """
    replays = replays or [replay(r, dev, p) for r in recs]
    n = len(p.thresholds)
    nw = n + p.n_cell_cols                      # weight columns: the PI operators, then the KP cells
    has_x = any(r.x is not None for r in recs)
    has_us = any(r.us is not None for r in recs)
    nd = 1 + drift_terms if has_x else 0
    n_par = nw + nd + (1 if has_us else 0)      # W (partial sums) | cells | x offset, rate, curv | us offset
    diff = _weight_map(p, n, nw)                # w = diff @ theta[:nw]
    lin_w = p.all_weights() if np.any(p.all_weights()) else None
    iters = 1
    h0s = None                  # the stroke of the current weights (the first linearisation's)
    if math.isfinite(p.y_sat):
        if lin_w is not None:
            h0s = [lin_w @ rp.z for rp in replays]
            if any(float(np.max(np.abs(h))) > DEEP_SAT * p.y_sat for h in h0s):
                lin_w = h0s = None      # start the saturation's linearisation afresh from no sag
        iters = gn_iter + (1 if lin_w is None else 0)
    # a load pick-off follows the push rod: a drift of the displacement reaches the sensor too
    nt = drift_terms if (has_x and has_us and p.pick == "load") else 0
    # with KP cells or a drift the saturation's Gauss-Newton steps are damped: a step that raises the training
    # cost is re-solved with a Levenberg-Marquardt term (up to four, growing), else the solve stops
    # where it was. Cells and operators combine into directions that shift the whole stroke while
    # the channel offsets take the shift back: free for the linearised problem, not for the
    # saturation (a full step moved the stroke by 12 um and the cost rose 3e4 -> 5e6, rig-052).
    # So are they with a drift: its rate and curvature columns trade with the saturation's known
    # part, and one full step from weights fitted without them landed at a cost of 3.9e9 against
    # 1.8e5 (rig-d11-021, a saturation at 117 um): the drift screened 0.71 worse than none and was
    # never fitted. Without cells or a drift the full step stays: halved steps left a screening
    # whose weights had to move far short of them, and a first mode went unseen (rig-046)
    damped = math.isfinite(p.y_sat) and (p.n_cells > 0 or drift_terms > 0)
    r_last = residuals(recs, dev, p, lam, replays) if (damped and lin_w is not None) else None
    for _ in range(iters):
        before = _linear_state(p)
        kx, ks = nw + 1 + nd, nw + 2 + nt       # rows of the x and us designs
        Mx, cx, Ms, cs = np.zeros((kx, kx)), np.zeros(kx), np.zeros((ks, ks)), np.zeros(ks)
        for i, (r, rp) in enumerate(zip(recs, replays)):
            cols = _columns(p, rp, lin_w, None if h0s is None else h0s[i])
            # (the two channels' normal equations are independent: on the two threads)
            chans = [c for c in ("x", "us") if getattr(r, c) is not None]
            got = workers.each(lambda c: _normal(c, r, dev, p, cols, nw, nd - 1 if c == "x" else nt, rows),
                               chans)
            for c, (g, v) in zip(chans, got):
                if c == "x":
                    Mx += g
                    cx += v
                else:
                    Ms += g
                    cs += v
        # coefficient maps: c_x = Px theta + qx, c_s = Ps theta + qs
        Px = np.zeros((kx, n_par))
        Px[:nw, :nw] = diff
        Px[nw + 1:, nw:nw + nd] = np.eye(nd)
        qx = np.zeros(kx)
        qx[nw] = 1.0
        grams = (Mx, cx, Ms, cs, Px, qx)
        dims = (n, nw, nd, nt, n_par, ks, has_x, has_us, has_x and has_us and fit_sensor_gain, drift_terms)
        hint = _scale_hint(recs, dev, p)
        prior = _theta(p, dims)
        _solve_into(p, grams, dims, lam, hint, before, prior, 0.0)
        if damped:
            r_new = residuals(recs, dev, p, lam, replays)
            if r_last is not None and r_new @ r_new > r_last @ r_last:
                # Levenberg-Marquardt: the step held towards where it started, more and more
                for lm in LM_STEPS:
                    _solve_into(p, grams, dims, lam, hint, before, prior, lm)
                    r_new = residuals(recs, dev, p, lam, replays)
                    if r_new @ r_new <= r_last @ r_last:
                        break
                else:
                    _restore(p, before)
                    break
            r_last = r_new
        lin_w = p.all_weights()
        h0s = None
    if not want_residuals:
        return None
    if r_last is not None:
        return r_last
    return residuals(recs, dev, p, lam, replays)


LM_STEPS = (1e-4, 1e-2, 1.0, 100.0)   # Levenberg-Marquardt terms tried (scaled coordinates) after a failed step


def _weight_map(p, n, nw):
    """The matrix taking the solve's first ``nw`` unknowns to the weights: the PI's partial sums
    (each bounded below, so the model stays invertible), or with ``p.classical`` the PI's weights
    themselves (each bounded below: a classical loop); the cells' weights as they are (any sign)."""
    diff = np.eye(nw)
    if not p.classical:
        diff[:n, :n] -= np.eye(n, k=-1)
    return diff


def _theta(p, dims):
    """The linear parameters of ``p`` as the solve's vector: partial sums of the PI weights, the
    cells' weights (or their scale), the x offset and drift, the us offset."""
    n, nw, nd, nt, n_par, ks, has_x, has_us, bilinear, drift_terms = dims
    th = np.zeros(n_par)
    th[:n] = p.weights if p.classical else np.cumsum(p.weights)
    if nw > n:
        th[n:nw] = [p.cell_scale] if p.cells_held else p.cell_w
    if has_x:
        th[nw:nw + nd] = [p.off_x, p.rate, p.curv][:nd]
    if has_us:
        th[n_par - 1] = p.off_s
    return th


def _solve_into(p, grams, dims, lam, hint, before, prior, lm):
    """Solve the linearised problem (Levenberg-Marquardt term ``lm`` towards ``prior``), the sensor
    gain alternated with the weights from its value ``before``; write the result into ``p``."""
    Mx, cx, Ms, cs, Px, qx = grams
    n, nw, nd, nt, n_par, ks, has_x, has_us, bilinear, drift_terms = dims
    diff = _weight_map(p, n, nw)
    S = float(before["S"])
    # the sensor gain and the weights alternate until the gain settles: with both channels
    # the alternation converges only linearly, and a gain far from the data's (a sensor of
    # another sensitivity) needs tens of rounds; three left the displacement at a fifth of
    # its stroke (rig-125). Every third round the gain's sequence is extrapolated to its limit
    # (Aitken): a linearly converging sequence's limit from three of its terms
    seq = [S]
    for _ in range(S_ROUNDS if bilinear else 1):
        S_prev = S
        G = np.zeros((n_par, n_par))
        rhs = np.zeros(n_par)
        if has_x:
            G += lam["x"] * (Px.T @ Mx @ Px)
            rhs += lam["x"] * (Px.T @ (cx - Mx @ qx))
        if has_us:
            Ps = np.zeros((ks, n_par))
            Ps[:nw, :nw] = S * diff
            Ps[nw + 1, n_par - 1] = 1.0
            for j in range(nt):
                Ps[nw + 2 + j, nw + 1 + j] = S
            qs = np.zeros(ks)
            qs[nw] = S
            G += lam["us"] * (Ps.T @ Ms @ Ps)
            rhs += lam["us"] * (Ps.T @ (cs - Ms @ qs))
        sol = _bounded_normal_solve(G, rhs, n, scale_hint=hint, ridge=(n, nw), prior=prior, lm=lm)
        w = diff @ sol[:nw]
        if bilinear:
            # us = S * (force columns @ w + known + drift terms) + offset: regression on
            # (prediction, 1)
            v = np.zeros(ks)
            v[:nw] = w
            v[nw] = 1.0
            v[nw + 2:] = sol[nw + 1:nw + 1 + nt]
            pp = v @ Ms @ v
            p1 = v @ Ms[:, nw + 1]
            py = v @ cs
            a = np.array([[pp, p1], [p1, Ms[nw + 1, nw + 1]]])
            try:
                s_new = np.linalg.solve(a, [py, cs[nw + 1]])[0]
            except np.linalg.LinAlgError:
                s_new = S
            if s_new > 0 and np.isfinite(s_new):
                S = float(s_new)
            if abs(S - S_prev) <= S_TOL * abs(S):
                break
            seq.append(S)
            if len(seq) == 3:
                S = _aitken(seq, S)
                seq = [S]
    p.weights = w[:n]
    if nw > n:
        if p.cells_held:
            p.cell_scale = float(w[n])
        else:
            p.cell_w, p.cell_scale = w[n:], 1.0
    p.S = S
    if has_x:
        p.off_x = float(sol[nw])
        p.rate = float(sol[nw + 1]) if drift_terms >= 1 else 0.0
        p.curv = float(sol[nw + 2]) if drift_terms >= 2 else 0.0
    if has_us:
        p.off_s = float(sol[n_par - 1])


def _aitken(seq, S):
    """The limit of the gain's three last alternation values ``seq`` (Aitken's delta-squared), or
    ``S`` when they do not contract towards one (or it would not be a positive gain)."""
    d1, d2 = seq[1] - seq[0], seq[2] - seq[1]
    if d1 == 0.0 or abs(d2) >= abs(d1) or d2 * d1 <= 0.0:
        return S
    s_lim = seq[2] - d2 * d2 / (d2 - d1)
    return float(s_lim) if (s_lim > 0.0 and math.isfinite(s_lim)) else S


_LINEAR = ("weights", "cell_w", "cell_scale", "S", "off_x", "rate", "curv", "off_s")


def _linear_state(p):
    return {k: (None if getattr(p, k) is None else np.array(getattr(p, k), float)) for k in _LINEAR}


def _restore(p, state):
    for k in _LINEAR:
        v = state[k]
        setattr(p, k, v if (v is None or v.ndim) else float(v))


def _runs(r, heldout):
    """Contiguous runs ``(start, stop)`` of held-out (or training) samples, cached per recording."""
    key = "_ho_runs" if heldout else "_tr_runs"
    runs = r.__dict__.get(key)
    if runs is None:
        mask = r.heldout if heldout else ~r.heldout
        m = np.concatenate([[False], mask, [False]]).astype(np.int8)
        d = np.diff(m)
        runs = list(zip(np.nonzero(d == 1)[0].tolist(), np.nonzero(d == -1)[0].tolist()))
        r.__dict__[key] = runs
    return runs


def _gram(cmat, r, rows):
    """``C C^T`` over the training samples, summed over their runs (all samples minus the held-out
    runs lost the small directions of nearly collinear columns to cancellation: KP cells)."""
    if rows != "train":
        return cmat @ cmat.T
    g = None
    for a, b in _runs(r, heldout=False):
        blk = cmat[:, a:b]
        g = blk @ blk.T if g is None else g + blk @ blk.T
    return g if g is not None else np.zeros((cmat.shape[0], cmat.shape[0]))


def _gram_vec(cmat, y, r, rows):
    if rows != "train":
        return cmat @ y
    v = np.zeros(cmat.shape[0])
    for a, b in _runs(r, heldout=False):
        v += cmat[:, a:b] @ y[a:b]
    return v


def _scale_hint(recs, dev, p):
    """Rough size of the free stroke [x units] the weights must produce (sets their lower bound)."""
    spans = [np.ptp(r.x) / dev.mech_gain for r in recs if r.x is not None]
    k_us = dev.k_force * (dev.mech_gain * dev.k_load if p.pick == "load" else 1.0)
    spans += [np.ptp(r.us) / max(abs(p.S) * k_us, 1e-300) for r in recs if r.us is not None]
    return max(max(spans or [1.0]), 1e-12)


def _bounded_normal_solve(G, rhs, n_bounded, scale_hint=1.0, ridge=(0, 0), prior=None, lm=0.0):
    """min ||M theta - y|| given ``G = M^T M`` and ``rhs = M^T y``; theta[:n_bounded] >= eps.

    ``lm`` > 0 adds ``lm ||D (theta - prior)||^2`` (``D``: the columns' norms): a
    Levenberg-Marquardt step held towards ``prior``.

    ``ridge``: the slice ``(start, stop)`` of parameters held small by a ridge of :data:`CELL_RIDGE`
    (relative to each column's norm): the KP cells' weights. Cells overlap one another and the play
    operators (a Preisach grid can draw a play operator too), and a cell the record barely moves is
    nearly a constant: without the ridge such near-collinear columns get weights of 1e9 that cancel
    (rig-030)."""
    # a column the data never move (an operator whose threshold the input's reversals never reach)
    # has no information: a floor relative to the largest column keeps its weight at 0 instead of
    # 1/1e-150 (rig-096: a weight of 2.5e145 um, then a model file with a negative scale)
    diag = np.diag(G)
    d = np.sqrt(np.maximum(diag, 1e-18 * max(float(np.max(diag)), 1e-300)))
    Gs = G / np.outer(d, d)
    if ridge[1] > ridge[0]:
        idx = np.arange(ridge[0], ridge[1])
        Gs[idx, idx] += CELL_RIDGE
    rs = rhs / d
    if lm > 0.0:
        Gs = Gs + lm * np.eye(len(d))
        rs = rs + lm * d * prior
    jitter = 1e-12
    for _ in range(6):
        try:
            c, low = cho_factor(Gs + jitter * np.eye(len(d)))
            break
        except np.linalg.LinAlgError:
            jitter *= 100
    R = np.triu(c) if not low else np.tril(c).T
    q = solve_triangular(R, rs, trans="T")
    unc = cho_solve((c, low), rs)
    eps = 1e-6 * scale_hint       # partial sums stay positive after rounding to 8 digits
    lb = np.full(len(d), -np.inf)
    lb[:n_bounded] = eps * d[:n_bounded]
    if np.all(unc[:n_bounded] >= lb[:n_bounded]):
        return unc / d
    sol = _active_set(R, q, lb, n_bounded, unc[:n_bounded] < lb[:n_bounded])
    if sol is None:
        sol = lsq_linear(R, q, bounds=(lb, np.full(len(d), np.inf)), method="bvls", lsmr_tol=None).x
    return sol / d


def _active_set(R, q, lb, n_bounded, guess, rounds=AS_ROUNDS):
    """``min ||R t - q||`` with ``t[:n_bounded] >= lb[:n_bounded]`` (``R`` square, upper
    triangular, full rank) by primal-dual active sets started from ``guess`` (the bounded entries
    held at their bound): a least-squares solve on the free columns, then every free entry below
    its bound joins the set and every held one whose gradient points into the feasible side
    leaves it, until the KKT conditions hold.

    The minimiser is unique, so this is the solution ``lsq_linear(method="bvls")`` approximates,
    in one or two solves where bvls takes tens of iterations (the caller starts from the bounds
    the unconstrained solution violates, which are nearly always the active ones); the weights'
    solve runs inside the sensor gain's alternation, tens of times per linear solve.
    The solves are on ``R``'s columns (QR), not on ``R^T R``: the KP cells' and the finer loop's
    columns are nearly collinear, and the normal matrix squares their condition. ``None`` when the
    sets have not settled after ``rounds``: the caller runs bvls."""
    n = len(q)
    held = np.zeros(n, bool)
    held[:n_bounded] = guess
    tol = 1e-10 * max(float(np.max(np.abs(R.T @ q))), 1e-300)
    t = np.empty(n)
    for _ in range(rounds):
        free = ~held
        t[held] = lb[held]
        t[free] = np.linalg.lstsq(R[:, free], q - R[:, held] @ lb[held], rcond=None)[0]
        g = R.T @ (R @ t - q)                           # the multipliers of the held entries
        below = free.copy()
        below[n_bounded:] = False
        below &= t < lb
        leave = held & (g < -tol)
        if not below.any() and not leave.any():
            return t
        held = (held & ~leave) | below
    return None


def residuals(recs, dev, p, lam, replays=None, rows="train"):
    """Weighted residual vector (measured - model) over the chosen rows of every recording."""
    out = []
    for i, r in enumerate(recs):
        pred = predict(r, dev, p, replays[i] if replays else None)
        m = r.train if rows == "train" else (r.heldout if rows == "heldout" else np.ones(r.n, bool))
        for c in r.channels():
            out.append(math.sqrt(lam[c]) * (getattr(r, c)[m] - pred[c][m]))
    return np.concatenate(out)
