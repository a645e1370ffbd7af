"""Random timing effect: ``sampling_jitter`` (DESIGN §7.2 vocabulary 1.1) — each sample of an IMU
(accelerometer and gyroscope alike) is taken at a random instant t + δ, δ ~ U(−w/2, w/2) drawn
independently per sample, w the ``width`` in s.  A free-running sensor clock does this: the
stamp says t, the ADC sampled a little before or after.

Kind ``"random"``: the effect changes no mean (E δ = 0), so the mean-effect machinery
(:func:`~accel_bayes.physics.effects.model_outputs`, the LM refits) skips it; it changes the
*distribution* of the residuals.

Model, linearised in δ like ``time_offset`` (:mod:`.timing`): the six outputs of IMU k at sample t,

    y_tk = μ_tk + v_tk δ_tk + e_tk,   e ~ N(0, D),  δ ~ U(−w/2, w/2),

with v = d(outputs)/dt (``ctx.acc_rate``, ``ctx.gyro_rate``: one 6-vector per IMU and sample)
and D the diagonal noise variances.  The marginal over δ is exact in closed form
(:func:`log_marginal_gain`): with a = vᵀD⁻¹v and b = vᵀD⁻¹r (r = y − μ),

    p(r) = N(r; 0, D) · E_δ[exp(bδ − aδ²/2)]
         = N(r; 0, D) · exp(b²/2a) · √(2π/a) · [Φ(√a(w/2 − b/a)) − Φ(√a(−w/2 − b/a))] / w.

It couples the IMU's six channels (a rank-1 structure per sample).  The Gaussian moment-matched
alternative, covariance D + (w²/12) v vᵀ, is what :meth:`SamplingJitter.variance` gives per
channel (its diagonal): the predicted extra variance used for budgets and χ²/dof, not for the
likelihood.  The neglected second-order term δ²/2 · d²y/dt² is below w/8 × (curvature/rate) of
the effect, < 1e-3 relative for w ≤ 1 ms and motion under ~50 Hz.

The exact (non-linearised) form is what :func:`accel_bayes.simulate.simulate` evaluates: the
continuous trajectory at the jittered instants :func:`jittered_times`.
"""
from __future__ import annotations

import math

import torch

from ...errors import UserError
from .base import Effect, Param, register_effect

__all__ = ["SamplingJitter", "jittered_times", "log_marginal_gain"]


def jittered_times(time, width: float, generator: torch.Generator):
    """The instants (s) at which samples stamped ``time`` (s, (T,) tensor) are taken by an IMU
    with sampling jitter of full width ``width`` (s): t + δ, δ ~ U(−width/2, width/2) i.i.d.
    (seeded by ``generator``; one uniform draw per sample, always, so the stream does not
    depend on the width)."""
    time = torch.as_tensor(time, dtype=torch.float64)
    u = torch.rand(time.shape, generator=generator, dtype=torch.float64)
    return time + (u - 0.5) * float(width)


def _log1mexp(x: torch.Tensor) -> torch.Tensor:
    """log(1 − eˣ) for x ≤ 0, accurate at both ends (Mächler 2012)."""
    return torch.where(x > -math.log(2.0), torch.log(-torch.expm1(x)), torch.log1p(-torch.exp(x)))


def _log_ndtr_diff(hi: torch.Tensor, lo: torch.Tensor) -> torch.Tensor:
    """log(Φ(hi) − Φ(lo)) for hi > lo, without cancellation: reflected so the pair sits mostly in
    the lower tail, where log Φ is accurate (Φ(hi) − Φ(lo) = Φ(−lo) − Φ(−hi))."""
    flip = (hi + lo) > 0
    h = torch.where(flip, -lo, hi)
    l_ = torch.where(flip, -hi, lo)
    lh, ll = torch.special.log_ndtr(h), torch.special.log_ndtr(l_)
    return lh + _log1mexp((ll - lh).clamp_max(0.0))


def log_marginal_gain(a: torch.Tensor, b: torch.Tensor, width) -> torch.Tensor:
    """log E_δ[exp(bδ − aδ²/2)], δ ~ U(−w/2, w/2): the exact log-likelihood gain of the jitter
    marginal over the plain Gaussian N(r; 0, D) (module docstring), elementwise.

    a = vᵀD⁻¹v (s⁻²), b = vᵀD⁻¹r (s⁻¹), per IMU and sample (any shape); ``width`` w in s
    (a number or a tensor broadcasting with a).  Returns 0 where w = 0 or a = 0.  For
    √a·w and |b|·w below 1e-3 the cumulant series (b² − a)·w²/24 is used (error < 1e-12 of the
    value's scale), elsewhere the closed form with a cancellation-free log(Φ − Φ)."""
    a = torch.as_tensor(a, dtype=torch.float64)
    b = torch.as_tensor(b, dtype=torch.float64)
    w = torch.as_tensor(width, dtype=torch.float64)
    a, b, w = torch.broadcast_tensors(a, b, w)
    small = (torch.sqrt(a) * w < 1e-3) & (b.abs() * w < 1e-3)
    series = (b * b - a) * w * w / 24.0
    a_s = torch.where(small, torch.ones_like(a), a)
    w_s = torch.where(small, torch.ones_like(w), w)
    m = b / a_s
    sa = torch.sqrt(a_s)
    exact = (b * m / 2 + 0.5 * torch.log(2 * math.pi / a_s)
             + _log_ndtr_diff(sa * (w_s / 2 - m), sa * (-w_s / 2 - m)) - torch.log(w_s))
    return torch.where(small, series, exact)


@register_effect
class SamplingJitter(Effect):
    """Each sample of IMU k (accelerometer and gyroscope alike) is taken at a random instant,
    uniform within ±``width``/2 s of its time stamp, independently from sample to sample
    (DESIGN §7.2 vocabulary 1.1; the model and its exact marginal in the module docstring).
    Kind ``"random"``: no mean change; the detector profiles ``width`` on the exact marginal
    likelihood (:mod:`accel_bayes.mismatch.jitter`)."""

    name = "sampling_jitter"
    description = "samples taken at random instants around their time stamps (free-running sensor clocks)"
    kind = "random"
    local_axis = False
    sensor = "both"
    needs_rates = True
    parameters = (Param("width", (), "s", None, "full width of the uniform sampling-instant error", null=0.0),)

    def set_params(self, values: dict) -> "SamplingJitter":
        super().set_params(values)
        if float(self.params["width"]) < 0:
            raise UserError(f"sampling_jitter: width: expected a width >= 0 s, got {float(self.params['width'])!r}")
        return self

    def variance(self, params, ctx):
        """Predicted extra variance per sample and channel, (d_var_acc, d_var_gyro) (T, K, 3) in
        (m/s²)² and (rad/s)²: (w²/12)·(d output/dt)² on IMU k (the diagonal of the moment-matched
        covariance (w²/12) v vᵀ), zero elsewhere."""
        k = self._imu_checked(ctx)
        if ctx.acc_rate is None or ctx.gyro_rate is None:
            raise UserError("sampling_jitter: the signal context has no output rates (acc_rate, gyro_rate)")
        w = float(self._p(params)["width"])
        va = torch.zeros_like(ctx.acc)
        vg = torch.zeros_like(ctx.gyro)
        va[:, k] = w * w / 12.0 * ctx.acc_rate[:, k] ** 2
        vg[:, k] = w * w / 12.0 * ctx.gyro_rate[:, k] ** 2
        return va, vg

    def predicted_variance(self, params, ctx):
        """The residual budget's hook (:func:`accel_bayes.mismatch.budget.predicted_extra_variance`):
        the same as :meth:`variance`."""
        return self.variance(params, ctx)

    def explain(self, params=None):
        w = float(self._p(params)["width"])
        iv = self.stats.get("width_interval_s")
        tail = f" (95 % interval {iv[0] * 1e3:.3g}–{iv[1] * 1e3:.3g} ms)" if iv else ""
        return (f"IMU {self.imu} takes each sample at a random instant within ±{w / 2 * 1e3:.3g} ms of its time stamp"
                f"{tail}, so its readings scatter more where the motion changes fast.")


@register_effect
class TimingWander(SamplingJitter):
    """The sampling instants of one sensor triad of IMU k wander around their time stamps: the
    instant error δ_t is a stationary Gauss–Markov (AR(1)) process with the variance of a uniform
    jitter of full width ``width`` (σ_δ = width/√12) and lag-one ``correlation`` ρ between
    consecutive samples (ρ^(Δt/Δt₀) across a gap of Δt, Δt₀ the median step).  ρ = 0 is
    ``sampling_jitter`` in its Gaussian form on one sensor; ρ → 1 a drifting time offset.  The
    physics: a sensor sampled on its own free-running clock and read by a host on another, whose
    beat wanders with the clocks' frequencies (e.g. an IMU's internal output-data-rate clock read
    at 62.5 Hz).

    Not in the DESIGN §7.2 vocabulary (an extension, reported under this name).  Kind
    ``"random"``: no mean change; the detector fits (width, correlation) on the exact marginal
    likelihood of the linearised model (:mod:`accel_bayes.mismatch.wander`, banded O(T)).  Its
    predicted extra variance per sample is that of the instant error, (width²/12)·rate², on the
    sensor's channels of IMU k, plus ``excess_noise_var``: the white noise the triad has beyond the
    model's, fitted together with the wander so that the wander is not credited with a constant
    variance inflation (its evidence is against the triad's best noise-only model)."""

    name = "timing_wander"
    in_vocabulary = False
    description = "sampling instants of one sensor that wander around their time stamps (beating clocks)"
    sensor = "gyro"
    options = ("sensor",)
    parameters = (Param("width", (), "s", None, "√12 × the std of the instant error (the width of a uniform jitter "
                        "with the same variance)", null=0.0),
                  Param("correlation", (), "1", None, "lag-one correlation of the instant error", null=0.0),
                  Param("excess_noise_var", (), "sensor units²", None, "white noise the triad has beyond the model's "
                        "(fitted with the wander, so that the wander is not credited with it)", null=0.0))

    def __init__(self, imu=None, axis=None, params=None, sensor: str = "gyro"):
        if sensor not in ("acc", "gyro"):
            raise UserError(f"timing_wander: sensor: expected 'acc' or 'gyro', got {sensor!r}")
        self.which = sensor
        super().__init__(imu, axis, params)

    def set_params(self, values: dict) -> "TimingWander":
        super().set_params(values)
        r = float(self.params["correlation"])
        if not 0.0 <= r < 1.0:
            raise UserError(f"timing_wander: correlation: expected 0 <= correlation < 1, got {r!r}")
        if float(self.params["excess_noise_var"]) < 0:
            raise UserError("timing_wander: excess_noise_var: expected a variance >= 0")
        return self

    def location(self):
        return {"imu": self.imu, "axis": None, "sensor": self.which}

    @classmethod
    def candidates(cls, layout):
        from .output import _imus_by_sensor

        return [cls(imu=k, sensor=sensor) for sensor, ks in _imus_by_sensor(layout) for k in ks]

    def variance(self, params, ctx):
        va, vg = super().variance(params, ctx)
        extra = float(self._p(params)["excess_noise_var"])
        k = self._imu_checked(ctx)
        if self.which == "acc":
            va[:, k] = va[:, k] + extra
            return va, torch.zeros_like(vg)
        vg[:, k] = vg[:, k] + extra
        return torch.zeros_like(va), vg

    def report_parameters(self, params=None):
        out = super().report_parameters(params)
        out["sensor"] = self.which
        return out

    def explain(self, params=None):
        p = self._p(params)
        sd = float(p["width"]) / math.sqrt(12.0)
        what = "accelerometer" if self.which == "acc" else "gyroscope"
        text = (f"IMU {self.imu}'s {what} samples at instants that wander around their time stamps (std "
                f"{sd * 1e3:.3g} ms, correlation {float(p['correlation']):.2f} between consecutive samples), as a sensor "
                f"on its own free-running clock would: its readings lag or lead the motion by a slowly changing amount.")
        m, rms = self.stats.get("instant_mean_s"), self.stats.get("instant_rms_s")
        if m is not None and rms and abs(m) > 0.5 * rms:
            # the conditional mean of the instants (accel_bayes.mismatch.jitter.random_offsets)
            text += (f" Their estimated instants average {m * 1e3:+.3g} ms (rms {rms * 1e3:.3g} ms): mostly a constant "
                     f"{'lag' if m < 0 else 'lead'} of this sensor, as a filter's group delay would give.")
        return text
