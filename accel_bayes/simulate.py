"""Simulated inertial sensor array recordings with known ground truth.

:func:`simulate` draws a true geometry around a :class:`~accel_bayes.physics.arrays.SensorArray`
design, moves the board with a motion from :mod:`accel_bayes.physics.motion_generators`, computes each IMU's
sensor-frame outputs with :func:`accel_bayes.physics.models.imu_outputs` (the package's one signal
model, [C21] eq. 4), adds white Gaussian noise and clips at the sensor ranges.  It returns a
:class:`~accel_bayes.data.recording.Recording` that holds only what a real file would (nominal design,
stated noise, outputs) and, separately, the ``truth`` dict that a simulator writes to the
sidecar ``REC.truth.json`` (DESIGN §7.1: ground truth never goes in a recording file).

Random streams: one seed (or generator) is split into three independent child seeds, for the
motion, the geometry errors and the sensor noise, in that order.
"""
from __future__ import annotations

from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np
import torch

from .physics.arrays import SensorArray
from .data.outputs import to_jsonable
from .errors import UserError, nonnegative
from .physics.geometry import boxminus, boxplus
from .physics.models import imu_outputs
from .physics.motion_generators import make_motion
from .physics.trajectories import MotionTrace, as_generator
from .physics.effects.timing import sample_times
from .data.recording import Recording

__all__ = ["SimResult", "simulate", "TRUTH_SCHEMA", "memory_estimate", "motion_rms"]

TRUTH_SCHEMA = "accel_bayes.truth/1"

# Peak resident memory of simulate + write_recording per sample and IMU, measured with the
# mimu32 preset, smooth motion: 10.9 kB per sample at T = 2·10⁵ (≈ 340 B per IMU), rounded up.
BYTES_PER_IMU_SAMPLE = 400


def memory_estimate(T: int, K: int) -> int:
    """Bytes of memory a simulation of ``T`` samples of a ``K``-IMU array needs (peak, approximate)."""
    return int(T) * int(K) * BYTES_PER_IMU_SAMPLE


@dataclass
class SimResult:
    """What :func:`simulate` returns.

    recording : the simulated :class:`Recording` (nothing in it is ground truth).
    truth : JSON-ready dict for the truth sidecar (true geometry, motion, noise, seed, settings).
    motion : the :class:`MotionTrace` used (its ``trajectory`` re-evaluates continuous motions).
    true_positions (K, 3) m, true_orientations (K, 4): the geometry the outputs were made with.
    acc_clean, gyro_clean : (T, K, 3) noise-free, unclipped sensor-frame outputs (all IMUs).
    """

    recording: Recording
    truth: dict
    motion: MotionTrace
    true_positions: torch.Tensor
    true_orientations: torch.Tensor
    acc_clean: torch.Tensor
    gyro_clean: torch.Tensor
    sampling_instants: dict | None = None  # IMU → (T,) s: the instants a sampling_jitter IMU sampled at


def motion_rms(trace: MotionTrace) -> tuple[float, float]:
    """RMS over samples of |ω_t| (rad/s) and of |s_t| (m/s²) of a motion trace."""
    w_rms = float(torch.sqrt((trace.omega ** 2).sum(-1).mean()))
    s_rms = float(torch.sqrt((trace.s ** 2).sum(-1).mean()))
    return w_rms, s_rms


def _per_imu(x, K: int, name: str, default: torch.Tensor) -> torch.Tensor:
    if x is None:
        return default.clone()
    t = torch.as_tensor(x, dtype=torch.float64)
    if t.dim() == 0:
        t = t.expand(K).clone()
    if t.shape != (K,):
        raise UserError(f"{name}: expected a scalar or {K} values (one per IMU), got shape {tuple(t.shape)}")
    if bool((t < 0).any()) or not bool(torch.isfinite(t).all()):
        raise UserError(f"{name}: expected finite standard deviations >= 0, got {t.tolist()}")
    return t


def _clip(y: torch.Tensor, limit: float | None, present: torch.Tensor, clip: bool):
    """Clip at ±limit; flags (T, K) where any axis reached the range (present IMUs only)."""
    if not clip or limit is None:
        return y, None
    flags = (y.abs() >= limit).any(-1) & present
    return y.clamp(-limit, limit), flags


def simulate(
    array: SensorArray,
    motion: MotionTrace | str = "smooth",
    T: int = 500,
    rate: float = 100.0,
    *,
    seed: int | None = 0,
    generator: torch.Generator | None = None,
    position_error_std: float = 1e-4,
    orientation_error_std: float = 0.0,
    true_positions=None,
    true_orientations=None,
    acc_noise_std=None,
    gyro_noise_std=None,
    clip: bool = True,
    motion_kwargs: dict | None = None,
    time_offsets=None,
    description: str | None = None,
    validate: bool = True,
    effects=None,
) -> SimResult:
    """Simulate a recording of ``array`` under a motion, with a perturbed true geometry.

    Parameters
    ----------
    array : the design (nominal positions/orientations, triads present, noise, ranges).
    motion : a :class:`MotionTrace`, or a generator name "iid" / "smooth" / "table" called with
        ``T`` samples at ``rate`` Hz and ``motion_kwargs`` (ignored for a given trace).
    seed / generator : the random source (a generator wins over the seed); same seed → same
        recording, bit for bit.
    position_error_std : m — true positions = nominal + N(0, σ²) per axis; the reference IMU
        stays exactly at its nominal position (it defines the origin, [C21] r₁ ≡ 0).
    orientation_error_std : rad — true orientation = nominal ⊞ δ, δ ~ N(0, σ² I₃) (rotation
        vector, :func:`~accel_bayes.physics.geometry.boxplus`); the reference IMU keeps its nominal.
    true_positions (K, 3) / true_orientations (K, 4) : explicit truth, overriding the above.
    acc_noise_std (m/s²) / gyro_noise_std (rad/s) : scalar or (K,); default the array's.  The
        same values are the recording's stated noise.
    clip : clip outputs at ±acc_range / ±gyro_range and flag (T, K) samples where any axis hit it.
    time_offsets : (K,) s or None — IMU k's sample stamped t is taken at t + δ_k (positive =
        sampled late, DESIGN §7.2 ``time_offset``); needs a continuous motion ("smooth",
        "table"), whose trajectory is re-evaluated at the shifted times.  Recorded in the truth.
    effects : list of :class:`accel_bayes.physics.effects.Effect` instances (with their
        parameter values) or dicts ``{"effect": name, "imu": k, "axis": a, "parameters": {...}}``
        (DESIGN §7.2 names) — physics the nominal model leaves out, simulated with the *same*
        definitions the mismatch detector fits (:func:`accel_bayes.physics.effects.apply_effects`):
        mean effects are added to the noise-free outputs (computed from the true motion and
        geometry; ``time_offset`` uses the trajectory's exact output rates, so it needs a
        continuous motion), ``noise_level`` scales the true noise (the recording still states
        the nominal noise), ``saturation`` clips after the noise (and is *not* flagged in
        ``acc_clipped``/``gyro_clipped``: an unstated range).  Listed in ``truth["effects"]``;
        ``acc_clean``/``gyro_clean`` then include the mean effects.  ``sampling_jitter`` (kind
        "random") is simulated exactly: the IMU's outputs are the continuous trajectory evaluated
        at the jittered instants t (+ its time offset) + δ, δ ~ U(−w/2, w/2) per sample, drawn
        from the noise stream *after* the noise (so adding it never shifts the noise draws);
        the instants are returned in ``SimResult.sampling_instants``.
    validate : check the result with :func:`accel_bayes.data.validation.validate_recording` when
        that module is available.

    Returns a :class:`SimResult` (recording, truth sidecar dict, motion, truth tensors,
    noise-free outputs).  IMUs without an accelerometer (gyroscope) get NaN outputs there.
    """
    if not isinstance(array, SensorArray):
        raise UserError(f"array: expected a SensorArray, got {type(array).__name__}")
    arr = array.to(dtype=torch.float64, device=torch.device("cpu"))
    K = arr.K
    pos_std = nonnegative(position_error_std, "position_error_std", "m")
    ori_std = nonnegative(orientation_error_std, "orientation_error_std", "rad")
    acc_std = _per_imu(acc_noise_std, K, "acc_noise_std", arr.acc_noise_std)
    gyro_std = _per_imu(gyro_noise_std, K, "gyro_noise_std", arr.gyro_noise_std)

    base = generator if generator is not None else as_generator(seed)
    child = torch.randint(0, 2**62, (3,), generator=base).tolist()
    g_motion, g_geom, g_noise = (torch.Generator().manual_seed(int(c)) for c in child)

    # ---- motion
    if isinstance(motion, MotionTrace):
        tr = motion
        kind = tr.kind
    elif isinstance(motion, str):
        kind = motion
        tr = make_motion(motion, T, rate, generator=g_motion, **(motion_kwargs or {}))
    else:
        raise UserError(f"motion: expected 'iid', 'smooth', 'table' or a MotionTrace, got {type(motion).__name__}")
    cast = lambda x: x.detach().to(dtype=torch.float64, device="cpu")  # noqa: E731
    time, omega, omega_dot, s = cast(tr.time), cast(tr.omega), cast(tr.omega_dot), cast(tr.s)
    Tn = time.shape[0]
    if Tn > 1 and not bool((torch.diff(time) > 0).all()):
        raise UserError("motion.time: expected strictly increasing sample times")

    # ---- true geometry (draws happen even when overridden, so the noise stream never shifts)
    ref = arr.reference_imu
    dpos = pos_std * torch.randn(K, 3, generator=g_geom, dtype=torch.float64)
    drot = ori_std * torch.randn(K, 3, generator=g_geom, dtype=torch.float64)
    dpos[ref] = 0.0
    drot[ref] = 0.0
    if true_positions is not None:
        p_true = torch.as_tensor(true_positions, dtype=torch.float64).clone()
        if p_true.shape != (K, 3):
            raise UserError(f"true_positions: expected shape ({K}, 3), got {tuple(p_true.shape)}")
    else:
        p_true = arr.positions + dpos
    if true_orientations is not None:
        q_true = torch.as_tensor(true_orientations, dtype=torch.float64).clone()
        if q_true.shape != (K, 4) or bool((q_true.norm(dim=-1) == 0).any()):
            raise UserError(f"true_orientations: expected ({K}, 4) non-zero quaternions, got shape {tuple(q_true.shape)}")
        q_true = q_true / q_true.norm(dim=-1, keepdim=True)
    else:
        q_true = boxplus(arr.orientations, drot) if ori_std > 0 else arr.orientations.clone()

    # ---- outputs: the one signal model, then noise and clipping
    acc0, gyro0 = imu_outputs(p_true, q_true, omega, omega_dot, s)  # (T, K, 3) sensor frame
    offsets = None
    if time_offsets is not None:
        offsets = torch.as_tensor(time_offsets, dtype=torch.float64).reshape(-1)
        if offsets.shape != (K,) or not bool(torch.isfinite(offsets).all()):
            raise UserError(f"time_offsets: expected {K} finite values in s (one per IMU), got {list(offsets.shape)}")
        if bool((offsets != 0).any()) and tr.trajectory is None:
            raise UserError(f"time_offsets: need a continuous motion ('smooth' or 'table'); {kind!r} has no trajectory")
        for k in torch.nonzero(offsets).flatten().tolist():
            late = tr.trajectory.trace(sample_times(time, offsets[k]))  # exact: the trajectory at t + δ_k
            a_k, g_k = imu_outputs(p_true[k : k + 1], q_true[k : k + 1], cast(late.omega), cast(late.omega_dot), cast(late.s))
            acc0[:, k], gyro0[:, k] = a_k[:, 0], g_k[:, 0]
    e_acc = torch.randn(Tn, K, 3, generator=g_noise, dtype=torch.float64)
    e_gyro = torch.randn(Tn, K, 3, generator=g_noise, dtype=torch.float64)
    eff_list = _effects_list(effects)
    instants = _jitter(eff_list, tr, kind, time, offsets, p_true, q_true, acc0, gyro0, g_noise)
    if eff_list:
        acc, gyro, acc0, gyro0 = _apply_effects(eff_list, tr, kind, time, omega, omega_dot, s, p_true, q_true,
                                                acc0, gyro0, acc_std[:, None] * e_acc, gyro_std[:, None] * e_gyro)
    else:
        acc = acc0 + acc_std[:, None] * e_acc
        gyro = gyro0 + gyro_std[:, None] * e_gyro
    has_acc, has_gyro = arr.has_acc, arr.has_gyro
    acc, acc_flags = _clip(acc, arr.acc_range, has_acc, clip)
    gyro, gyro_flags = _clip(gyro, arr.gyro_range, has_gyro, clip)
    nan = torch.tensor(float("nan"), dtype=torch.float64)
    acc = torch.where(has_acc[:, None], acc, nan)
    gyro = torch.where(has_gyro[:, None], gyro, nan)

    settings = {
        "T": Tn, "rate": tr.rate if isinstance(motion, MotionTrace) and Tn > 1 else float(rate), "motion": kind,
        "position_error_std": pos_std, "orientation_error_std": ori_std,
        "true_positions_given": true_positions is not None,
        "true_orientations_given": true_orientations is not None,
        "clip": bool(clip), "motion_kwargs": to_jsonable(motion_kwargs or {}, unknown="repr"),
        "time_offsets": None if offsets is None else offsets.tolist(),
        "motion_given": isinstance(motion, MotionTrace),
    }
    seed_used = None if generator is not None else int(seed if seed is not None else 0)
    from . import __version__

    src = (f"accel_bayes {__version__} simulate: array={arr.name} motion={kind} T={Tn} "
           f"rate={settings['rate']:g} Hz seed={seed_used} position_error_std={pos_std:g} m "
           f"orientation_error_std={ori_std:g} rad clip={bool(clip)}; truth in the .truth.json sidecar")
    rec = Recording(
        time=time.numpy().copy(),
        acc=acc.numpy().copy(),
        gyro=gyro.numpy().copy() if bool(has_gyro.any()) else None,
        nominal_position=arr.positions.numpy().copy(),
        nominal_orientation=arr.orientations.numpy().copy(),
        acc_noise_std=acc_std.numpy().copy(),
        gyro_noise_std=gyro_std.numpy().copy(),
        acc_clipped=None if acc_flags is None else acc_flags.numpy().copy(),
        gyro_clipped=None if (gyro_flags is None or not bool(has_gyro.any())) else gyro_flags.numpy().copy(),
        segment=None if tr.segment is None else np.asarray(tr.segment, dtype=str).copy(),
        reference_imu=int(ref),
        acc_range=None if arr.acc_range is None else float(arr.acc_range),
        gyro_range=None if arr.gyro_range is None else float(arr.gyro_range),
        description=description if description is not None else f"simulated {arr.name} array, {kind} motion",
        source=src,
        attrs={},
    )

    frac = lambda f, present: None if f is None or not bool(present.any()) else float(f[:, present].double().mean())  # noqa: E731
    truth = {
        "schema": TRUTH_SCHEMA,
        "generator": f"accel_bayes {__version__} simulate",
        "array": arr.name,
        "reference_imu": int(ref),
        "true_position": p_true.tolist(),
        "true_position_relative": (p_true - p_true[ref]).tolist(),
        "true_orientation": q_true.tolist(),
        "nominal_position": arr.positions.tolist(),
        "nominal_orientation": arr.orientations.tolist(),
        "position_error": (p_true - arr.positions).tolist(),
        "orientation_error": boxminus(q_true, arr.orientations).tolist(),
        "acc_noise_std": acc_std.tolist(),
        "gyro_noise_std": gyro_std.tolist(),
        "clipped_fraction": {"acc": frac(acc_flags, has_acc), "gyro": frac(gyro_flags, has_gyro)},
        "motion": tr.to_dict() if tr.kind == kind else {**tr.to_dict(), "kind": kind},
        "seed": seed_used,
        "settings": settings,
    }
    if eff_list:
        truth["effects"] = [{"effect": e.name, **e.location(), "parameters": to_jsonable(e.report_parameters(), unknown="repr")}
                            for e in eff_list]
    if validate:
        _validate(rec)
    return SimResult(recording=rec, truth=truth, motion=tr, true_positions=p_true, true_orientations=q_true,
                     acc_clean=acc0, gyro_clean=gyro0, sampling_instants=instants)


def _validate(rec: Recording) -> None:
    try:
        from .data.validation import validate_recording
    except ImportError:  # the validation module is optional at this stage of the package
        return
    validate_recording(rec)


def _effects_list(effects) -> list:
    """Effects given to :func:`simulate` as instances or report-style dicts → instances."""
    if effects is None:
        return []
    from .physics.effects import Effect, make_effect

    out = []
    for e in effects:
        if isinstance(e, Effect):
            out.append(e)
        elif isinstance(e, dict):
            d = dict(e)
            name = d.pop("effect", None)
            if name is None:
                raise UserError(f"effects: each dict needs an 'effect' name, got {e!r}")
            out.append(make_effect(name, **d))
        else:
            raise UserError(f"effects: expected Effect instances or dicts, got {type(e).__name__}")
    return out


def _jitter(eff_list, tr, kind, time, offsets, p_true, q_true, acc0, gyro0, g_noise):
    """Exact sampling jitter (see ``effects`` in :func:`simulate`): overwrite the jittered IMUs'
    columns of ``acc0``/``gyro0`` in place with the trajectory at their sampling instants.
    Returns {IMU: (T,) instants in s} or None."""
    from .physics.effects.jitter import jittered_times

    jit = [e for e in eff_list if e.kind == "random"]
    if not jit:
        return None
    if tr.trajectory is None:
        raise UserError(f"effects: sampling_jitter needs a continuous motion ('smooth' or 'table'); {kind!r} has none")
    out = {}
    cast = lambda x: x.detach().to(dtype=torch.float64, device="cpu")  # noqa: E731
    for e in jit:
        k = e._imu_checked(SimpleNamespace(K=acc0.shape[1]))
        base = time if offsets is None else sample_times(time, offsets[k])
        t_k = jittered_times(base, float(e.params["width"]), g_noise)
        m = tr.trajectory.trace(t_k)
        a_k, g_k = imu_outputs(p_true[k:k + 1], q_true[k:k + 1], cast(m.omega), cast(m.omega_dot), cast(m.s))
        acc0[:, k], gyro0[:, k] = a_k[:, 0], g_k[:, 0]
        out[k] = t_k
    return out


def _apply_effects(eff_list, tr, kind, time, omega, omega_dot, s, p_true, q_true, acc0, gyro0, acc_noise, gyro_noise):
    """Outputs with effects (see ``effects`` in :func:`simulate`); returns (acc, gyro, acc_clean, gyro_clean)."""
    from .physics.effects import SignalContext, apply_effects, model_outputs

    acc_rate = gyro_rate = None
    if any(e.needs_rates for e in eff_list):
        if tr.trajectory is None:
            raise UserError(f"effects: time_offset needs a continuous motion ('smooth' or 'table'); {kind!r} has none")
        h = 1e-5  # s; central difference of the analytic trajectory, error O(h²)
        outs = []
        for sign in (1.0, -1.0):
            m = tr.trajectory.trace(time + sign * h)
            c = lambda x: x.detach().to(dtype=torch.float64, device="cpu")  # noqa: E731
            outs.append(imu_outputs(p_true, q_true, c(m.omega), c(m.omega_dot), c(m.s)))
        acc_rate = (outs[0][0] - outs[1][0]) / (2 * h)
        gyro_rate = (outs[0][1] - outs[1][1]) / (2 * h)
    ctx = SignalContext(time, omega, omega_dot, s, p_true, q_true, acc0, gyro0, acc_rate, gyro_rate)
    acc, gyro = apply_effects(eff_list, ctx, acc_noise, gyro_noise)
    clean_acc, clean_gyro = model_outputs([e for e in eff_list if e.kind == "mean"], ctx)
    return acc, gyro, clean_acc, clean_gyro
