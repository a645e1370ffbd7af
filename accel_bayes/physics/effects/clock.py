"""``sampling_clock`` (DESIGN §7.2 vocabulary 1.2): an IMU that samples on its own free-running
clock, holds the latest sample in a register and is read asynchronously by the host.

Physics.  The IMU ticks at f_k = internal_rate_hz (≈ 1 kHz, a few ‰ off nominal); the host reads
at f_read.  The sample the host gets was taken ``age`` seconds before the read, and that data age
is a deterministic sawtooth on [0, 1/f_k) whose phase advances by beat/f_read cycles per read,

    age(t) = W · frac(phase + beat_hz·t + ½·drift_hz_per_s·t²),   W = √12 · age_rms_s ≈ 1/f_k,

t in s on the recording's own time axis (phase is the sawtooth's at t = 0), beat_hz =
f_k − round(f_k/f_read)·f_read ∈ (−f_read/2, f_read/2] (the sign: positive beat = the age grows
from read to read).  The accelerometer and the gyroscope of one IMU share every tick, so both
outputs are the true signals at t − age − (filter delay): y(t) = y_true(t − age(t) − d_s).  The
absolute filter delay d_s is common to the whole board (the datasheet's) and absorbed by the
motion; only the accelerometer's delay beyond the gyro's, ``filter_delay_acc_minus_gyro_s``, is
identifiable.  Linearised (like ``time_offset``, :mod:`.timing`):

    d_gyro = −age(t)·λ·R_k ω̇(t),   d_acc = −(age(t) + filter_delay_acc_minus_gyro_s)·ȧ(t),

R_k ω̇ the gyro output's rate from the context's angular acceleration (:func:`board_gyro_rate`:
the rate at the sample instant, which the finite difference of the sampled outputs is not once
the board vibrates above the read's Nyquist rate), ȧ the accelerometer output rate
(``ctx.acc_rate``).  λ = ``rate_scale`` is the true gyro rate per unit of the context's R_k ω̇
(1 where the motion states are right): the per-sample ω̇ states carry the fitted lever arms' scale
error and noise, and the age is physical only with that scale taken apart
(:func:`accel_bayes.mismatch.clock.rate_scale` measures it from the gyro's own increments).  The neglected term is age²/2 · ÿ, below 1e-3 of the effect for ages ≤ 1 ms
and motion under ~50 Hz.

The phase, beat and drift enter through a discontinuous sawtooth, so the effect is not fitted by
the LM refits: :mod:`accel_bayes.mismatch.clock` estimates it by a beat-frequency search and the
detector holds it fixed (``screened = False``; one finding per IMU that has it, not capped by
``max_findings``).  ``internal_rate_hz`` is reported (f_read·round(f_nominal/f_read) + beat), it
does not enter the linearised outputs beyond the sawtooth's width.
"""
from __future__ import annotations

import math

import torch

from ...errors import UserError
from ..geometry import quat_to_matrix
from .base import Effect, Param, register_effect, _onehot

__all__ = ["SamplingClock", "clock_age", "board_gyro_rate"]


def clock_age(time, beat_hz, phase, drift_hz_per_s, width_s):
    """The data age (s) of a sampling clock at the read times ``time`` (s; tensor (T,)):
    width_s · frac(phase + beat_hz·t + ½·drift_hz_per_s·t²) (module docstring).  Broadcasts."""
    t = torch.as_tensor(time, dtype=torch.float64)
    x = phase + beat_hz * t + 0.5 * drift_hz_per_s * t * t
    return width_s * (x - torch.floor(x))


def board_gyro_rate(ctx) -> torch.Tensor:
    """(T, K, 3) d/dt of the nominal gyro outputs (rad/s²): R_k ω̇_t, the context's own angular
    acceleration (array frame, ``ctx.omega_dot``) turned into each IMU's sensor frame.

    Why not the finite difference of the sampled outputs (``ctx.gyro_rate``): board vibration above
    the read's Nyquist rate folds to f_read − f, where the sampled signal's derivative is −(f_read −
    f)/f times the true one (flipped and shrunk), so a data age loaded on it has the wrong sign and
    size.  ω̇_t is the rigid board's angular acceleration at the sample instant itself — a per-sample
    motion state the accelerometer array measures through the tangential term ω̇ × r — so nothing
    folds."""
    R = quat_to_matrix(ctx.orientations.to(ctx.omega_dot.dtype))
    return torch.einsum("kij,tj->tki", R, ctx.omega_dot)


@register_effect
class SamplingClock(Effect):
    """IMU k's data age is its own clock's sawtooth (module docstring); shared by acc and gyro,
    plus the acc − gyro filter-delay difference on the accelerometer."""

    name = "sampling_clock"
    description = "the IMU samples on its own clock and is read asynchronously (data age a sawtooth)"
    screened = False  # estimated by mismatch.clock's beat search, held fixed in the fits
    sensor = "both"
    needs_rates = True
    parameters = (
        Param("internal_rate_hz", (), "Hz", None, "the IMU's own sampling rate f_k", null=1000.0),
        Param("beat_hz", (), "Hz", None, "f_k − round(f_k/f_read)·f_read: the data-age sawtooth's frequency"),
        Param("phase", (), "1", None, "the sawtooth's phase at t = 0 of the recording's time axis, in cycles [0, 1)"),
        Param("drift_hz_per_s", (), "Hz s-1", None, "rate of change of the beat frequency"),
        Param("age_rms_s", (), "s", None, "rms of the data age about its mean: width/√12 (0: no clock effect)"),
        Param("filter_delay_acc_minus_gyro_s", (), "s", None, "accelerometer filter delay beyond the gyroscope's"),
        Param("rate_scale", (), "1", None, "true gyro rate per unit of the model's R_k ω̇ (the regressor's scale)",
              null=1.0),
    )

    def age(self, time, params=None) -> torch.Tensor:
        """The data age (s) at the times ``time`` (s) (:func:`clock_age`), the sawtooth's width the
        fitted one (√12 · ``age_rms_s``): the age that scales this clock's mean effect."""
        p = self._p(params)
        return clock_age(time, p["beat_hz"], p["phase"], p["drift_hz_per_s"], math.sqrt(12.0) * p["age_rms_s"])

    def physical_age(self, time, params=None) -> torch.Tensor:
        """The data age (s) at the times ``time`` (s) on the hold's own sawtooth, width 1/``internal_rate_hz``.

        What loads the unresolved motion (issue #27 budget): the fitted width is a regression coefficient
        of the outputs on their rate, shrunk where that regressor is noisy (0.12–0.32 ms rms on the six
        real recordings where the hold gives 0.29 ms), and a term loaded on it would carry the shrinkage
        in its scale, which then means something else in every recording."""
        p = self._p(params)
        return clock_age(time, p["beat_hz"], p["phase"], p["drift_hz_per_s"], 1.0 / float(p["internal_rate_hz"]))

    def perturbation(self, params, ctx):
        p = self._p(params)
        k = self._imu_checked(ctx)
        if ctx.acc_rate is None:
            raise UserError("sampling_clock: the signal context has no accelerometer output rate (acc_rate)")
        age = self.age(ctx.time, p)[:, None, None]
        m = _onehot(ctx.K, k, None, ctx.acc)
        return (-(age + p["filter_delay_acc_minus_gyro_s"]) * m * ctx.acc_rate,
                -age * p["rate_scale"] * m * board_gyro_rate(ctx))

    def explain(self, params=None):
        p = {k: float(v) for k, v in self._p(params).items()}
        return (f"IMU {self.imu} samples on its own clock ({p['internal_rate_hz']:.5g} Hz) and is read "
                f"asynchronously: its data age is a {math.sqrt(12) * p['age_rms_s'] * 1e3:.3g} ms sawtooth beating at "
                f"{p['beat_hz']:.4g} Hz against the read rate, shared by its accelerometer and gyroscope.")
