"""Random motion generators for simulated inertial sensor array recordings.

Three draw a :class:`~accel_bayes.physics.trajectories.MotionTrace` (ω, ω̇, s per sample):

* :func:`iid_motion` — the [C21] §IV-A "hand twist" model: ω, ω̇ and s drawn i.i.d. zero-mean
  normal per axis and sample (std 1000 °/s, 35000 °/s², 20 m/s²).  No attitude: gravity is not
  modelled separately and consecutive samples are unrelated (the [C21] model needs neither).
* :func:`smooth_motion` — a random :class:`~accel_bayes.physics.trajectories.SmoothTrajectory`
  (hand-like), scaled to a target RMS angular rate and acceleration, gravity included.
* :func:`table_motion` — rotation-table-like motion in the spirit of [S16] §VI-B
  (:class:`~accel_bayes.physics.trajectories.TableTrajectory`).

:func:`make_motion` picks one by name (:data:`MOTIONS`).  A fourth, :func:`simulate_process_motion`,
returns no trajectory but motion *states* [a_lin, ω, ω̇] drawn from the [S16] process model itself
(eq. 7, integrated exactly; a_lin is not gravity-consistent): data on which the
self-calibration's process residuals vanish at the truth.

Units SI (rad/s, rad/s², m/s², s, Hz).  Every generator takes a ``torch.Generator`` or an integer
seed; random numbers are drawn on the CPU in float64 and then cast, so a seed gives the same
motion on every device.
"""
from __future__ import annotations

import math

import torch

from ..constants import DEG_TO_RAD, G0
from ..errors import UserError
from .geometry import random_quaternion
from .trajectories import MotionTrace, SmoothTrajectory, TableTrajectory, as_generator, sample_times

__all__ = ["iid_motion", "smooth_motion", "table_motion", "simulate_process_motion", "MOTIONS", "make_motion"]


def iid_motion(
    T: int,
    *,
    omega_std: float = 1000 * DEG_TO_RAD,
    omega_dot_std: float = 35000 * DEG_TO_RAD,
    s_std: float = 20.0,
    rate: float = 100.0,
    t0: float = 0.0,
    generator: torch.Generator | int | None = None,
    seed: int | None = None,
    dtype=torch.float64,
    device=None,
) -> MotionTrace:
    """[C21] §IV-A motion: ω, ω̇, s i.i.d. N(0, std²) per axis and sample.

    Defaults are the paper's 1000 °/s, 35000 °/s² and 20 m/s² (standard deviations, in SI:
    rad/s, rad/s², m/s²).  ``rate`` (Hz) only sets the time stamps.  No attitude or position.
    """
    for nm, v in (("omega_std", omega_std), ("omega_dot_std", omega_dot_std), ("s_std", s_std)):
        if not (v >= 0 and math.isfinite(v)):
            raise UserError(f"{nm}: expected a finite standard deviation >= 0, got {v!r}")
    time = sample_times(T, rate, t0, dtype, device)
    gen = as_generator(generator, seed)
    z = torch.randn(int(T), 3, 3, generator=gen, dtype=torch.float64).to(dtype=dtype, device=device)
    return MotionTrace(time=time, omega=omega_std * z[:, 0], omega_dot=omega_dot_std * z[:, 1],
                       s=s_std * z[:, 2], kind="iid")


def _rms_norm(x: torch.Tensor) -> float:
    return float(torch.sqrt((x * x).sum(-1).mean()))


def smooth_motion(
    T: int,
    rate: float = 100.0,
    *,
    omega_rms: float = 400 * DEG_TO_RAD,
    accel_rms: float = 5.0,
    freq_range: tuple[float, float] = (0.2, 3.0),
    n_components: int = 4,
    initial_attitude="random",
    t0: float = 0.0,
    generator: torch.Generator | int | None = None,
    seed: int | None = None,
    dtype=torch.float64,
    device=None,
) -> MotionTrace:
    """Continuous hand-like motion (:class:`SmoothTrajectory`) sampled at ``rate`` Hz.

    omega_rms : rad/s — RMS of |ω| over the T samples, met to 1e-9 relative by scaling the angle
        amplitudes (fixed-point iteration; |ω| is nearly linear in that scale).
    accel_rms : m/s² — RMS of |p̈₀| (the origin's world acceleration, gravity excluded) over the
        samples, met exactly (linear).  0 keeps the origin still.
    freq_range : Hz — band of the sinusoids; its top must stay below rate/2.
    initial_attitude : "random" (Haar), "level" (identity) or a quaternion (4,).

    Returns a trace whose ``trajectory`` can be evaluated at other times.
    """
    if not (omega_rms >= 0 and math.isfinite(omega_rms)):
        raise UserError(f"omega_rms: expected a finite RMS angular rate >= 0 (rad/s), got {omega_rms!r}")
    if not (accel_rms >= 0 and math.isfinite(accel_rms)):
        raise UserError(f"accel_rms: expected a finite RMS acceleration >= 0 (m/s²), got {accel_rms!r}")
    time = sample_times(T, rate, t0, torch.float64, None)
    if float(freq_range[1]) >= rate / 2:
        raise UserError(f"freq_range: top frequency {freq_range[1]} Hz must be below half the sample rate ({rate / 2} Hz)")
    gen = as_generator(generator, seed)
    traj = SmoothTrajectory.random(gen, freq_range=freq_range, n_components=n_components,
                                   initial_attitude=initial_attitude)
    a_now = _rms_norm(traj.evaluate(time)["acceleration"])
    accel_factor = 0.0 if accel_rms == 0 or a_now == 0 else accel_rms / a_now
    angle_factor = 0.0
    if omega_rms > 0:
        angle_factor = 1.0
        for _ in range(100):
            w_now = _rms_norm(traj.scaled(angle_factor).evaluate(time)["omega"])
            if w_now == 0:
                break
            ratio = omega_rms / w_now
            angle_factor *= ratio
            if abs(ratio - 1) < 1e-12:
                break
        else:  # the map is close to linear, so only an absurd target (1e300 rad/s) ends here
            raise UserError(f"omega_rms: could not reach {omega_rms!r} rad/s RMS with this motion (reached "
                            f"{w_now:.3g}); expected a physically possible rate, e.g. below 100 rad/s")
    traj = traj.scaled(angle_factor, accel_factor)
    tr = traj.trace(time.to(dtype=dtype, device=device))
    return tr


def table_motion(
    T: int,
    rate: float = 125.0,
    *,
    axes="xyz",
    omega_amplitude: float = 200 * DEG_TO_RAD,
    frequency: float = 1.0,
    rest_duration: float = 0.0,
    center=(0.0, 0.0, 0.0),
    initial_attitude="level",
    t0: float = 0.0,
    generator: torch.Generator | int | None = None,
    seed: int | None = None,
    dtype=torch.float64,
    device=None,
) -> MotionTrace:
    """Rotation-table-like motion ([S16] §VI-B), see :class:`TableTrajectory`.

    axes : "xyz" (default) or a sequence of body axes (letters or 0/1/2), one segment each,
        turned in that order.  The segments share the record equally after the rests.
    omega_amplitude : rad/s — amplitude of the sinusoidal angular rate before the sin⁴ taper.
    frequency : Hz — its frequency.
    rest_duration : s — rest before each segment and at the end; > 0 labels samples
        "static"/"dynamic" in ``segment``.
    center : (3,) m — the fixed centre of rotation in the array frame (0: origin at the table
        centre, so the origin does not accelerate).
    initial_attitude : "level" (identity), "random" (Haar, uses the generator) or a quaternion.

    The defaults follow [S16]'s 125 Hz; their 5.4 s record is T = 675.
    """
    time = sample_times(T, rate, t0, torch.float64, None)
    if isinstance(axes, str):
        try:
            axes_seq = ["xyz".index(a) for a in axes.lower()]
        except ValueError:
            raise UserError(f"axes: expected letters from 'xyz', got {axes!r}") from None
    else:
        axes_seq = [int(a) for a in axes]
    n = len(axes_seq)
    duration = int(T) / rate
    seg = (duration - (n + 1) * rest_duration) / max(n, 1)
    if isinstance(initial_attitude, str):
        if initial_attitude == "level":
            q0 = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
        elif initial_attitude == "random":
            q0 = random_quaternion(generator=as_generator(generator, seed))
        else:
            raise UserError(f"initial_attitude: expected 'level', 'random' or a quaternion, got {initial_attitude!r}")
    else:
        q0 = torch.as_tensor(initial_attitude, dtype=torch.float64)
    if frequency >= rate / 2:
        raise UserError(f"frequency: {frequency} Hz must be below half the sample rate ({rate / 2} Hz)")
    traj = TableTrajectory(q0, axes_seq, omega_amplitude, frequency, seg, rest_duration, center, t0=t0)
    return traj.trace(time.to(dtype=dtype, device=device))


def simulate_process_motion(
    T: int,
    dt: float,
    *,
    segment_length: int = 25,
    omega_dot_std: float = 8.0,
    omega0_std: float = 1.0,
    acc_std: float = 3.0,
    acc_segment_length: int | None = None,
    omega_max: float = 6.0,
    gravity: float = G0,
    generator: torch.Generator | None = None,
    seed: int | None = None,
    dtype=torch.float64,
    device=None,
) -> torch.Tensor:
    """Motion states drawn from the [S16] process model itself (eq. 7), integrated exactly.

    ω̇ is piecewise constant (a new N(0, omega_dot_std²) value every ``segment_length`` samples,
    rad/s²); ω_{i+1} = ω_i + ω̇_i Δt holds to machine precision, so the integration residual of
    eq. 14 is zero at the truth; a_lin is piecewise constant (gravity-sized, new values every
    ``acc_segment_length`` samples, default 4 × segment_length).  Where |ω| would exceed
    ``omega_max`` rad/s, the next ω̇ segment is drawn to point back towards zero (keeps the
    accelerations within a triad's range).  Returns states (T, 9).
    """
    g = generator
    if g is None:
        g = torch.Generator(device="cpu")
        g.manual_seed(0 if seed is None else int(seed))
    acc_seg = acc_segment_length or 4 * segment_length
    n_seg = (T + segment_length - 1) // segment_length
    n_aseg = (T + acc_seg - 1) // acc_seg
    wd_draws = torch.randn(n_seg, 3, generator=g, dtype=torch.float64) * omega_dot_std
    w = torch.randn(3, generator=g, dtype=torch.float64) * omega0_std
    a_dir = torch.randn(n_aseg, 3, generator=g, dtype=torch.float64)
    a = gravity * a_dir / a_dir.norm(dim=-1, keepdim=True) + acc_std * torch.randn(n_aseg, 3, generator=g, dtype=torch.float64)
    # The piecewise structure is a short loop over segments (not samples); the sample loop is a
    # cumulative sum, exact in the sense of eq. 7 up to float64 rounding.
    wd = torch.empty(T, 3, dtype=torch.float64)
    w_seg = w.clone()
    for k in range(n_seg):
        lo, hi = k * segment_length, min(T, (k + 1) * segment_length)
        d = wd_draws[k]
        end = w_seg + d * dt * (hi - lo)
        if end.norm() > omega_max:  # steer back: point ω̇ against ω, same magnitude
            d = -d.norm() * w_seg / w_seg.norm().clamp_min(1e-12)
            end = w_seg + d * dt * (hi - lo)
        wd[lo:hi] = d
        w_seg = end
    omega = torch.cat((w.unsqueeze(0), w + torch.cumsum(wd[:-1] * dt, 0)), 0)
    a_lin = a.repeat_interleave(acc_seg, 0)[:T]
    return torch.cat((a_lin, omega, wd), -1).to(dtype=dtype, device=device)


MOTIONS = {"iid": iid_motion, "smooth": smooth_motion, "table": table_motion}


def make_motion(kind: str, T: int, rate: float, generator: torch.Generator | int | None = None,
                dtype=torch.float64, device=None, **kwargs) -> MotionTrace:
    """Dispatch to a generator by name ("iid", "smooth", "table") with T samples at ``rate`` Hz."""
    if kind not in MOTIONS:
        raise UserError(f"motion: expected one of {sorted(MOTIONS)}, got {kind!r}")
    fn = MOTIONS[kind]
    try:
        if kind == "iid":
            return fn(T, rate=rate, generator=generator, dtype=dtype, device=device, **kwargs)
        return fn(T, rate, generator=generator, dtype=dtype, device=device, **kwargs)
    except TypeError as exc:  # unknown keyword in motion_kwargs
        raise UserError(f"motion_kwargs: {exc}") from None
