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

from ..core import plant
from ..core.compiled import jit
from ..core.linear import TINY

__all__ = ["BLOCK", "DESIGN_ROWS", "kernels"]

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
# from this many rows on a design's rows are filtered side by side in one buffer (the loop over
# them vectorises), below it four at a time with their states in registers; a row alone is one
# pass. On the Intel Xeon, ns per sample, row and section (200 k samples; old = side by side for
# every design, sections one after another for a row): 1 row 1 / 2 sections 5.9 / 5.4 -> 5.1 /
# 2.7; 4 rows 6.3 / 4.4 -> 4.0 / 3.0; 20 rows 2.6 side by side against 2.8 four at a time
DESIGN_ROWS = 8

@lru_cache(maxsize=1)
def kernels():
    """The compiled kernels (numba, compiled on first use): ``amp_run, play_run, pi_run, cell_run,
    sos_run``."""
    amp_step = jit(plant.amp_step, nogil=True)

    @jit(nogil=True)
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

    @jit(nogil=True, inline="always")
    def play(z, v, r):
        # one play operator (threshold r) moved by the input v: the rule of core.hysteresis.pi_step
        lo = v - r
        if z < lo:
            return lo
        return min(z, v + r)

    @jit(nogil=True)
    def play_run(v, r, z, z0):
        # the operators are independent: one pass per operator keeps the writes contiguous
        for i in range(r.size):
            ri = r[i]
            zi = z0[i]
            row = z[i]
            for k in range(v.size):
                zi = play(zi, v[k], ri)
                row[k] = zi
        return z

    @jit(nogil=True)
    def pi_run(v, r, w, y_inv, out, z0):
        # the weighted sum of the operators (and the strain saturation) without storing them
        out[:] = 0.0
        for i in range(r.size):
            ri = r[i]
            wi = w[i]
            zi = z0[i]
            for k in range(v.size):
                zi = play(zi, v[k], ri)
                out[k] += wi * zi
        if y_inv > 0.0:
            for k in range(v.size):
                out[k] = out[k] / (1.0 + abs(out[k]) * y_inv)
        return out

    @jit(nogil=True)
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

    @jit(nogil=True, inline="always")
    def section(sos, s):
        # one second-order section's coefficients [b0 b1 b2 1 a1 a2]: b0, b1, b2, a1, a2
        return sos[s, 0], sos[s, 1], sos[s, 2], sos[s, 4], sos[s, 5]

    @jit(nogil=True, inline="always")
    def flush(v):
        # a filter state below TINY is zero (see TINY)
        return v if abs(v) >= TINY else 0.0

    @jit(nogil=True)
    def sos_row(sos, x, gain, c0, dc, out, i, settled, dstep):
        # one row, BLOCK samples at a time, the states in registers. A row's recursion waits on
        # each multiply-add: with one or two sections, input, sections and output are one pass
        # (two sections' recursions then overlap); more sections run one after another
        m = x.shape[1]
        ns = sos.shape[0]
        ci = c0[i] if settled else 0.0
        b0, b1, b2, a1, a2 = section(sos, 0)
        s1 = 0.0
        s2 = 0.0
        if ns == 1:
            for k0 in range(0, m, BLOCK):
                for k in range(k0, min(k0 + BLOCK, m)):
                    xi = x[i, k] * gain - ci if settled else x[i, k] * gain
                    yi = b0 * xi + s1
                    s1 = b1 * xi - a1 * yi + s2
                    s2 = b2 * xi - a2 * yi
                    out[i, k] = yi + dc[k * dstep] * ci if settled else yi
                s1 = flush(s1)
                s2 = flush(s2)
            return
        if ns == 2:
            e0, e1, e2, d1, d2 = section(sos, 1)
            t1 = 0.0
            t2 = 0.0
            for k0 in range(0, m, BLOCK):
                for k in range(k0, min(k0 + BLOCK, m)):
                    xi = x[i, k] * gain - ci if settled else x[i, k] * gain
                    yi = b0 * xi + s1
                    s1 = b1 * xi - a1 * yi + s2
                    s2 = b2 * xi - a2 * yi
                    zi = e0 * yi + t1
                    t1 = e1 * yi - d1 * zi + t2
                    t2 = e2 * yi - d2 * zi
                    out[i, k] = zi + dc[k * dstep] * ci if settled else zi
                s1 = flush(s1)
                s2 = flush(s2)
                t1 = flush(t1)
                t2 = flush(t2)
            return
        for k in range(m):
            out[i, k] = x[i, k] * gain - ci if settled else x[i, k] * gain
        for s in range(ns):
            b0, b1, b2, a1, a2 = section(sos, s)
            s1 = 0.0
            s2 = 0.0
            for k0 in range(0, m, BLOCK):
                for k in range(k0, min(k0 + BLOCK, m)):
                    xi = out[i, k]
                    yi = b0 * xi + s1
                    s1 = b1 * xi - a1 * yi + s2
                    s2 = b2 * xi - a2 * yi
                    out[i, k] = yi
                s1 = flush(s1)
                s2 = flush(s2)
        if settled:
            for k in range(m):
                out[i, k] = out[i, k] + dc[k * dstep] * ci

    @jit(nogil=True)
    def sos_four(sos, x, gain, c0, dc, out, i, settled, dstep):
        # rows i..i+3 side by side, BLOCK samples at a time (in the cache), section after section:
        # four independent recursions overlap, their states in registers
        m = x.shape[1]
        ns = sos.shape[0]
        st = np.zeros((ns, 8))
        ca = c0[i] if settled else 0.0
        cb = c0[i + 1] if settled else 0.0
        cc = c0[i + 2] if settled else 0.0
        cd = c0[i + 3] if settled else 0.0
        ra = out[i]
        rb = out[i + 1]
        rc = out[i + 2]
        rd = out[i + 3]
        for k0 in range(0, m, BLOCK):
            ke = min(k0 + BLOCK, m)
            for k in range(k0, ke):
                if settled:
                    ra[k] = x[i, k] * gain - ca
                    rb[k] = x[i + 1, k] * gain - cb
                    rc[k] = x[i + 2, k] * gain - cc
                    rd[k] = x[i + 3, k] * gain - cd
                else:
                    ra[k] = x[i, k] * gain
                    rb[k] = x[i + 1, k] * gain
                    rc[k] = x[i + 2, k] * gain
                    rd[k] = x[i + 3, k] * gain
            for s in range(ns):
                b0, b1, b2, a1, a2 = section(sos, s)
                pa, qa, pb, qb, pc, qc, pd, qd = st[s, 0], st[s, 1], st[s, 2], st[s, 3], st[s, 4], st[s, 5], \
                    st[s, 6], st[s, 7]
                for k in range(k0, ke):
                    xa = ra[k]
                    xb = rb[k]
                    xc = rc[k]
                    xd = rd[k]
                    ya = b0 * xa + pa
                    yb = b0 * xb + pb
                    yc = b0 * xc + pc
                    yd = b0 * xd + pd
                    pa = b1 * xa - a1 * ya + qa
                    pb = b1 * xb - a1 * yb + qb
                    pc = b1 * xc - a1 * yc + qc
                    pd = b1 * xd - a1 * yd + qd
                    qa = b2 * xa - a2 * ya
                    qb = b2 * xb - a2 * yb
                    qc = b2 * xc - a2 * yc
                    qd = b2 * xd - a2 * yd
                    ra[k] = ya
                    rb[k] = yb
                    rc[k] = yc
                    rd[k] = yd
                st[s, 0], st[s, 1], st[s, 2], st[s, 3] = flush(pa), flush(qa), flush(pb), flush(qb)
                st[s, 4], st[s, 5], st[s, 6], st[s, 7] = flush(pc), flush(qc), flush(pd), flush(qd)
            if settled:
                for k in range(k0, ke):
                    d = dc[k * dstep]
                    ra[k] = ra[k] + d * ca
                    rb[k] = rb[k] + d * cb
                    rc[k] = rc[k] + d * cc
                    rd[k] = rd[k] + d * cd

    @jit(nogil=True)
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

    @jit(nogil=True)
    def sos_run(sos, x, gain, c0, dc, out):
        # scipy's sosfilt recursion (transposed direct form II, from rest) on every row of x, with
        # the states flushed at the end of each BLOCK samples (TINY): otherwise bit for bit. With
        # the chain's ends in the same pass (each the numpy expression's operations): the input
        # x * gain - c0 (c0 per row, none when empty), the output y + dc * c0 (dc per sample, or
        # one value). A row alone (a prediction) in one pass, a few rows four at a time, many
        # side by side (DESIGN_ROWS, measured): the same operations on each row, so a row gives
        # the same numbers alone or in a design
        n = x.shape[0]
        settled = c0.size > 0
        dstep = 1 if dc.size > 1 else 0
        if n >= DESIGN_ROWS:
            sos_design(sos, x, gain, c0, dc, out, settled, dstep)
            return out
        i = 0
        while i + 4 <= n:
            sos_four(sos, x, gain, c0, dc, out, i, settled, dstep)
            i += 4
        while i < n:
            sos_row(sos, x, gain, c0, dc, out, i, settled, dstep)
            i += 1
        return out

    return amp_run, play_run, pi_run, cell_run, sos_run
