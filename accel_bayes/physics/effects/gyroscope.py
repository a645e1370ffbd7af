"""Gyroscope effects: bias, scale factor, misalignment (off-diagonal scale), g-sensitivity,
second-order response.  Sensor frame of the IMU, SI units (DESIGN §7.2).
"""
from __future__ import annotations

import torch

from ...constants import DEG_TO_RAD, G0
from ...errors import UserError
from .base import Effect, Param, register_effect, _fmt, _onehot, _CrossAxisCoupling


@register_effect
class GyroBias(Effect):
    """Constant gyroscope offset on one axis: output_a += bias (rad/s)."""

    name = "gyro_bias"
    description = "gyroscope offset"
    local_axis = True
    sensor = "gyro"
    parameters = (Param("bias", (), "rad s-1", 0.1, "offset added to the gyro axis output"),)

    def perturbation(self, params, ctx):
        p = self._p(params)
        k = self._imu_checked(ctx)
        m = _onehot(ctx.K, k, self.axis_index, ctx.gyro)
        return torch.zeros_like(ctx.acc), p["bias"] * m.expand_as(ctx.gyro)

    def explain(self, params=None):
        b = float(self._p(params)["bias"])
        return (f"The {self.axis} axis of IMU {self.imu}'s gyroscope reads {abs(b) / DEG_TO_RAD:.3g} °/s "
                f"{'too high' if b > 0 else 'too low'} at all times (a gyro offset).")


@register_effect
class GyroScale(Effect):
    """Scale-factor error of one gyroscope axis: output_a += scale · ω_a (relative)."""

    name = "gyro_scale"
    description = "gyroscope scale-factor error"
    local_axis = True
    sensor = "gyro"
    parameters = (Param("scale", (), "1", 0.05, "relative scale error (0.01 = 1 %)"),)

    @classmethod
    def from_report(cls, parameters, options):
        # a report's gyro_scale may carry from_axis; equal to the own axis, it is the diagonal
        # (an off-diagonal one is claimed by GyroMisalignment.reads_report)
        parameters.pop("from_axis", None)
        options.pop("from_axis", None)
        return parameters, options

    def perturbation(self, params, ctx):
        p = self._p(params)
        k = self._imu_checked(ctx)
        m = _onehot(ctx.K, k, self.axis_index, ctx.gyro)
        return torch.zeros_like(ctx.acc), p["scale"] * m * ctx.gyro

    def explain(self, params=None):
        s = float(self._p(params)["scale"])
        return (f"The {self.axis} axis of IMU {self.imu}'s gyroscope reads {abs(100 * s):.3g} % "
                f"{'more' if s > 0 else 'less'} than the true rotation rate (a gyro scale-factor error).")


@register_effect
class GyroMisalignment(_CrossAxisCoupling):
    """Cross-axis coupling of one gyroscope axis: gyro axis ``axis`` also senses ``coupling`` ×
    the ``from_axis`` component of the rotation rate (rad; a gyro sensing axis tilted towards
    another one, to first order), output_a += coupling · ω_b, sensor frame.

    Together with ``gyro_scale`` (the diagonal) this spans the gyroscope's full 3 × 3 linear
    error of [S16]-style intrinsic models.  Unlike ``triad_orientation`` it moves the gyro
    triad only, and a single coupling need not come with its antisymmetric partner: a
    non-orthogonal gyro triad is *not* a rotation, and fitting a mounting rotation to it gives a
    rotation vector that depends on the distribution of ω in the recording (the projection of
    a symmetric error onto rotations), which does not carry over to other recordings."""

    name = "gyro_misalignment"
    # Reports use the DESIGN §7.2 vocabulary (a fixed contract), where ``gyro_scale`` is the
    # "gyroscope scale-factor / misalignment error": this term is reported as a gyro_scale
    # finding with {"scale": coupling, "from_axis": b} — the (axis, from_axis) element of the
    # gyro's relative scale/misalignment matrix, whose diagonal is GyroScale.
    vocabulary_name = "gyro_scale"
    description = "cross-axis coupling / non-orthogonal gyroscope axes"
    sensor = "gyro"
    same_axis_hint = "; the same-axis term is gyro_scale"
    parameters = (Param("coupling", (), "rad", 0.05, "fraction of the from_axis rotation rate added"),)

    @classmethod
    def reads_report(cls, axis, parameters, options):
        frm = options.get("from_axis", parameters.get("from_axis"))
        return frm is not None and frm != axis

    @classmethod
    def from_report(cls, parameters, options):
        if "scale" in parameters:
            parameters["coupling"] = parameters.pop("scale")
        return parameters, options

    def vocabulary_parameters(self, params=None):
        """The report's parameters under the vocabulary name gyro_scale."""
        out = self.report_parameters(params)
        return {"scale": out.pop("coupling"), "from_axis": out.pop("from_axis"), **out}

    def explain(self, params=None):
        c = float(self._p(params)["coupling"])
        return (f"The {self.axis} axis of IMU {self.imu}'s gyroscope also picks up {_fmt(100 * c)} % of the "
                f"{self.from_axis}-axis rotation rate (cross-axis coupling, a gyro sensing axis not orthogonal to "
                f"the others).")


@register_effect
class GyroGSensitivity(Effect):
    """Gyroscope output that depends on specific force: gyro axis i += sensitivity_i · f_i
    (rad/s per m/s², f the sensor-frame specific force at the IMU)."""

    name = "gyro_g_sensitivity"
    description = "gyroscope output that depends on specific force"
    local_axis = False
    sensor = "gyro"
    parameters = (Param("sensitivity", (3,), "rad s-1 per m s-2", 1e-3, "gyro axis i sees force axis i"),)

    def perturbation(self, params, ctx):
        p = self._p(params)
        k = self._imu_checked(ctx)
        m = _onehot(ctx.K, k, None, ctx.gyro)
        return torch.zeros_like(ctx.acc), m * p["sensitivity"] * ctx.acc

    def explain(self, params=None):
        s = self._p(params)["sensitivity"].detach().cpu().double()
        per_g = [float(v) * G0 / DEG_TO_RAD for v in s]
        return (f"IMU {self.imu}'s gyroscope reading shifts with the specific force it feels "
                f"([{', '.join(f'{v:.3g}' for v in per_g)}] (°/s)/g on x, y, z): a g-sensitive gyro.")


@register_effect
class GyroNonlinearity(Effect):
    """Second-order response of one gyroscope axis (DESIGN §7.2 vocabulary 1.1):
    output_a += k2 · ω_a², k2 in (rad/s)⁻¹, ω_a the true rotation rate about sensor axis a
    (the nominal output ``ctx.gyro``).  Exact (the effect is this term, nothing is linearised).

    Identifiability: ω_a² is even in ω_a, so it is told apart from ``gyro_scale`` (odd) by any
    recording whose rate changes sign, and from ``gyro_bias`` (constant) by any recording whose
    |ω_a| varies; the rate itself is pinned by the other gyros and the accelerometer lever arms,
    so every gyro axis, the reference IMU's included, is a candidate (the score test drops one
    whose efficient information is singular in a given recording)."""

    name = "gyro_nonlinearity"
    description = "second-order gyroscope response"
    local_axis = True
    sensor = "gyro"
    # prior scale: 0.01 (rad/s)⁻¹ is 1 rad/s of error at 10 rad/s, far beyond any MEMS gyro, so
    # the prior is weak wherever the data say anything
    parameters = (Param("k2", (), "(rad s-1)-1", 1e-2, "output += k2 · ω²"),)

    def perturbation(self, params, ctx):
        p = self._p(params)
        k = self._imu_checked(ctx)
        m = _onehot(ctx.K, k, self.axis_index, ctx.gyro)
        return torch.zeros_like(ctx.acc), p["k2"] * m * ctx.gyro * ctx.gyro

    def explain(self, params=None):
        k2 = float(self._p(params)["k2"])
        w = 100 * DEG_TO_RAD  # a reference rate the sentence can quote in familiar units
        return (f"The {self.axis} axis of IMU {self.imu}'s gyroscope responds quadratically to the rotation rate: "
                f"it adds {_fmt(k2, '(rad/s)⁻¹')} × ω², i.e. {_fmt(abs(k2) * w * w / DEG_TO_RAD, '°/s')} "
                f"{'too high' if k2 > 0 else 'too low'} at 100 °/s either way round (a second-order nonlinearity).")


@register_effect
class GyroLinear(Effect):
    """The whole linear error of one gyroscope triad: output += M·ω + b, sensor frame, with M
    (3 × 3, relative: its diagonal is the three scale-factor errors, its off-diagonal entries
    the cross-axis couplings) and b (rad/s) the offsets — ``gyro_scale`` on every axis,
    ``gyro_misalignment`` on every pair and ``gyro_bias`` on every axis of the IMU at once.

    Why one 12-parameter block.  Raw MEMS gyros carry all twelve terms together (the MIMU4444's
    reach 1.85 % per entry, experiments/gyro_linear_check.md), and a detector that adds one 1-df
    term per round leaves the other eleven in the residual, where a random timing effect
    explains them better (experiments/mismatch_multi.md: 1/21 cases named right while they were
    there).  The detector tests these blocks in a stage of their own, before its rounds
    (:mod:`accel_bayes.mismatch.detector`, step 3a); they are not round candidates
    (``screened = False``).

    Reported under the vocabulary name ``gyro_scale`` (DESIGN §7.2: "gyroscope scale-factor /
    misalignment error") with axis null and parameters {"scale": M as 3 rows (output axis) of 3
    (from axis), "bias": b}; a report finding of that form is read back as this class.

    ``imu=None``: the same error on every gyro, expressed in the **array** frame (matrix and
    bias array-frame; IMU k's sensor-frame block is R_k·matrix·R_kᵀ and R_k·bias).  The gyros
    alone cannot see such a common error (the rate absorbs it); the accelerometer lever arms do,
    through the centripetal terms, which is how the detector's stage fits it (after the
    relative blocks, see :mod:`accel_bayes.mismatch.gyro_linear`).
    """

    name = "gyro_linear"
    vocabulary_name = "gyro_scale"
    description = "gyroscope scale-factor, misalignment and offset errors of one triad"
    screened = False
    sensor = "gyro"
    parameters = (Param("matrix", (3, 3), "1", 0.05, "relative linear error: output += matrix · ω"),
                  Param("bias", (3,), "rad s-1", 0.1, "offset added to the three gyro outputs"))

    @classmethod
    def reads_report(cls, axis, parameters, options):
        s = parameters.get("scale")
        return axis is None and isinstance(s, (list, tuple)) and len(s) == 3

    @classmethod
    def from_report(cls, parameters, options):
        if "scale" in parameters:
            parameters["matrix"] = parameters.pop("scale")
        return parameters, options

    def __init__(self, imu=None, axis=None, params=None):
        if imu is None:  # the common (array-frame) error of every gyro
            if axis is not None:
                raise UserError(f"{self.name}: is not local to one axis; axis must be None, got {axis!r}")
            self.imu, self.axis, self.axis_index = None, None, None
            self._init_params(params)
        else:
            super().__init__(imu, axis, params)

    def vocabulary_parameters(self, params=None):
        """The report's parameters under the vocabulary name gyro_scale: {"scale": 3 × 3 rows,
        "bias": 3-vector (rad/s)}."""
        p = self._p(params)
        return {"scale": p["matrix"].detach().cpu().double().tolist(),
                "bias": p["bias"].detach().cpu().double().tolist()}

    def invert(self, y):
        """The rate a gyro with this (one-IMU) block saw: (I + matrix)⁻¹ (y − bias), y (..., 3)
        sensor-frame outputs, rad/s (numpy array or tensor, returned as given; a sample with a NaN
        channel comes back NaN on all three)."""
        if self.imu is None:
            raise UserError(f"{self.name}: invert needs a one-IMU block (the common block is array-frame)")
        p = self.params
        t = torch.as_tensor(y, dtype=torch.float64)
        out = torch.linalg.solve(torch.eye(3, dtype=torch.float64) + p["matrix"], (t - p["bias"]).unsqueeze(-1)).squeeze(-1)
        return out if torch.is_tensor(y) else out.numpy()

    def perturbation(self, params, ctx):
        p = self._p(params)
        if self.imu is None:
            R = ctx.rotation  # (K, 3, 3) array → sensor
            Mk = R @ p["matrix"] @ R.transpose(1, 2)
            bk = R @ p["bias"]
            return torch.zeros_like(ctx.acc), torch.einsum("kij,tkj->tki", Mk, ctx.gyro) + bk
        k = self._imu_checked(ctx)
        m = _onehot(ctx.K, k, None, ctx.gyro)
        return torch.zeros_like(ctx.acc), m * (ctx.gyro @ p["matrix"].transpose(0, 1) + p["bias"])

    def explain(self, params=None):
        p = self._p(params)
        M = p["matrix"].detach().cpu().double()
        b = p["bias"].detach().cpu().double()
        diag = ", ".join(f"{100 * float(M[i, i]):+.3g} %" for i in range(3))
        off = float((M - torch.diag(torch.diagonal(M))).abs().max())
        who = "Every gyroscope (array frame) has" if self.imu is None else f"IMU {self.imu}'s gyroscope has"
        return (f"{who} a linear error: scale-factor errors {diag} on x, y, z, cross-axis "
                f"couplings up to {100 * off:.3g} %, offsets up to {float(b.abs().max()) / DEG_TO_RAD:.3g} °/s "
                f"(a gyro scale / misalignment / bias error, all twelve terms fitted together).")
