"""Ordinary twins: whether a present effect gives the same record as the nominal physics re-tuned.

The rig calls an effect present when it changes the record by 3 noise rms beyond each channel's
gain and offset. Some do so in a way the device's ordinary physics, which a diagnosis must
recalibrate before it names anything, draws as well: a further mode where the first mode is
above the sample rate's reach is a first mode at the further mode's frequency; a command delay
is an amplifier lag (a slower stage, or a second one) where the drive holds no fast content; with
one recorded channel a delay of whole samples is that channel's sampling lag. For each such effect
this module builds the twin with the rig's own equations (the case's plant and command, the effect
taken out, an ordinary parameter moved in its place and its amplifier lag searched) and measures
how far it lies from the record, as the visibility does (rms beyond an affine fit, in noise rms,
the larger channel).
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from .plant import Effects, Plant, Simulator

__all__ = ["MODE_RANGE_HZ", "SECOND_STAGE", "TWIN_SAME", "ordinary_twins"]

MODE_RANGE_HZ = (100.0, 20000.0)   # where a device's first mode may lie (issue 12's nominal range)
TWIN_SAME = 3.0                    # a twin this close (noise rms beyond affine) is the same record
SECOND_STAGE = (0.5, 1.0, 1.5)     # a delay's two-stage twins: the internal stage this many delays slower


def _beyond_affine(full, twin, sigma):
    """rms of ``full`` minus the best affine map of ``twin``, over ``sigma``."""
    t0 = twin - twin.mean()
    d0 = full - full.mean()
    tt = float(t0 @ t0)
    beta = float(t0 @ d0) / tt if tt > 0 else 0.0
    return float(np.sqrt(np.mean((d0 - beta * t0) ** 2)) / sigma)


def _distance(full, twin, plant: Plant, channels):
    sig = {"x": plant.sigma_x, "us": plant.sigma_us}
    return max(_beyond_affine(full[ch], twin[ch], sig[ch]) for ch in channels)


def _lag_searched(plant: Plant, u, effects: Effects, full, channels, lo, hi, n=7, steps=6):
    """The twin's output-stage lag searched in ``lo`` .. ``hi`` [s] (a log grid, then a golden
    refinement around the best): ``(distance, tau)``."""
    cache = {}

    def dist(log_tau):
        tau = math.exp(log_tau)
        if tau not in cache:
            sim = Simulator(replace(plant, amp_tau=tau), u)
            cache[tau] = _distance(full, sim.run(effects), plant, channels)
        return cache[tau]

    grid = np.linspace(math.log(lo), math.log(hi), n)
    vals = [dist(g) for g in grid]
    k = int(np.argmin(vals))
    a, b = grid[max(k - 1, 0)], grid[min(k + 1, n - 1)]
    g = (math.sqrt(5) - 1) / 2
    c, d = b - g * (b - a), a + g * (b - a)
    for _ in range(steps):
        if dist(c) < dist(d):
            b, d = d, c
            c = b - g * (b - a)
        else:
            a, c = c, d
            d = a + g * (b - a)
    best = min(cache, key=cache.get)
    return cache[best], best


def ordinary_twins(sim: Simulator, effects: Effects, full: dict, channels) -> dict:
    """The closest ordinary twin of each present effect that may have one.

    Parameters
    ----------
    sim : Simulator
        The case's plant and command.
    effects : Effects
        The effects put in.
    full : dict
        The noise-free channels of the case (``Simulator.run(effects)``).
    channels : list of str
        The recorded channels.

    Returns
    -------
    dict
        ``{effect: {"twin": what it is, "distance": noise rms beyond affine (the larger
        channel), "same": distance < TWIN_SAME, "amp_tau_s": the twin's output-stage lag [s]
        where searched}}`` for ``time_delay`` (the amplifier's output stage slower, or its internal
        stage slower or added, ``amp_tau2_s``, with the output stage searched beside it; with one
        channel and a delay of whole samples also that channel sampled late) and
        ``extra_resonance`` with its frequency in :data:`MODE_RANGE_HZ` (the first mode there,
        the sensor on the push rod).
    """
    plant, u = sim.plant, sim.u
    out = {}
    td = effects.get("time_delay")
    if td is not None and td["steps_internal"] > 0:
        rest = effects.without("time_delay")
        delay = td["delay"]
        d_lag, tau = _lag_searched(plant, u, rest, full, channels, plant.amp_tau,
                                   plant.amp_tau + 3.0 * delay)
        best = {"twin": "no delay, the amplifier's output stage slower", "distance": d_lag,
                "amp_tau_s": tau}
        # the amplifier's order is ordinary physics too: a second stage (or the internal stage
        # slower) of about the delay, the output stage searched beside it (rig-d22-020: a 0.35 ms
        # delay beside a one-stage 1.15 ms amplifier lies 5.0 noise rms from the best slower stage
        # and 0.61 from stages of 0.96 + 0.53 ms)
        for k in SECOND_STAGE:
            tau2 = plant.amp_tau2 + k * delay
            d2, tau = _lag_searched(replace(plant, amp_tau2=tau2), u, rest, full, channels,
                                    0.6 * plant.amp_tau, plant.amp_tau + 2.0 * delay, n=5, steps=4)
            if d2 < best["distance"]:
                what = "its internal stage slower" if plant.amp_tau2 > 0 else "a second stage"
                best = {"twin": f"no delay, the amplifier with {what} ({1e3 * tau2:.3g} ms)",
                        "distance": d2, "amp_tau_s": tau, "amp_tau2_s": tau2}
        k = td["steps_internal"] / plant.oversample
        if len(channels) == 1 and abs(k - round(k)) < 1e-9:
            y = sim.run(rest)[channels[0]]
            k = int(round(k))
            shifted = {channels[0]: np.concatenate([np.full(k, y[0]), y[:-k]])}
            d_shift = _distance(full, shifted, plant, channels)
            if d_shift < best["distance"]:
                best = {"twin": f"no delay, the one channel sampled {k} sample(s) late", "distance": d_shift}
        out["time_delay"] = best
    er = effects.get("extra_resonance")
    if er is not None and MODE_RANGE_HZ[0] <= er["f"] <= MODE_RANGE_HZ[1]:
        rest = effects.without("extra_resonance")
        twin_plant = replace(plant, f1=er["f"], zeta1=er["zeta"], pickoff="displacement")
        # the device's own mode, gone from the twin, had added phase lag 2 zeta / w below it
        own_lag = 2.0 * plant.zeta1 / (2.0 * math.pi * plant.f1)
        d, tau = _lag_searched(twin_plant, u, rest, full, channels, 0.7 * plant.amp_tau,
                               plant.amp_tau + 3.0 * own_lag + 0.3 * plant.amp_tau)
        out["extra_resonance"] = {"twin": f"no further mode, the first mode at {er['f']:.4g} Hz "
                                          f"(damping {er['zeta']:.3g}), the sensor on the push rod",
                                  "distance": d, "amp_tau_s": tau}
    for v in out.values():
        v["same"] = bool(v["distance"] < TWIN_SAME)
        v["distance"] = round(float(v["distance"]), 3)
    return out
