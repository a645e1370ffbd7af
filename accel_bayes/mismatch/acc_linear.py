"""The detector's accelerometer linear stage (:func:`accel_bayes.mismatch.detect`, step 3a', opt-in
``DetectOptions(acc_linear=True)``): every accelerometer triad's whole linear error,
y_k = (I + M_k) f_k + b_k (sensor frame; f_k the specific force the triad feels, M_k 3 × 3 relative,
b_k m/s²; :class:`~accel_bayes.physics.effects.AccLinear`), after the gyro linear stage and before
the clock stage and the rounds.

Why.  Raw MEMS accelerometers carry all twelve terms on every triad.  Where the recording rests in
several orientations the preparation calibrates them from the rests ([S16], ``prep``'s intrinsics);
where it rests in one (a board moved by hand from a table, the concealed clock recordings of
``experiments/clockgen``) it cannot, and the rounds name at most ``max_findings`` one-axis terms.
The rest stays in the residual as excess that the §7.2 budget does not credit: on the 30 concealed
clock recordings the accelerometer budget's systematic shortfall (median b/a of "all" 0.81) is these
errors; inverting the generator's blocks brings it to 1.04, and the same regression estimated from
the recording to 1.01 (``experiments/budget_gap_probe.md``, ``acc_known`` / ``acc_blocks``).

How: the gyro stage's machinery (:func:`accel_bayes.mismatch.linear_blocks.linear_stage`, the method
in :mod:`accel_bayes.mismatch.gyro_linear`'s docstring) with the accelerometers' outputs regressed on
the fitted specific force [f̂_k, 1], f̂_k = R_k(s + ω̇ × c_k + ω × (ω × c_k)) ([C21] eq. 4), the
same group and per-block tests (χ²_{12n}; χ²_12 and two significant terms; all at 1 − α/m) and the
same alternation with the motion.  What differs:

* **The spread test** (are the errors on several triads, or one triad's error seen through the
  motion?) inverts the strongest triad's block alone, refits the motion and asks whether the others'
  blocks are still above χ²_{12(n−1)} (:func:`~accel_bayes.mismatch.linear_blocks.others_after_top`).
  The gyros' spread share does not carry over: one triad's acc error leaks into the others through
  the angular acceleration and their lever arms, not as a common pattern (share 0.44–0.69 for one
  triad's acc_scale, acc_bias, acc_misalignment or triad_orientation on mimu8).

* **No common part.**  The fitted linear motion s is free per sample, so an error shared by every
  triad moves it: the common offset is absorbed exactly, the common 3 × 3 error except for its
  action on the lever-arm terms' differences between triads, which the positions partly absorb.
  The blocks are therefore relative to the array's mean accelerometer, and the stage does not try
  to recover that mean (the gyros' common part is seen through the accelerometers' centripetal
  terms; nothing plays that role for the accelerometers' own).
* **The array-size gauge** is the same: one isotropic scale error on every triad rescales s and the
  lever-arm terms together, which the positions absorb (c_k → (1 + ε) c_k); the median triad's
  isotropic scale is held at zero.
* **The gyro stage around it** (:func:`restage`).  The gyro stage's common part (one array-frame
  error of every gyro) is seen only through the accelerometers' centripetal terms; fitted on the
  uncorrected accelerometers it takes their errors (clockgen's clock-000, mimu4444: entries up to
  0.29 against true gyro errors of 0.5–3 %, and the calibration with that report put four IMUs 2 mm
  off).  So with this stage on, the detector's first gyro pass fits the relative blocks only; then
  (where either stage kept blocks) the whole gyro stage runs again on the recording with this stage's
  blocks inverted, and this stage again on its gyros.
* **Where ``prep`` applied intrinsics** the blocks are what the rests leave, estimated on the
  rest-calibrated outputs (``details.acc_linear_stage.outputs``,
  :data:`accel_bayes.constants.ACC_OUTPUTS`), and ``calibrate --model`` inverts them only after the
  same preparation.  The rests' intrinsics (bias,
  scale, non-orthogonality) fix a triad's axes by convention and cannot hold its rotation on the board;
  the motion sees it (the real MIMU board: ±3 mrad about the board's normal, alternating with the side
  the chip sits on, and the underside IMUs ~0.15 mm off without it: ``experiments/mimu_blind_acc.md``).
  Before 2026-11-29 the stage was skipped there.

The stage's blocks are held fixed from here on (the rounds run on the corrected recording; no
``acc_bias`` / ``acc_scale`` / ``acc_misalignment`` round candidate on a triad that has one) and are
credited in the budget's b through the corrected outputs (:mod:`accel_bayes.mismatch.budget`: a is
the baseline's residual on the recording as given).  The data transform's Jacobian (|I + M_k|⁻¹ per
sample) is left out of the log-likelihoods compared, as in the gyro stage.

Measured: experiments/acc_linear_budget.md (the concealed clock recordings' budget with and without
the stage).
"""
from __future__ import annotations

from ..physics.effects import AccLinear
from .fit import fit_model
from .gyro_linear import gyro_linear_stage
from .linear_blocks import LinearStage, block_arrays, corrected_outputs, linear_stage
from .model import ModelFit
from .prepared import Prepared

__all__ = ["acc_linear_stage", "restage", "ACC_LINEAR_TERMS", "PASSES"]

#: the vocabulary terms an acc_linear block contains (never round candidates on a triad that has one)
ACC_LINEAR_TERMS = ("acc_bias", "acc_scale", "acc_misalignment")


#: alternations of (blocks | motion and geometry) in the stage.  The blocks trade with the positions along a
#: weakly determined direction (a block's offset and matrix against the lever arms' mean centripetal terms),
#: and the alternation converges slowly along it: on clockgen's clock-012 (mimu4444) the calibration with the
#: report put the x–y positions 0.73 mm (4 %) in after 2 passes, 0.28 mm after 6, 0.26 mm after 12; with the
#: generator's own blocks 0.18 mm (``experiments/percov_blind_acc.md``)
PASSES = 6


def acc_linear_stage(prep: Prepared, base: ModelFit, *, m: int, alpha: float, passes: int = PASSES) -> LinearStage:
    """Run step 3a' (module docstring) from the fit ``base`` of ``prep`` (the gyro stage's, when it
    ran); ``m`` and ``alpha`` are the detector's Bonferroni count and family-wise error rate."""
    return linear_stage(prep, base, sensor="acc", block=lambda k, p: AccLinear(imu=k, params=p), m=m, alpha=alpha,
                        passes=passes, spread_test="others")


def restage(prep0: Prepared, acc_stage: LinearStage, *, m: int, alpha: float) -> tuple[LinearStage, LinearStage]:
    """The gyro stage run again on ``prep0`` (the recording before either stage) with ``acc_stage``'s blocks
    inverted, then this stage again on ``prep0`` with the new gyro blocks inverted (module docstring).
    Returns (gyro stage, acc stage), both with ``prep`` / ``fit`` the recording corrected for both sets of
    blocks and the fit on it."""
    p_acc = corrected_outputs(prep0, *block_arrays(acc_stage.blocks, prep0.K), "acc")
    g = gyro_linear_stage(p_acc, fit_model(p_acc, (), init=acc_stage.fit, laplace=False), m=m, alpha=alpha)
    p_gyro = corrected_outputs(prep0, *block_arrays(g.blocks, prep0.K), "gyro")  # its gyros, the raw accelerometers
    a = acc_linear_stage(p_gyro, fit_model(p_gyro, (), init=g.fit, laplace=False), m=m, alpha=alpha)
    a.info["restaged"] = "after the gyro stage was run again on the accelerometers corrected by a first pass"
    g.prep, g.fit = a.prep, a.fit
    return g, a
