"""An independent test rig: concealed synthetic recordings with known ground truth.

``piezo-fmu diagnose`` names the physics a recording shows and the nominal model lacks. Judging
it on recordings made by the project's own model would prove little: a generator that shares
the model's structure shares its blind spots, and a diagnosis tuned to it can pass by
recognising the simulator rather than the physics. This rig was written without reading the
project's model code. It draws its own plant, from the paper's magnitudes, with different
equations throughout:

* hysteresis from other families (Bouc-Wen integrated exactly, a Krasnosel'skii-Pokrovskii
  Preisach plane, Prandtl-Ishlinskii with other threshold grids), ``hysteresis.py``;
* a two-stage amplifier with an exact current (slew) limit, a log-law creep (a convolution, no
  set of time constants), a push-rod mode with the stack force ``k_a (x_f - x)`` as what the
  quartz measures, charge leakage as a high-pass, probe and sensor gains, offsets, coloured
  noise, a sampling lag, point sampling of a finer internal grid, ``plant.py``;
* programmes of 2-4 segments (steps with long holds, multisines, sine sets, decaying
  triangles, chirps, rests; unipolar or bipolar), ``excitation.py``;
* every parameter randomised around the paper's device (+-30 %), ``caseset.py``; the sizes of the
  effects, ``mechanisms.py``.

Public API
----------
``cases(quick=False)``
    The evaluation set: a list of ``CaseSpec`` (deterministic; 185 cases, or 16 short ones).
``generate(spec, twins=False, noise_draw=0)``
    Simulate one case: a ``RigRecording`` with ``time`` [s], ``u`` [V], ``x`` [um] and/or
    ``us`` [V] (an absent channel is None) and ``truth`` (with ``twins``, also each present
    delay's and further mode's closest *ordinary twin*, ``twins.py``; with ``noise_draw`` k >= 1,
    the same device and truth with another realisation of its noise: a repeated measurement).
``write_csv(rec, path)``
    ``time,u,x,us`` (present channels), one ``#`` line of units, nothing of the truth.

``python -m piezo_fmu.rig --out DIR [--quick]`` writes every case's CSV to
``DIR/recordings/`` and the truth, apart, to ``DIR/truth.json`` (the full set: ~2 min, ~0.6 s
per case on average, at most ~3.5 s).

``truth`` holds ``mechanisms`` (catalogue names present and visible), ``hidden`` (present
below visibility), ``group`` (clean, single, pair, control, one_channel), ``control`` (the
off-catalogue effect or None), ``params`` (every drawn parameter as ``{value, unit}``),
``visibility`` and ``visibility_beyond_affine`` (per effect and channel: rms of the effect over
the channel's noise rms, see ``caseset``), ``nuisance_visibility`` (the first mode and the
sampling lag, which are nominal physics), ``pi9_misfit``, ``segments`` (the programme),
``fs``, ``duration``, ``channels``, ``case_id``, ``seed``, ``attempt``; with ``twins``,
``ordinary_twins`` (per effect: the twin, its distance from the record in noise rms beyond
affine, and ``same`` when below 3: the record does not tell the effect from ordinary physics
re-tuned, a further mode from a first mode at its frequency, a delay from a slower amplifier or,
on one channel, a sampling lag).

Catalogue names: ``creep``, ``sensor_leakage``, ``amplifier_current_limit``, ``time_delay``,
``extra_resonance``, ``thermal_drift``, ``hysteresis_shape``. Controls (not catalogue names; a
correct diagnosis names nothing): ``mains_hum``, ``us_offset_drift``, ``push_rod_backlash``,
``probe_quantisation``, ``probe_gain_modulation``.

Example
-------
>>> from piezo_fmu.rig import cases, generate, write_csv
>>> spec = cases(quick=True)[0]
>>> rec = generate(spec)
>>> path = write_csv(rec, "case.csv")       # doctest: +SKIP
"""
from .caseset import GROUPS, CaseSpec, cases, compatible, generate, pi9_misfit, visibility
from .plant import CATALOGUE, CONTROLS
from .recording import RigRecording, read_csv, write_csv

__all__ = ["CATALOGUE", "CONTROLS", "GROUPS", "CaseSpec", "RigRecording", "cases", "compatible",
           "generate", "pi9_misfit", "read_csv", "visibility", "write_csv"]
