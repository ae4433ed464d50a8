"""Hysteresis families of the test rig, written independently of the project's model.

Three rate-independent families draw the stack's free stroke from its voltage. Each is
normalised to a unit mean slope (one volt of stroke-equivalent per volt of drive over a
full sweep) so that the caller scales it to micrometres with one sensitivity ``d_eff``:

* ``bouc_wen``: ``H = u - h`` with ``dh = alpha du - beta |du| h - gamma du |h|``
  (Bouc-Wen with exponent 1), integrated exactly between samples (the equation is linear in
  ``h`` on each side of ``h = 0``, so the solution is an exponential in the input path length).
* ``kp``: Krasnosel'skii-Pokrovskii: a discretised Preisach half-plane of cells
  ``(a, b)``, ``a - b >= w``, each a relay smoothed into two ramps of width ``w``,
  ``s = clip(s_prev, ramp_up(u), ramp_down(u))``, weighted by a density ``mu(a, b)`` plus a
  reversible linear part.
* ``pi_other``: Prandtl-Ishlinskii with a threshold grid that is not the paper's nine
  (4-20 operators, power-law spacing), perturbed positive weights.

A ``shape`` term (the catalogue's ``hysteresis_shape``) adds a rate-independent feature that a
positive-weight PI with symmetric play operators cannot draw: a loop width that depends on the
absolute level, a cluster of switching cells at fixed voltages (domain switching), or a
high-field knee that begins part-way up the stroke.

Every kernel is a sequential loop (hysteresis is), compiled with numba.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numba import njit

FAMILIES = ("bouc_wen", "kp", "pi_other")
SHAPES = ("level_width", "switching_cluster", "knee")


# ----------------------------------------------------------------------------------------------
# kernels


@njit(cache=True)
def _bouc_wen(u, alpha, beta, gamma, h0):  # pragma: no cover - compiled
    n = u.size
    h = np.empty(n)
    hc = h0
    h[0] = hc
    for k in range(1, n):
        du = u[k] - u[k - 1]
        if du == 0.0:
            h[k] = hc
            continue
        sg = 1.0 if du > 0.0 else -1.0
        s = abs(du)
        z = sg * hc                      # dz/ds = alpha - beta z - gamma |z|, s = path length
        while s > 0.0:
            if z >= 0.0:
                c = beta + gamma
                zeq = alpha / c
                z = zeq + (z - zeq) * np.exp(-c * s)
                s = 0.0
            else:
                c = beta - gamma
                zeq = alpha / c
                s0 = np.log((zeq - z) / zeq) / c     # path length to reach z = 0
                if s0 >= s:
                    z = zeq + (z - zeq) * np.exp(-c * s)
                    s = 0.0
                else:
                    z = 0.0
                    s -= s0
        hc = sg * z
        h[k] = hc
    return h, hc


@njit(cache=True)
def _kp(u, a, b, width, weight, s0):  # pragma: no cover - compiled
    n = u.size
    m = a.size
    out = np.empty(n)
    s = s0.copy()
    for k in range(n):
        v = u[k]
        acc = 0.0
        for i in range(m):
            lo = 2.0 * (v - a[i]) / width[i] + 1.0
            if lo > 1.0:
                lo = 1.0
            elif lo < -1.0:
                lo = -1.0
            hi = 2.0 * (v - b[i]) / width[i] - 1.0
            if hi > 1.0:
                hi = 1.0
            elif hi < -1.0:
                hi = -1.0
            si = s[i]
            if si < lo:
                si = lo
            elif si > hi:
                si = hi
            s[i] = si
            acc += weight[i] * si
        out[k] = acc
    return out, s


@njit(cache=True)
def _plays(u, r, y0):  # pragma: no cover - compiled
    n = u.size
    m = r.size
    out = np.empty((n, m))
    y = y0.copy()
    for k in range(n):
        v = u[k]
        for i in range(m):
            lo = v - r[i]
            hi = v + r[i]
            yi = y[i]
            if yi < lo:
                yi = lo
            elif yi > hi:
                yi = hi
            y[i] = yi
            out[k, i] = yi
    return out, y


def plays(u: np.ndarray, thresholds: np.ndarray, y0: np.ndarray | None = None) -> np.ndarray:
    """Outputs of symmetric play (backlash) operators.

    Parameters
    ----------
    u : ndarray, shape (n,)
        Input sequence [any unit, e.g. V].
    thresholds : ndarray, shape (m,)
        Half-widths ``r_i >= 0`` [same unit as ``u``].
    y0 : ndarray, shape (m,), optional
        Initial operator outputs; default ``u[0]`` (a relaxed start).

    Returns
    -------
    ndarray, shape (n, m)
        ``y_i[k] = clip(y_i[k-1], u[k] - r_i, u[k] + r_i)``.
    """
    u = np.ascontiguousarray(u, dtype=float)
    r = np.ascontiguousarray(thresholds, dtype=float)
    if y0 is None:
        y0 = np.full(r.size, u[0] if u.size else 0.0)
    out, _ = _plays(u, r, np.asarray(y0, dtype=float))
    return out


# ----------------------------------------------------------------------------------------------
# the device's hysteresis


@dataclass
class Hysteresis:
    """One drawn hysteresis: family, its parameters, an optional shape feature.

    ``__call__(ua)`` maps the stack voltage [V] to a stroke-equivalent [V] with unit mean
    slope; multiply by the stack sensitivity [um/V] for micrometres. The device is prepared
    before every run: driven from ``u_rest`` up to ``u_top`` and back (as a rig is exercised
    before a measurement), so its memory does not depend on where the array starts.
    """

    family: str
    params: dict
    u_rest: float
    u_top: float
    norm: float = 1.0
    shape: str | None = None
    shape_params: dict = field(default_factory=dict)
    shape_amplitude: float = 0.0          # [V of stroke-equivalent], the size knob of the feature

    # -- pieces ----------------------------------------------------------------------------------
    def _prep(self, ua: np.ndarray) -> tuple[np.ndarray, int]:
        up = np.linspace(self.u_rest, self.u_top, 400)
        down = np.linspace(self.u_top, ua[0], 400)
        pre = np.concatenate([up, down])
        return np.concatenate([pre, np.asarray(ua, dtype=float)]), pre.size

    def base(self, ua: np.ndarray) -> np.ndarray:
        """The family's stroke-equivalent [V] (normalised), without the shape feature."""
        full, n0 = self._prep(ua)
        p = self.params
        if self.family == "bouc_wen":
            h, _ = _bouc_wen(full, p["alpha"], p["beta"], p["gamma"], 0.0)
            y = full - h
        elif self.family == "kp":
            s0 = -np.ones(p["a"].size)
            hyst, _ = _kp(full, p["a"], p["b"], p["w"], p["mu"], s0)
            y = p["lin"] * full + hyst
        elif self.family == "pi_other":
            y = plays(full, p["r"], np.full(p["r"].size, self.u_rest)) @ p["weights"]
        else:
            raise ValueError(f"unknown hysteresis family {self.family!r}")
        return self.norm * y[n0:]

    def feature(self, ua: np.ndarray, base: np.ndarray) -> np.ndarray:
        """The shape feature [V of stroke-equivalent] for this input; zeros without one."""
        if self.shape is None or self.shape_amplitude == 0.0:
            return np.zeros_like(base)
        q = self.shape_params
        a = self.shape_amplitude
        span = self.u_top - self.u_rest
        if self.shape == "level_width":
            # loop width grows (or shrinks) with the absolute level: non-congruent minor loops
            full, n0 = self._prep(ua)
            dev = plays(full, np.array([q["r"]]), np.array([self.u_rest]))[:, 0] - full
            level = (full - q["centre"]) / span
            return (a / q["r"]) * (level * dev)[n0:]
        if self.shape == "switching_cluster":
            full, n0 = self._prep(ua)
            out, _ = _kp(full, q["a"], q["b"], q["w"], q["mu"], -np.ones(q["a"].size))
            return a * out[n0:]
        if self.shape == "knee":
            over = np.maximum(base - q["knee"], 0.0) / (self.u_top - q["knee"])
            return -a * over ** 2
        raise ValueError(f"unknown shape {self.shape!r}")

    def __call__(self, ua: np.ndarray, with_shape: bool = True) -> np.ndarray:
        y = self.base(ua)
        if with_shape:
            y = y + self.feature(ua, y)
        return y

    def describe(self) -> dict:
        """Plain parameters (for the truth record), arrays as lists, with units."""
        out = {"hysteresis.family": {"value": self.family, "unit": ""}}
        units = {"alpha": "1", "beta": "1/V", "gamma": "1/V", "lin": "1", "r": "V",
                 "weights": "1", "a": "V", "b": "V", "w": "V", "mu": "V"}
        for k, v in self.params.items():
            out[f"hysteresis.{k}"] = {"value": np.asarray(v).tolist(), "unit": units.get(k, "")}
        out["hysteresis.normalisation"] = {"value": self.norm, "unit": "1"}
        if self.shape is not None:
            out["hysteresis_shape.variant"] = {"value": self.shape, "unit": ""}
            out["hysteresis_shape.amplitude"] = {"value": self.shape_amplitude, "unit": "V"}
            for k, v in self.shape_params.items():
                out[f"hysteresis_shape.{k}"] = {"value": np.asarray(v).tolist(), "unit": "V"}
        return out


def _triangle_cells(lo: float, hi: float, n: int):
    """Cell corners ``(a, b)`` with ``a - b >= w`` on an ``n``-step grid over [lo, hi]."""
    w = (hi - lo) / n
    grid = lo + w * np.arange(n + 1)
    a, b = np.meshgrid(grid, grid, indexing="ij")
    keep = (a - b) >= w * (1 - 1e-9)
    return a[keep], b[keep], w


def draw_hysteresis(rng: np.random.Generator, u_rest: float, u_lo: float, u_top: float,
                    family: str | None = None, calm: float = 0.0) -> Hysteresis:
    """Draw a device hysteresis around the paper's magnitudes (widest loop 3-25 % of the stroke).

    Parameters
    ----------
    rng : numpy.random.Generator
    u_rest, u_lo, u_top : float
        Rest voltage, lowest and highest stack voltage of the case [V].
    family : str, optional
        One of ``FAMILIES``; drawn when omitted.
    calm : float
        0 to 1: pulls the draw towards smoother loops that saturate within ~25 V of a
        reversal (used when a draw came out with more shape than a clean case may have).

    Returns
    -------
    Hysteresis
        Normalised to unit mean slope over a ``u_lo -> u_top -> u_lo`` sweep.
    """
    if family is None:
        family = FAMILIES[rng.integers(len(FAMILIES))]
    # distance [V] over which the hysteretic part saturates after a reversal
    v_sat = rng.uniform(4.5, 9.0) * (1.0 - calm) + 6.5 * calm
    if family == "bouc_wen":
        gamma_ratio = rng.uniform(-0.1, 0.1) * (1.0 - calm)
        beta = 1.0 / (v_sat * (1.0 + gamma_ratio))
        params = {"alpha": rng.uniform(0.28, 0.45), "beta": beta, "gamma": gamma_ratio * beta}
    elif family == "kp":
        lo, hi = min(u_lo, u_rest) - 10.0, u_top + 10.0
        n = int(rng.integers(14, 22))
        a, b, w = _triangle_cells(lo, hi, n)
        width = a - b
        mu = np.exp(-width / (2.0 * v_sat)) * (
            1.0 + 0.1 * (1.0 - calm) * rng.standard_normal(a.size)).clip(0.5)
        # mu * 2 is the jump of one cell; scale the hysteretic part to 8-20 % of the span
        mu *= rng.uniform(0.2, 0.4) * (hi - lo) / (2.0 * mu.sum())
        params = {"a": a, "b": b, "w": np.full(a.size, w), "mu": mu, "lin": rng.uniform(0.45, 0.75)}
    elif family == "pi_other":
        m = int(rng.choice([4, 5, 6, 7, 8, 10, 12, 14, 16, 20]))
        power = rng.uniform(0.6, 1.8)
        r = 2.5 * v_sat * (np.arange(m) / m) ** power
        weights = np.exp(-r / v_sat) * np.exp(0.25 * (1.0 - calm) * rng.standard_normal(m))
        weights[0] = rng.uniform(0.5, 1.0) * weights[1:].sum() if m > 1 else 1.0
        params = {"r": r, "weights": weights}
    else:
        raise ValueError(f"unknown hysteresis family {family!r}")
    hyst = Hysteresis(family, params, u_rest=u_rest, u_top=u_top)
    sweep = np.concatenate([np.linspace(u_lo, u_top, 2000), np.linspace(u_top, u_lo, 2000)])
    y = hyst.base(sweep)
    hyst.norm = (u_top - u_lo) / (y[1999] - y[0])
    return hyst


def draw_shape(rng: np.random.Generator, hyst: Hysteresis, u_lo: float,
               variant: str | None = None) -> None:
    """Give ``hyst`` a shape feature (in place); its size is set later via ``shape_amplitude``.

    The ``shape_amplitude`` knob is in volts of stroke-equivalent: about the feature's peak
    contribution to the loop.
    """
    if variant is None:
        variant = SHAPES[rng.integers(len(SHAPES))]
    span = hyst.u_top - u_lo
    if variant == "level_width":
        q = {"r": span * rng.uniform(0.06, 0.15),
             "centre": u_lo + span * rng.choice([rng.uniform(0.0, 0.2), rng.uniform(0.8, 1.0)])}
    elif variant == "switching_cluster":
        a0 = u_lo + span * rng.uniform(0.55, 0.85)
        b0 = u_lo + span * rng.uniform(0.15, 0.45)
        spread = span * rng.uniform(0.03, 0.08)
        k = 4
        da, db = np.meshgrid(np.linspace(-1, 1, k), np.linspace(-1, 1, k), indexing="ij")
        a = a0 + spread * da.ravel()
        b = b0 + spread * db.ravel()
        w = np.full(a.size, spread)
        q = {"a": a, "b": b, "w": w, "mu": np.full(a.size, 0.5 / a.size)}
    elif variant == "knee":
        q = {"knee": u_lo + span * rng.uniform(0.45, 0.7)}
    else:
        raise ValueError(f"unknown shape {variant!r}")
    hyst.shape = variant
    hyst.shape_params = q
