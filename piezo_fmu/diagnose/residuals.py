"""The residuals of a parameter set (training and held-out rows per channel, the peaks of their
spectra, the share of a change that lies in a frequency band) and the acceptance thresholds every
decision of the diagnosis uses (see docs/diagnose.md, "How a finding is decided").

Kept apart from :mod:`.select` and :mod:`.recalibrate`, which both need them, so that neither
imports the other at module level.
"""
from __future__ import annotations

import math

import numpy as np

from .engine import predict
from .fit import Fitter
from .stats import psd

__all__ = ["ACCEPT", "MODE_BAND_WIDTH", "SLOW_HELDOUT_MIN", "STILL_SHARE", "band_share", "full_residuals",
           "heldout_rmse", "hold_runs", "holds_still", "residual_peaks", "residual_sets", "spectral_peaks",
           "taken_in_holds"]

MODE_BAND_WIDTH = 1.25   # a mode's own band: f_n / width .. f_n * width
ACCEPT = {
    "p_lr": 1e-3,            # likelihood-ratio test on training rows (effective sample size)
    "dbic": 10.0,            # BIC difference (effective sample size), > 10 = very strong
    "explained": 0.15,       # share of the structured residual removed (its best channel)
    "beta_heldout": 0.5,     # held-out residual regressed on the candidate's change there (1 = all of it)
    "z_heldout": 3.0,        # ... and that regression's significance
    "worse": 0.02,           # no channel's held-out RMSE may grow by more than this
    "bound": 0.01,           # a fitted value within 1 % (log scale) of its search range's ends is at a bound
}


# a slow mechanism is judged on the held-out samples away from the command's jumps when at least
# this share of them is (else on all: a drive of jumps throughout leaves no slow part to judge apart)
SLOW_HELDOUT_MIN = 0.5


def residual_sets(fitter: Fitter, p):
    """channel -> train/heldout residuals, held-out blocks, weight (model orientation); and, for a
    slow mechanism, ``heldout_slow``/``blocks_slow``: the held-out residuals away from the
    command's jumps (:func:`.recordings.after_jumps`, see :data:`SLOW_HELDOUT_MIN`)."""
    out = {}
    rps = fitter.replays(p)
    preds = [predict(r, fitter.dev, p, rp) for r, rp in zip(fitter.recs, rps)]
    for ch in ("x", "us"):
        tr, ho, blocks, ho_q, blocks_q = [], [], [], [], []
        for r, pr in zip(fitter.recs, preds):
            y = getattr(r, ch)
            if y is None:
                continue
            e = y - pr[ch]
            tr.append(e[r.train])
            ho.append(e[r.heldout])
            quiet = r.heldout if r.transient is None else r.heldout & ~r.transient
            ho_q.append(e[quiet])
            for b in np.unique(r.block[r.heldout]):
                blocks.append(e[r.block == b])
                inside = quiet & (r.block == b)
                if inside.any():
                    blocks_q.append(e[inside])
        if tr:
            out[ch] = {"train": np.concatenate(tr), "heldout": np.concatenate(ho), "blocks": blocks,
                       "lam": fitter.lam[ch]}
            h_q = np.concatenate(ho_q)
            quiet_enough = h_q.size >= SLOW_HELDOUT_MIN * out[ch]["heldout"].size
            out[ch]["heldout_slow"] = h_q if quiet_enough else out[ch]["heldout"]
            out[ch]["blocks_slow"] = blocks_q if quiet_enough else blocks
            out[ch]["slow_away"] = quiet_enough and h_q.size < out[ch]["heldout"].size
    return out, preds


def heldout_rmse(sets):
    """Held-out rmse per channel of :func:`residual_sets`' ``sets``, over every held-out sample (what
    the report's table compares; a slow candidate's own statistics leave the jumps' transients out)."""
    return {c: math.sqrt(float(v["heldout"] @ v["heldout"]) / max(v["heldout"].size, 1))
            for c, v in sets.items()}


def full_residuals(fitter, p):
    rps = fitter.replays(p)
    out = []
    for r, rp in zip(fitter.recs, rps):
        pr = predict(r, fitter.dev, p, rp)
        out.append({ch: getattr(r, ch) - pr[ch] for ch in r.channels()})
    return out


def residual_peaks(fitter: Fitter, p, n=3):
    """Peaks of the residual spectrum of every recorded channel (see :func:`spectral_peaks`)."""
    out = []
    for r in fitter.recs:
        pr = predict(r, fitter.dev, p, direct=True)
        for c in r.channels():
            out += spectral_peaks(getattr(r, c) - pr[c], 1 / r.dt, n)
    return sorted({round(f, 4) for f in out})


def spectral_peaks(e, fs, n=3, fmin=5.0):
    """Frequencies [Hz] of the largest local maxima of the residual spectrum above ``fmin``.

    Fine resolution (segments of up to 1/0.2 Hz, i.e. 5 s, or the whole record) and a parabola
    through each peak's log-power: a lightly damped mode's peak is narrower than a coarse bin."""
    nper = int(min(e.size, 2 ** int(math.ceil(math.log2(max(fs / 0.2, 64))))))
    f, pw = psd(e, fs, nper)
    if f.size < 4:
        return []
    lp = np.log(np.maximum(pw, 1e-300))
    loc = np.nonzero((lp[1:-1] > lp[:-2]) & (lp[1:-1] > lp[2:]))[0] + 1
    loc = loc[f[loc] > fmin]
    loc = loc[np.argsort(-pw[loc])][:n]
    df = f[1] - f[0]
    out = []
    for k in loc:
        a, b, c = lp[k - 1], lp[k], lp[k + 1]
        den = a - 2 * b + c
        off = 0.5 * (a - c) / den if den < 0 else 0.0
        out.append(float(f[k] + np.clip(off, -0.5, 0.5) * df))
    return out


HOLD_MIN_S = 0.2       # a hold: the command exactly constant for at least this long [s]
HOLD_SETTLE_S = 0.02   # its first part is left out (the transient of the step before it) [s]


def hold_runs(u, dt):
    """``(start, stop)`` sample ranges where the command ``u`` stays exactly constant for at least
    ``HOLD_MIN_S``, each without its first ``HOLD_SETTLE_S``."""
    span = float(np.ptp(u)) or 1.0
    moves = np.flatnonzero(np.abs(np.diff(u)) > 1e-9 * span) + 1
    edges = np.concatenate([[0], moves, [u.size]])
    skip = int(round(HOLD_SETTLE_S / dt))
    return [(int(a) + skip, int(b)) for a, b in zip(edges[:-1], edges[1:])
            if (b - a) * dt >= HOLD_MIN_S and b - a - skip > 10]


STILL_SHARE = 0.01     # a command within this share of its span for HOLD_MIN_S holds still (measured too)


def holds_still(u, dt) -> bool:
    """Whether the command ``u`` stays within ``STILL_SHARE`` of its span for at least ``HOLD_MIN_S``
    somewhere (two adjacent blocks of half that length): a hold, also where the command was
    measured and carries noise (JPK01466's 3 s hold; :func:`hold_runs` asks for an exact one)."""
    span = float(np.ptp(u))
    n = max(int(round(0.5 * HOLD_MIN_S / dt)), 2)
    m = u.size // n
    if span <= 0.0 or m < 2:
        return span <= 0.0
    b = np.asarray(u[: m * n]).reshape(m, n)
    lo, hi = b.min(axis=1), b.max(axis=1)
    return bool(np.any(np.maximum(hi[1:], hi[:-1]) - np.minimum(lo[1:], lo[:-1]) <= STILL_SHARE * span))


def taken_in_holds(fitter: Fitter, p_before, p_after, ch, own=None):
    """How much of the change from ``p_before`` to ``p_after`` in channel ``ch`` the residual of
    ``p_before`` takes within the command's holds, each hold's mean removed (so only the motion
    during a hold counts): ``(beta, strength)``, beta the regression coefficient (1: all of it, 0:
    none), strength the rms of the change within holds over the noise times the square root of
    their samples (the z a beta of 1 would have); ``None`` without holds or without the channel.

    ``own(rec, p)``: the mechanism's own term in ``ch`` (a drift's trend). Then beta is that term's
    change, fitted beside what the other parameters' refit changed (rig-060: the drift's own change
    taken at 0.86 in the holds, the pick-off switched beside it at -1.1: 0.06 in all), and the
    strength is the part of it the other change cannot stand in for."""
    g = np.zeros((2, 2))
    v = np.zeros(2)
    for r in fitter.recs:
        y = getattr(r, ch)
        if y is None:
            continue
        runs = hold_runs(r.u, r.dt)
        if not runs:
            continue
        before = predict(r, fitter.dev, p_before)[ch]
        change = predict(r, fitter.dev, p_after)[ch] - before
        mine = change if own is None else own(r, p_after) - own(r, p_before)
        for a, b in runs:
            e = y[a:b] - before[a:b]
            cols = [mine[a:b], change[a:b] - mine[a:b]]
            cols = [c - np.mean(c) for c in cols]
            g += [[ci @ cj for cj in cols] for ci in cols]
            v += [float((e - np.mean(e)) @ c) for c in cols]
    noise = fitter.noise.get(ch, 0.0)
    if g[0, 0] <= 0.0 or noise <= 0.0:
        return None
    if g[1, 1] <= 1e-12 * g[0, 0]:
        return float(v[0] / g[0, 0]), math.sqrt(g[0, 0]) / noise
    free = g[0, 0] - g[0, 1] ** 2 / g[1, 1]       # the own change's part the other cannot draw
    if free <= 1e-6 * g[0, 0]:
        return None
    return float(np.linalg.solve(g, v)[0]), math.sqrt(free) / noise


def band_share(fitter: Fitter, p, f, q=None, width=MODE_BAND_WIDTH, below=None):
    """Share of what the further mode of ``p`` itself changes (``p`` against ``q``, by default ``p``
    without it, every other value kept) that lies within ``f / below .. f * width`` [Hz] (``below``
    defaults to ``width``), over every recorded channel (energies of the change's spectrum, its mean
    removed). A lightly damped mode rings at its own frequency; a "mode" changing the response mostly
    elsewhere reshapes another part."""
    if q is None:
        q = p.copy()
        q.res = None
    near = total = 0.0
    for r in fitter.recs:
        a, b = predict(r, fitter.dev, p, direct=True), predict(r, fitter.dev, q, direct=True)
        for c in r.channels():
            d = a[c] - b[c]
            spec = np.abs(np.fft.rfft((d - np.mean(d)) * np.hanning(d.size))) ** 2
            fr = np.fft.rfftfreq(d.size, r.dt)
            near += float(np.sum(spec[(fr >= f / (below or width)) & (fr <= f * width)]))
            total += float(np.sum(spec[1:]))
    return near / total if total > 0 else 0.0
