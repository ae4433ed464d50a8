"""The words for what a residual leaves unexplained: a trend, a band, where over the operating range.

Used by :func:`.results.assemble` for diagnosis.json's ``unexplained`` entries.
"""
from __future__ import annotations

import math

import numpy as np

from . import locate

__all__ = ["bandpass", "describe_band", "dominant_freq", "range_sentence", "trend"]


def bandpass(e, band, fs):
    from scipy.signal import butter, sosfiltfilt

    lo, hi = band
    ny = fs / 2
    lo = max(lo, 1e-3 * ny)
    hi = min(max(hi, lo * 1.2), 0.99 * ny)
    try:
        sos = butter(2, [lo / ny, hi / ny], btype="band", output="sos")
        return sosfiltfilt(sos, e)
    except ValueError:
        return e - np.mean(e)


def trend(e, t, noise):
    """A quadratic trend in time that carries most of a structured residual, or ``None``."""
    tn = t / max(float(t[-1]), 1e-12)
    a = np.vstack([np.ones_like(tn), tn, tn * tn]).T
    coef, *_ = np.linalg.lstsq(a, e, rcond=None)
    fit = a @ coef
    structured = max(float(np.mean(e * e)) - noise ** 2, 0.0)
    trend_var = float(np.var(fit))
    if structured <= 0 or trend_var < 0.5 * structured or math.sqrt(trend_var) < 0.5 * noise:
        return None
    return {"rms": math.sqrt(trend_var), "change": float(fit[-1] - fit[0]),
            "share": min(1.0, trend_var / structured)}


def range_sentence(e, u, rate, noise):
    """Where over the operating range a residual is largest, when it clearly depends on it."""
    rng = locate.operating_range(e, u, rate)
    parts = []
    for key, label, unit in (("rate", "command rate", "V/s"), ("amplitude", "command level", "V")):
        rows = rng.get(key, [])
        if len(rows) < 3:
            continue
        rms = np.array([r["rms"] for r in rows])
        struct = np.sqrt(np.clip(rms ** 2 - noise ** 2, 0.0, None))
        k_hi, k_lo = int(np.argmax(struct)), int(np.argmin(struct))
        if struct[k_hi] > 1.5 * struct[k_lo] + 0.2 * noise:
            lo, hi = rows[k_hi]["range"]
            parts.append(f"largest at {label} {lo:.3g}-{hi:.3g} {unit} ({rms[k_hi]:.3g} rms against "
                         f"{rms[k_lo]:.3g} at {rows[k_lo]['range'][0]:.3g}-{rows[k_lo]['range'][1]:.3g} {unit})")
    return "; ".join(parts)


def dominant_freq(u, dt):
    """Frequency [Hz] of a command dominated by one periodic component (else ``None``)."""
    u = np.asarray(u, float) - np.mean(u)
    if u.size < 16:
        return None
    spec = np.abs(np.fft.rfft(u * np.hanning(u.size))) ** 2
    spec[0] = 0.0
    k = int(np.argmax(spec))
    share = float(np.sum(spec[max(1, k - 3):k + 4]) / max(np.sum(spec), 1e-300))
    if share < 0.5 or k < 1 or k >= spec.size - 1:
        return None
    a, b, c = np.log(spec[k - 1:k + 2] + 1e-300)
    off = 0.5 * (a - c) / (a - 2 * b + c) if (a - 2 * b + c) != 0 else 0.0
    return float((k + off) / (u.size * dt))


def describe_band(b, noise, f0=None):
    lo, hi = b["band_hz"]
    width = hi - lo
    harmonic = None
    if f0:
        k = round(b["peak_hz"] / f0)
        if k >= 1 and abs(b["peak_hz"] - k * f0) <= max(0.03 * k * f0, b.get("df", 0.0)):
            harmonic = k
    if harmonic:
        rel = (f"harmonic {harmonic} of the command's {f0:.4g} Hz: a periodic, phase-locked response to the "
               "input that the model's loop shape (or another rate-independent nonlinearity) gets wrong")
        if harmonic % 2 == 0:
            rel += ("; an even harmonic means an asymmetry the symmetric play operators cannot draw (e.g. an "
                    "asymmetric loop, or a displacement sensor that is not linear, like a capacitive gap sensor)")
    elif b["coherence"] > 0.5:
        rel = "coherent with the command: a response to the input that the model gets wrong"
    elif b["coherence"] > 0.2:
        rel = "partly coherent with the command"
    else:
        rel = "not coherent with the command: a disturbance or an interference, not a response to the input"
    if width <= max(4.0 * b.get("df", 0.0), 0.25 * b["peak_hz"]) and b["peak_hz"] > 0:
        kind = f"narrow-band line at {b['peak_hz']:.4g} Hz"
    elif hi < 2.0:
        kind = f"slow residual below {hi:.3g} Hz"
    else:
        kind = f"broad-band residual {lo:.4g}-{hi:.4g} Hz"
    return f"{kind}, {b['rms']:.3g} rms ({b['rms'] / noise:.2g} x the noise), {rel}"
