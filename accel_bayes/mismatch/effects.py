"""The effects library: one class per physical effect the nominal array model leaves out.

Vocabulary v1 (DESIGN §7.2) — each entry is one class below, registered under its name in
:data:`EFFECTS`; adding an effect is adding one class (STYLE.md, Kalibr's ``IccSensors``):

=====================  ====================================================  ==========  =========
name                   physics left out                                      local IMU   local axis
=====================  ====================================================  ==========  =========
acc_bias               constant accelerometer offset                         yes         yes
acc_scale              accelerometer scale-factor error                      yes         yes
acc_misalignment       cross-axis coupling / non-orthogonal axes             yes         yes
acc_nonlinearity       second-order accelerometer response                   yes         yes
axis_displacement      sensing axes not collocated in the package            yes         yes
triad_orientation      IMU mounted rotated from its nominal orientation      yes         no
gyro_bias              gyroscope offset                                      yes         yes
gyro_scale             gyroscope scale-factor error                          yes         yes
  (gyro_misalignment)  the off-diagonal part of gyro_scale, see below        yes         yes
gyro_g_sensitivity     gyro output that depends on specific force            yes         no
time_offset            one IMU sampled late relative to the others           yes         no
saturation             samples clipped at (an unstated) sensor range         optional    optional
noise_level            noise larger than stated                              optional    no
unexplained            a located mismatch no candidate explains (finding     –           –
                       kind only, no signal model)
=====================  ====================================================  ==========  =========

Every effect class holds

* ``name``, ``description`` (plain-language physics), ``local_imu`` / ``local_axis``;
* its parameters (:class:`Param`: name, shape, unit, prior scale) — names, shapes and units are
  exactly the DESIGN §7.2 report parameters, sensor frame of the IMU, SI units;
* the perturbation it adds to the signal model, a differentiable torch function of its
  parameters given a :class:`SignalContext` (motion, geometry and the nominal sensor-frame
  outputs of :func:`accel_bayes.models.imu_outputs`, the package's one signal model);
* :meth:`Effect.report_parameters` (JSON) and :meth:`Effect.explain` (one sentence).

Three kinds of effect (``Effect.kind``):

``"mean"``
    adds ``(d_acc, d_gyro)`` (T, K, 3), sensor frame, to the nominal outputs.  All mean effects
    are zero at zero parameters and their perturbation of IMU k depends only on IMU k's own
    position and orientation (the fitting code relies on this separability).
``"clip"`` (saturation)
    replaces the outputs by ``clamp(outputs, −L, L)`` on its channels, after every mean
    effect.  Likelihood treatment: the fitted mean is the clamped output and the noise stays
    Gaussian around it.  A sensor that clips *after* its noise (what :func:`apply_effects`
    simulates) puts clipped samples exactly at ±L, so there the residual is ~0 instead of a
    censored (Tobit) term ``log Φ((|f|−L)/σ)``; the evidence is therefore slightly optimistic
    but never changes sign, and the mean-clamp form is what a least-squares solver can fit.
``"noise"`` (noise_level)
    changes no mean; multiplies the stated noise standard deviation of its IMU(s)/sensor by
    ``factor``.  Its likelihood term is the Gaussian normaliser −n·log(factor) plus the
    rescaled quadratic form; the fitting code estimates it in closed form from
    leverage-corrected residuals (see :mod:`accel_bayes.mismatch.refine`).

Linearised terms (documented per class): ``time_offset`` uses δ·d/dt of the nominal output (the
context supplies the rates); everything else is exact (``axis_displacement`` is exact because
the specific force is affine in the position, [C21] eq. 4a).

Identifiability (what the candidate lists below include, see :meth:`Effect.candidates`): every
effect local to one IMU is identifiable from a rotating recording with ≥ 3 non-collinear
accelerometer triads, the reference IMU included — a single IMU's bias, scale, rotation or
displaced axis cannot be absorbed by the per-sample specific force s (common to all IMUs) nor
by that IMU's position (which moves all three of its axes together).  At the reference IMU
(position fixed at the origin) a shift of its whole triad is a shift of the origin, absorbed by
the other IMUs' free positions, so no such effect exists; one axis' ``axis_displacement`` is the
difference of that axis from its triad and stays identifiable; a ``triad_orientation`` of the
reference is its rotation relative to the other IMUs (equivalently, all the others rotated the
opposite way together with the array frame) and is identifiable too.  What is *not*
identifiable, and therefore never a candidate: the same array-frame accelerometer bias on every
IMU (absorbed by s), the same time offset on every IMU (a shift of the time axis), the same
rotation of every IMU (a rotation of the array frame), and gyro effects with a single gyroscope
triad beyond what the accelerometers constrain (the score test in
:mod:`accel_bayes.mismatch.detect` drops candidates whose efficient information is singular).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch

from ..errors import UserError
from ..geometry import quat_exp, quat_to_matrix
from ..models import imu_outputs, specific_force, to_array_frame

__all__ = [
    "AXES",
    "Param",
    "SignalContext",
    "Effect",
    "AccBias",
    "AccScale",
    "AccMisalignment",
    "AccNonlinearity",
    "AxisDisplacement",
    "TriadOrientation",
    "GyroBias",
    "GyroScale",
    "GyroMisalignment",
    "GyroGSensitivity",
    "TimeOffset",
    "Saturation",
    "NoiseLevel",
    "Unexplained",
    "EFFECTS",
    "VOCABULARY",
    "register_effect",
    "get_effect",
    "make_effect",
    "model_outputs",
    "noise_factors",
    "apply_effects",
    "output_rates",
    "CandidateLayout",
]

AXES = ("x", "y", "z")
DEG = math.pi / 180.0
G0 = 9.80665


def _axis_index(axis) -> int:
    if isinstance(axis, str) and axis in AXES:
        return AXES.index(axis)
    if isinstance(axis, (int, np.integer)) and 0 <= int(axis) < 3:
        return int(axis)
    raise UserError(f"axis: expected one of {AXES} (sensor-frame axis), got {axis!r}")


# ------------------------------------------------------------------------------------ context

@dataclass
class SignalContext:
    """Everything an effect may need to compute its perturbation (torch tensors, one dtype).

    time : (T,) s.  omega (T, 3) rad/s, omega_dot (T, 3) rad/s², s (T, 3) m/s²: the motion,
    array frame ([C21] eq. 4; true motion when simulating, the fitted one when fitting).
    positions (K, 3) m, array frame; orientations (K, 4) array → sensor quaternions (§7.0).
    acc, gyro : (T, K, 3) the nominal sensor-frame outputs :func:`accel_bayes.models.imu_outputs`
    gives for that motion and geometry (m/s², rad/s).
    acc_rate, gyro_rate : (T, K, 3) or None — d/dt of the nominal outputs (m/s³, rad/s²), needed
    by ``time_offset`` only (from the continuous trajectory when simulating, from the fitted
    outputs when fitting, :func:`output_rates`).
    """

    time: torch.Tensor
    omega: torch.Tensor
    omega_dot: torch.Tensor
    s: torch.Tensor
    positions: torch.Tensor
    orientations: torch.Tensor
    acc: torch.Tensor
    gyro: torch.Tensor
    acc_rate: torch.Tensor | None = None
    gyro_rate: torch.Tensor | None = None

    @classmethod
    def from_motion(cls, positions, orientations, omega, omega_dot, s, time=None, acc_rate=None,
                    gyro_rate=None) -> "SignalContext":
        """Build the context with the nominal outputs of :func:`accel_bayes.models.imu_outputs`
        (differentiable in every argument)."""
        acc, gyro = imu_outputs(positions, orientations, omega, omega_dot, s)
        if time is None:
            time = torch.arange(omega.shape[0], dtype=omega.dtype, device=omega.device)
        return cls(time, omega, omega_dot, s, positions, orientations, acc, gyro, acc_rate, gyro_rate)

    @property
    def T(self) -> int:
        return int(self.acc.shape[0])

    @property
    def K(self) -> int:
        return int(self.acc.shape[1])

    @property
    def rotation(self) -> torch.Tensor:
        """(K, 3, 3) R(q): array → sensor."""
        return quat_to_matrix(self.orientations)


def output_rates(time, acc, gyro, gap_factor: float = 1.5):
    """d/dt of sampled outputs (T, K, 3) by second-order finite differences (``np.gradient``,
    non-uniform spacing allowed), done separately on each run of contiguous samples (a gap is a
    step larger than ``gap_factor`` × the median step) so no derivative spans a gap.
    Returns (acc_rate, gyro_rate) tensors like the inputs."""
    t = np.asarray(torch.as_tensor(time).detach().cpu(), dtype=float)
    out = []
    for y in (acc, gyro):
        yn = np.asarray(torch.as_tensor(y).detach().cpu(), dtype=float)
        d = np.zeros_like(yn)
        if len(t) >= 2:
            dt = np.diff(t)
            cut = np.flatnonzero(dt > gap_factor * np.median(dt)) + 1
            for lo, hi in zip(np.r_[0, cut], np.r_[cut, len(t)]):
                if hi - lo >= 3:
                    d[lo:hi] = np.gradient(yn[lo:hi], t[lo:hi], axis=0, edge_order=2)
                elif hi - lo == 2:
                    d[lo:hi] = (yn[lo + 1] - yn[lo]) / (t[lo + 1] - t[lo])
        out.append(torch.as_tensor(d, dtype=torch.as_tensor(y).dtype))
    return out[0], out[1]


# ------------------------------------------------------------------------------------ params

@dataclass(frozen=True)
class Param:
    """One parameter of an effect: ``shape`` () or (3,), SI ``unit``, ``prior_scale`` (the
    standard deviation of the weak zero-mean Gaussian prior used when fitting; None = flat),
    ``null`` the value at which the effect is absent."""

    name: str
    shape: tuple
    unit: str
    prior_scale: float | None
    doc: str = ""
    null: float = 0.0

    @property
    def size(self) -> int:
        return int(np.prod(self.shape)) if self.shape else 1


@dataclass
class CandidateLayout:
    """What the candidate enumeration needs to know about a recording."""

    K: int
    has_acc: np.ndarray
    has_gyro: np.ndarray
    reference: int = 0


def _onehot(K: int, k: int, a: int | None, like: torch.Tensor) -> torch.Tensor:
    """(K, 3) mask selecting IMU k (axis a, or all axes)."""
    m = torch.zeros(K, 3, dtype=like.dtype, device=like.device)
    if a is None:
        m[k] = 1.0
    else:
        m[k, a] = 1.0
    return m


def _fmt(x: float, unit: str = "") -> str:
    s = f"{x:.3g}"
    return f"{s} {unit}".strip()


# ------------------------------------------------------------------------------------ base

class Effect:
    """Base class of a physical effect at one location (see the module docstring).

    Parameters
    ----------
    imu : IMU label the effect sits on (None for effects not local to one IMU).
    axis : sensor-frame axis "x"/"y"/"z" (or 0–2) for axis-local effects, else None.
    params : optional dict name → value (defaults to the null values).
    Sub-classes may take further options (``from_axis``, ``sensor``).

    The instance holds the current parameter values in ``self.params`` (torch tensors);
    fitting code writes estimates back there, and ``self.std`` (same keys) may hold their
    Laplace standard deviations.
    """

    name: ClassVar[str] = ""
    vocabulary_name: ClassVar[str | None] = None  # name in reports if not ``name`` (DESIGN §7.2)
    description: ClassVar[str] = ""
    kind: ClassVar[str] = "mean"  # "mean" | "clip" | "noise" | "finding"
    local_imu: ClassVar[bool] = True
    local_axis: ClassVar[bool] = False
    sensor: ClassVar[str] = "acc"  # which outputs it perturbs: "acc", "gyro", "both"
    parameters: ClassVar[tuple] = ()
    needs_rates: ClassVar[bool] = False

    @classmethod
    def reads_report(cls, axis, parameters: dict, options: dict) -> bool:
        """Whether a report finding named ``cls.vocabulary_name`` with these parameters and
        options is this class (for a class reported under a vocabulary name other than its own;
        see :func:`make_effect`)."""
        return False

    @classmethod
    def from_report(cls, parameters: dict, options: dict) -> tuple[dict, dict]:
        """(parameters, options) of a report finding, renamed to this class's own keys (the
        inverse of :meth:`vocabulary_parameters` where a class has one)."""
        return parameters, options

    def __init__(self, imu: int | None = None, axis=None, params: dict | None = None):
        if self.local_imu:
            if imu is None or isinstance(imu, bool) or not isinstance(imu, (int, np.integer)) or int(imu) < 0:
                raise UserError(f"{self.name}: imu: expected a non-negative IMU label, got {imu!r}")
            self.imu = int(imu)
        else:
            if imu is not None:
                raise UserError(f"{self.name}: is not local to one IMU; imu must be None, got {imu!r}")
            self.imu = None
        if self.local_axis:
            self.axis_index = _axis_index(axis)
            self.axis = AXES[self.axis_index]
        else:
            if axis is not None:
                raise UserError(f"{self.name}: is not local to one axis; axis must be None, got {axis!r}")
            self.axis_index, self.axis = None, None
        self.params = self.null_params()
        self.std: dict = {}
        self.stats: dict = {}
        if params:
            self.set_params(params)

    # ---------------------------------------------------------------- parameters
    @classmethod
    def param_specs(cls) -> tuple:
        return cls.parameters

    @property
    def df(self) -> int:
        """Number of free parameters (degrees of freedom of its likelihood-ratio test)."""
        return sum(p.size for p in self.parameters)

    def null_params(self, dtype=torch.float64, device=None) -> dict:
        return {p.name: torch.full(p.shape, float(p.null), dtype=dtype, device=device) for p in self.parameters}

    def set_params(self, values: dict) -> "Effect":
        """Set parameter values (numbers, lists or tensors); unknown names are refused."""
        known = {p.name: p for p in self.parameters}
        for k, v in values.items():
            if k not in known:
                raise UserError(f"{self.name}: unknown parameter {k!r}; expected {sorted(known)}")
            t = torch.as_tensor(v, dtype=torch.float64).reshape(known[k].shape)
            if not bool(torch.isfinite(t).all()) and not (self.kind == "clip"):
                raise UserError(f"{self.name}: parameter {k!r} must be finite, got {v!r}")
            self.params[k] = t.clone()
        return self

    def flatten(self, params: dict | None = None) -> torch.Tensor:
        params = self.params if params is None else params
        return torch.cat([params[p.name].reshape(-1) for p in self.parameters]) if self.parameters else \
            torch.zeros(0, dtype=torch.float64)

    def unflatten(self, vec: torch.Tensor) -> dict:
        out, i = {}, 0
        for p in self.parameters:
            out[p.name] = vec[i:i + p.size].reshape(p.shape)
            i += p.size
        return out

    def prior_scales(self) -> torch.Tensor:
        """(df,) prior standard deviations (inf = flat)."""
        vals = []
        for p in self.parameters:
            vals += [math.inf if p.prior_scale is None else float(p.prior_scale)] * p.size
        return torch.tensor(vals, dtype=torch.float64)

    # ---------------------------------------------------------------- signal model
    def perturbation(self, params: dict | None, ctx: SignalContext):
        """(d_acc, d_gyro), each (T, K, 3) sensor frame, added to the nominal outputs."""
        z = torch.zeros_like(ctx.acc)
        return z, torch.zeros_like(ctx.gyro)

    def transform(self, params: dict | None, acc, gyro, ctx: SignalContext):
        """Output transform after all mean effects (``kind == "clip"`` only)."""
        return acc, gyro

    def noise_factors(self, params: dict | None, K: int):
        """(acc_factor (K,), gyro_factor (K,)) multiplying the stated noise std (``kind == "noise"``)."""
        one = torch.ones(K, dtype=torch.float64)
        return one, one.clone()

    def update_stats(self, acc, gyro) -> None:
        """Refresh derived, non-differentiable statistics (``self.stats``) from the outputs the
        effect acts on (before it acts); a no-op for most effects."""

    def _p(self, params):
        return self.params if params is None else params

    def _imu_checked(self, ctx: SignalContext) -> int:
        if self.imu is not None and not 0 <= self.imu < ctx.K:
            raise UserError(f"{self.name}: imu {self.imu} out of range for K={ctx.K} IMUs")
        return self.imu

    # ---------------------------------------------------------------- words
    def report_parameters(self, params: dict | None = None) -> dict:
        """JSON-ready parameters, DESIGN §7.2 names and units (floats, or lists for vectors)."""
        p = self._p(params)
        out = {}
        for spec in self.parameters:
            v = p[spec.name].detach().cpu().double()
            out[spec.name] = float(v) if spec.shape == () else [float(x) for x in v.reshape(-1)]
        return out

    def explain(self, params: dict | None = None) -> str:  # pragma: no cover - overridden
        return f"{self.description} at {self.where_text()}."

    def where_text(self) -> str:
        if self.imu is None:
            return "all IMUs"
        return f"IMU {self.imu}" + (f", sensor axis {self.axis}" if self.axis else "")

    def label(self) -> str:
        """Short unique label, e.g. ``acc_bias[imu=3,axis=y]``."""
        bits = [f"{k}={v}" for k, v in self.location().items() if v is not None]
        return f"{self.name}[{','.join(bits)}]"

    def location(self) -> dict:
        return {"imu": self.imu, "axis": self.axis}

    def copy(self) -> "Effect":
        new = make_effect(self.name, **self.location())
        for attr in ("where", "excess"):
            if hasattr(self, attr):
                setattr(new, attr, dict(getattr(self, attr)))
        new.params = {k: v.clone() for k, v in self.params.items()}
        new.std = {k: (v.clone() if torch.is_tensor(v) else v) for k, v in self.std.items()}
        new.stats = dict(self.stats)
        return new

    def __repr__(self) -> str:
        return f"{self.label()}({self.report_parameters()})"

    # ---------------------------------------------------------------- candidates
    @classmethod
    def candidates(cls, layout: CandidateLayout) -> list["Effect"]:
        """Every identifiable location of this effect in a recording (module docstring)."""
        imus = cls._imus(layout)
        if cls.local_axis:
            return [cls(imu=k, axis=a) for k in imus for a in AXES]
        return [cls(imu=k) for k in imus]

    @classmethod
    def _imus(cls, layout: CandidateLayout) -> list[int]:
        ha, hg = np.asarray(layout.has_acc, bool), np.asarray(layout.has_gyro, bool)
        if cls.sensor == "acc":
            ok = ha
        elif cls.sensor == "gyro":
            ok = hg
        else:
            ok = ha | hg
        return [int(k) for k in np.flatnonzero(ok)]


# ------------------------------------------------------------------------------------ registry

EFFECTS: dict[str, type] = {}


def register_effect(cls):
    """Class decorator: add an :class:`Effect` sub-class to :data:`EFFECTS` under ``cls.name``."""
    if not cls.name or cls.name in EFFECTS:
        raise ValueError(f"register_effect: name {cls.name!r} missing or already registered")
    EFFECTS[cls.name] = cls
    return cls


def get_effect(name: str) -> type:
    """The effect class registered as ``name``."""
    try:
        return EFFECTS[name]
    except KeyError:
        raise UserError(f"effect: unknown name {name!r}; expected one of {sorted(EFFECTS)}") from None


def make_effect(name: str, imu=None, axis=None, parameters: dict | None = None, **options) -> Effect:
    """Instantiate an effect by name: ``make_effect("acc_bias", imu=3, axis="y", parameters={"bias": 0.1})``.
    Options such as ``from_axis`` (acc_misalignment) or ``sensor`` (saturation, noise_level)
    go as keywords; ``parameters`` may also carry them (as a report's parameters do)."""
    parameters = dict(parameters or {})
    # A report names effects in the DESIGN §7.2 vocabulary; a class reported under another
    # class's name (e.g. gyro_misalignment as an off-diagonal gyro_scale) claims the findings it
    # recognises, and every class renames the report's keys to its own.
    cls = next((c for c in EFFECTS.values() if c.vocabulary_name == name and c.reads_report(axis, parameters, options)),
               None) or get_effect(name)
    parameters, options = cls.from_report(parameters, dict(options))
    for opt in getattr(cls, "options", ()):
        if opt in parameters:
            options.setdefault(opt, parameters.pop(opt))
    for extra in getattr(cls, "derived", ()):
        parameters.pop(extra, None)
    return cls(imu=imu, axis=axis, params=parameters or None, **options)


# ------------------------------------------------------------------------------------ accelerometer

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


class _CrossAxisCoupling(Effect):
    """Shared mechanics of the cross-axis couplings (``acc_misalignment``, ``gyro_misalignment``):
    axis ``axis`` of the sensor ``sensor`` also reads ``coupling`` × its ``from_axis`` component
    (sensor frame).  Sub-classes give name, description, parameters and the sentence."""

    local_axis = True
    options = ("from_axis",)
    same_axis_hint = ""  # appended to the error when from_axis == axis

    def __init__(self, imu=None, axis=None, params=None, from_axis=None):
        super().__init__(imu, axis, params)
        if from_axis is None:
            raise UserError(f"{self.name}: from_axis: expected 'x', 'y' or 'z' (different from axis)")
        self.from_index = _axis_index(from_axis)
        if self.from_index == self.axis_index:
            raise UserError(f"{self.name}: from_axis must differ from axis ({self.axis!r}){self.same_axis_hint}")
        self.from_axis = AXES[self.from_index]

    def location(self):
        return {"imu": self.imu, "axis": self.axis, "from_axis": self.from_axis}

    @classmethod
    def candidates(cls, layout):
        return [cls(imu=k, axis=a, from_axis=b) for k in cls._imus(layout) for a in AXES for b in AXES if b != a]

    def perturbation(self, params, ctx):
        p = self._p(params)
        k = self._imu_checked(ctx)
        out = ctx.acc if self.sensor == "acc" else ctx.gyro
        src = out[..., self.from_index:self.from_index + 1]  # (T, K, 1)
        d = p["coupling"] * _onehot(ctx.K, k, self.axis_index, out) * src
        return (d, torch.zeros_like(ctx.gyro)) if self.sensor == "acc" else (torch.zeros_like(ctx.acc), d)

    def report_parameters(self, params=None):
        out = super().report_parameters(params)
        out["from_axis"] = self.from_axis
        return out


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


@register_effect
class TriadOrientation(Effect):
    """IMU k is mounted rotated from its nominal orientation by ``rotation_vector`` ρ (rad,
    nominal sensor frame): its true orientation is q_true = exp(ρ) ∘ q_nominal, so both its
    triads read R(exp ρ) × (their nominal reading).  In the array frame this is the simulator's
    orientation error δ = R(q_nominal)ᵀ ρ with q_true = q_nominal ⊞ δ (``rotation_vector_array``
    in the report).  Exact (not linearised)."""

    name = "triad_orientation"
    description = "IMU mounted rotated from its nominal orientation"
    local_axis = False
    sensor = "both"
    derived = ("rotation_vector_array", "angle_deg")
    parameters = (Param("rotation_vector", (3,), "rad", 0.1, "rotation of the sensor frame, nominal sensor frame"),)

    def _rot(self, p):
        return quat_to_matrix(quat_exp(p["rotation_vector"]))

    def perturbation(self, params, ctx):
        p = self._p(params)
        k = self._imu_checked(ctx)
        dR = self._rot(p) - torch.eye(3, dtype=ctx.acc.dtype, device=ctx.acc.device)
        m = _onehot(ctx.K, k, None, ctx.acc)
        d_acc = m * (ctx.acc @ dR.T)
        d_gyro = m * (ctx.gyro @ dR.T)
        return d_acc, d_gyro

    def report_parameters(self, params=None, orientations=None):
        out = super().report_parameters(params)
        rho = self._p(params)["rotation_vector"].detach().cpu().double()
        out["angle_deg"] = float(rho.norm()) / DEG
        if orientations is not None:
            q = torch.as_tensor(orientations, dtype=torch.float64)[self.imu]
            out["rotation_vector_array"] = [float(v) for v in to_array_frame(rho.reshape(1, 3), q.reshape(1, 4))[0]]
        return out

    def explain(self, params=None):
        rho = self._p(params)["rotation_vector"].detach().cpu().double()
        ang = float(rho.norm()) / DEG
        ax = (rho / rho.norm()).tolist() if ang > 0 else [0.0, 0.0, 1.0]
        return (f"IMU {self.imu} is mounted rotated by {ang:.3g}° from its nominal orientation (about the sensor-frame "
                f"direction [{', '.join(f'{v:.2f}' for v in ax)}]), so both its accelerometer and gyroscope see the "
                f"motion from a slightly turned frame.")


# ------------------------------------------------------------------------------------ gyroscope

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
        return (f"The {self.axis} axis of IMU {self.imu}'s gyroscope reads {abs(b) / DEG:.3g} °/s "
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
        per_g = [float(v) * G0 / DEG for v in s]
        return (f"IMU {self.imu}'s gyroscope reading shifts with the specific force it feels "
                f"([{', '.join(f'{v:.3g}' for v in per_g)}] (°/s)/g on x, y, z): a g-sensitive gyro.")


# ------------------------------------------------------------------------------------ timing

@register_effect
class TimeOffset(Effect):
    """IMU k is sampled ``offset`` seconds late (positive = late): its sample stamped t holds
    the output at t + offset.  Linearised: both triads get offset × d/dt(nominal output)
    (``ctx.acc_rate``, ``ctx.gyro_rate``); the neglected term is offset²/2 × d²/dt², below
    1e-3 of the effect for offsets ≤ 1 ms and motion under ~50 Hz."""

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


# ------------------------------------------------------------------------------------ clipping

@register_effect
class Saturation(Effect):
    """Outputs clipped at ±``limit`` (m/s² or rad/s) — a range smaller than stated, or unflagged
    clipping.  Channel(s): one sensor ("acc" or "gyro") and either one IMU axis or, with
    imu=None and axis=None, every channel of that sensor.  Kind "clip": applied after all mean
    effects (likelihood treatment in the module docstring).  ``clipped_fraction`` is derived
    (fraction of the channel's samples whose unclipped model output exceeds the limit)."""

    name = "saturation"
    description = "samples clipped at the sensor range"
    kind = "clip"
    local_imu = True
    local_axis = True
    sensor = "both"
    options = ("sensor",)
    derived = ("clipped_fraction",)
    parameters = (Param("limit", (), "m s-2 or rad s-1", None, "clipping level", null=math.inf),)

    def __init__(self, imu=None, axis=None, params=None, sensor: str = "acc"):
        if sensor not in ("acc", "gyro"):
            raise UserError(f"saturation: sensor: expected 'acc' or 'gyro', got {sensor!r}")
        self.which = sensor
        if (imu is None) != (axis is None):
            raise UserError("saturation: give both imu and axis (one channel) or neither (every channel)")
        if imu is None:
            # the all-channels variant: bypass the local checks of the base class
            self.imu, self.axis, self.axis_index = None, None, None
            self.params = self.null_params()
            self.std, self.stats = {}, {}
            if params:
                self.set_params(params)
        else:
            super().__init__(imu, axis, params)

    def location(self):
        return {"imu": self.imu, "axis": self.axis, "sensor": self.which}

    @classmethod
    def candidates(cls, layout):
        out = []
        for sensor, has in (("acc", layout.has_acc), ("gyro", layout.has_gyro)):
            ks = [int(k) for k in np.flatnonzero(np.asarray(has, bool))]
            if not ks:
                continue
            out += [cls(imu=k, axis=a, sensor=sensor) for k in ks for a in AXES]
            out.append(cls(sensor=sensor))
        return out

    def channel_mask(self, K: int, like: torch.Tensor) -> torch.Tensor:
        if self.imu is None:
            return torch.ones(K, 3, dtype=torch.bool, device=like.device)
        return _onehot(K, self.imu, self.axis_index, like).bool()

    def transform(self, params, acc, gyro, ctx):
        L = self._p(params)["limit"]
        y = acc if self.which == "acc" else gyro
        m = self.channel_mask(y.shape[1], y)
        clipped = torch.minimum(torch.maximum(y, -L), L)
        new = torch.where(m, clipped, y)
        return (new, gyro) if self.which == "acc" else (acc, new)

    def update_stats(self, acc, gyro) -> None:
        """``clipped_fraction``: share of the channel(s)' samples beyond the limit."""
        with torch.no_grad():
            y = acc if self.which == "acc" else gyro
            m = self.channel_mask(y.shape[1], y)
            L = float(self.params["limit"])
            self.stats["clipped_fraction"] = float((y.abs() > L)[:, m].double().mean()) if bool(m.any()) else 0.0

    def report_parameters(self, params=None):
        L = float(self._p(params)["limit"])
        return {"limit": L, "clipped_fraction": float(self.stats.get("clipped_fraction", float("nan"))),
                "sensor": self.which}

    def explain(self, params=None):
        L = float(self._p(params)["limit"])
        unit = "m/s²" if self.which == "acc" else "rad/s"
        where = (f"the {self.axis} axis of IMU {self.imu}'s {'accelerometer' if self.which == 'acc' else 'gyroscope'}"
                 if self.imu is not None else f"every {'accelerometer' if self.which == 'acc' else 'gyroscope'} channel")
        frac = self.stats.get("clipped_fraction")
        tail = f" ({100 * frac:.2g} % of its samples)" if frac is not None and math.isfinite(frac) else ""
        return f"Readings of {where} are clipped at ±{_fmt(L, unit)}{tail}, below what the motion reached."


# ------------------------------------------------------------------------------------ noise

@register_effect
class NoiseLevel(Effect):
    """Noise larger than stated: the white-noise std of one sensor ("acc" or "gyro") of IMU k
    (or, with imu=None, of every IMU) is ``factor`` × the stated one.  Kind "noise": no mean
    change; likelihood term −n·log(factor) − ½ Σ r²/(factor² σ²)."""

    name = "noise_level"
    description = "noise larger than stated"
    kind = "noise"
    local_imu = True
    local_axis = False
    sensor = "both"
    options = ("sensor",)
    parameters = (Param("factor", (), "1", None, "× stated standard deviation", null=1.0),)

    def __init__(self, imu=None, axis=None, params=None, sensor: str = "acc"):
        if sensor not in ("acc", "gyro"):
            raise UserError(f"noise_level: sensor: expected 'acc' or 'gyro', got {sensor!r}")
        self.which = sensor
        if imu is None:
            if axis is not None:
                raise UserError("noise_level: is not local to one axis; axis must be None")
            self.imu, self.axis, self.axis_index = None, None, None
            self.params = self.null_params()
            self.std, self.stats = {}, {}
            if params:
                self.set_params(params)
        else:
            super().__init__(imu, axis, params)

    def location(self):
        return {"imu": self.imu, "axis": None, "sensor": self.which}

    @classmethod
    def candidates(cls, layout):
        out = []
        for sensor, has in (("acc", layout.has_acc), ("gyro", layout.has_gyro)):
            ks = [int(k) for k in np.flatnonzero(np.asarray(has, bool))]
            if not ks:
                continue
            out += [cls(imu=k, sensor=sensor) for k in ks]
            out.append(cls(sensor=sensor))
        return out

    def noise_factors(self, params, K):
        f = float(self._p(params)["factor"])
        fa = torch.ones(K, dtype=torch.float64)
        fg = torch.ones(K, dtype=torch.float64)
        tgt = fa if self.which == "acc" else fg
        if self.imu is None:
            tgt[:] = f
        else:
            tgt[self.imu] = f
        return fa, fg

    def report_parameters(self, params=None):
        return {"factor": float(self._p(params)["factor"]), "sensor": self.which}

    def explain(self, params=None):
        f = float(self._p(params)["factor"])
        what = "accelerometer" if self.which == "acc" else "gyroscope"
        where = f"IMU {self.imu}'s {what}" if self.imu is not None else f"every {what}"
        return f"The noise of {where} is {f:.3g}× the level stated in the recording."


# ------------------------------------------------------------------------------------ finding only

@register_effect
class Unexplained(Effect):
    """A located mismatch that no candidate explains.  Not a signal model: it carries the
    location (IMU, axis, sensor, regime/time window) and the size of the excess."""

    name = "unexplained"
    description = "a located mismatch that no candidate explains"
    kind = "finding"
    local_imu = False
    local_axis = False
    sensor = "both"
    parameters = ()

    def __init__(self, imu=None, axis=None, params=None, sensor=None, where=None, excess=None):
        self.imu = None if imu is None else int(imu)
        self.axis = axis
        self.axis_index = None if axis is None else _axis_index(axis)
        self.which = sensor
        self.where = dict(where or {})
        self.excess = dict(excess or {})
        self.params, self.std, self.stats = {}, {}, {}

    def location(self):
        return {"imu": self.imu, "axis": self.axis, "sensor": self.which}

    @classmethod
    def candidates(cls, layout):
        return []

    def report_parameters(self, params=None):
        return dict(self.excess)

    def explain(self, params=None):
        what = {"acc": "accelerometer", "gyro": "gyroscope"}.get(self.which, "sensor")
        where = f"the {self.axis} axis of IMU {self.imu}'s {what}" if self.imu is not None else "the recording"
        reg = self.where.get("regime")
        tw = self.where.get("time_s")
        when = f" in the '{reg}' regime" if reg else ""
        if tw:
            when += f" between {tw[0]:.3g} s and {tw[1]:.3g} s"
        ratio = self.excess.get("chi2_ratio")
        size = f" (residual power {ratio:.3g}× the stated noise)" if ratio else ""
        return (f"Residuals of {where} exceed the stated noise{when}{size}, and none of the candidate effects "
                f"explains them.")


VOCABULARY = tuple(n for n, c in EFFECTS.items() if c.vocabulary_name is None)  # DESIGN §7.2 table order


# ------------------------------------------------------------------------------------ composition

def model_outputs(effects, ctx: SignalContext, params_list=None):
    """Sensor-frame outputs of the nominal model plus ``effects`` (mean effects summed, each
    computed from the nominal context; then clip effects in order).  ``params_list`` (one dict
    per effect, or None to use each effect's own values).  Returns (acc, gyro) (T, K, 3)."""
    acc, gyro = ctx.acc, ctx.gyro
    params_list = [None] * len(effects) if params_list is None else params_list
    for e, p in zip(effects, params_list):
        if e.kind == "mean":
            da, dg = e.perturbation(p, ctx)
            acc, gyro = acc + da, gyro + dg
    for e, p in zip(effects, params_list):
        if e.kind == "clip":
            acc, gyro = e.transform(p, acc, gyro, ctx)
    return acc, gyro


def noise_factors(effects, K: int, params_list=None):
    """Product of the noise factors of the ``noise`` effects: (acc (K,), gyro (K,))."""
    fa = torch.ones(K, dtype=torch.float64)
    fg = torch.ones(K, dtype=torch.float64)
    params_list = [None] * len(effects) if params_list is None else params_list
    for e, p in zip(effects, params_list):
        if e.kind == "noise":
            a, g = e.noise_factors(p, K)
            fa, fg = fa * a, fg * g
    return fa, fg


def apply_effects(effects, ctx: SignalContext, acc_noise: torch.Tensor, gyro_noise: torch.Tensor):
    """Simulated outputs with effects: nominal + mean effects, plus noise scaled by the noise
    effects, then clip effects (a real sensor clips after its noise).

    acc_noise, gyro_noise : (T, K, 3) noise at the *stated* level (std × standard normal).
    Returns (acc, gyro) (T, K, 3).  Used by :func:`accel_bayes.simulate.simulate` (``effects=``).
    """
    effects = list(effects)
    for e in effects:
        if e.kind == "finding":
            raise UserError("unexplained: is a finding, not a simulatable effect")
        if e.imu is not None and not 0 <= e.imu < ctx.K:
            raise UserError(f"{e.label()}: imu out of range for K={ctx.K}")
    acc, gyro = ctx.acc, ctx.gyro
    for e in effects:
        if e.kind == "mean":
            da, dg = e.perturbation(None, ctx)
            acc, gyro = acc + da, gyro + dg
    fa, fg = noise_factors(effects, ctx.K)
    acc = acc + fa.to(acc.dtype)[:, None] * acc_noise
    gyro = gyro + fg.to(gyro.dtype)[:, None] * gyro_noise
    for e in effects:
        if e.kind == "clip":
            e.update_stats(acc, gyro)
            acc, gyro = e.transform(None, acc, gyro, ctx)
    return acc, gyro
