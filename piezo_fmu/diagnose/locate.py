"""Where a residual lives: in time (which input segments), in frequency, over the operating range.

The input is described sample by sample (:func:`input_context`): steps, holds (and how long since
the last step), reversals, the local frequency and rate of the command, the start of the record.
A residual is then located

* in time: windows whose local RMS stands above the noise floor (:func:`windows`), each
  explained by the input context it falls in;
* in frequency: bands of the residual spectrum above the noise floor and their coherence with
  the input (:func:`bands`);
* over the operating range: RMS by command level and by command rate (:func:`operating_range`);
* per channel (the caller runs everything per channel).
"""
from __future__ import annotations

import itertools
import math

import numpy as np
from scipy import stats as sst
from scipy.ndimage import maximum_filter1d, minimum_filter1d, uniform_filter1d
from scipy.signal import coherence

from .stats import psd

__all__ = ["bands", "describe_window", "input_context", "operating_range", "segment_rms", "windows"]


def input_context(t, u, dt):
    """Per-sample description of the command: dict of arrays and the list of steps."""
    n = u.size
    span = float(np.ptp(u)) or 1.0
    du = np.diff(u, prepend=u[0])
    # steps: a jump of more than 3 % of the span within one sample
    step_idx = np.nonzero(np.abs(du) > 0.03 * span)[0]
    # a step sample followed by more step samples within 2 ms belongs to the same step
    steps = []
    for k in step_idx:
        if steps and k - steps[-1][0] <= max(1, int(0.002 / dt)):
            steps[-1][1] += du[k]
            continue
        steps.append([int(k), float(du[k])])
    # holds: the command stays within 0.5 % of the span over 50 ms (the turning points of a sine
    # slower than about 0.5 Hz count as holds too: the device sees the same)
    w = max(3, int(round(0.05 / dt)))
    rng_local = maximum_filter1d(u, w) - minimum_filter1d(u, w)
    hold = rng_local < 0.005 * span
    since_step = np.full(n, np.inf)
    for k, _ in steps:
        seg = np.arange(k, n)
        since_step[k:] = np.minimum(since_step[k:], (seg - k) * dt)
    # local rate [V/s] (smoothed over 2 ms) and local frequency from reversals
    rate = np.abs(uniform_filter1d(du, max(1, int(round(0.002 / dt))))) / dt
    sm = uniform_filter1d(u, max(1, int(round(0.001 / dt))))
    d = np.diff(sm)
    thr = 1e-4 * span
    sgn = np.where(d > thr, 1, np.where(d < -thr, -1, 0))
    nz = np.nonzero(sgn)[0]
    rev = np.zeros(n, bool)
    if nz.size > 1:
        flips = nz[1:][sgn[nz[1:]] != sgn[nz[:-1]]]
        rev[flips] = True
    win = max(3, int(round(0.5 / dt)))
    rev_rate = uniform_filter1d(rev.astype(float), win) / dt          # reversals per second
    freq = rev_rate / 2.0
    near_rev = maximum_filter1d(rev.astype(np.uint8), max(3, int(round(0.004 / dt)))).astype(bool)
    return {"t": t, "u": u, "span": span, "steps": steps, "hold": hold, "since_step": since_step,
            "rate": rate, "freq": freq, "reversal": near_rev & ~hold, "dt": dt}


def segment_masks(ctx):
    """Named masks of the input segments the issue talks about."""
    hold_after = ctx["hold"] & (ctx["since_step"] < 3.0)
    fast = (ctx["freq"] >= 8.0) & ~ctx["hold"]
    start = ctx["t"] < min(0.5, 0.05 * ctx["t"][-1] + ctx["dt"])
    return {
        "holds_after_steps": hold_after,
        "other_holds": ctx["hold"] & ~hold_after,
        "reversals": ctx["reversal"],
        "fast_inputs": fast & ~ctx["reversal"],
        "slow_inputs": ~ctx["hold"] & ~fast & ~ctx["reversal"],
        "start": start,
    }


def segment_rms(e, ctx, mask=None):
    """Residual RMS in every input segment (``mask`` restricts to e.g. held-out samples)."""
    out = {}
    for name, m in segment_masks(ctx).items():
        mm = m if mask is None else (m & mask)
        if np.count_nonzero(mm) >= 5:
            out[name] = {"rms": float(np.sqrt(np.mean(e[mm] ** 2))),
                         "share_of_samples": float(np.mean(mm))}
    return out


def describe_window(ctx, k0, k1):
    """A sentence on what the command does in samples ``k0..k1``."""
    t, u, dt = ctx["t"], ctx["u"], ctx["dt"]
    sl = slice(k0, k1 + 1)
    parts = []
    # steps by where they lie: before the window (at most 3 s before it), inside it, after it
    before = [(k, a) for k, a in ctx["steps"] if k0 - int(3.0 / dt) <= k <= k0]
    inside = [(k, a) for k, a in ctx["steps"] if k0 < k <= k1]
    after = [(k, a) for k, a in ctx["steps"] if k1 < k]
    hold_share = float(np.mean(ctx["hold"][sl]))
    if t[k0] < 0.3 and k0 == 0 or (t[k0] < 0.3 and np.any(u[: max(1, k0)] == 0)):
        parts.append("start of the recording (device leaving rest)")
    if inside:
        k, a = inside[0]
        more = f" (and {len(inside) - 1} more step(s) to {t[k1]:.4g} s)" if len(inside) > 1 else ""
        parts.append(f"step of {a:+.4g} V at {t[k]:.4g} s{more}")
        if hold_share > 0.5 and k - k0 > 0.5 * (k1 - k0):
            parts.append(f"hold at {np.mean(u[k0:k]):.4g} V before it")
    elif before and hold_share > 0.5:
        k, a = before[-1]
        parts.append(f"hold after the step of {a:+.4g} V at {t[k]:.4g} s")
    elif hold_share > 0.5:
        parts.append(f"hold at {np.mean(u[sl]):.4g} V")
    if not inside and after and hold_share > 0.5 and after[0][0] - k1 <= max(1, int(0.05 / dt)):
        k, a = after[0]
        parts.append(f"before the step of {a:+.4g} V at {t[k]:.4g} s")
    f = float(np.median(ctx["freq"][sl]))
    if hold_share <= 0.5:
        rate = float(np.max(ctx["rate"][sl]))
        if f >= 8.0:
            parts.append(f"fast input, about {f:.3g} Hz, rate up to {rate:.3g} V/s")
        elif f > 0:
            parts.append(f"slow input, about {f:.3g} Hz")
        if np.mean(ctx["reversal"][sl]) > 0.3:
            parts.append("around reversals of the input")
    parts.append(f"command {np.min(u[sl]):.3g}-{np.max(u[sl]):.3g} V")
    return "; ".join(parts)


def windows(score, ctx, level, min_len_s=0.02, max_windows=6, merge_gap_s=None):
    """Contiguous windows where ``score`` (a non-negative per-sample energy) exceeds ``level``.

    Returns a list of dicts ``t0, t1, energy`` (sorted by energy, largest first).
    """
    dt = ctx["dt"]
    t = ctx["t"]
    w = max(3, int(round(max(min_len_s, 10 * dt) / dt)))
    sm = uniform_filter1d(score, w)
    on = sm > level
    if not np.any(on):
        return []
    gap = max(1, int(round((merge_gap_s or 5 * w * dt) / dt)))
    idx = np.nonzero(on)[0]
    runs = []
    start = prev = idx[0]
    for k in idx[1:]:
        if k - prev > gap:
            runs.append((start, prev))
            start = k
        prev = k
    runs.append((start, prev))
    out = []
    for a, b in runs:
        energy = float(np.sum(score[a:b + 1]) * dt)
        out.append({"k0": int(a), "k1": int(b), "t0": float(t[a]), "t1": float(t[b]), "energy": energy})
    out.sort(key=lambda r: -r["energy"])
    return out[:max_windows]


def bands(e, u, fs, noise, min_share=0.05):
    """Bands where the residual spectrum stands above its white-noise floor.

    Returns a list of dicts ``band_hz, rms, peak_hz, coherence`` (mean magnitude-squared coherence of
    residual and command in the band), largest first.
    """
    f, p = psd(e, fs)
    df = f[1] - f[0]
    floor = noise ** 2 / (fs / 2.0)
    nseg = max(1, int(2 * e.size / max(1, 2 * (f.size - 1))) - 1)
    dof = 2 * nseg
    crit = floor * sst.chi2.ppf(0.999, dof) / dof
    above = (p > max(crit, 2.0 * floor))
    if not np.any(above):
        return []
    excess = np.clip(p - floor, 0, None)
    total = float(np.sum(np.clip(p - floor, 0, None)))
    nper = min(e.size, 2 * (f.size - 1))
    try:
        _, coh = coherence(e, u, fs=fs, nperseg=nper)
    except ValueError:
        coh = np.zeros_like(f)
    out = []
    idx = np.nonzero(above)[0]
    start = prev = idx[0]
    runs = []
    for k in idx[1:]:
        if k - prev > max(2, int(0.05 * k)):
            runs.append((start, prev))
            start = k
        prev = k
    runs.append((start, prev))
    for a, b in runs:
        en = float(np.sum(excess[a:b + 1]))
        if total <= 0 or en / total < min_share:
            continue
        pk = a + int(np.argmax(p[a:b + 1]))
        out.append({"band_hz": [round(float(f[a]), 4), round(float(f[b]), 4)], "df": float(df),
                    "rms": math.sqrt(en * df), "share": en / total, "peak_hz": round(float(f[pk]), 4),
                    "coherence": float(np.mean(coh[a:b + 1])) if coh.size == f.size else 0.0})
    out.sort(key=lambda r: -r["rms"])
    return out


def operating_range(e, u, rate, n_bins=5):
    """Residual RMS by command level and by command rate (quantile bins)."""
    out = {}
    for name, v, unit in (("amplitude", u, "V"), ("rate", rate, "V/s")):
        qs = np.unique(np.quantile(v, np.linspace(0, 1, n_bins + 1)))
        rows = []
        for lo, hi in itertools.pairwise(qs):
            m = (v >= lo) & (v <= hi)
            if np.count_nonzero(m) < 5:
                continue
            rows.append({"range": [float(lo), float(hi)], "unit": unit,
                         "rms": float(np.sqrt(np.mean(e[m] ** 2))), "samples": int(np.count_nonzero(m))})
        out[name] = rows
    return out
