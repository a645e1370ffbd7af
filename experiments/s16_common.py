"""Shared pieces of the [S16] experiments (s16_table2.py, s16_convergence.py, bench_lm.py).

* The simulated prototype: the Table I plate (``arrays.s16_plate``) with fixed, seeded "true"
  orientations and triad parameters (S, o) — the parameters a reference calibration would have
  produced ([S16] §V).
* Reference motions as a rotation table logs them: states x_i = [a_lin, ω, ω̇] on the sample grid,
  with ω̇_i = (ω_{i+1} − ω_i)/Δt (forward differences of the sampled rate, so the integration
  constraint of [S16] eq. 7 holds exactly).  Simulated measurements apply the observation model
  to these states, as [S16] §V does with the table's motion.  ``physical=True`` keeps the
  analytic ω̇(t_i) instead: then eq. 7 (Euler integration, σ_int² = 10⁻⁷) is violated by
  ≈ ½ ω̈ Δt², which biases the self-calibration (reported as a separate row of Table II).
* ``one_thread()``: what every task calls first (the dask runner is ``_dask.py``, shared by all experiments).
"""
from __future__ import annotations


import torch

from accel_bayes import s16_plate
from accel_bayes.constants import DEG_TO_RAD
from accel_bayes.physics import models
from accel_bayes.physics.geometry import boxplus
from accel_bayes.physics.motion_generators import smooth_motion, table_motion

RATE = 125.0
T_S16 = 675  # 5.4 s at 125 Hz ([S16] §V)

# [S16] Table II (simulation), mean (± std) over 100 trials: position 1e-6 m, orientation 1e-3 °.
PAPER_TABLE2 = {
    "self-calibration": ((5.42, 81.84), (1.00, 14.93)),
    "conventional, table": ((1.43, 32.43), (0.40, 9.20)),
    "conventional, gyro calibrated": ((4.17, 75.66), (0.80, 16.66)),
    "conventional, gyro uncalibrated": ((31.40, 1827.58), (7.34, 487.46)),
}


def prototype(seed: int = 2016):
    """The simulated prototype: true poses and triad parameters, and the construction plan.

    Returns a dict: positions (5, 3) m (Table I), orientations (5, 4) (a few degrees off the
    identity), sens (5, 6) parameters of S (1 % scale, ~0.3° axis misalignment), offset (5, 3)
    m/s², nominal_positions / nominal_orientations (the plan: Table I rounded to mm, identity),
    with triad 1 (index 0) — the fixed one — at its true pose.
    """
    g = torch.Generator().manual_seed(seed)
    arr = s16_plate()
    n = lambda *s: torch.randn(*s, generator=g, dtype=torch.float64)  # noqa: E731
    q = boxplus(arr.orientations, 2.0 * DEG_TO_RAD * n(5, 3))
    sens = torch.tensor([1.0, 0.0, 1.0, 0.0, 0.0, 1.0], dtype=torch.float64) + torch.stack(
        (0.01 * n(5), 0.005 * n(5), 0.01 * n(5), 0.005 * n(5), 0.005 * n(5), 0.01 * n(5)), -1)
    offset = 0.05 * n(5, 3)
    nom_p = torch.round(arr.positions * 1e3) / 1e3
    nom_q = arr.orientations.clone()
    nom_p[0], nom_q[0] = arr.positions[0], q[0]
    return {"positions": arr.positions.clone(), "orientations": q, "sens": sens, "offset": offset,
            "nominal_positions": nom_p, "nominal_orientations": nom_q, "array": arr}


def states_from_trace(trace, physical: bool = False) -> torch.Tensor:
    """(T, 9) states [s, ω, ω̇] of a MotionTrace; ω̇ by forward differences unless ``physical``."""
    x = torch.cat((trace.s, trace.omega, trace.omega_dot), -1).to(torch.float64)
    if physical:
        return x
    dt = torch.diff(trace.time.to(torch.float64))
    wd = torch.diff(x[:, 3:6], dim=0) / dt[:, None]
    x[:, 6:9] = torch.cat((wd, wd[-1:]), 0)
    return x


# The motions of the experiments.  "table1": slow 3-axis table motion (the Table II motion);
# "table2": another, 20 s long ([S16] §VI-B); "sinusoid": segments of sinusoidal rate about one
# axis at a time (the paper's synthetic motion); "hand": faster, with translation (waved by hand).
MOTIONS = {
    "sinusoid": dict(kind="table", T=T_S16, kw=dict(axes="xyz", omega_amplitude=6.0, frequency=0.3)),
    "table1": dict(kind="smooth", T=T_S16, kw=dict(omega_rms=6.0, freq_range=(0.05, 0.2), accel_rms=0.0, seed=1)),
    "table2": dict(kind="smooth", T=2500, kw=dict(omega_rms=5.0, freq_range=(0.05, 0.25), accel_rms=0.0, seed=7)),
    "hand": dict(kind="smooth", T=T_S16, kw=dict(omega_rms=4.0, freq_range=(0.1, 0.6), accel_rms=3.0, seed=3)),
}


def motion_trace(name: str, T: int | None = None):
    """The MotionTrace of one named motion (deterministic)."""
    spec = MOTIONS[name]
    T = spec["T"] if T is None else T
    if spec["kind"] == "table":
        return table_motion(T, RATE, **spec["kw"])
    return smooth_motion(T, RATE, **spec["kw"])


def measurements(states, proto, noise_std: float, generator: torch.Generator | None):
    """Triad outputs (T, 5, 3) of the prototype for given states, plus white noise."""
    S = models.sensitivity_matrix(proto["sens"])
    z = models.triad_output(states, proto["orientations"], proto["positions"], S, proto["offset"])
    if noise_std > 0:
        z = z + noise_std * torch.randn(z.shape, generator=generator, dtype=z.dtype)
    return z


def one_thread():
    torch.set_num_threads(1)
