"""Timing effects: an IMU sampled late.  One parameter, one sign convention (DESIGN §7.2):
``offset`` δ in s, **positive = sampled late** — the sample stamped t holds the output at t + δ.
:func:`sample_times` is that convention, used by the exact evaluation (the simulator evaluates
the trajectory at those times) and stated by the linearised one (:class:`TimeOffset`,
δ·d/dt of the nominal output); ``tests/physics/test_effects.py`` compares the two (error O(δ²)).
"""
from __future__ import annotations

from ...errors import UserError
from .base import Effect, Param, register_effect, _onehot

__all__ = ["sample_times", "TimeOffset", "GyroDelay"]


def sample_times(time, offset):
    """The instants (s) at which samples stamped ``time`` (s) are taken by an IMU with time
    offset ``offset`` (s; DESIGN §7.2, positive = sampled late): t + δ.  Broadcasts."""
    return time + offset


@register_effect
class TimeOffset(Effect):
    """IMU k is sampled ``offset`` seconds late (positive = late): its sample stamped t holds
    the output y(t + offset) (:func:`sample_times`).  Linearised: both triads get
    offset × d/dt(nominal output) (``ctx.acc_rate``, ``ctx.gyro_rate``), the first-order Taylor
    term of y(t + δ) − y(t); the neglected term is offset²/2 × d²/dt², below 1e-3 of the effect
    for offsets ≤ 1 ms and motion under ~50 Hz.  The exact form is what
    :func:`accel_bayes.simulate.simulate` evaluates for ``time_offsets=``."""

    name = "time_offset"
    description = "one IMU sampled late relative to the others"
    local_axis = False
    sensor = "both"
    needs_rates = True
    parameters = (Param("offset", (), "s", 0.01, "positive = sampled late"),)

    def perturbation(self, params, ctx):
        p = self._p(params)
        k = self._imu_checked(ctx)
        if ctx.acc_rate is None or ctx.gyro_rate is None:
            raise UserError("time_offset: the signal context has no output rates (acc_rate, gyro_rate)")
        m = _onehot(ctx.K, k, None, ctx.acc)
        return p["offset"] * m * ctx.acc_rate, p["offset"] * m * ctx.gyro_rate

    def explain(self, params=None):
        d = float(self._p(params)["offset"])
        return (f"IMU {self.imu} is sampled {abs(d) * 1e3:.3g} ms {'late' if d > 0 else 'early'} relative to the "
                f"others, so its readings lag the common motion.")


@register_effect
class GyroDelay(Effect):
    """IMU k's **gyroscope** output lags the motion by ``delay`` seconds relative to its own
    accelerometer (positive = the gyro lags): gyro += −delay × d/dt(nominal gyro output).

    Not in the DESIGN §7.2 vocabulary (a name of our own, documented here and in the report): the
    physics is a filter or sampling delay of one sensor only — e.g. a digital low-pass filter with
    a different group delay on the gyroscope than on the accelerometer (a first-order low-pass
    with time constant τ delays slow signals by τ), or a gyro read from an earlier internal
    sample.  ``time_offset`` moves both sensors of an IMU together; a gyro-only delay explains
    the gyro's residuals as well as ``time_offset`` does but leaves the accelerometer alone, so
    the two are told apart by the accelerometer channels.  Linearised like ``time_offset`` (first
    Taylor term; for a first-order low-pass the neglected term is τ²·d²ω/dt², below 1 % of the
    effect for τ ≤ 1 ms and motion under ~15 Hz, tests/mismatch/test_characterise.py)."""

    name = "gyro_delay"
    in_vocabulary = False
    description = "gyroscope output delayed relative to the accelerometer (filter or sampling delay)"
    local_axis = False
    sensor = "gyro"
    needs_rates = True
    parameters = (Param("delay", (), "s", 0.01, "positive = the gyro output lags the motion"),)

    def perturbation(self, params, ctx):
        p = self._p(params)
        k = self._imu_checked(ctx)
        if ctx.gyro_rate is None:
            raise UserError("gyro_delay: the signal context has no output rates (gyro_rate)")
        m = _onehot(ctx.K, k, None, ctx.gyro)
        return ctx.acc.new_zeros(ctx.acc.shape), -p["delay"] * m * ctx.gyro_rate

    def explain(self, params=None):
        d = float(self._p(params)["delay"])
        return (f"IMU {self.imu}'s gyroscope {'lags' if d > 0 else 'leads'} its accelerometer by {abs(d) * 1e3:.3g} ms "
                f"(a filter or sampling delay of the gyroscope alone).")

