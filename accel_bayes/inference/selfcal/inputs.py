"""The arrays a self-calibration starts from, checked and converted once: :func:`solve_inputs`
returns them as one :class:`SolveInputs` record (every check raises naming its argument)."""
from __future__ import annotations

from dataclasses import dataclass

import torch

from ...errors import UserError
from ...physics import models
from ...physics.arrays import check_triad_geometry
from ...physics.geometry import quat_normalize
from .factors import _as_inv_std

__all__ = ["SolveInputs", "solve_inputs"]


@dataclass(frozen=True)
class SolveInputs:
    """The checked inputs of :func:`~accel_bayes.inference.selfcal.self_calibrate`.

    acc (T, A, 3) m/s² triad outputs (sensor frames); dt (T−1,) s steps between fitted samples;
    steps None or (T−1,) grid steps per fitted step (left-out samples); p0 (A, 3) m and q0 (A, 4)
    the start (nominal) poses; fixed the index of the triad held there; inv_std (A, 3) 1/(m/s²);
    S (A, 3, 3) and offset (A, 3) m/s² the known sensor parameters (None: ideal)."""

    acc: torch.Tensor
    dt: torch.Tensor
    steps: object
    p0: torch.Tensor
    q0: torch.Tensor
    fixed: int
    inv_std: torch.Tensor
    S: torch.Tensor | None
    offset: torch.Tensor | None

    @property
    def T(self) -> int:
        """Number of fitted samples."""
        return self.acc.shape[0]

    @property
    def A(self) -> int:
        """Number of triads."""
        return self.acc.shape[1]


def solve_inputs(acc, time_or_dt, steps, nominal_positions, nominal_orientations, fixed, acc_noise_std,
                 sensor_params, dtype, device) -> SolveInputs:
    """Check and convert the array arguments of
    :func:`~accel_bayes.inference.selfcal.self_calibrate` (same meanings and units)."""
    acc = torch.as_tensor(acc, dtype=dtype, device=device)
    if acc.dim() != 3 or acc.shape[-1] != 3:
        raise ValueError(f"acc: expected shape (T, A, 3), got {tuple(acc.shape)}")
    T, A = acc.shape[0], acc.shape[1]
    if T < 3:
        # the process model ([S16] eq. 7–8) links consecutive samples: fewer than 3 leave it nothing to constrain
        raise UserError(f"acc: self-calibration needs at least 3 samples (time), the recording has {T}")
    if not bool(torch.isfinite(acc).all()):
        raise ValueError("acc: expected finite triad outputs (NaN/inf found); drop missing triads or samples first")
    if not 0 <= int(fixed) < A:
        raise ValueError(f"fixed: expected a triad index in 0..{A - 1}, got {fixed}")
    fixed = int(fixed)
    p0 = torch.as_tensor(nominal_positions, dtype=dtype, device=device)
    if p0.shape != (A, 3):
        raise ValueError(f"nominal_positions: expected shape ({A}, 3), got {tuple(p0.shape)}")
    if nominal_orientations is None:
        q0 = torch.zeros(A, 4, dtype=dtype, device=device)
        q0[:, 0] = 1.0
    else:
        q0 = torch.as_tensor(nominal_orientations, dtype=dtype, device=device)
        if q0.shape != (A, 4):
            raise ValueError(f"nominal_orientations: expected shape ({A}, 4), got {tuple(q0.shape)}")
        q0 = quat_normalize(q0)
    check_triad_geometry(p0)
    dt = _time_steps(time_or_dt, T, dtype, acc.device)
    inv_std = _as_inv_std(acc_noise_std, A, dtype, acc.device)
    S, offset = _sensor_params(sensor_params, A, dtype, acc.device)
    return SolveInputs(acc, dt, steps, p0, q0, fixed, inv_std, S, offset)


def _time_steps(time_or_dt, T: int, dtype, device) -> torch.Tensor:
    t = torch.as_tensor(time_or_dt, dtype=dtype, device=device)
    if t.dim() == 0:
        dt = t.expand(T - 1).clone()
    elif t.shape == (T,):
        dt = torch.diff(t)
    else:
        raise ValueError(f"time_or_dt: expected a scalar step (s) or sample times of shape ({T},), got {tuple(t.shape)}")
    if not bool(torch.isfinite(dt).all()) or bool((dt <= 0).any()):
        raise ValueError("time_or_dt: sample times must be finite and strictly increasing (steps > 0)")
    return dt


def _sensor_params(sensor_params, A: int, dtype, device):
    if sensor_params is None:
        return None, None
    if isinstance(sensor_params, dict):
        S = sensor_params.get("S", sensor_params.get("sensitivity"))
        o = sensor_params.get("offset")
    else:
        S, o = sensor_params
    if S is not None:
        S = torch.as_tensor(S, dtype=dtype, device=device)
        if S.shape == (A, 6):
            S = models.sensitivity_matrix(S)
        if S.shape != (A, 3, 3):
            raise ValueError(f"sensor_params: S expected (A, 3, 3) or (A, 6) with A={A}, got {tuple(S.shape)}")
    if o is not None:
        o = torch.as_tensor(o, dtype=dtype, device=device)
        if o.shape != (A, 3):
            raise ValueError(f"sensor_params: offset expected ({A}, 3), got {tuple(o.shape)}")
    return S, o
