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

from .engine import chain, leak, predict, replay, saturate, shift
from .model_io import Device, Params

__all__ = ["residuals", "solve_linear"]

S_ROUNDS = 200     # most alternations of the sensor gain with the weights per solve
S_TOL = 1e-9       # relative change of the sensor gain at which the alternation stops


def _design(rec, dev, p, rp, lin_w):
    """Columns (per weight) of x and of the sensor force, plus the known part from saturation."""
    z = rp.z
    if math.isfinite(p.y_sat) and lin_w is not None:
        h0 = lin_w @ z
        gp = 1.0 / (1.0 + np.abs(h0) / p.y_sat) ** 2
        c0 = saturate(h0, p.y_sat) - gp * h0
        cols = np.vstack([z * gp, c0[None, :]])
    else:
        cols = np.vstack([z, np.zeros((1, z.shape[1]))])
    ax = shift(chain(cols, "x", dev, p, rec.dt), p.lag_x) if rec.x is not None else None
    asf = shift(chain(cols, "us", dev, p, rec.dt), p.lag_us) if rec.us is not None else None
    return ax, asf


def solve_linear(recs, dev: Device, p: Params, lam: dict, *, drift_terms=0, fit_sensor_gain=True,
                 replays=None, gn_iter=2, rows="train", want_residuals=True):
    """Fit the PI weights, offsets, drift and sensor gain for fixed dynamics; update ``p`` in place.

    Minimises ``sum_c lam[c] * ||y_c - model_c||^2`` over the training rows with every partial sum
    of the weights >= a small positive bound (the model stays invertible; concave loading curves
    allowed). ``drift_terms``: 0 (offset only), 1 (+ rate) or 2 (+ curvature). The sensor gain
    (bilinear with the weights) is alternated with them; strain saturation is handled by
    Gauss-Newton steps from the current weights. Everything after the design matrices works on
    their small Gram matrices. Returns the weighted residual vector (training rows).
    """
    replays = replays or [replay(r, dev, p) for r in recs]
    n = len(p.thresholds)
    has_x = any(r.x is not None for r in recs)
    has_us = any(r.us is not None for r in recs)
    nd = 1 + drift_terms if has_x else 0
    n_par = n + nd + (1 if has_us else 0)       # W (partial sums) | x offset, rate, curv | us offset
    diff = np.eye(n) - np.eye(n, k=-1)          # w = diff @ W
    lin_w = np.asarray(p.weights, float) if np.any(p.weights) else None
    iters = 1
    if math.isfinite(p.y_sat):
        iters = gn_iter + (1 if lin_w is None else 0)
    # a load pick-off follows the push rod: a drift of the displacement reaches the sensor too
    nt = drift_terms if (has_x and has_us and p.pick == "load") else 0
    for _ in range(iters):
        kx, ks = n + 1 + nd, n + 2 + nt         # rows of the x and us designs
        Mx, cx, Ms, cs = np.zeros((kx, kx)), np.zeros(kx), np.zeros((ks, ks)), np.zeros(ks)
        for r, rp in zip(recs, replays):
            ax, asf = _design(r, dev, p, rp, lin_w)
            if r.x is not None:
                cmat = np.empty((kx, r.n))
                cmat[:n + 1] = ax
                if nd >= 1:
                    cmat[n + 1] = 1.0
                if nd >= 2:
                    tl = shift(r.t, p.lag_x)
                    cmat[n + 2] = tl
                if nd >= 3:
                    cmat[n + 3] = tl * tl
                Mx += _gram(cmat, r, rows)
                cx += _gram_vec(cmat, r.x, r, rows)
            if r.us is not None:
                cmat = np.empty((ks, r.n))
                cmat[:n + 1] = asf
                cmat[n + 1] = 1.0
                for j in range(nt):              # the drift's rate and curvature terms in the force
                    cmat[n + 2 + j] = shift(leak(dev.k_load * r.t ** (j + 1), p.tau_leak, r.dt), p.lag_us)
                Ms += _gram(cmat, r, rows)
                cs += _gram_vec(cmat, r.us, r, rows)
        # coefficient maps: c_x = Px theta + qx, c_s = Ps theta + qs
        Px = np.zeros((kx, n_par))
        Px[:n, :n] = diff
        Px[n + 1:, n:n + nd] = np.eye(nd)
        qx = np.zeros(kx)
        qx[n] = 1.0
        S = p.S
        # the sensor gain and the weights alternate until the gain settles: with both channels
        # the alternation converges only linearly, and a gain far from the data's (a sensor of
        # another sensitivity) needs tens of rounds; three left the displacement at a fifth of
        # its stroke (rig-125)
        bilinear = has_x and has_us and fit_sensor_gain
        for _ in range(S_ROUNDS if bilinear else 1):
            S_prev = S
            G = np.zeros((n_par, n_par))
            rhs = np.zeros(n_par)
            if has_x:
                G += lam["x"] * (Px.T @ Mx @ Px)
                rhs += lam["x"] * (Px.T @ (cx - Mx @ qx))
            if has_us:
                Ps = np.zeros((ks, n_par))
                Ps[:n, :n] = S * diff
                Ps[n + 1, n_par - 1] = 1.0
                for j in range(nt):
                    Ps[n + 2 + j, n + 1 + j] = S
                qs = np.zeros(ks)
                qs[n] = S
                G += lam["us"] * (Ps.T @ Ms @ Ps)
                rhs += lam["us"] * (Ps.T @ (cs - Ms @ qs))
            sol = _bounded_normal_solve(G, rhs, n, scale_hint=_scale_hint(recs, dev, p))
            w = diff @ sol[:n]
            if has_x and has_us and fit_sensor_gain:
                # us = S * (force columns @ w + known + drift terms) + offset: regression on
                # (prediction, 1)
                v = np.zeros(ks)
                v[:n] = w
                v[n] = 1.0
                v[n + 2:] = sol[n + 1:n + 1 + nt]
                pp = v @ Ms @ v
                p1 = v @ Ms[:, n + 1]
                py = v @ cs
                a = np.array([[pp, p1], [p1, Ms[n + 1, n + 1]]])
                try:
                    s_new = np.linalg.solve(a, [py, cs[n + 1]])[0]
                except np.linalg.LinAlgError:
                    s_new = S
                if s_new > 0 and np.isfinite(s_new):
                    S = float(s_new)
                if abs(S - S_prev) <= S_TOL * abs(S):
                    break
        p.weights = w
        p.S = S
        if has_x:
            p.off_x = float(sol[n])
            p.rate = float(sol[n + 1]) if drift_terms >= 1 else 0.0
            p.curv = float(sol[n + 2]) if drift_terms >= 2 else 0.0
        if has_us:
            p.off_s = float(sol[n_par - 1])
        lin_w = w
    if not want_residuals:
        return None
    return residuals(recs, dev, p, lam, replays)


def _heldout_runs(r):
    runs = r.__dict__.get("_ho_runs")
    if runs is None:
        ho = np.concatenate([[False], r.heldout, [False]]).astype(np.int8)
        d = np.diff(ho)
        runs = list(zip(np.nonzero(d == 1)[0].tolist(), np.nonzero(d == -1)[0].tolist()))
        r.__dict__["_ho_runs"] = runs
    return runs


def _gram(cmat, r, rows):
    """``C C^T`` over the training samples: over all samples minus the held-out runs."""
    g = cmat @ cmat.T
    if rows == "train":
        for a, b in _heldout_runs(r):
            blk = cmat[:, a:b]
            g -= blk @ blk.T
    return g


def _gram_vec(cmat, y, r, rows):
    v = cmat @ y
    if rows == "train":
        for a, b in _heldout_runs(r):
            v -= cmat[:, a:b] @ y[a:b]
    return v


def _scale_hint(recs, dev, p):
    """Rough size of the free stroke [x units] the weights must produce (sets their lower bound)."""
    spans = [np.ptp(r.x) / dev.mech_gain for r in recs if r.x is not None]
    k_us = dev.k_force * (dev.mech_gain * dev.k_load if p.pick == "load" else 1.0)
    spans += [np.ptp(r.us) / max(abs(p.S) * k_us, 1e-300) for r in recs if r.us is not None]
    return max(max(spans or [1.0]), 1e-12)


def _bounded_normal_solve(G, rhs, n_bounded, scale_hint=1.0):
    """min ||M theta - y|| given ``G = M^T M`` and ``rhs = M^T y``; theta[:n_bounded] >= eps."""
    # a column the data never move (an operator whose threshold the input's reversals never reach)
    # has no information: a floor relative to the largest column keeps its weight at 0 instead of
    # 1/1e-150 (rig-096: a weight of 2.5e145 um, then a model file with a negative scale)
    diag = np.diag(G)
    d = np.sqrt(np.maximum(diag, 1e-18 * max(float(np.max(diag)), 1e-300)))
    Gs = G / np.outer(d, d)
    rs = rhs / d
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
    res = lsq_linear(R, q, bounds=(lb, np.full(len(d), np.inf)), method="bvls", lsmr_tol=None)
    return res.x / d


def residuals(recs, dev, p, lam, replays=None, rows="train"):
    """Weighted residual vector (measured - model) over the chosen rows of every recording."""
    out = []
    for i, r in enumerate(recs):
        pred = predict(r, dev, p, replays[i] if replays else None)
        m = r.train if rows == "train" else (r.heldout if rows == "heldout" else np.ones(r.n, bool))
        for c in r.channels():
            out.append(math.sqrt(lam[c]) * (getattr(r, c)[m] - pred[c][m]))
    return np.concatenate(out)
