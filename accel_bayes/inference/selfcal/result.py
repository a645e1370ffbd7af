"""What a self-calibration returns: :class:`SelfCalResult`, the error :class:`SelfCalDiverged`
raised when a diverged estimate's poses are read, and the Laplace covariance of the poses from
the final LM run (:func:`pose_covariance`)."""
from __future__ import annotations

from dataclasses import dataclass, field

import torch

from ..lm.linear import NotPositiveDefinite

__all__ = ["SelfCalDiverged", "SelfCalResult", "pose_covariance"]


class SelfCalDiverged(RuntimeError):
    """The self-calibration ended in a diverged minimum ([S16] Table III); no poses are given.

    ``result`` holds the :class:`SelfCalResult` (status "diverged", the reason, cost log and the
    raw estimate for inspection through ``result.raw_positions``).
    """

    def __init__(self, message: str, result: "SelfCalResult | None" = None):
        super().__init__(message)
        self.result = result


@dataclass
class SelfCalResult:
    """Outcome of :func:`self_calibrate`.

    Poses are in the array frame defined by the fixed triad sitting at its nominal pose
    ([S16] eq. 16): ``positions`` (A, 3) m — the fixed triad's row is its nominal position —
    and ``orientations`` (A, 4) array → sensor quaternions (DESIGN §7.0).  Accessing either on a
    diverged result raises :class:`SelfCalDiverged`: a diverged estimate is never a calibration.

    Attributes
    ----------
    status : "ok" or "diverged"; reason : why it diverged ("" when ok).
    fixed : index of the fixed triad.
    states : (T, 9) estimated motion [a_lin (m/s²), ω (rad/s), ω̇ (rad/s²)], array frame; with
        ``process_noise="estimate-snap"`` (T, 15): ω̈ (rad/s³) and ȧ_lin (m/s³) appended.
    cost : final F of [S16] eq. 15 (Σ eᵀΣ⁻¹e, i.e. twice the solver's ½-scaled cost).
    cost_log : one dict per LM iteration of the returned run: iteration, F, F_triad, F_process
        (paper scaling), F_per_constraint (F / number of constraints, [S16] Fig. 5), lambda,
        accepted.
    full_cost_log : the cost logs of all runs made, in order (entries carry "run" and "stage":
        "motion" for the motion-only warm start, "joint" for the pose + motion LM).
    n_constraints : {"triad": T·A, "process": T−1}.
    position_cov : (A, 3, 3) m² Laplace covariance (zeros for the fixed triad).
    rotation_cov : (A, 3, 3) rad² covariance of the rotation vector δ with q = q̂ ∘ exp(δ)
        (full rotation angles, not the half-angles of [S16] eq. 18).
    angle_std : (A,) rad — √trace(rotation_cov), the RMS rotation-angle error.
    covariance : (6(A−1), 6(A−1)) joint Laplace covariance of the free coordinates, ordered
        [positions of the free triads (x, y, z each), rotation vectors of the free triads].
    runs : one dict per LM run made (first run, then the re-run from the estimate): label, F,
        rms_residual, n_iter, lm_reason, converged, diverged (reason or None), kept (re-run),
        and that run's raw estimate (positions, orientations, states) for diagnostics.
    converged, lm_reason, n_iter : of the returned run; seconds : total wall time.
    """

    status: str
    reason: str
    fixed: int
    raw_positions: torch.Tensor
    raw_orientations: torch.Tensor
    states: torch.Tensor
    cost: float
    cost_log: list
    n_constraints: dict
    position_cov: torch.Tensor | None = None
    rotation_cov: torch.Tensor | None = None
    covariance: torch.Tensor | None = None
    runs: list = field(default_factory=list)
    full_cost_log: list = field(default_factory=list)
    converged: bool = False
    lm_reason: str = ""
    n_iter: int = 0
    seconds: float = 0.0
    process_noise: dict = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    def _require_ok(self):
        if not self.ok:
            raise SelfCalDiverged(f"self-calibration diverged: {self.reason}", self)

    @property
    def positions(self) -> torch.Tensor:
        """(A, 3) m, array frame (raises :class:`SelfCalDiverged` if diverged)."""
        self._require_ok()
        return self.raw_positions

    @property
    def orientations(self) -> torch.Tensor:
        """(A, 4) array → sensor quaternions (raises :class:`SelfCalDiverged` if diverged)."""
        self._require_ok()
        return self.raw_orientations

    @property
    def relative_positions(self) -> torch.Tensor:
        """Positions relative to the fixed triad, (A, 3) m."""
        p = self.positions
        return p - p[self.fixed]

    @property
    def position_std(self) -> torch.Tensor | None:
        """(A, 3) m — per-axis Laplace standard deviations."""
        return None if self.position_cov is None else torch.diagonal(self.position_cov, dim1=-2, dim2=-1).clamp_min(0).sqrt()

    @property
    def angle_std(self) -> torch.Tensor | None:
        """(A,) rad — √trace of the rotation-vector covariance (RMS rotation-angle error)."""
        if self.rotation_cov is None:
            return None
        return torch.diagonal(self.rotation_cov, dim1=-2, dim2=-1).sum(-1).clamp_min(0).sqrt()


def pose_covariance(res, A: int, fixed: int):
    """Laplace covariance of the free poses (Gauss–Newton information, motion marginalised).

    The solver's cost is ½Σ‖e‖², so its Gauss–Newton matrix JᵀJ is the information matrix of the
    whitened model; its Schur complement over the motion is the information of the poses.
    ``res``: the final :class:`~accel_bayes.inference.lm.LMResult` of the [S16] graph (A triads,
    ``fixed`` held).  Returns (position_cov (A, 3, 3) m², rotation_cov (A, 3, 3) rad², the joint
    (6(A−1), 6(A−1)) covariance) as :class:`SelfCalResult` holds them, or None when the
    Gauss–Newton matrix is not positive definite.
    """
    try:
        C = res.covariance()
    except NotPositiveDefinite:
        return None
    labels = res.free_labels()
    free = [j for j in range(A) if j != fixed]
    nf = len(free)
    pos_cov = C.new_zeros(A, 3, 3)
    rot_cov = C.new_zeros(A, 3, 3)
    # free_labels order: "position" rows (free triads × xyz), then "rotation" rows.
    assert len(labels) == 6 * nf and labels[0][0] == "position" and labels[3 * nf][0] == "rotation"
    for k, j in enumerate(free):
        pos_cov[j] = C[3 * k:3 * k + 3, 3 * k:3 * k + 3]
        o = 3 * nf + 3 * k
        rot_cov[j] = C[o:o + 3, o:o + 3]
    return pos_cov, rot_cov, C
