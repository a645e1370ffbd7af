"""Accelerometer effects: bias, scale, cross-axis coupling, second-order response, displaced
sensing axes.  Sensor frame of the IMU, SI units (DESIGN §7.2).
"""
from __future__ import annotations

import torch

from ..geometry import quat_to_matrix
from ..models import specific_force, to_array_frame
from ...constants import G0
from .base import AXES, Effect, Param, register_effect, _fmt, _onehot, _CrossAxisCoupling


@register_effect
class AccBias(Effect):
    """Constant accelerometer offset on one axis: output_a += bias (m/s²)."""

    name = "acc_bias"
    description = "constant accelerometer offset"
    local_axis = True
    sensor = "acc"
    parameters = (Param("bias", (), "m s-2", 1.0, "offset added to the axis output"),)

    def perturbation(self, params, ctx):
        p = self._p(params)
        k = self._imu_checked(ctx)
        m = _onehot(ctx.K, k, self.axis_index, ctx.acc)
        return p["bias"] * m.expand_as(ctx.acc), torch.zeros_like(ctx.gyro)

    def explain(self, params=None):
        b = float(self._p(params)["bias"])
        return (f"The {self.axis} axis of IMU {self.imu}'s accelerometer reads {_fmt(abs(b), 'm/s²')} "
                f"{'too high' if b > 0 else 'too low'} at all times (a constant offset the model did not include).")


@register_effect
class AccScale(Effect):
    """Scale-factor error of one accelerometer axis: output_a += scale · f_a (relative)."""

    name = "acc_scale"
    description = "accelerometer scale-factor error"
    local_axis = True
    sensor = "acc"
    parameters = (Param("scale", (), "1", 0.05, "relative scale error (0.01 = 1 %)"),)

    def perturbation(self, params, ctx):
        p = self._p(params)
        k = self._imu_checked(ctx)
        m = _onehot(ctx.K, k, self.axis_index, ctx.acc)
        return p["scale"] * m * ctx.acc, torch.zeros_like(ctx.gyro)

    def explain(self, params=None):
        s = float(self._p(params)["scale"])
        return (f"The {self.axis} axis of IMU {self.imu}'s accelerometer reads {_fmt(abs(100 * s))} % "
                f"{'more' if s > 0 else 'less'} than the specific force it feels (a scale-factor error).")


@register_effect
class AccMisalignment(_CrossAxisCoupling):
    """Cross-axis coupling: axis ``axis`` also senses ``coupling`` × the ``from_axis`` component
    of the specific force (rad; a non-orthogonal or tilted sensing axis, to first order)."""

    name = "acc_misalignment"
    description = "cross-axis coupling / non-orthogonal accelerometer axes"
    sensor = "acc"
    parameters = (Param("coupling", (), "rad", 0.05, "fraction of the from_axis component added"),)

    def explain(self, params=None):
        c = float(self._p(params)["coupling"])
        return (f"The {self.axis} axis of IMU {self.imu}'s accelerometer also picks up {_fmt(100 * c)} % of the "
                f"{self.from_axis}-axis specific force (cross-axis coupling, a sensing axis not orthogonal to the others).")


@register_effect
class AccNonlinearity(Effect):
    """Second-order response of one accelerometer axis: output_a += k2 · f_a², k2 in (m/s²)⁻¹."""

    name = "acc_nonlinearity"
    description = "second-order accelerometer response"
    local_axis = True
    sensor = "acc"
    parameters = (Param("k2", (), "(m s-2)-1", 1e-2, "output += k2 · a²"),)

    def perturbation(self, params, ctx):
        p = self._p(params)
        k = self._imu_checked(ctx)
        m = _onehot(ctx.K, k, self.axis_index, ctx.acc)
        return p["k2"] * m * ctx.acc * ctx.acc, torch.zeros_like(ctx.gyro)

    def explain(self, params=None):
        k2 = float(self._p(params)["k2"])
        return (f"The {self.axis} axis of IMU {self.imu}'s accelerometer responds quadratically: it adds "
                f"{_fmt(k2, '(m/s²)⁻¹')} × a², i.e. {_fmt(abs(k2) * G0 ** 2, 'm/s²')} at 1 g (a second-order nonlinearity).")


@register_effect
class AccLinear(Effect):
    """The whole linear error of one accelerometer triad: output += M·f + b, sensor frame, with M
    (3 × 3, relative: its diagonal the three scale-factor errors, its off-diagonal entries the
    cross-axis couplings) and b (m/s²) the offsets — ``acc_scale`` on every axis,
    ``acc_misalignment`` on every pair and ``acc_bias`` on every axis of the triad at once.

    Why one 12-parameter block: the gyroscopes' reason (:class:`~accel_bayes.physics.effects.GyroLinear`).
    Raw MEMS accelerometers carry all twelve terms, and where the recording rests in one
    orientation only, the preparation cannot calibrate them from the rests (S16); a detector that
    adds one 1-df term per round leaves the rest in the residual, as excess the §7.2 budget cannot
    credit (experiments/budget_gap_probe.md: on the concealed clock recordings the accelerometer
    budget's systematic shortfall is these errors).  The detector estimates the blocks in a stage
    of its own (:mod:`accel_bayes.mismatch.acc_linear`); they are not round candidates
    (``screened = False``).

    Reported under the vocabulary name ``acc_scale`` (DESIGN §7.2: "accelerometer scale-factor
    error") with axis null and parameters {"scale": M as 3 rows (output axis) of 3 (from axis),
    "bias": b}; a report finding of that form is read back as this class.  A block is always one
    triad's (``imu`` set): an error common to every accelerometer is not fitted (its offset and most
    of its matrix are absorbed by the per-sample linear motion).
    """

    name = "acc_linear"
    vocabulary_name = "acc_scale"
    description = "accelerometer scale-factor, misalignment and offset errors of one triad"
    screened = False
    sensor = "acc"
    parameters = (Param("matrix", (3, 3), "1", 0.05, "relative linear error: output += matrix · f"),
                  Param("bias", (3,), "m s-2", 1.0, "offset added to the three accelerometer outputs"))

    @classmethod
    def reads_report(cls, axis, parameters, options):
        s = parameters.get("scale")
        return axis is None and isinstance(s, (list, tuple)) and len(s) == 3

    @classmethod
    def from_report(cls, parameters, options):
        if "scale" in parameters:
            parameters["matrix"] = parameters.pop("scale")
        return parameters, options

    def vocabulary_parameters(self, params=None):
        """The report's parameters under the vocabulary name acc_scale: {"scale": 3 × 3 rows,
        "bias": 3-vector (m/s²)}."""
        p = self._p(params)
        return {"scale": p["matrix"].detach().cpu().double().tolist(),
                "bias": p["bias"].detach().cpu().double().tolist()}

    def invert(self, y):
        """The specific force a triad with this block felt: (I + matrix)⁻¹ (y − bias), y (..., 3)
        sensor-frame outputs, m/s² (numpy array or tensor, returned as given; a sample with a NaN
        channel comes back NaN on all three)."""
        p = self.params
        t = torch.as_tensor(y, dtype=torch.float64)
        out = torch.linalg.solve(torch.eye(3, dtype=torch.float64) + p["matrix"], (t - p["bias"]).unsqueeze(-1)).squeeze(-1)
        return out if torch.is_tensor(y) else out.numpy()

    def perturbation(self, params, ctx):
        p = self._p(params)
        k = self._imu_checked(ctx)
        m = _onehot(ctx.K, k, None, ctx.acc)
        return m * (ctx.acc @ p["matrix"].transpose(0, 1) + p["bias"]), torch.zeros_like(ctx.gyro)

    def explain(self, params=None):
        p = self._p(params)
        M = p["matrix"].detach().cpu().double()
        b = p["bias"].detach().cpu().double()
        diag = ", ".join(f"{100 * float(M[i, i]):+.3g} %" for i in range(3))
        off = float((M - torch.diag(torch.diagonal(M))).abs().max())
        return (f"IMU {self.imu}'s accelerometer has a linear error: scale-factor errors {diag} on x, y, z, "
                f"cross-axis couplings up to {100 * off:.3g} %, offsets up to {_fmt(float(b.abs().max()), 'm/s²')} "
                f"(an accelerometer scale / misalignment / bias error, all twelve terms fitted together).")


@register_effect
class AxisDisplacement(Effect):
    """The sensing element of one accelerometer axis sits ``displacement`` (m, sensor frame) away
    from the triad's position (the "size effect"): that axis reads the specific force of the
    displaced point.  Exact: f(r + Rᵀd) − f(r) = ω×(ω×Rᵀd) + ω̇×Rᵀd because the specific
    force is affine in the position ([C21] eq. 4a)."""

    name = "axis_displacement"
    description = "accelerometer sensing axes not collocated inside the package (size effect)"
    local_axis = True
    sensor = "acc"
    parameters = (Param("displacement", (3,), "m", 5e-3, "offset of this axis' sensing point, sensor frame"),)

    def perturbation(self, params, ctx):
        p = self._p(params)
        k = self._imu_checked(ctx)
        q = ctx.orientations[k:k + 1]
        d_array = to_array_frame(p["displacement"].reshape(1, 3), q)  # Rᵀ d, (1, 3)
        zero = torch.zeros_like(ctx.s)
        extra = specific_force(d_array, ctx.omega, ctx.omega_dot, zero)  # (T, 1, 3) array frame
        extra_s = (quat_to_matrix(q) @ extra.unsqueeze(-1)).squeeze(-1)  # sensor frame of IMU k
        m = _onehot(ctx.K, k, self.axis_index, ctx.acc)
        d_acc = m * extra_s[:, 0:1, self.axis_index:self.axis_index + 1]
        return d_acc, torch.zeros_like(ctx.gyro)

    def explain(self, params=None):
        d = self._p(params)["displacement"].detach().cpu().double()
        n = float(d.norm())
        return (f"The {self.axis}-axis accelerometer of IMU {self.imu} senses at a point "
                f"{_fmt(1e3 * n, 'mm')} from the rest of its triad (sensor-frame offset "
                f"[{', '.join(f'{1e3 * float(v):.2f}' for v in d)}] mm), so it feels extra centripetal and "
                f"tangential acceleration when the board rotates.")


# ------------------------------------------------------------------------------------ gain form
# The linear accelerometer effects of one IMU add up to a general 3×3 gain and a bias, sensor
# frame:  y = (I + M) f + b,  M_aa = acc_scale(a), M_ab = acc_misalignment(a from b),
# b_a = acc_bias(a).  The intrinsic calibration (lower-triangular T, :mod:`accel_bayes.prep.intrinsics`)
# and the [S16] sensor parameters (upper-triangular S plus offset o, eq. 21–22) are two
# triangular parametrisations of the same gain; the functions below convert between them.
#
# Gauge.  A general gain has 9 numbers, a triangular one 6: the other 3 are a rotation.  Every
# invertible gain with det > 0 factors uniquely as  gain = L Q  with L lower-triangular with a
# positive diagonal and Q a rotation (RQ decomposition).  Q acts on f before the triangular part,
# i.e. it is a rotation of the sensor frame: it goes into the triad orientation (R(q) → Q R(q)),
# where a self-calibration estimates it together with the pose.  The triangular forms fix that
# gauge by putting the sensor x axis along the first sensing axis (and y in the plane of the
# first two), as [S16] eq. 21 states for S.

def acc_gain_effects(gain, bias, imu: int) -> list:
    """The accelerometer effects of IMU ``imu`` (sensor frame) whose outputs are
    y = gain · f + bias: 3 ``acc_scale`` (gain_aa − 1), 6 ``acc_misalignment`` (gain_ab, axis a
    from axis b) and 3 ``acc_bias`` (m/s²).  gain (3, 3) dimensionless, bias (3,) m/s²."""
    gain = torch.as_tensor(gain, dtype=torch.float64)
    bias = torch.as_tensor(bias, dtype=torch.float64)
    M = gain - torch.eye(3, dtype=gain.dtype)
    out = [AccScale(imu, AXES[a], {"scale": M[a, a]}) for a in range(3)]
    out += [AccMisalignment(imu, AXES[a], {"coupling": M[a, b]}, from_axis=AXES[b])
            for a in range(3) for b in range(3) if b != a]
    out += [AccBias(imu, AXES[a], {"bias": bias[a]}) for a in range(3)]
    return out


def acc_gain_of_effects(effects, imu: int):
    """Inverse of :func:`acc_gain_effects`: the gain (3, 3) and bias (3,) m/s² that the
    ``acc_scale`` / ``acc_misalignment`` / ``acc_bias`` effects of IMU ``imu`` add up to (other
    effects and other IMUs are ignored)."""
    M = torch.zeros(3, 3, dtype=torch.float64)
    b = torch.zeros(3, dtype=torch.float64)
    for e in effects:
        if e.imu != imu:
            continue
        if isinstance(e, AccScale):
            M[e.axis_index, e.axis_index] += e.params["scale"]
        elif isinstance(e, AccMisalignment):
            M[e.axis_index, e.from_index] += e.params["coupling"]
        elif isinstance(e, AccBias):
            b[e.axis_index] += e.params["bias"]
    return torch.eye(3, dtype=torch.float64) + M, b


def triangular_gauge(gain: torch.Tensor):
    """gain (..., 3, 3), det > 0 → (L, Q) with gain = L Q, L lower-triangular with a positive
    diagonal, Q a rotation (det +1): the gauge of the triangular forms (see above)."""
    Qt, Rt = torch.linalg.qr(gain.transpose(-1, -2))  # gainᵀ = Qt Rt  ⇒  gain = Rtᵀ Qtᵀ
    sgn = torch.sign(torch.diagonal(Rt, dim1=-2, dim2=-1))
    sgn = torch.where(sgn == 0, torch.ones_like(sgn), sgn)
    L = (sgn.unsqueeze(-1) * Rt).transpose(-1, -2)  # flip rows of Rt (columns of L) to a positive diagonal
    Q = (Qt * sgn.unsqueeze(-2)).transpose(-1, -2)
    return L, Q


def intrinsics_gain(T: torch.Tensor, b: torch.Tensor):
    """The gain form of the intrinsic model a_true = T (a_raw − b) (:class:`accel_bayes.prep.intrinsics.
    Intrinsics`, T lower-triangular): a_raw = T⁻¹ a_true + b.  Returns (gain = T⁻¹, bias = b)."""
    T = torch.as_tensor(T, dtype=torch.float64)
    return torch.linalg.inv(T), torch.as_tensor(b, dtype=torch.float64)


def gain_to_intrinsics(gain: torch.Tensor, bias: torch.Tensor):
    """Inverse of :func:`intrinsics_gain` in the triangular gauge: (T lower-triangular, b, Q)
    with gain = T⁻¹ Q; Q (identity for a lower-triangular gain) belongs to the orientation."""
    L, Q = triangular_gauge(torch.as_tensor(gain, dtype=torch.float64))
    return torch.linalg.inv(L), torch.as_tensor(bias, dtype=torch.float64), Q


def s16_gain(S: torch.Tensor, offset: torch.Tensor):
    """The gain form of the [S16] sensor model z = Sᵀ R(q) f + o (eq. 4, 21–22; S upper-triangular,
    :func:`accel_bayes.physics.models.triad_output`): gain = Sᵀ on the sensor-frame specific force R(q) f,
    bias = o.  Returns (gain, bias)."""
    return torch.as_tensor(S, dtype=torch.float64).transpose(-1, -2), torch.as_tensor(offset, dtype=torch.float64)


def gain_to_s16(gain: torch.Tensor, bias: torch.Tensor):
    """Inverse of :func:`s16_gain` in the triangular gauge: (S upper-triangular, o, Q) with
    gain = Sᵀ Q; the triad orientation becomes Q R(q)."""
    L, Q = triangular_gauge(torch.as_tensor(gain, dtype=torch.float64))
    return L.transpose(-1, -2), torch.as_tensor(bias, dtype=torch.float64), Q
