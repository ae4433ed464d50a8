"""What diagnose fits, and the model file it comes from and goes back to.

* :class:`Device` - constants diagnose never changes (amplifier gain and capacitance, rails,
  stiffnesses, sensor capacitance), taken from the nominal model;
* :class:`Params` - everything diagnose may fit: the ordinary physics of any specimen (PI weights,
  amplifier lag of first or second order, the mechanics' first mode, what the sensor follows,
  channel gains, offsets and sampling lags) and the catalogue's mechanisms;
* :class:`Recording` - one recording in the model's orientation, with its validation blocks;
* :func:`device_from_model`, :func:`params_from_model`, :func:`model_from_params` - the mapping
  to and from model files (``model_from_params`` writes every value with its provenance).
"""
from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field

import numpy as np

from ..core.plant import EPS0

__all__ = ["Device", "Params", "Recording", "device_from_model", "model_from_params", "params_from_model"]


@dataclass(frozen=True)
class Device:
    """Constants of the model that diagnose never changes (taken from the nominal model)."""

    k_amp: float
    C_a: float
    u_min: float
    u_max: float
    k_a: float
    k_f: float
    C_sensor: float        # C_s + C_load [F]

    @property
    def k_force(self):
        return self.k_a * 1e-6

    @property
    def k_load(self):
        return self.k_f * 1e-6

    @property
    def mech_gain(self):
        """Static displacement per free stroke (k_a / (k_a + k_f))."""
        return self.k_a / (self.k_a + self.k_f)

    @property
    def k_total(self):
        return self.k_a + self.k_f


@dataclass
class Params:
    """Everything diagnose may fit (SI units; displacements in the recording's x units)."""

    tau: float                       # amplifier output stage R C_a [s]
    u_norm: float                    # PI input normalisation [V]
    thresholds: np.ndarray           # normalised
    weights: np.ndarray              # free stroke per operator output [um]
    m: float = 0.0                   # moving mass [kg] (sets the first mode with k_a + k_f)
    c: float = 0.0                   # damping [N s/m]
    tau2: float = 0.0                # amplifier input stage [s] (0: first-order amplifier)
    pick: str = "stack"              # what the sensor's force is: stack (F_out) or load (k_f x)
    lag_x: int = 0                   # sampling lag of the displacement channel [samples]
    lag_us: int = 0                  # sampling lag of the sensor channel [samples]
    y_sat: float = math.inf          # strain saturation [um]
    slew: float = math.inf           # I_max / C_a [V/s]
    delay: float = 0.0               # command latency [s]
    creep: list = field(default_factory=list)     # [(gain, tau [s]), ...]
    res: tuple | None = None         # further mode (f_n [Hz], zeta)
    res_at: str = "output"           # where it acts: output (on x) or drive (on the free stroke)
    off_x: float = 0.0               # drift.offset [um]
    rate: float = 0.0                # drift.rate [um/s]
    curv: float = 0.0                # drift.curvature [um/s^2]
    drift_tau: float = math.inf      # drift.time_constant [s]: the curvature term's warm-up (inf: t^2)
    S: float = 1.0                   # sensor sensitivity [V/N]
    off_s: float = 0.0               # sensor offset [V]
    tau_leak: float = math.inf       # [s]
    leak_settled: bool = False       # the sensor's charge at the first sample leaked already (it sees
                                     # only the force's changes); False: charged with the first force
    prep: float = 0.0                # the operators' state at the first sample: 0 relaxed; > 0 after a
                                     # preparation sweep up to this stack voltage [V] and back to the start
    cells: np.ndarray | None = None  # KP cells beside the PI, (3, m): switch-up, switch-down, ramp width
                                     # [normalised like the thresholds]; None: none
    cell_w: np.ndarray | None = None  # their weights [um of free stroke per unit of cell state]
    cells_held: bool = False         # the cells' weights held in their ratios (one column, one scale)
    cell_scale: float = 1.0          # that scale: the cells' weights are cell_w * cell_scale
    path_lag: bool = False           # the stroke moves along the amplifier's lag between samples (the
                                     # model's simulation.stroke_path amplifier_lag), not a straight line
    classical: bool = False          # every PI weight >= 0 (the paper's identification: a classical
                                     # loop), not only their partial sums (the recalibration's)

    @property
    def n_cells(self):
        return 0 if self.cells is None else int(self.cells.shape[1])

    @property
    def n_cell_cols(self):
        """Columns the cells add to the linear solve: one each, or one in all when held."""
        return min(self.n_cells, 1) if self.cells_held else self.n_cells

    def all_weights(self):
        """The weights of the columns of :func:`.engine.operators`: the PI's, then the cells' (or,
        held, the scale 1 of their weighted sum)."""
        if not self.n_cells:
            return np.asarray(self.weights, float)
        tail = [self.cell_scale] if self.cells_held else self.cell_weights()
        return np.concatenate([np.asarray(self.weights, float), tail])

    def cell_weights(self):
        """The cells' weights [um]."""
        return np.asarray(self.cell_w, float) * self.cell_scale

    def hold_cells(self, held=True):
        """A copy with the cells' weights held in their ratios (``held``) or free again."""
        q = self.copy()
        if q.n_cells and q.cells_held != held:
            q.cell_w, q.cell_scale, q.cells_held = q.cell_weights(), 1.0, held
        return q

    def copy(self):
        return copy.deepcopy(self)

    def mode(self, dev: Device):
        """First mode of the mechanics: ``(f [Hz], zeta)``."""
        k = dev.k_total
        return math.sqrt(k / self.m) / (2 * math.pi), self.c / (2 * math.sqrt(k * self.m))

    def set_mode(self, dev: Device, f=None, zeta=None):
        f0, z0 = self.mode(dev)
        f = f0 if f is None else f
        zeta = z0 if zeta is None else zeta
        k = dev.k_total
        self.m = k / (2 * math.pi * f) ** 2
        self.c = 2 * zeta * math.sqrt(k * self.m)


@dataclass
class Recording:
    """One recording in model orientation: ``x`` and ``us`` already multiplied by their sign."""

    name: str
    t: np.ndarray            # time since the first sample [s]
    dt: float
    u: np.ndarray            # amplifier command [V]
    x: np.ndarray | None
    us: np.ndarray | None
    heldout: np.ndarray      # bool per sample
    t0: float = 0.0          # time of the first sample in the file [s]
    block: np.ndarray | None = None   # validation block of every sample
    sign: dict = field(default_factory=dict)   # channel -> +1/-1 (file = sign * model)
    split: str = ""          # how the held-out blocks were chosen (recordings.blocks)
    oversample: int = 1      # internal steps of the replay per sample (see engine.at_samples)
    transient: np.ndarray | None = None   # bool per sample: just after a jump of the command
                                          # (recordings.after_jumps; None: no sample is)

    @property
    def n(self):
        return self.u.size

    @property
    def h(self):
        """The replay's internal step [s]: ``dt / oversample``."""
        return self.dt / self.oversample

    @property
    def train(self):
        return ~self.heldout

    def channels(self):
        return [c for c in ("x", "us") if getattr(self, c) is not None]


def device_from_model(model) -> Device:
    a, me, s = model["amplifier"], model["mechanics"], model["sensor"]
    c_s = EPS0 * s["eps_r"] * s["area"] / s["thickness"]
    return Device(k_amp=a["k_amp"], C_a=a["C_a"], u_min=a["u_min"], u_max=a["u_max"],
                  k_a=me["k_a"], k_f=me["k_f"], C_sensor=c_s + s["C_load"])


def params_from_model(model, dt=None) -> Params:
    """The model's values; ``dt`` [s] (the recording's step) resolves the sampling lags."""
    a, h, s, me = model["amplifier"], model["hysteresis"], model["sensor"], model["mechanics"]
    dev = device_from_model(model)
    cr, res, dr = model["creep"], model["resonance"], model["drift"]
    meas = model.sections.get("measurement", {})

    def lag(v):
        return int(round(v / dt)) if (dt and v > 0) else 0

    cells = np.array([h.get(f"cells_{k}", []) for k in ("up", "down", "width")], float)
    return Params(
        cells=cells if cells.shape[1] else None,
        cell_w=h["scale"] * np.array(h.get("cells_weights", []), float) if cells.shape[1] else None,
        tau=a["R"] * a["C_a"], u_norm=h["u_norm"], thresholds=np.array(h["thresholds"], float),
        weights=h["scale"] * np.array(h["weights"], float), m=me["m"], c=me["c"],
        tau2=a.get("tau_2", 0.0), pick=me.get("pickoff", "stack"),
        lag_x=lag(meas.get("lag", 0.0)), lag_us=lag(s.get("lag", 0.0)),
        y_sat=h.get("saturation", math.inf), prep=h.get("prepared", 0.0),
        slew=a.get("I_max", math.inf) / a["C_a"], delay=a.get("delay", 0.0),
        creep=list(zip(cr.get("gains", []), cr.get("time_constants", []))),
        res=(res["f_n"], res["zeta"]) if res.get("f_n", 0.0) > 0 else None,
        res_at=res.get("position", "output"),
        off_x=dr.get("offset", 0.0), rate=dr.get("rate", 0.0), curv=dr.get("curvature", 0.0),
        drift_tau=dr.get("time_constant", math.inf),
        S=s["d11"] / dev.C_sensor, off_s=s.get("offset", 0.0), tau_leak=s.get("tau_leak", math.inf),
        path_lag=model.sections.get("simulation", {}).get("stroke_path", "linear") == "amplifier_lag")


def _num(v, digits=8):
    return float(f"{float(v):.{digits}g}")


def model_from_params(base, p: Params, sources: dict, dt=None):
    """A copy of ``base`` carrying ``p``; ``sources`` maps (section, key) -> provenance text.

    Keys not in ``sources`` get a generic 'fitted by piezo-fmu diagnose' provenance.
    """
    m = base.copy()
    C_a = m["amplifier"]["C_a"]

    def put(sec, key, value, default_src):
        m.set(sec, key, value, sources.get((sec, key), default_src))

    fitted = "fitted by piezo-fmu diagnose to the recording(s)"
    put("amplifier", "R", _num(p.tau / C_a), fitted + " (R = tau / C_a, tau the amplifier lag)")
    put("amplifier", "tau_2", _num(p.tau2), fitted + " (second lag stage)" if p.tau2 > 0
        else "diagnose: a first-order amplifier fits the recording")
    put("amplifier", "I_max", _num(p.slew * C_a) if math.isfinite(p.slew) else math.inf,
        fitted if math.isfinite(p.slew) else "diagnose: no current limit found")
    delay = p.delay
    if dt and delay > 0:
        delay = round(delay / dt) * dt
    put("amplifier", "delay", _num(delay, 10), fitted if delay > 0 else "diagnose: no latency found")
    put("mechanics", "m", _num(p.m), fitted + " (with c: the first mode of the mechanics)")
    put("mechanics", "c", _num(p.c), fitted + " (with m: the first mode of the mechanics)")
    put("mechanics", "pickoff", p.pick, "diagnose: what the sensor channel follows, chosen from the data")
    if p.path_lag or "stroke_path" in m.sections.get("simulation", {}):
        put("simulation", "stroke_path", "amplifier_lag" if p.path_lag else "linear",
            "diagnose: the base model's path of the stroke between samples (the fit replayed it)")
    if dt:
        put("sensor", "lag", _num(p.lag_us * dt, 10), "diagnose: sampling lag of the sensor channel, "
            f"{p.lag_us} sample(s) of the recording")
        put("measurement", "lag", _num(p.lag_x * dt, 10), "diagnose: sampling lag of the displacement "
            f"channel, {p.lag_x} sample(s) of the recording")
    w = np.asarray(p.weights, float)
    total = float(np.sum(w))
    put("hysteresis", "u_norm", _num(p.u_norm), "diagnose: input normalisation, the recording's stack-voltage span")
    put("hysteresis", "thresholds", [_num(v) for v in p.thresholds], "diagnose: the nominal thresholds on the recording's span")
    put("hysteresis", "scale", _num(total), fitted + " (sum of the weights: stroke per PI unit)")
    # full precision: weights of a poorly conditioned fit can cancel (+761, -761 um) and leave a
    # partial sum of 1e-7 that rounding to 8 digits would make 0 (not invertible; rig-083)
    # and a partial sum the bounded fit left at its bound of ~0 (an operator the record hardly
    # moves; rig-025) is lifted to 1e-9 of the stroke: the same loop, and an invertible model
    partial = np.maximum(np.cumsum(w / total), 1e-9)
    ws = [float(v) for v in np.diff(partial, prepend=0.0)]
    put("hysteresis", "weights", ws, fitted + " (bounded least squares, every partial sum > 0)")
    put("hysteresis", "saturation", _num(p.y_sat) if math.isfinite(p.y_sat) else math.inf,
        "diagnose: nominal saturation, scaled with the recalibrated stroke")
    if p.n_cells:
        src = fitted + (" (KP cells on a Preisach grid over the recording's stack voltages: a loop shape "
                        "the play operators cannot draw)")
        for i, key in enumerate(("cells_up", "cells_down", "cells_width")):
            put("hysteresis", key, [float(v) for v in p.cells[i]], src)
        put("hysteresis", "cells_weights", [float(v) for v in p.cell_weights() / total], src)
    else:
        for key in ("cells_up", "cells_down", "cells_width", "cells_weights"):
            put("hysteresis", key, [], "diagnose: no loop shape beyond the play operators")
    put("hysteresis", "prepared", _num(p.prep),
        "diagnose: the recording starts with the memory of a sweep up to this stack voltage" if p.prep > 0
        else "diagnose: the recording starts relaxed")
    put("creep", "gains", [_num(g) for g, _ in p.creep], fitted if p.creep else "diagnose: no creep found")
    put("creep", "time_constants", [_num(t) for _, t in p.creep], fitted if p.creep else "diagnose: no creep found")
    put("resonance", "f_n", _num(p.res[0]) if p.res else 0.0, fitted if p.res else "diagnose: no further mode found")
    put("resonance", "zeta", _num(p.res[1]) if p.res else 0.05, fitted if p.res else "default")
    put("resonance", "position", p.res_at if p.res else "output",
        "diagnose: where the further mode acts, chosen from the data" if p.res else "default")
    put("drift", "offset", _num(p.off_x), fitted + " (offset of the displacement channel)")
    put("drift", "rate", _num(p.rate), fitted if p.rate else "diagnose: no drift found")
    put("drift", "curvature", _num(p.curv), fitted if p.curv else "diagnose: no drift found")
    warm = bool(p.curv) and math.isfinite(p.drift_tau)
    put("drift", "time_constant", _num(p.drift_tau) if warm else math.inf,
        fitted + " (the drift's warm-up)" if warm else "diagnose: no warm-up of the drift found")
    dev = device_from_model(m)
    put("sensor", "d11", _num(p.S * dev.C_sensor), fitted + " (effective: absorbs the sensor chain's gain)")
    put("sensor", "offset", _num(p.off_s), fitted)
    put("sensor", "tau_leak", _num(p.tau_leak) if math.isfinite(p.tau_leak) else math.inf,
        fitted if math.isfinite(p.tau_leak) else "diagnose: no charge leakage found")
    return m
