"""What a slowly sampled recording leaves between its samples: the straight-line path's misfit.

At one replay step per sample (the default) the mechanics see the stroke as a straight line from
sample to sample. Where the amplifier settles within a sample or the first mode rings within a few,
the true path is far from that line, and a recalibrated model of a device with nothing missing
leaves a structured residual of several noise rms right after the command's jumps: of rig draw
23's 27 clean devices, 9 ended "a structured residual remains", 8 of them sampled at 283 Hz-3.2 kHz,
most with a first mode near or above the Nyquist frequency that the recalibration's search (up to
0.8 x the sample rate, on the straight line) did not find. Replaying all the time at a finer step,
or along the amplifier's lag, moves decisions the search was set on (``--replay-rate``, stop 47;
the model's ``simulation.stroke_path``, stops 48 and 76), so this asks only at the
end, when nothing is named and more than the ordinary misfit is left: replayed at
:data:`~.recordings.INTERNAL_RATE` inside, with a first mode searched up to twice the sample rate
when none was found, does the recalibrated model leave no more than the ordinary misfit? If so,
what was left is the path between the samples, not missing physics.
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from .engine import predict
from .fit import Fitter, free_names
from .recalibrate import mode_at, mode_picks
from .recordings import INTERNAL_RATE, internal_steps

__all__ = ["between_samples"]


def between_samples(fitter: Fitter, p, struct, noise, step=None):
    """Refit the ordinary parameters of ``p`` (``fitter.ordinary`` and ``struct``'s) with the
    recordings replayed at :data:`INTERNAL_RATE` inside, and return ``{"rate_hz", "steps_per_sample",
    "structured_rms": {channel: value in the channel's unit}, "rmse", "first_mode"}`` over all
    samples (with the ``noise`` levels per channel; ``first_mode.found_here``: searched by
    :func:`_first_mode`, up to twice the sample rate), or None when every recording is sampled at
    that rate or faster."""
    fine = [replace(r, oversample=internal_steps(r.dt, r.n, INTERNAL_RATE)) for r in fitter.recs]
    if all(r.oversample == 1 for r in fine):
        return None
    if step:
        step(f"refitting the recalibrated model with {max(r.oversample for r in fine)} steps per sample "
             "(the stroke's path between the samples)")
    fit = Fitter(fine, fitter.dev, fitter.lam)
    fit.limits = dict(fitter.limits)
    fit.restart = dict(fitter.restart)
    fit.ordinary = list(fitter.ordinary)
    q, found = p, False
    if "mech_f" not in fit.ordinary:
        q = _first_mode(fit, p, struct)
        found = "mech_f" in fit.ordinary
    q = fit.fit(q, struct, free=free_names(struct, fit.ordinary), max_nfev=10, held=True).params
    structured, rmse = {}, {}
    for c in noise:
        e = [getattr(r, c) - predict(r, fit.dev, q)[c] for r in fine if getattr(r, c) is not None]
        if not e:
            continue
        ms = float(np.mean(np.concatenate(e) ** 2))
        structured[c] = math.sqrt(max(ms - noise[c] ** 2, 0.0))
        rmse[c] = math.sqrt(ms)
    f1, z1 = q.mode(fit.dev)
    return {"rate_hz": INTERNAL_RATE, "steps_per_sample": max(r.oversample for r in fine),
            "structured_rms": structured, "rmse": rmse,
            "first_mode": {"frequency_hz": float(f"{f1:.5g}"), "zeta": float(f"{z1:.4g}"),
                           "found_here": found}}


# where the first mode is searched, in units of the sample rate: a mode above the Nyquist frequency
# that the command's jumps ring (rig-d23-004: 466 Hz, zeta 0.27, sampled at 517 Hz; rig-d23-118:
# 314 Hz at 307 Hz) shows at the samples only through the path between them, which a replay at
# one step per sample does not have, and the recalibration's search stops at 0.8 x the rate
MODE_SPAN = (0.3, 2.0)


def _first_mode(fit: Fitter, p, struct):
    """``p`` with the first mode that fits the finely replayed recordings best (screened over
    :data:`MODE_SPAN` with the weights held, the best two starts fitted with every pick-off the
    channels allow), or ``p`` itself when none fits better; ``fit.ordinary`` gains the mode's
    parameters when one is taken."""
    lo, hi = (MODE_SPAN[0] * fit.fs, MODE_SPAN[1] * fit.fs)
    fit.limits["mech_f"] = (max(100.0, 0.5 * lo), min(25000.0, 1.5 * hi))
    picks = mode_picks(fit)
    starts, qs = [], []
    for pick in picks:
        for f in np.exp(np.linspace(math.log(lo), math.log(hi), 12)):
            for z in (0.05, 0.25):
                q = p.copy()
                q.pick = pick
                q.set_mode(fit.dev, f=float(f), zeta=z)
                starts.append((float(f), z))
                qs.append(q)
    best, cost0 = None, fit.cost(p)
    for _, (f, z) in sorted(zip(fit.quick_many(qs), starts))[:2]:
        fr = mode_at(fit, p, struct, f, z)
        if fr is not None and fr.cost < cost0 and (best is None or fr.cost < best.cost):
            best = fr
    if best is None:
        return p
    fit.ordinary = fit.ordinary + ["mech_f", "mech_zeta"]
    return best.params

