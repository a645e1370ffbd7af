"""The effects library: one class per physical effect the nominal array model leaves out.

Vocabulary v1.1 (DESIGN §7.2) — each entry is one class below, registered under its name in
:data:`EFFECTS`; adding an effect is adding one class (STYLE.md, Kalibr's ``IccSensors``):

=====================  ====================================================  ==========  =========
name                   physics left out                                      local IMU   local axis
=====================  ====================================================  ==========  =========
acc_bias               constant accelerometer offset                         yes         yes
acc_scale              accelerometer scale-factor error                      yes         yes
acc_misalignment       cross-axis coupling / non-orthogonal axes             yes         yes
acc_nonlinearity       second-order accelerometer response                   yes         yes
  (acc_linear)         a triad's whole 3 × 3 acc_scale + acc_bias, one       yes         no
                       12-parameter block (the detector's acc linear stage)
axis_displacement      sensing axes not collocated in the package            yes         yes
triad_orientation      IMU mounted rotated from its nominal orientation      yes         no
gyro_bias              gyroscope offset                                      yes         yes
gyro_scale             gyroscope scale-factor error                          yes         yes
  (gyro_misalignment)  the off-diagonal part of gyro_scale, see below        yes         yes
  (gyro_linear)        a triad's whole 3 × 3 gyro_scale + gyro_bias, one     yes         no
                       12-parameter block (the detector's stage 4a)
gyro_g_sensitivity     gyro output that depends on specific force            yes         no
gyro_nonlinearity      second-order gyroscope response (k2·ω², vocab. 1.1)   yes         yes
time_offset            one IMU sampled late relative to the others           yes         no
saturation             samples clipped at (an unstated) sensor range         optional    optional
noise_level            noise larger than stated                              optional    no
sampling_jitter        samples taken at random instants (free-running clock)  yes         no
sampling_clock         own free-running clock read asynchronously: data age   yes         no
                       a sawtooth (vocab. 1.2; estimated by mismatch.clock)
unexplained            a located mismatch no candidate explains (finding     –           –
                       kind only, no signal model)
=====================  ====================================================  ==========  =========

Extensions — documented effects of our own beyond the vocabulary (``in_vocabulary = False``,
listed in :data:`EXTENSIONS`, reported under their own names, which DESIGN §7.2 allows; a
scorer of the vocabulary does not credit them):

=====================  ====================================================  ==========  =========
gyro_delay             gyroscope output delayed relative to its own          yes         no
                       accelerometer (filter group delay, sampling delay)
timing_wander          one sensor's sampling instants wander around their    yes         no
                       time stamps (AR(1) instant error: beating clocks);
                       random effect {"width", "correlation"}, option sensor
=====================  ====================================================  ==========  =========

Every effect class holds

* ``name``, ``description`` (plain-language physics), ``local_imu`` / ``local_axis``;
* its parameters (:class:`Param`: name, shape, unit, prior scale) — names, shapes and units are
  exactly the DESIGN §7.2 report parameters, sensor frame of the IMU, SI units;
* the perturbation it adds to the signal model, a differentiable torch function of its
  parameters given a :class:`SignalContext` (motion, geometry and the nominal sensor-frame
  outputs of :func:`accel_bayes.physics.models.imu_outputs`, the package's one signal model);
* :meth:`Effect.report_parameters` (JSON) and :meth:`Effect.explain` (one sentence).

Four kinds of effect (``Effect.kind``):

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
    leverage-corrected residuals (see :mod:`accel_bayes.mismatch.fit`).

``"random"`` (sampling_jitter)
    changes no mean; adds a random, sample-to-sample independent term whose marginal
    likelihood the detector evaluates exactly (:mod:`.jitter`); skipped by the mean machinery.

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
:mod:`accel_bayes.mismatch.detector` drops candidates whose efficient information is singular).

Layout (one module per sensor): :mod:`.base` (context, parameters, the :class:`Effect` base
class, registry, composition), :mod:`.accelerometer`, :mod:`.mounting`, :mod:`.gyroscope`,
:mod:`.timing`, :mod:`.output`, :mod:`.jitter`.  The import order below is the registration order, which
is the order of :data:`VOCABULARY`: the DESIGN §7.2 table order, except that the vocabulary-1.1
additions sit with their module (``gyro_nonlinearity`` after ``gyro_g_sensitivity``,
``sampling_jitter`` after ``unexplained``).
"""
from __future__ import annotations

from .base import (AXES, EFFECTS, CandidateLayout, Effect, Param, SignalContext, apply_effects, check_effects,
                   get_effect, make_effect, model_outputs, noise_factors, output_rates, register_effect)
from .accelerometer import AccBias, AccScale, AccMisalignment, AccNonlinearity, AccLinear, AxisDisplacement
from .accelerometer import (acc_gain_effects, acc_gain_of_effects, gain_to_intrinsics, gain_to_s16, intrinsics_gain,
                            s16_gain, triangular_gauge)
from .mounting import TriadOrientation
from .gyroscope import GyroBias, GyroScale, GyroMisalignment, GyroGSensitivity, GyroNonlinearity, GyroLinear
from .timing import GyroDelay, TimeOffset, sample_times
from .output import Saturation, NoiseLevel, Unexplained
from .jitter import SamplingJitter, TimingWander, jittered_times, log_marginal_gain
from .clock import SamplingClock, board_gyro_rate, clock_age

VOCABULARY = tuple(n for n, c in EFFECTS.items()
                   if c.vocabulary_name is None and c.in_vocabulary)  # DESIGN §7.2 table order
#: documented effects of our own beyond the vocabulary (DESIGN §7.2 allows them in reports)
EXTENSIONS = tuple(n for n, c in EFFECTS.items() if not c.in_vocabulary)

__all__ = [
    "AXES",
    "Param",
    "SignalContext",
    "Effect",
    "AccBias",
    "AccScale",
    "AccMisalignment",
    "AccNonlinearity",
    "AccLinear",
    "AxisDisplacement",
    "acc_gain_effects",
    "acc_gain_of_effects",
    "triangular_gauge",
    "intrinsics_gain",
    "gain_to_intrinsics",
    "s16_gain",
    "gain_to_s16",
    "TriadOrientation",
    "GyroBias",
    "GyroScale",
    "GyroMisalignment",
    "GyroGSensitivity",
    "GyroNonlinearity",
    "GyroLinear",
    "TimeOffset",
    "sample_times",
    "Saturation",
    "NoiseLevel",
    "Unexplained",
    "SamplingJitter",
    "jittered_times",
    "log_marginal_gain",
    "EFFECTS",
    "VOCABULARY",
    "EXTENSIONS",
    "GyroDelay",
    "TimingWander",
    "SamplingClock",
    "clock_age",
    "board_gyro_rate",
    "register_effect",
    "get_effect",
    "make_effect",
    "model_outputs",
    "noise_factors",
    "apply_effects",
    "check_effects",
    "output_rates",
    "CandidateLayout",
]
