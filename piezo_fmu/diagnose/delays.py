"""Whole-sample delays: where the search for a command delay starts and how a fitted one is stepped.

A delay is resolved to whole samples and trades off against the amplifier's lag (and, through
the weights, the loop's width), so neither is searched alone: :func:`delay_search` profiles the
lag at every delay the screening tries (the catalogue's ``time_delay`` start), and
:func:`refine_delay` steps a fitted delay while the cost, with the lag re-searched and the weights
re-solved, falls (after a fit, and in the lag account of a swapped mode, :mod:`.starts`).
"""
from __future__ import annotations

import math

import numpy as np

from .fit import Fitter

__all__ = ["SPLIT_SHARES", "delay_search", "refine_delay"]

SPLIT_SHARES = (0.15, 0.35)   # the second stage's shares of the lag a delay's best start is re-screened at


def delay_search(fitter: Fitter, p, struct, dt, both):
    """``(q, cost)``: the best whole-sample delay, each with its best lag (``both``: the two lag
    stages scaled together, else the first alone); timing trades off against the loop's width."""
    nd_max = max(1, min(64, int(round(0.02 / dt))))
    # every delay up to 10 samples (a delay is resolved to whole samples), log-spaced above
    nds = sorted({k for k in range(1, min(nd_max, 10) + 1)}
                 | {int(round(v)) for v in np.exp(np.linspace(math.log(10), math.log(nd_max), 6))
                    if nd_max > 10})
    total = p.tau + (p.tau2 if both else 0.0)
    best, best_c = None, math.inf
    for nd in nds:
        # the total lag is roughly conserved: start the lag search from what is left of it
        k0 = max(1.0 - nd * dt / total, 1 / 20)
        q, c = _lag_profile(fitter, p, struct, nd * dt, p.tau * k0, both)
        if c < best_c:
            best, best_c = q, c
        elif best is not None and c > 3 * best_c:
            break                       # far past the best delay
    nd0 = int(round(best.delay / dt))
    for nd in (nd0 - 1, nd0 + 1):
        if nd < 1 or nd in nds:
            continue
        q, c = _lag_profile(fitter, p, struct, nd * dt, best.tau, both)
        if c < best_c:
            best, best_c = q, c
    if both:
        # how the lag left beside the delay splits between the stages is not the recalibration's
        # split (rig-d22-117: 1.09 + 1.81 ms recalibrated, with a 131 Hz mode, for a one-sample
        # delay beside 1.19 + 0.65 ms; the delay scaled with that split screened 1.35 x the model
        # without it, fitted it takes 0.43 x): the best delay re-screened at other splits
        total = best.tau + best.tau2
        for share in SPLIT_SHARES:
            r = best.copy()
            r.tau, r.tau2 = total * (1.0 - share), total * share
            q, c = _lag_profile(fitter, r, struct, best.delay, r.tau, both=True)
            if c < best_c:
                best, best_c = q, c
    return best, best_c


def _lag_profile(fitter: Fitter, p, struct, delay, tau0, both=False):
    """Best amplifier lag for a given delay (the screening: weights held, each channel's gain and
    offset re-solved): three lags and a parabola in log tau (``both``: the second stage scaled
    with the first). Returns the parameters and the cost."""
    lo = fitter.bounds("tau")[0]

    def at(x):
        q = p.copy()
        q.delay = delay
        q.tau = math.exp(x)
        if both:
            q.tau2 = p.tau2 * q.tau / p.tau
        return q

    xs = sorted({math.log(max(tau0 * f, lo)) for f in (0.5, 1.0, 2.0)})
    qs = [at(x) for x in xs]
    pts = list(zip(qs, fitter.quick_many(qs)))
    cs = [c for _, c in pts]
    best = pts[int(np.argmin(cs))]
    if len(xs) == 3:
        a = np.polyfit(xs, cs, 2)
        if a[0] > 0:
            x_star = min(max(-a[1] / (2 * a[0]), xs[0] - 0.7), xs[-1] + 0.7)
            q = at(x_star)
            cand = q, fitter.quick(q)
            if cand[1] < best[1]:
                best = cand
    return best


def refine_delay(fitter, p, struct, reach=3):
    """Step the integer delay while the training cost, with the lag re-searched and the weights
    re-solved (the loop's width trades off against lag, so they must move with it), falls."""
    dt = fitter.dt
    nd = int(round(p.delay / dt))

    def at(k, tau):
        q = p.copy()
        q.delay = k * dt
        lo = max(fitter.bounds("tau")[0], tau / 4)
        return fitter.fit_scalar(q, struct, "tau", quick=False, bounds=(lo, tau * 4), xatol=0.02)

    best, best_c = at(nd, p.tau)
    for direction in (1, -1):
        moved = False
        for k in range(1, reach + 1):
            if nd + direction * k < 1:
                break
            q, c = at(nd + direction * k, max(best.tau - direction * dt, p.tau / 10))
            if c < best_c:
                best, best_c, moved = q, c, True
            else:
                break
        if moved:
            break
    return best
