"""How an IMU sits on the board: a triad mounted rotated from its nominal orientation (both
triads of the IMU turn together, DESIGN §7.0).
"""
from __future__ import annotations

import torch

from ..geometry import quat_exp, quat_to_matrix
from ..models import to_array_frame
from ...constants import DEG_TO_RAD
from .base import Effect, Param, register_effect, _onehot


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
        out["angle_deg"] = float(rho.norm()) / DEG_TO_RAD
        if orientations is not None:
            q = torch.as_tensor(orientations, dtype=torch.float64)[self.imu]
            out["rotation_vector_array"] = [float(v) for v in to_array_frame(rho.reshape(1, 3), q.reshape(1, 4))[0]]
        return out

    def explain(self, params=None):
        rho = self._p(params)["rotation_vector"].detach().cpu().double()
        ang = float(rho.norm()) / DEG_TO_RAD
        ax = (rho / rho.norm()).tolist() if ang > 0 else [0.0, 0.0, 1.0]
        return (f"IMU {self.imu} is mounted rotated by {ang:.3g}° from its nominal orientation (about the sensor-frame "
                f"direction [{', '.join(f'{v:.2f}' for v in ax)}]), so both its accelerometer and gyroscope see the "
                f"motion from a slightly turned frame.")
