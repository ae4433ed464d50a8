"""Reading recordings and cutting them into validation blocks.

A recording is a CSV with ``time`` [s] (uniform), ``u`` [V] (the amplifier command) and ``x`` [um]
and/or ``us`` [V]. Each one is cut into :data:`N_BLOCKS` consecutive blocks; every
:data:`HELDOUT_EVERY`-th block (starting with block ``HELDOUT_EVERY // 2``) is held out: no
parameter is fitted on its measured outputs, and every RMSE diagnose reports is over them.

A recording whose command moves in a few places only (a step up and a step down after rests)
can have every response fall into held-out blocks, or none: then the fit never sees what the
validation judges (rig-045: both ramps of a current-limited amplifier held out, the lag fitted
to noise). When the default pattern leaves the training blocks less than a tenth of their due
share of the command's activity, or holds out the first sample of every jump of the command (a
step's ringing decays within tens of samples: rig-d11-149, two steps, only the last 30 ms of one
response trained, and a 1.5 kHz first mode at damping ratio 0.01 could not improve the fit), the
blocks are held out by rank of activity instead
(:func:`blocks`): the second, sixth, ... most active, so that both sides see the largest moves
(no other phase of the pattern can serve then: the moves all lie in blocks of one phase). When the
command moves throughout but its largest moves (at least :data:`LARGEST` of the largest change
within one sample) all lie in held-out blocks, the blocks are held out by rank of the largest move
in each: a current limit binds there only (rig-d21-086, 390 Hz: a multisine of 371 small "jumps" and
two steps of 28.4 V, both held out; the limit's fit left the training cost at 4386.3 while the
held-out data took all of its correction, and nothing was named). Only
then: a split that merely leans one way changed the outcome of cases both ways when tried
(rig-006 and rig-154 lost their names with a phase that gave the held-out blocks more of the
steps), so the default stays wherever the fit sees the moves.

With a replay rate (``diagnose --replay-rate HZ``) a recording sampled slower is replayed with
several internal steps per sample (:func:`internal_steps`, :func:`.engine.at_samples`). At one step
per sample (the default) the mechanics see the stroke as a straight line from sample to sample;
where the amplifier settles within a sample, or the first mode rings within a few, its path between
the samples is far from that line and the mechanics' response (the push rod, the contact force)
differs by more than the noise. For the true parameters of rig draw 6, 51 of its 185 devices differ
by over one noise rms, nearly all sampled below 2 kHz (rig-d6-116, 545 Hz: 61 noise rms in the force
pick-off; rig-d4-157, 1.04 kHz, a 0.72 ms lag and a 248 Hz mode: 17); at 8 kHz inside
(:data:`INTERNAL_RATE`, the rate to ask for), every one stays below 0.75. Not the default: on the 135
devices of rig draw 7 sampled below 5 kHz it recognised 103 of 131 true mechanisms against 99 with
one step per sample, a false name in 6 cases against 7, clean "nothing is missing" in 17 of 22
against 18, at 1.9 times the time (see docs/diagnose-history.md, stop 47).
"""
from __future__ import annotations

import math

import numpy as np

from ..errors import UserError
from ..recording import read_csv_table
from .model_io import Recording

__all__ = ["HELDOUT_EVERY", "INTERNAL_RATE", "JUMP", "LARGEST", "N_BLOCKS", "RESPONSE_S", "activity",
           "after_jumps", "blocks", "internal_steps", "load_recordings", "make_recordings"]

N_BLOCKS = 64
HELDOUT_EVERY = 4
INTERNAL_RATE = 8000.0      # [Hz] the replay rate measured on the rig (see above)
MAX_OVERSAMPLE = 32         # internal steps per sample at most
MAX_INTERNAL = 160000       # internal steps in one recording at most (20 s at INTERNAL_RATE)
# the response a command change starts is counted over this long after it [s] (amplifier lags
# of 0.2-3 ms, a current-limited step's ramp of tens of ms): a step at the end of one block
# belongs to the next, where its response is
RESPONSE_S = 0.05
# a jump of the command: a change within one sample of at least this share of its span; the
# RESPONSE_S after each are the fast dynamics' (the lags, a mode, the loop's transient), not where a
# slow mechanism is judged (see :func:`after_jumps`)
JUMP = 0.05
# the command's largest moves: changes within one sample of at least this share of the largest
LARGEST = 0.5
# the training blocks are starved when they get less than this share of their due share (75 %)
# of the command's activity
STARVED = 0.1


def internal_steps(dt, n, rate=None):
    """Internal steps per sample of a recording's replay (``dt`` [s], ``n`` samples): one without a
    replay ``rate`` [Hz] or from it up, else enough for ``rate``, within :data:`MAX_OVERSAMPLE` and
    :data:`MAX_INTERNAL`."""
    if rate is None or dt * rate <= 1.0 + 1e-9:
        return 1
    want = math.ceil(rate * dt - 1e-9)
    return int(max(1, min(want, MAX_OVERSAMPLE, MAX_INTERNAL // max(n, 1))))


def load_recordings(paths, columns=None, scale=None):
    """Read recordings: columns time [s], u [V] and x [um] and/or us [V] (after --columns/--scale; a
    unit in a header, ``x [nm]``, is converted, and each entry's ``converted`` says from what)."""
    if not paths:
        raise UserError("give at least one recording (CSV with time, u and x and/or us)")
    out = []
    for path in paths:
        tab = read_csv_table(path, required=("time", "u"), one_of=("x", "us"), columns=columns,
                             scale=scale, uniform=True, min_rows=50)
        out.append({"name": str(path), "time": tab["time"], "u": tab["u"],
                    "x": tab.columns.get("x"), "us": tab.columns.get("us"),
                    "converted": {c: v for c, v in tab.converted.items() if c in ("time", "u", "x", "us")}})
    return out


def activity(u, dt):
    """The command's activity per sample: ``|du|`` [V] spread over the :data:`RESPONSE_S` after it."""
    a = np.abs(np.diff(np.asarray(u, float), prepend=float(u[0])))
    k = max(1, int(round(RESPONSE_S / dt)))
    return np.convolve(a, np.full(k, 1.0 / k))[:a.size]


def _jump_onsets(u):
    """Samples where the command ``u`` [V] jumps: a change of at least :data:`JUMP` of its span
    within one sample."""
    u = np.asarray(u, float)
    span = float(np.ptp(u))
    du = np.abs(np.diff(u, prepend=float(u[0])))
    return np.flatnonzero(du >= JUMP * span) if span > 0 else np.zeros(0, int)


def after_jumps(u, dt):
    """Samples within :data:`RESPONSE_S` after a jump of the command ``u`` [V] (a change of at
    least :data:`JUMP` of its span within one sample; ``dt`` [s] its step): True there.

    A slow mechanism (creep, leakage, a drift) is judged on the held-out samples away from them.
    The transient after a step is the fast dynamics' and the loop's: the PI weights, solved
    again with any candidate, draw it in directions the training blocks need not fix (rig-d8-038,
    three steps after a rest: creep re-solved the weights, its held-out step from rest rose with a
    plateau, and 85 samples of it took the held-out share of its correction from 1.00 to 0.27).
    """
    u = np.asarray(u, float)
    mask = np.zeros(u.size, bool)
    k = max(1, int(round(RESPONSE_S / dt)))
    for j in _jump_onsets(u):
        mask[j:j + k] = True
    return mask


def blocks(n, n_blocks=N_BLOCKS, u=None, dt=None):
    """Validation block of every sample, the held-out mask and how the blocks were chosen.

    Parameters
    ----------
    n : int
        Samples.
    n_blocks : int
        Blocks (fewer for short recordings: 20 samples at least per block).
    u : ndarray, optional
        The command [V]; with ``dt`` [s] (its step), a default split that starves the training
        blocks of the command's moves is replaced (module docstring).

    Returns
    -------
    block : ndarray of int
    heldout : ndarray of bool
    how : str
    """
    nb = n_blocks if n >= 20 * n_blocks else max(4, n // 20)
    block = np.minimum((np.arange(n) * nb) // n, nb - 1)
    default = HELDOUT_EVERY // 2
    how = f"every {HELDOUT_EVERY}th block, starting with block {default}"
    if u is None or dt is None:
        return block, (block % HELDOUT_EVERY) == default, how
    per_block = np.bincount(block, weights=activity(u, dt), minlength=nb)
    total = float(per_block.sum())
    default_held = np.arange(nb) % HELDOUT_EVERY == default
    trained = 1.0 - float(per_block[default_held].sum()) / total if total > 0.0 else 1.0
    # the jumps' first samples: where the fast dynamics (a lightly damped mode's ringing) show at all
    onsets = _jump_onsets(u)
    jumps_trained = onsets.size == 0 or not bool(np.all(default_held[block[onsets]]))
    # the largest moves (at least LARGEST of the largest change within one sample): where a
    # current limit binds and a slow lag shows most
    du = np.abs(np.diff(u, prepend=float(u[0])))
    largest = np.flatnonzero(du >= LARGEST * du.max()) if du.max() > 0.0 else np.zeros(0, int)
    largest_trained = largest.size == 0 or not bool(np.all(default_held[block[largest]]))
    fed = trained >= STARVED * (1.0 - 1.0 / HELDOUT_EVERY)
    if fed and jumps_trained and largest_trained:
        return block, default_held[block], how
    if fed and jumps_trained:
        # by rank of the largest move in each block, then of activity: the block with the largest
        # move trained, the second held out, ...
        biggest = np.zeros(nb)
        np.maximum.at(biggest, block, du)
        rank = np.lexsort((-per_block, -biggest))
        held_blocks = rank[np.arange(nb) % HELDOUT_EVERY == 1]
        return block, np.isin(block, held_blocks), (
            f"{held_blocks.size} of {nb} blocks by rank of the largest move of the command in each "
            "(the second, sixth, ... largest): the every-4th pattern held out all "
            f"{largest.size} of its largest moves (from block {default})")
    # by rank of activity (stable: quiet blocks keep their order): the second, sixth, ... most
    # active blocks held out, so both sets see the largest moves of the command
    rank = np.argsort(-per_block, kind="stable")
    held_blocks = rank[np.arange(nb) % HELDOUT_EVERY == 1]
    why = (f"the training blocks would have had {100 * trained:.0f} % of them" if jumps_trained else
           f"every one of the command's {onsets.size} jumps would have started in a held-out block")
    return block, np.isin(block, held_blocks), (
        f"{held_blocks.size} of {nb} blocks by rank of the command's activity (the second, sixth, ... "
        "most active): no phase of the every-4th pattern shared the command's few moves between "
        f"training and held-out blocks (from block {default} {why})")


def make_recordings(raw, replay_rate=None):
    """:class:`.model_io.Recording` objects from read (or in-memory) recordings; ``replay_rate``
    [Hz]: replay those sampled slower with internal steps up to that rate (:func:`internal_steps`)."""
    if replay_rate is not None and not (math.isfinite(replay_rate) and replay_rate > 0):
        raise UserError(f"the replay rate must be a positive number of Hz, not {replay_rate!r}")
    recs = []
    for r in raw:
        t = np.asarray(r["time"], float)
        dt = float(np.median(np.diff(t)))
        u = np.asarray(r["u"], float)
        block, held, how = blocks(t.size, u=u, dt=dt)
        recs.append(Recording(r["name"], t - t[0], dt, u,
                              None if r.get("x") is None else np.asarray(r["x"], float),
                              None if r.get("us") is None else np.asarray(r["us"], float),
                              held, float(t[0]), block, {}, how, internal_steps(dt, t.size, replay_rate),
                              after_jumps(u, dt)))
    return recs
