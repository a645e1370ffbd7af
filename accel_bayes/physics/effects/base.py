"""The mechanics of the effects library: the signal context an effect reads, parameters, the
:class:`Effect` base class, the registry, and the composition of effects into outputs
(:func:`model_outputs`, :func:`noise_factors`, :func:`apply_effects`).  The effect classes live
in the sibling modules, one per sensor (see :mod:`accel_bayes.physics.effects`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch

from ...errors import UserError
from ..geometry import quat_to_matrix
from ..models import imu_outputs

AXES = ("x", "y", "z")


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
    acc, gyro : (T, K, 3) the nominal sensor-frame outputs :func:`accel_bayes.physics.models.imu_outputs`
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
        """Build the context with the nominal outputs of :func:`accel_bayes.physics.models.imu_outputs`
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
    # False: a documented effect of our own beyond the DESIGN §7.2 vocabulary (reported under its
    # ``name``; listed in ``EXTENSIONS``, which reports may also use)
    in_vocabulary: ClassVar[bool] = True
    description: ClassVar[str] = ""
    kind: ClassVar[str] = "mean"  # "mean" | "clip" | "noise" | "random" | "finding"
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
        self._init_params(params)

    def _init_params(self, params: dict | None) -> None:
        """Null parameters, no std or statistics yet, then ``params`` where given.  Also the
        whole initialisation of the effects whose every-channel variant has no location
        (``imu``, ``axis`` and ``axis_index`` set to None before)."""
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


def check_effects(effects, K: int, what: str) -> list:
    """The effects as a list, refused in one line if one is the finding ``unexplained`` (it has
    no model) or sits on an IMU outside 0..K-1.  ``what`` names the use ("simulatable effect",
    "model effect") in the message.  Shared by the simulator and the mismatch refits."""
    effects = list(effects)
    for e in effects:
        if e.kind == "finding":
            raise UserError(f"unexplained: is a finding, not a {what}")
        if e.imu is not None and not 0 <= e.imu < K:
            raise UserError(f"{e.label()}: imu out of range for K={K}")
    return effects


def apply_effects(effects, ctx: SignalContext, acc_noise: torch.Tensor, gyro_noise: torch.Tensor):
    """Simulated outputs with effects: nominal + mean effects, plus noise scaled by the noise
    effects, then clip effects (a real sensor clips after its noise).

    acc_noise, gyro_noise : (T, K, 3) noise at the *stated* level (std × standard normal).
    Returns (acc, gyro) (T, K, 3).  Used by :func:`accel_bayes.simulate.simulate` (``effects=``).
    """
    effects = check_effects(effects, ctx.K, "simulatable effect")
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
