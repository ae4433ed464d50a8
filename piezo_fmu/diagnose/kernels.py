"""The compiled kernels of the diagnose engine's replay (:mod:`.engine`).

``amp_run`` (the core's amplifier up to the stack voltage), ``play_run`` / ``pi_run`` (the play
operators, stored or weighted and summed), ``cell_run`` (the KP cells) and ``sos_run`` (second-order
sections on every row of a design, or one row: scipy's sosfilt to the bit but for the flush
below). All are compiled with numba (:func:`piezo_fmu.core.compiled.jit`, cached) and release the
GIL, so the worker threads (:mod:`.workers`) run them side by side.
"""
from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from ..core.compiled import jit, rebind
from ..core.plant import amp_step
from ..core.linear import TINY

__all__ = ["BLOCK", "kernels"]

# The filters' states are flushed to zero at the end of every BLOCK samples where their magnitude
# is below TINY. A filter whose input has come back to an exact zero (a column of a design before
# its operator first moves, a chain settled at its start) decays into subnormal doubles and, with
# their coarse rounding, can stay there in a limit cycle for the rest of the record; on an Intel
# Xeon each operation on a subnormal costs some hundred cycles (on the AMD EPYC of the earlier
# stops far less): a 39-row design of rig-d14-095 took 36 ns per sample and row against 12 ns on
# random input, and its subnormal outputs slowed the Gram products after it. 1e-290 is below
# anything a signal in these units can mean and above where a product with a filter coefficient
# turns subnormal. Everything else is scipy's sosfilt to the bit (tests/test_diagnose.py). The
# core's units use the same threshold (core.linear.TINY), flushed every step.
BLOCK = 64
# Which path a filter takes (sos_run), measured on the Intel Xeon, 200 k samples, ns per sample, row
# and section, before -> after (before: rows side by side in a buffer for every design, a row alone
# section after section): one section 1 row 5.4-5.6 -> 4.4, 4 rows 3.9 -> 2.1, 20 rows 2.5 -> 2.1;
# two sections 1 row 4.7-4.9 -> 2.8, 4 rows 2.8-3.2 -> 1.8-2.0, 8-16 rows 2.6 either way, 24-40 rows
# 4.1-4.7 -> 3.4; three sections side by side stay (5 rows 2.1, four at a time would be 4.9)


def amp_run(uc, nd, k_amp, tau, slew, u_min, u_max, h, tau2, out):
    # the core's actuator_step up to ua (delay line, input stage, output stage)
    decay = math.exp(-h / tau)
    d2 = math.exp(-h / tau2) if tau2 > 0.0 else 0.0
    m2 = (tau2 / h) * (1.0 - d2) if tau2 > 0.0 else 0.0
    ua = 0.0
    y = 0.0
    out[0] = 0.0
    for k in range(uc.size - 1):
        c = uc[k - nd] if k >= nd else 0.0
        if tau2 > 0.0:
            e2 = y - c
            y = c + e2 * d2
            c = c + e2 * m2
        target = k_amp * c
        if target < u_min:
            target = u_min
        elif target > u_max:
            target = u_max
        ua = amp_step(ua, target, tau, slew, h, decay)
        out[k + 1] = ua
    return out


def play(z, v, r):
    # one play operator (threshold r) moved by the input v: the rule of core.hysteresis.pi_step
    lo = v - r
    if z < lo:
        return lo
    return min(z, v + r)


def play_run(v, r, z, z0):
    # the operators are independent: four at a time (their recursions, each waiting on its
    # comparisons, overlap), each row's writes contiguous
    n = r.size
    i = 0
    while i + 4 <= n:
        ra, rb, rc, rd = r[i], r[i + 1], r[i + 2], r[i + 3]
        za, zb, zc, zd = z0[i], z0[i + 1], z0[i + 2], z0[i + 3]
        for k in range(v.size):
            vk = v[k]
            za = play(za, vk, ra)
            zb = play(zb, vk, rb)
            zc = play(zc, vk, rc)
            zd = play(zd, vk, rd)
            z[i, k] = za
            z[i + 1, k] = zb
            z[i + 2, k] = zc
            z[i + 3, k] = zd
        i += 4
    while i < n:
        ri = r[i]
        zi = z0[i]
        for k in range(v.size):
            zi = play(zi, v[k], ri)
            z[i, k] = zi
        i += 1
    return z


def pi_run(v, r, w, y_inv, out, z0):
    # the weighted sum of the operators (and the strain saturation) without storing them: four
    # operators at a time, added in their order (the sum of one operator after another)
    out[:] = 0.0
    n = r.size
    i = 0
    while i + 4 <= n:
        ra, rb, rc, rd = r[i], r[i + 1], r[i + 2], r[i + 3]
        wa, wb, wc, wd = w[i], w[i + 1], w[i + 2], w[i + 3]
        za, zb, zc, zd = z0[i], z0[i + 1], z0[i + 2], z0[i + 3]
        for k in range(v.size):
            vk = v[k]
            za = play(za, vk, ra)
            zb = play(zb, vk, rb)
            zc = play(zc, vk, rc)
            zd = play(zd, vk, rd)
            out[k] = out[k] + wa * za + wb * zb + wc * zc + wd * zd
        i += 4
    while i < n:
        ri = r[i]
        wi = w[i]
        zi = z0[i]
        for k in range(v.size):
            zi = play(zi, v[k], ri)
            out[k] += wi * zi
        i += 1
    if y_inv > 0.0:
        for k in range(v.size):
            out[k] = out[k] / (1.0 + abs(out[k]) * y_inv)
    return out


def cell_run(v, up, down, width, s0, ref, mu, out):
    # each KP cell on its own (the rule of core.preisach.kp_step), counted from its relaxed
    # state: its states into out[i], or (mu given) its weighted states summed into out[0]
    summed = mu.size > 0
    for i in range(up.size):
        a = up[i]
        b = down[i]
        w = width[i]
        s = s0[i]
        r = ref[i]
        row = out[0] if summed else out[i]
        m = mu[i] if summed else 0.0
        for k in range(v.size):
            lo = min(max(2.0 * (v[k] - a) / w + 1.0, -1.0), 1.0)
            hi = min(max(2.0 * (v[k] - b) / w - 1.0, -1.0), 1.0)
            if s < lo:
                s = lo
            elif s > hi:
                s = hi
            if summed:
                row[k] += m * (s - r)
            else:
                row[k] = s - r
    return out


def section(sos, s):
    # one second-order section's coefficients [b0 b1 b2 1 a1 a2]: b0, b1, b2, a1, a2
    return sos[s, 0], sos[s, 1], sos[s, 2], sos[s, 4], sos[s, 5]


def flush(v):
    # a filter state below TINY is zero (see TINY)
    return v if abs(v) >= TINY else 0.0


def step(xi, s1, s2, b0, b1, b2, a1, a2):
    # one sample through one section (transposed direct form II): output, new states
    yi = b0 * xi + s1
    return yi, b1 * xi - a1 * yi + s2, b2 * xi - a2 * yi


def sos_row(sos, x, gain, c0, dc, out, i, settled, dstep):
    # one row, BLOCK samples at a time, the states in registers. A row's recursion waits on
    # each multiply-add: with one or two sections, input, sections and output are one pass
    # (two sections' recursions then overlap); more sections run one after another
    m = x.shape[1]
    ns = sos.shape[0]
    ci = c0[i] if settled else 0.0
    b0, b1, b2, a1, a2 = section(sos, 0)
    e0, e1, e2, d1, d2 = section(sos, ns - 1)
    s1 = s2 = t1 = t2 = 0.0
    if ns <= 2:
        for k0 in range(0, m, BLOCK):
            for k in range(k0, min(k0 + BLOCK, m)):
                yi, s1, s2 = step(x[i, k] * gain - ci if settled else x[i, k] * gain, s1, s2,
                                  b0, b1, b2, a1, a2)
                if ns == 2:
                    yi, t1, t2 = step(yi, t1, t2, e0, e1, e2, d1, d2)
                out[i, k] = yi + dc[k * dstep] * ci if settled else yi
            s1, s2, t1, t2 = flush(s1), flush(s2), flush(t1), flush(t2)
        return
    for k in range(m):
        out[i, k] = x[i, k] * gain - ci if settled else x[i, k] * gain
    for s in range(ns):
        b0, b1, b2, a1, a2 = section(sos, s)
        s1 = s2 = 0.0
        for k0 in range(0, m, BLOCK):
            for k in range(k0, min(k0 + BLOCK, m)):
                out[i, k], s1, s2 = step(out[i, k], s1, s2, b0, b1, b2, a1, a2)
            s1, s2 = flush(s1), flush(s2)
    if settled:
        for k in range(m):
            out[i, k] = out[i, k] + dc[k * dstep] * ci


def sos_four(sos, x, gain, c0, dc, out, i, settled, dstep):
    # rows i..i+3 of a filter of one or two sections in one pass, BLOCK samples at a time: four
    # (eight) independent recursions overlap, their states in registers
    m = x.shape[1]
    two = sos.shape[0] == 2
    b0, b1, b2, a1, a2 = section(sos, 0)
    e0, e1, e2, d1, d2 = section(sos, sos.shape[0] - 1)
    ca = c0[i] if settled else 0.0
    cb = c0[i + 1] if settled else 0.0
    cc = c0[i + 2] if settled else 0.0
    cd = c0[i + 3] if settled else 0.0
    pa = qa = pb = qb = pc = qc = pd = qd = 0.0
    ua = va = ub = vb = uc = vc = ud = vd = 0.0
    for k0 in range(0, m, BLOCK):
        for k in range(k0, min(k0 + BLOCK, m)):
            if settled:
                ya, pa, qa = step(x[i, k] * gain - ca, pa, qa, b0, b1, b2, a1, a2)
                yb, pb, qb = step(x[i + 1, k] * gain - cb, pb, qb, b0, b1, b2, a1, a2)
                yc, pc, qc = step(x[i + 2, k] * gain - cc, pc, qc, b0, b1, b2, a1, a2)
                yd, pd, qd = step(x[i + 3, k] * gain - cd, pd, qd, b0, b1, b2, a1, a2)
            else:
                ya, pa, qa = step(x[i, k] * gain, pa, qa, b0, b1, b2, a1, a2)
                yb, pb, qb = step(x[i + 1, k] * gain, pb, qb, b0, b1, b2, a1, a2)
                yc, pc, qc = step(x[i + 2, k] * gain, pc, qc, b0, b1, b2, a1, a2)
                yd, pd, qd = step(x[i + 3, k] * gain, pd, qd, b0, b1, b2, a1, a2)
            if two:
                ya, ua, va = step(ya, ua, va, e0, e1, e2, d1, d2)
                yb, ub, vb = step(yb, ub, vb, e0, e1, e2, d1, d2)
                yc, uc, vc = step(yc, uc, vc, e0, e1, e2, d1, d2)
                yd, ud, vd = step(yd, ud, vd, e0, e1, e2, d1, d2)
            if settled:
                d = dc[k * dstep]
                out[i, k] = ya + d * ca
                out[i + 1, k] = yb + d * cb
                out[i + 2, k] = yc + d * cc
                out[i + 3, k] = yd + d * cd
            else:
                out[i, k] = ya
                out[i + 1, k] = yb
                out[i + 2, k] = yc
                out[i + 3, k] = yd
        pa, qa, pb, qb, pc, qc, pd, qd = (flush(pa), flush(qa), flush(pb), flush(qb), flush(pc), flush(qc),
                                          flush(pd), flush(qd))
        ua, va, ub, vb, uc, vc, ud, vd = (flush(ua), flush(va), flush(ub), flush(vb), flush(uc), flush(vc),
                                          flush(ud), flush(vd))


def sos_design(sos, x, gain, c0, dc, out, settled, dstep):
    n, m = x.shape
    ns = sos.shape[0]
    # many rows: BLOCK samples of every row at a time in a buffer that stays in the cache, the
    # rows side by side (their recursions are independent: the loop over them vectorises while
    # each waits on its own multiply-adds)
    z1 = np.zeros((ns, n))
    z2 = np.zeros((ns, n))
    buf = np.empty((BLOCK, n))
    for k0 in range(0, m, BLOCK):
        nb = min(BLOCK, m - k0)
        for i in range(n):
            for j in range(nb):
                buf[j, i] = x[i, k0 + j] * gain - c0[i] if settled else x[i, k0 + j] * gain
        for s in range(ns):
            b0, b1, b2, a1, a2 = section(sos, s)
            p1 = z1[s]
            p2 = z2[s]
            for j in range(nb):
                row = buf[j]
                for i in range(n):
                    xi = row[i]
                    yi = b0 * xi + p1[i]
                    p1[i] = b1 * xi - a1 * yi + p2[i]
                    p2[i] = b2 * xi - a2 * yi
                    row[i] = yi
            for i in range(n):
                p1[i] = flush(p1[i])
                p2[i] = flush(p2[i])
        for i in range(n):
            if settled:
                for j in range(nb):
                    out[i, k0 + j] = buf[j, i] + dc[(k0 + j) * dstep] * c0[i]
            else:
                for j in range(nb):
                    out[i, k0 + j] = buf[j, i]


def sos_run(sos, x, gain, c0, dc, out):
    # scipy's sosfilt recursion (transposed direct form II, from rest) on every row of x, with
    # the states flushed at the end of each BLOCK samples (TINY): otherwise bit for bit. With
    # the chain's ends in the same pass (each the numpy expression's operations): the input
    # x * gain - c0 (c0 per row, none when empty), the output y + dc * c0 (dc per sample, or
    # one value). With one or two sections (most chains) rows four at a time, the rest one by
    # one, each in one pass; with more, a row alone in passes section by section, several side
    # by side. The same operations on each row: a row gives the same numbers alone or in a
    # design
    n = x.shape[0]
    settled = c0.size > 0
    dstep = 1 if dc.size > 1 else 0
    i = 0
    if sos.shape[0] > 2 and n > 1:
        sos_design(sos, x, gain, c0, dc, out, settled, dstep)
        return out
    if sos.shape[0] <= 2:
        while i + 4 <= n:
            sos_four(sos, x, gain, c0, dc, out, i, settled, dstep)
            i += 4
    while i < n:
        sos_row(sos, x, gain, c0, dc, out, i, settled, dstep)
        i += 1
    return out


# The kernels above are plain functions of this module, compiled by kernels() with their callees
# re-bound to the compiled ones (core.compiled.rebind). Nested in kernels(), as they were until
# stop 67, they were closures over the compiled callees, and numba's cache keys a closure by its
# pickled cells, which differ in every process: each process compiled all of them again and added
# a copy to the cache folder (192 of sos_four after a day of evaluations). On the EPYC, rig-d14-095
# with the search cut at 1 s of budget: 14.8 s in a fresh process, 3.3 s repeated in the same one;
# with the cache found, 4.8 s in a fresh process.
_INLINED = ("play", "section", "flush", "step")     # inlined into their callers
_RUNNERS = ("amp_run", "play_run", "pi_run", "cell_run", "sos_row", "sos_four", "sos_design", "sos_run")


@lru_cache(maxsize=1)
def kernels():
    """The compiled kernels (numba, compiled on first use, cached on disk): ``amp_run, play_run,
    pi_run, cell_run, sos_run``."""
    here = globals()
    compiled = {"amp_step": jit(amp_step, nogil=True)}
    for name in _INLINED:
        compiled[name] = jit(rebind(here[name], compiled), nogil=True, inline="always")
    for name in _RUNNERS:      # callees first
        compiled[name] = jit(rebind(here[name], compiled), nogil=True)
    return tuple(compiled[n] for n in ("amp_run", "play_run", "pi_run", "cell_run", "sos_run"))
