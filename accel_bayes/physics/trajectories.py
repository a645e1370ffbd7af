"""The motion of a simulated board: its sampled trace and the continuous trajectories behind it.

A motion is what the signal model of :mod:`accel_bayes.physics.models` needs per sample: the angular
velocity ω, the angular acceleration ω̇ (both array frame, rad/s and rad/s²) and the specific
force s of the array origin (array frame, m/s²).  :class:`MotionTrace` holds them for a grid of
sample times.  Two continuous trajectories (:class:`ContinuousMotion`) give them in closed form
at any time:

* :class:`SmoothTrajectory` — a continuous rigid-body trajectory: the attitude is an analytic
  product of three rotations about fixed orthonormal axes whose angles are sums of band-limited
  sinusoids, the origin moves along a sum of sinusoids, and ω, ω̇, s are its exact derivatives
  (closed form, no numerical integration), gravity included.
* :class:`TableTrajectory` — rotation-table-like motion in the spirit of [S16] §VI-B: segments of
  sinusoidal rotation about one body axis at a time, rotating about a fixed centre, gravity
  consistent with the attitude.

The random generators that draw these (and the i.i.d. [C21] motion) are in
:mod:`accel_bayes.physics.motion_generators`.

Frames and conventions.  The attitude quaternion ``q_wb`` maps array → world,
``v_world = R(q_wb) v_array`` (``R`` is :func:`accel_bayes.physics.geometry.quat_to_matrix`; note that a
*sensor* orientation maps the other way, array → sensor, DESIGN §7.0).  ω and ω̇ are body
(array-frame) quantities, Ṙ = R Ω(ω).  World gravity is g = (0, 0, −9.80665) m/s², so a board at
rest, level, reads s = (0, 0, +9.80665).  The specific force of the origin is
s = Rᵀ(p̈₀ − g), and the world position of a board point r is p₀(t) + R(t) r
(:func:`point_trajectory`); its second time derivative equals
R (ω×(ω×r) + ω̇×r + s) + g = R · models.specific_force(r, ω, ω̇, s) + g ([C21] eq. 4a).

The continuous trajectories can be evaluated at any times (``trajectory.trace(t)``), e.g. at
``t + δ`` to simulate one IMU sampled late.

Every random path takes a ``torch.Generator`` or an integer seed (:func:`as_generator`); random
numbers are drawn on the CPU in float64 and then cast, so a seed gives the same motion on every
device.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from ..constants import G0
from ..errors import UserError
from .geometry import quat_conj, quat_exp, quat_mul, quat_rotate, quat_to_matrix, random_quaternion
from .models import specific_force

__all__ = [
    "G_WORLD",
    "MotionTrace",
    "ContinuousMotion",
    "SmoothTrajectory",
    "TableTrajectory",
    "point_trajectory",
    "trajectory_from_dict",
    "as_generator",
    "sample_times",
]

G_WORLD = (0.0, 0.0, -G0)  # world-frame gravity, m/s² (z up)


def as_generator(generator: torch.Generator | int | None = None, seed: int | None = None) -> torch.Generator:
    """A CPU ``torch.Generator`` from a generator, an integer seed, or ``seed`` (default 0)."""
    if isinstance(generator, torch.Generator):
        return generator
    if generator is not None and seed is not None:
        raise UserError("seed: give either a generator/seed positionally or seed=, not both")
    s = generator if generator is not None else (0 if seed is None else seed)
    try:
        s = int(s)
    except (TypeError, ValueError):
        raise UserError(f"seed: expected an integer or a torch.Generator, got {s!r}") from None
    if s < 0:
        raise UserError(f"seed: expected a non-negative integer, got {s}")
    return torch.Generator().manual_seed(s)


def sample_times(T: int, rate: float, t0: float, dtype, device) -> torch.Tensor:
    """The (T,) sample times t0 + i / rate, s, of T samples at ``rate`` Hz (checked: T a positive
    integer, rate positive and finite)."""
    if int(T) != T or T < 1:
        raise UserError(f"T: expected a positive integer number of samples, got {T!r}")
    if not (rate > 0 and math.isfinite(rate)):
        raise UserError(f"rate: expected a positive sample rate in Hz, got {rate!r}")
    return t0 + torch.arange(int(T), dtype=torch.float64).to(dtype=dtype, device=device) / rate


def _gravity(like: torch.Tensor) -> torch.Tensor:
    return torch.tensor(G_WORLD, dtype=like.dtype, device=like.device)


# ---------------------------------------------------------------------------------- the trace

@dataclass
class MotionTrace:
    """Rigid-body motion sampled at ``time`` (all tensors share dtype and device).

    Attributes
    ----------
    time : (T,) s.
    omega : (T, 3) rad/s — angular velocity, array frame.
    omega_dot : (T, 3) rad/s² — angular acceleration, array frame.
    s : (T, 3) m/s² — specific force of the array origin, array frame, R_wbᵀ(a_world − g).
    attitude : (T, 4) or None — array → world quaternion q_wb (continuous motions only).
    position : (T, 3) m or None — world position of the array origin (continuous motions only).
    kind : str — "iid", "smooth", "table" or free text.
    segment : (T,) numpy str array ("static"/"dynamic") or None — only where the motion rests.
    trajectory : :class:`ContinuousMotion` or None — the analytic trajectory the trace was
        sampled from; ``trajectory.trace(t)`` re-evaluates it at other times.
    """

    time: torch.Tensor
    omega: torch.Tensor
    omega_dot: torch.Tensor
    s: torch.Tensor
    attitude: torch.Tensor | None = None
    position: torch.Tensor | None = None
    kind: str = "custom"
    segment: np.ndarray | None = None
    trajectory: "ContinuousMotion | None" = field(default=None, repr=False)

    def __post_init__(self):
        T = self.time.shape[0]
        if self.time.dim() != 1:
            raise ValueError(f"time: expected shape (T,), got {tuple(self.time.shape)}")
        for nm, shp in (("omega", (T, 3)), ("omega_dot", (T, 3)), ("s", (T, 3))):
            if tuple(getattr(self, nm).shape) != shp:
                raise ValueError(f"{nm}: expected shape {shp}, got {tuple(getattr(self, nm).shape)}")
        if self.attitude is not None and tuple(self.attitude.shape) != (T, 4):
            raise ValueError(f"attitude: expected shape {(T, 4)}, got {tuple(self.attitude.shape)}")
        if self.position is not None and tuple(self.position.shape) != (T, 3):
            raise ValueError(f"position: expected shape {(T, 3)}, got {tuple(self.position.shape)}")
        if self.segment is not None:
            self.segment = np.asarray(self.segment, dtype=str)
            if self.segment.shape != (T,):
                raise ValueError(f"segment: expected shape {(T,)}, got {self.segment.shape}")

    @property
    def T(self) -> int:
        """Number of samples."""
        return int(self.time.shape[0])

    @property
    def rate(self) -> float:
        """Median sample rate, Hz (nan for a single sample)."""
        if self.T < 2:
            return float("nan")
        return float(1.0 / torch.median(torch.diff(self.time)))

    @property
    def phi(self) -> torch.Tensor:
        """[C21] linear motion parameters φ = [ω̇; s], (T, 6)."""
        return torch.cat((self.omega_dot, self.s), -1)

    def to_dict(self) -> dict:
        """JSON-ready content (lists of floats) for a truth sidecar."""
        lst = lambda x: None if x is None else x.detach().cpu().double().tolist()  # noqa: E731
        return {
            "kind": self.kind,
            "omega": lst(self.omega),
            "omega_dot": lst(self.omega_dot),
            "s": lst(self.s),
            "attitude": lst(self.attitude),
            "position": lst(self.position),
            "trajectory": None if self.trajectory is None else self.trajectory.to_dict(),
        }


# ---------------------------------------------------------------------------------- trajectories

class ContinuousMotion:
    """A rigid-body trajectory given in closed form; subclasses implement :meth:`evaluate`.

    ``evaluate(t)`` returns a dict with ``attitude`` (T, 4) q_wb, ``omega``, ``omega_dot``
    (T, 3) array frame, ``position``, ``acceleration`` (T, 3) world frame (origin of the array).
    """

    kind = "continuous"

    def evaluate(self, t: torch.Tensor) -> dict:  # pragma: no cover - abstract
        raise NotImplementedError

    @staticmethod
    def _t(t, dtype=torch.float64, device=None) -> torch.Tensor:
        t = torch.as_tensor(t, dtype=dtype if not torch.is_tensor(t) else None, device=device)
        if not t.is_floating_point():
            t = t.to(torch.float64)
        return t.reshape(-1)

    def specific_force(self, t) -> torch.Tensor:
        """s(t) = R_wbᵀ(a_world − g), array frame, (T, 3) m/s²."""
        e = self.evaluate(self._t(t))
        return _specific_force_of_origin(e)

    def attitude(self, t) -> torch.Tensor:
        """q_wb(t), (T, 4)."""
        return self.evaluate(self._t(t))["attitude"]

    def omega(self, t) -> torch.Tensor:
        """ω(t), array frame, (T, 3) rad/s."""
        return self.evaluate(self._t(t))["omega"]

    def omega_dot(self, t) -> torch.Tensor:
        """ω̇(t), array frame, (T, 3) rad/s²."""
        return self.evaluate(self._t(t))["omega_dot"]

    def position(self, t) -> torch.Tensor:
        """World position of the array origin, (T, 3) m."""
        return self.evaluate(self._t(t))["position"]

    def acceleration(self, t) -> torch.Tensor:
        """World acceleration of the array origin p̈₀ (gravity excluded), (T, 3) m/s²."""
        return self.evaluate(self._t(t))["acceleration"]

    def segment_labels(self, t) -> np.ndarray | None:
        """"static"/"dynamic" labels where the motion has rests, else None."""
        return None

    def trace(self, t) -> MotionTrace:
        """Sample the trajectory at times t (s) into a :class:`MotionTrace`."""
        t = self._t(t)
        e = self.evaluate(t)
        return MotionTrace(
            time=t,
            omega=e["omega"],
            omega_dot=e["omega_dot"],
            s=_specific_force_of_origin(e),
            attitude=e["attitude"],
            position=e["position"],
            kind=self.kind,
            segment=self.segment_labels(t),
            trajectory=self,
        )

    def to_dict(self) -> dict:  # pragma: no cover - abstract
        raise NotImplementedError


def _specific_force_of_origin(e: dict) -> torch.Tensor:
    a = e["acceleration"] - _gravity(e["acceleration"])
    R = quat_to_matrix(e["attitude"])
    return (R.transpose(-1, -2) @ a.unsqueeze(-1)).squeeze(-1)


def point_trajectory(trajectory: ContinuousMotion, r: torch.Tensor, t) -> torch.Tensor:
    """World position of board points r (A, 3) (array frame, m) at times t: p₀(t) + R_wb(t) r.

    Returns (T, A, 3) m.  Its second time derivative is R · models.specific_force(r, ω, ω̇, s) + g,
    which the tests check by finite differences.
    """
    e = trajectory.evaluate(ContinuousMotion._t(t))
    R = quat_to_matrix(e["attitude"])  # (T, 3, 3)
    r = torch.as_tensor(r, dtype=R.dtype, device=R.device)
    return e["position"].unsqueeze(-2) + (R.unsqueeze(-3) @ r.unsqueeze(-1)).squeeze(-1)


def _sum_of_sines(t: torch.Tensor, amp: torch.Tensor, freq: torch.Tensor, phase: torch.Tensor):
    """x(t) = Σ_m amp_m sin(2π f_m t + phase_m) per channel and its first two derivatives.

    t (T,); amp/freq/phase (C, M) → three (T, C) tensors.
    """
    w = 2 * math.pi * freq
    arg = t[:, None, None] * w + phase  # (T, C, M)
    sn, cs = torch.sin(arg), torch.cos(arg)
    x = (amp * sn).sum(-1)
    xd = (amp * w * cs).sum(-1)
    xdd = -(amp * w * w * sn).sum(-1)
    return x, xd, xdd


def _param(x, like: torch.Tensor) -> torch.Tensor:
    return torch.as_tensor(x, dtype=like.dtype, device=like.device)


def _lst(x) -> list:
    return torch.as_tensor(x).detach().cpu().double().tolist()


class SmoothTrajectory(ContinuousMotion):
    """Continuous hand-like motion with an analytic attitude.

    Attitude: R_wb(t) = R(q0) · exp(θ₁(t) a₁) · exp(θ₂(t) a₂) · exp(θ₃(t) a₃) with fixed
    orthonormal axes a_i (rows of ``axes``, array frame) and angles
    θ_i(t) = Σ_m A_im sin(2π f_im t + φ_im).  Writing v_i = (exp(θ_{i+1}a_{i+1})⋯exp(θ₃a₃))ᵀ a_i,

        ω = Σ_i θ̇_i v_i,      ω̇ = Σ_i θ̈_i v_i + Σ_{i<k} θ̇_i θ̇_k (v_i × v_k)

    (from v̇_i = Σ_{k>i} θ̇_k v_i × v_k), exact to rounding at any t.  The origin's world
    position is p₀(t) = −Σ_m c_jm/(2πf_jm)² sin(2π f_jm t + ψ_jm) per world axis j, so that
    p̈₀ = Σ_m c_jm sin(…) exactly.

    Parameters (tensors, float64): q0 (4,); axes (3, 3); ang_amp, ang_freq, ang_phase (3, M)
    in rad, Hz, rad; pos_acc_amp, pos_freq, pos_phase (3, M') in m/s², Hz, rad.
    """

    kind = "smooth"

    def __init__(self, q0, axes, ang_amp, ang_freq, ang_phase, pos_acc_amp, pos_freq, pos_phase):
        f = lambda x: torch.as_tensor(x, dtype=torch.float64).clone()  # noqa: E731
        self.q0, self.axes = f(q0), f(axes)
        self.ang_amp, self.ang_freq, self.ang_phase = f(ang_amp), f(ang_freq), f(ang_phase)
        self.pos_acc_amp, self.pos_freq, self.pos_phase = f(pos_acc_amp), f(pos_freq), f(pos_phase)
        if self.q0.shape != (4,) or self.axes.shape != (3, 3):
            raise ValueError("SmoothTrajectory: q0 must have shape (4,) and axes shape (3, 3)")
        if not (self.ang_amp.shape == self.ang_freq.shape == self.ang_phase.shape) or self.ang_amp.shape[0] != 3:
            raise ValueError("SmoothTrajectory: ang_amp/ang_freq/ang_phase must share a shape (3, M)")
        if not (self.pos_acc_amp.shape == self.pos_freq.shape == self.pos_phase.shape) or self.pos_freq.shape[0] != 3:
            raise ValueError("SmoothTrajectory: pos_acc_amp/pos_freq/pos_phase must share a shape (3, M)")
        if bool((self.pos_freq <= 0).any()):
            raise ValueError("SmoothTrajectory: pos_freq must be > 0 (a sinusoid of zero frequency has no position)")

    def evaluate(self, t) -> dict:
        t = self._t(t)
        P = lambda x: _param(x, t)  # noqa: E731
        th, thd, thdd = _sum_of_sines(t, P(self.ang_amp), P(self.ang_freq), P(self.ang_phase))  # (T, 3)
        axes = P(self.axes)
        Q = quat_exp(th.unsqueeze(-1) * axes)  # (T, 3, 4): exp(θ_i a_i)
        # v_3 = a_3; v_2 = R₃ᵀ a_2; v_1 = (R₂R₃)ᵀ a_1; built with the running right product.
        v3 = axes[2].expand(t.shape[0], 3)
        P23 = Q[:, 2]
        v2 = quat_rotate(quat_conj(P23), axes[1].expand_as(v3))
        P123 = quat_mul(Q[:, 1], P23)
        v1 = quat_rotate(quat_conj(P123), axes[0].expand_as(v3))
        v = torch.stack((v1, v2, v3), 1)  # (T, 3, 3): v[:, i]
        omega = (thd.unsqueeze(-1) * v).sum(1)
        cross = torch.linalg.cross
        omega_dot = (thdd.unsqueeze(-1) * v).sum(1)
        omega_dot = omega_dot + (thd[:, 0:1] * thd[:, 1:2]) * cross(v1, v2, dim=-1)
        omega_dot = omega_dot + (thd[:, 0:1] * thd[:, 2:3]) * cross(v1, v3, dim=-1)
        omega_dot = omega_dot + (thd[:, 1:2] * thd[:, 2:3]) * cross(v2, v3, dim=-1)
        q = quat_mul(P(self.q0).expand(t.shape[0], 4), quat_mul(Q[:, 0], P123))
        q = q / q.norm(dim=-1, keepdim=True)  # no sign canonicalisation: keep q(t) continuous
        w = 2 * math.pi * P(self.pos_freq)
        amp = P(self.pos_acc_amp)
        p, _, acc = _sum_of_sines(t, -amp / (w * w), P(self.pos_freq), P(self.pos_phase))
        return {"attitude": q, "omega": omega, "omega_dot": omega_dot, "position": p, "acceleration": acc}

    def to_dict(self) -> dict:
        return {"class": "SmoothTrajectory", "q0": _lst(self.q0), "axes": _lst(self.axes),
                "ang_amp": _lst(self.ang_amp), "ang_freq": _lst(self.ang_freq), "ang_phase": _lst(self.ang_phase),
                "pos_acc_amp": _lst(self.pos_acc_amp), "pos_freq": _lst(self.pos_freq), "pos_phase": _lst(self.pos_phase)}

    @classmethod
    def random(
        cls,
        generator: torch.Generator | int | None = None,
        *,
        omega_scale: float = 1.0,
        accel_scale: float = 1.0,
        freq_range: tuple[float, float] = (0.2, 3.0),
        n_components: int = 4,
        initial_attitude="random",
    ) -> "SmoothTrajectory":
        """A random trajectory before RMS calibration (see :func:`smooth_motion`).

        Each angle θ_i gets ``n_components`` sinusoids with frequencies uniform in
        ``freq_range`` (Hz), uniform phases and rate amplitudes N(0, omega_scale²/n_components)
        (so θ̇_i has RMS ≈ omega_scale, rad/s); the position components likewise with
        acceleration amplitudes N(0, accel_scale²·2/(3·n_components)) (RMS |p̈₀| ≈ accel_scale).
        The axes are the columns of a Haar-random rotation.
        """
        gen = as_generator(generator)
        f_lo, f_hi = float(freq_range[0]), float(freq_range[1])
        if not (0 < f_lo <= f_hi and math.isfinite(f_hi)):
            raise UserError(f"freq_range: expected 0 < low <= high (Hz), got {freq_range!r}")
        M = int(n_components)
        if M < 1:
            raise UserError(f"n_components: expected a positive integer, got {n_components!r}")
        F = torch.float64
        U = lambda *s: torch.rand(*s, generator=gen, dtype=F)  # noqa: E731
        N = lambda *s: torch.randn(*s, generator=gen, dtype=F)  # noqa: E731
        q_axes = random_quaternion(generator=gen)
        axes = quat_to_matrix(q_axes).T.contiguous()  # rows: an orthonormal right-handed triple
        if isinstance(initial_attitude, str):
            if initial_attitude == "random":
                q0 = random_quaternion(generator=gen)
            elif initial_attitude == "level":
                q0 = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=F)
            else:
                raise UserError(f"initial_attitude: expected 'random', 'level' or a quaternion, got {initial_attitude!r}")
        else:
            q0 = torch.as_tensor(initial_attitude, dtype=F)
            if q0.shape != (4,) or float(q0.norm()) == 0:
                raise UserError("initial_attitude: expected a non-zero quaternion (w, x, y, z)")
            q0 = q0 / q0.norm()
        ang_freq = f_lo + (f_hi - f_lo) * U(3, M)
        ang_phase = 2 * math.pi * U(3, M)
        ang_rate_amp = omega_scale * math.sqrt(2.0 / M) * N(3, M)
        ang_amp = ang_rate_amp / (2 * math.pi * ang_freq)
        pos_freq = f_lo + (f_hi - f_lo) * U(3, M)
        pos_phase = 2 * math.pi * U(3, M)
        pos_acc_amp = accel_scale * math.sqrt(2.0 / (3 * M)) * N(3, M)
        return cls(q0, axes, ang_amp, ang_freq, ang_phase, pos_acc_amp, pos_freq, pos_phase)

    def scaled(self, angle_factor: float = 1.0, accel_factor: float = 1.0) -> "SmoothTrajectory":
        """The same trajectory with angle amplitudes × angle_factor and origin acceleration ×
        accel_factor (frequencies, phases and axes unchanged)."""
        return SmoothTrajectory(self.q0, self.axes, self.ang_amp * angle_factor, self.ang_freq, self.ang_phase,
                                self.pos_acc_amp * accel_factor, self.pos_freq, self.pos_phase)


class TableTrajectory(ContinuousMotion):
    """Rotation-table-like motion ([S16] §VI-B: "segments of sinusoidal angular velocity
    separately on each axis").

    Time is split into ``[rest][segment 1][rest][segment 2]…[segment n][rest…]``.  During
    segment j (duration D, local time τ ∈ [0, D]) the board turns about its own axis e_j
    (array frame x, y or z) by

        θ(τ) = Θ sin(2π f τ) sin⁴(π τ / D),       Θ = omega_amplitude / (2π f)

    and returns to the starting attitude at the end of each segment.  The sin⁴ taper makes θ
    and its first three derivatives vanish at both ends, so ω, ω̇ and the jerk are continuous
    (a C⁴ motion: finite differences of positions converge at their full order).  The rotation is about a fixed centre c
    (array frame, m; the table's axis intersection): the origin moves as
    p₀(t) = R(q0) c − R(t) c, so p̈₀ = −R (ω×(ω×c) + ω̇×c); c = 0 gives a still origin.
    Attitude R_wb(t) = R(q0) exp(θ(τ) e_j); ω = θ̇ e_j; ω̇ = θ̈ e_j.
    """

    kind = "table"

    def __init__(self, q0, axes_seq, omega_amplitude, frequency, segment_duration, rest_duration=0.0,
                 center=(0.0, 0.0, 0.0), t0=0.0):
        self.q0 = torch.as_tensor(q0, dtype=torch.float64).clone()
        self.q0 = self.q0 / self.q0.norm()
        self.axes_seq = [int(a) for a in axes_seq]
        if not self.axes_seq or any(a not in (0, 1, 2) for a in self.axes_seq):
            raise UserError(f"axes: expected a non-empty sequence of axis indices 0/1/2 (or 'xyz'), got {axes_seq!r}")
        self.omega_amplitude = float(omega_amplitude)
        self.segment_duration = float(segment_duration)
        self.rest_duration = float(rest_duration)
        if not self.segment_duration > 0:
            raise UserError(f"segment_duration: expected > 0 s, got {segment_duration!r} (too few samples for the rests?)")
        if self.rest_duration < 0:
            raise UserError(f"rest_duration: expected >= 0 s, got {rest_duration!r}")
        if not float(frequency) > 0:
            raise UserError(f"frequency: expected > 0 Hz, got {frequency!r}")
        self.frequency = float(frequency)
        self.center = torch.as_tensor(center, dtype=torch.float64).clone().reshape(3)
        self.t0 = float(t0)

    def _local(self, t: torch.Tensor):
        """Segment index (−1 at rest) and local time τ for each t."""
        period = self.segment_duration + self.rest_duration
        u = t - self.t0 - self.rest_duration
        j = torch.floor(u / period)
        tau = u - j * period
        n = len(self.axes_seq)
        moving = (u >= 0) & (j < n) & (tau <= self.segment_duration)
        return torch.where(moving, j, torch.full_like(j, -1.0)).long(), torch.where(moving, tau, torch.zeros_like(tau))

    def evaluate(self, t) -> dict:
        t = self._t(t)
        j, tau = self._local(t)
        D, f = self.segment_duration, self.frequency
        Th = self.omega_amplitude / (2 * math.pi * f)
        w, u = 2 * math.pi * f, math.pi / D
        sn, cs = torch.sin(w * tau), torch.cos(w * tau)
        S, C = torch.sin(u * tau), torch.cos(u * tau)
        win = S ** 4  # taper and its τ-derivatives
        d_win = 4 * u * S ** 3 * C
        dd_win = 4 * u * u * S * S * (3 * C * C - S * S)
        th = Th * sn * win
        thd = Th * (w * cs * win + sn * d_win)
        thdd = Th * (-w * w * sn * win + 2 * w * cs * d_win + sn * dd_win)
        moving = j >= 0
        zero = torch.zeros_like(th)
        th, thd, thdd = (torch.where(moving, x, zero) for x in (th, thd, thdd))
        axes_seq = torch.tensor(self.axes_seq, device=t.device)
        e = torch.zeros(t.shape[0], 3, dtype=t.dtype, device=t.device)
        e[moving] = torch.eye(3, dtype=t.dtype, device=t.device)[axes_seq[j[moving]]]
        omega = thd.unsqueeze(-1) * e
        omega_dot = thdd.unsqueeze(-1) * e
        q0 = _param(self.q0, t).expand(t.shape[0], 4)
        q = quat_mul(q0, quat_exp(th.unsqueeze(-1) * e))
        R = quat_to_matrix(q)
        c = _param(self.center, t)
        zero3 = torch.zeros_like(omega)
        # acceleration of the origin relative to the fixed centre, rotated to the world frame
        a_rel = specific_force(c.expand(t.shape[0], 1, 3), omega, omega_dot, zero3).squeeze(-2)
        acc = -(R @ a_rel.unsqueeze(-1)).squeeze(-1)
        pos = quat_rotate(q0, c.expand_as(omega)) - (R @ c.expand_as(omega).unsqueeze(-1)).squeeze(-1)
        return {"attitude": q, "omega": omega, "omega_dot": omega_dot, "position": pos, "acceleration": acc}

    def segment_labels(self, t) -> np.ndarray | None:
        if self.rest_duration <= 0:
            return None
        j, _ = self._local(self._t(t))
        return np.where(j.cpu().numpy() >= 0, "dynamic", "static")

    def to_dict(self) -> dict:
        return {"class": "TableTrajectory", "q0": _lst(self.q0), "axes_seq": list(self.axes_seq),
                "omega_amplitude": self.omega_amplitude, "frequency": self.frequency,
                "segment_duration": self.segment_duration, "rest_duration": self.rest_duration,
                "center": _lst(self.center), "t0": self.t0}


def trajectory_from_dict(d: dict) -> ContinuousMotion:
    """Rebuild a trajectory from its :meth:`to_dict` content (e.g. a truth sidecar's
    ``motion.trajectory``), so it can be re-evaluated at shifted times."""
    d = dict(d)
    cls = d.pop("class", None)
    if cls == "SmoothTrajectory":
        return SmoothTrajectory(**d)
    if cls == "TableTrajectory":
        return TableTrajectory(**d)
    raise UserError(f"trajectory.class: expected 'SmoothTrajectory' or 'TableTrajectory', got {cls!r}")
