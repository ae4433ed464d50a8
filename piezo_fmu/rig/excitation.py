"""Excitation programmes: 2-4 segments in random order, each starting and ending at rest.

Segment kinds (every voltage inside the amplifier's range ``[u_lo, u_hi]``, rest ``u_rest``):

* ``steps``: jumps from rest to 1-3 levels and back, every level held >= 1 s (creep, leakage,
  ringing and slew limiting show here);
* ``multisine``: 3-8 sines, 0.5 Hz to min(200 Hz, fs/5), random phases, faded in and out;
* ``sine_set``: 2-4 sines one after the other (0.5 Hz to min(50 Hz, fs/10)), whole periods
  from rest, ``u_rest + A (1 - cos 2 pi f t)`` (the paper's starting-at-minimum sine);
* ``triangle``: a decaying triangle, either from rest to falling peaks or centred with falling
  amplitude (nested reversal loops);
* ``chirp``: a logarithmic chirp from 0.5-2 Hz to min(100 Hz, fs/7), faded out;
* ``rest``: a hold at rest.
"""
from __future__ import annotations

import numpy as np

KINDS = ("steps", "multisine", "sine_set", "triangle", "chirp", "rest")
MIN_DURATION = {"steps": 2.3, "multisine": 1.0, "sine_set": 1.5, "triangle": 1.5, "chirp": 1.2,
                "rest": 0.5}


def _fade(n: int, fs: float, t_fade: float) -> np.ndarray:
    """Half-cosine envelope rising over ``t_fade`` and falling over the last ``t_fade`` [s]."""
    k = max(1, min(int(t_fade * fs), n // 2))
    env = np.ones(n)
    ramp = 0.5 - 0.5 * np.cos(np.pi * np.arange(k) / k)
    env[:k] = ramp
    env[n - k:] = ramp[::-1]
    return env


def _steps(rng, fs, n, u_rest, u_lo, u_hi):
    T = n / fs
    lead = rng.uniform(0.1, 0.3)
    holds_n = int(min(4, max(2, np.floor((T - lead) / 1.0))))
    holds_n = int(rng.integers(2, holds_n + 1))
    share = rng.dirichlet(np.ones(holds_n))
    holds = 1.0 + (T - lead - holds_n * 1.0) * share
    levels = []
    prev = u_rest
    for _ in range(holds_n - 1):
        for _try in range(20):
            lv = rng.uniform(u_lo if rng.random() < 0.3 else u_rest, u_hi)
            if abs(lv - prev) >= 0.25 * (u_hi - u_lo):
                break
        levels.append(lv)
        prev = lv
    levels.append(u_rest)
    u = np.full(n, u_rest)
    edges = lead + np.concatenate([[0.0], np.cumsum(holds)])
    for lv, t0, t1 in zip(levels, edges[:-1], edges[1:]):
        u[round(t0 * fs):round(t1 * fs)] = lv
    return u, {"levels": [float(v) for v in levels], "holds": [float(h) for h in holds]}


def _multisine(rng, fs, n, u_rest, u_lo, u_hi):
    t = np.arange(n) / fs
    fmax = min(200.0, fs / 5.0)
    k = int(rng.integers(3, 9))
    freqs = np.sort(np.exp(rng.uniform(np.log(0.5), np.log(fmax), k)))
    amps = 1.0 / np.sqrt(1.0 + freqs / 20.0)
    wave = sum(a * np.sin(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi)) for a, f in zip(amps, freqs))
    wave /= np.abs(wave).max()
    lo = u_lo if rng.random() < 0.5 else u_rest
    half = 0.5 * (u_hi - lo) * rng.uniform(0.5, 0.95)
    mid = lo + 0.5 * (u_hi - lo)
    env = _fade(n, fs, min(0.3, 0.2 * n / fs))
    return u_rest + env * (mid - u_rest + half * wave), {"freqs": freqs.tolist(), "amplitude": half}


def _sine_set(rng, fs, n, u_rest, u_lo, u_hi):
    fmax = min(50.0, fs / 10.0)
    choices = [f for f in (0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 50.0) if f <= fmax]
    k = int(rng.integers(2, 5))
    freqs = list(rng.choice(choices, size=k))
    T = n / fs
    u = np.full(n, u_rest)
    share = rng.dirichlet(np.ones(k)) * T
    pos = 0
    used = []
    for f, dur in zip(freqs, share):
        m = int(np.floor(dur * f)) if dur * f >= 1 else 0
        if m == 0:
            continue
        seg_n = round(m / f * fs)
        if pos + seg_n > n:
            break
        amp = 0.5 * (u_hi - u_rest) * rng.uniform(0.4, 1.0)
        tt = np.arange(seg_n) / fs
        u[pos:pos + seg_n] = u_rest + amp * (1 - np.cos(2 * np.pi * f * tt))
        used.append((float(f), float(amp)))
        pos += seg_n
    return u, {"sines": used}


def _triangle(rng, fs, n, u_rest, u_lo, u_hi):
    T = n / fs
    f = rng.uniform(0.5, min(5.0, fs / 20.0))
    cycles = max(1, int(np.floor(T * f)))
    f = cycles / T
    rho = rng.uniform(0.55, 0.9)
    peaks = (u_hi - u_rest) * rng.uniform(0.7, 1.0) * rho ** np.arange(cycles)
    centred = rng.random() < 0.5
    times = [0.0]
    vals = [u_rest]
    if centred:
        lo = min(u_rest, u_lo)
        mid = 0.5 * (lo + u_hi)
        amp = 0.5 * (u_hi - lo) * rng.uniform(0.7, 1.0) * rho ** np.arange(cycles)
        for c in range(cycles):
            t0 = c / f
            times += [t0 + 0.25 / f, t0 + 0.75 / f]
            vals += [mid + amp[c], mid - amp[c]]
        vals[-1] = u_rest
    else:
        for c in range(cycles):
            t0 = c / f
            times += [t0 + 0.5 / f, t0 + 1.0 / f]
            vals += [u_rest + peaks[c], u_rest]
    times[-1] = T
    t = np.arange(n) / fs
    return np.interp(t, times, vals), {"freq": float(f), "decay": float(rho), "centred": centred}


def _chirp(rng, fs, n, u_rest, u_lo, u_hi):
    T = n / fs
    t = np.arange(n) / fs
    f0 = rng.uniform(0.5, 2.0)
    f1 = max(f0 * 2, min(100.0, fs / 7.0))
    k = np.log(f1 / f0)
    phase = 2 * np.pi * f0 * T / k * (np.exp(t / T * k) - 1.0)
    amp = 0.5 * (u_hi - u_rest) * rng.uniform(0.4, 0.9)
    env = np.ones(n)
    tail = max(1, int(0.1 * n))
    env[n - tail:] = 0.5 + 0.5 * np.cos(np.pi * np.arange(tail) / tail)
    return u_rest + env * amp * (1 - np.cos(phase)), {"f0": f0, "f1": f1, "amplitude": amp}


def _rest(rng, fs, n, u_rest, u_lo, u_hi):
    return np.full(n, u_rest), {}


_MAKERS = {"steps": _steps, "multisine": _multisine, "sine_set": _sine_set,
           "triangle": _triangle, "chirp": _chirp, "rest": _rest}


def choose_kinds(rng: np.random.Generator, required: list[str], max_time: float) -> list[str]:
    """2-4 segment kinds, including every kind in ``required``, in random order.

    ``required`` may hold alternatives as ``"a|b"`` (one of them is taken). Kinds are added only
    while their minimum durations fit into ``max_time`` [s].
    """
    kinds = []
    for req in required:
        opts = req.split("|")
        if not any(o in kinds for o in opts):
            kinds.append(opts[rng.integers(len(opts))])
    target = int(rng.integers(2, 5))
    pool = ["steps", "multisine", "sine_set", "triangle", "chirp", "rest"]
    while len(kinds) < target:
        extra = pool[rng.integers(len(pool))]
        if sum(MIN_DURATION[k] for k in kinds) + MIN_DURATION[extra] > max_time:
            break
        kinds.append(extra)
    if len(kinds) < 2:
        kinds.append("rest")
    if all(k == "rest" for k in kinds):             # something must move the stack
        kinds[0] = pool[int(rng.integers(len(pool) - 1))]
    rng.shuffle(kinds)
    return kinds


def programme(rng: np.random.Generator, fs: float, duration: float, kinds: list[str],
              u_rest: float, u_lo: float, u_hi: float) -> tuple[np.ndarray, list[dict]]:
    """The command ``u`` [V] at ``fs`` [Hz] for ``duration`` [s], and its segment list.

    Parameters
    ----------
    rng : numpy.random.Generator
    fs : float
        Sample rate [Hz].
    duration : float
        Total duration [s]; at least the sum of ``MIN_DURATION`` of ``kinds``.
    kinds : list of str
        Segment kinds in order (see ``KINDS``).
    u_rest, u_lo, u_hi : float
        Rest voltage and the amplifier's range [V].

    Returns
    -------
    u : ndarray
        Command [V], ``round(duration * fs)`` samples.
    segments : list of dict
        ``kind``, ``start`` and ``stop`` [s] and the segment's parameters.
    """
    n_total = round(duration * fs)
    mins = np.array([MIN_DURATION[k] for k in kinds])
    spare = max(0.0, duration - mins.sum())
    durs = mins + spare * rng.dirichlet(np.ones(len(kinds)) * 2.0)
    bounds = np.round(np.concatenate([[0.0], np.cumsum(durs)]) / durs.sum() * n_total).astype(int)
    parts = []
    segments = []
    for kind, a, b in zip(kinds, bounds[:-1], bounds[1:]):
        seg, info = _MAKERS[kind](rng, fs, int(b - a), u_rest, u_lo, u_hi)
        parts.append(np.clip(seg, u_lo, u_hi))
        segments.append({"kind": kind, "start": a / fs, "stop": b / fs, **info})
    return np.concatenate(parts), segments
