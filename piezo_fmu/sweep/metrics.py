"""What one closed-loop run is worth to a designer: tracking error, stroke, overshoot, settling, stability.

Computed from the recorded samples of a run (``time`` [s], ``x_ref`` and ``x`` [um], ``uc`` [V]),
with the tracking error ``e = x - x_ref`` as in the reproduction (README, "How each error is
computed"):

* ``max_um = max|e|``, ``avg_um = mean|e|``, ``rms_um = sqrt(mean e^2)`` over the samples after
  ``skip`` seconds (0: every sample, the first period included, as in the paper's tables);
* ``stroke_um = max x - min x``;
* the *span* the output has to cover is ``[lo, hi]``, the range of ``x_ref`` and of the initial
  displacement (a step from rest covers rest -> final value);
  ``overshoot_pct = 100 max(0, max x - hi, lo - min x) / (hi - lo)``;
* ``settling_time_s``: time from the start after which ``|e|`` stays within
  ``settle_band * (hi - lo)`` (a step's settling time; for a sine, the time the loop needs to lock
  on); NaN when the last sample is still outside the band;
* ``stable`` (a heuristic, true or false): every value finite; the error does not grow (the largest
  ``|e|`` over the last third of the run is at most twice that over the middle third, plus 1 nm);
  and the command does not oscillate on its own: over the second half, ``uc`` reverses (turns
  back by more than 40 % of the command range ``uc_max - uc_min``) at most four times as often as
  the reference does, plus four. A loop driven unstable grows until the command saturates, then
  rails back and forth at the loop's own frequency: either test catches it. Poor tracking (a
  lagging feedforward at 200 Hz, a command clipped at a limit once per period) is not
  instability. On the paper's model, Kp = 12, Kd = 5e-4 s or Ki = 1e6 1/s oscillate rail to rail
  without any noise; Kp = 8 or Kd = 2e-4 s do so on the 1 mV sensor noise alone (counted as not
  stable: that loop is not usable either); Kp = 3 or Ki = 3e5 1/s amplify the noise but stay
  well inside the band (stable).

All are NaN (``stable`` false) when the run has no samples after ``skip``.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["METRIC_NAMES", "UNITS", "compute", "reversals"]

METRIC_NAMES = ("max_um", "avg_um", "rms_um", "stroke_um", "overshoot_pct", "settling_time_s", "stable")
UNITS = {"max_um": "um", "avg_um": "um", "rms_um": "um", "stroke_um": "um", "overshoot_pct": "%",
         "settling_time_s": "s", "stable": ""}
GROWTH = 2.0            # largest |e|, last third over middle third
GROWTH_FLOOR = 1e-3     # [um] below this no growth is counted (sensor noise is ~2 nm)
REVERSAL = 0.4          # a reversal of the command: turning back by this share of its range
OSCILLATION = 4.0       # command reversals allowed per reference reversal


def compute(t, x_ref, x, uc=None, uc_limits=None, skip=0.0, settle_band=0.02, ref_freq=0.0,
            names=METRIC_NAMES) -> dict:
    """The metrics ``names`` of one run (see the module docstring).

    Parameters
    ----------
    t : array
        Sample times [s].
    x_ref, x : array
        Reference and displacement [um].
    uc : array, optional
        Amplifier command [V] (for ``stable``).
    uc_limits : (float, float), optional
        The compensator's command limits ``(uc_min, uc_max)`` [V].
    skip : float
        Time left out of the error metrics at the start [s].
    settle_band : float
        Settling band as a fraction of the span (0.02: 2 %).
    ref_freq : float
        Frequency of a periodic reference [Hz] (0: not periodic), for ``stable``.
    names : sequence of str
        Which metrics.

    Returns
    -------
    dict
        ``{name: float}`` (``stable``: bool).
    """
    t = np.asarray(t, dtype=float)
    x_ref = np.asarray(x_ref, dtype=float)
    x = np.asarray(x, dtype=float)
    out = {}
    nan = math.nan
    keep = t >= t[0] + skip - 1e-12 if t.size else np.zeros(0, bool)
    e_all = x - x_ref
    e = e_all[keep]
    finite = bool(np.all(np.isfinite(x))) and bool(np.all(np.isfinite(x_ref)))
    if e.size == 0:
        return {n: (False if n == "stable" else nan) for n in names}
    lo = min(float(np.min(x_ref)), float(x[0])) if finite else nan
    hi = max(float(np.max(x_ref)), float(x[0])) if finite else nan
    span = hi - lo
    for n in names:
        if n == "max_um":
            out[n] = float(np.max(np.abs(e)))
        elif n == "avg_um":
            out[n] = float(np.mean(np.abs(e)))
        elif n == "rms_um":
            out[n] = float(np.sqrt(np.mean(e * e)))
        elif n == "stroke_um":
            out[n] = float(np.max(x[keep]) - np.min(x[keep]))
        elif n == "overshoot_pct":
            over = max(0.0, float(np.max(x)) - hi, lo - float(np.min(x)))
            out[n] = 100.0 * over / span if finite and span > 0 else nan
        elif n == "settling_time_s":
            out[n] = _settling(t, e_all, settle_band * span) if finite and span > 0 else nan
        elif n == "stable":
            out[n] = (finite and _not_growing(e_all)
                      and not _oscillating(t, uc, uc_limits, ref_freq))
        else:
            raise ValueError(f"unknown metric {n!r} (known: {', '.join(METRIC_NAMES)})")
    return out


def _settling(t, e, band):
    outside = np.flatnonzero(np.abs(e) > band)
    if outside.size == 0:
        return 0.0
    last = outside[-1]
    if last == e.size - 1:
        return math.nan
    return float(t[last + 1] - t[0])


def _not_growing(e):
    n = e.size
    if n < 3:
        return True
    middle = np.abs(e[n // 3: 2 * n // 3])
    last = np.abs(e[2 * n // 3:])
    if middle.size == 0 or last.size == 0:
        return True
    return bool(np.max(last) <= GROWTH * np.max(middle) + GROWTH_FLOOR)


def _oscillating(t, uc, limits, ref_freq):
    """Does the command reverse far more often than the reference over the second half?"""
    if uc is None:
        return False
    uc = np.asarray(uc, dtype=float)
    k = uc.size // 2
    half = uc[k:]
    if half.size < 3 or not np.all(np.isfinite(half)):
        return not np.all(np.isfinite(half))
    width = (limits[1] - limits[0]) if limits is not None else float(np.ptp(uc))
    if not width > 0:
        return False
    duration = float(t[-1] - t[k])
    expected = 2.0 * ref_freq * duration
    return reversals(half, REVERSAL * width) > OSCILLATION * expected + 4


def reversals(u, h) -> int:
    """How often ``u`` turns back by more than ``h`` (a peak or valley counted once it is left by
    ``h``; smaller wiggles ignored)."""
    u = np.asarray(u, dtype=float)
    u = u[np.concatenate(([True], np.diff(u) != 0))]        # plateaus: one sample each
    d = np.diff(u)
    turn = np.flatnonzero(np.sign(d[1:]) * np.sign(d[:-1]) < 0) + 1     # local extrema only
    pts = np.concatenate(([u[0]], u[turn], [u[-1]])).tolist()
    count = 0
    up = None
    ext = lo = hi = pts[0]
    for v in pts[1:]:
        if up is None:                       # no direction yet: wait for a move of h
            lo, hi = min(lo, v), max(hi, v)
            if hi - lo > h:
                up = v == hi
                ext = v
        elif up:
            if v > ext:
                ext = v
            elif ext - v > h:
                count += 1
                up, ext = False, v
        else:
            if v < ext:
                ext = v
            elif v - ext > h:
                count += 1
                up, ext = True, v
    return count
