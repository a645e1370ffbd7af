"""Rig calibration: two or more IMUs with gyroscopes, each with its own orientation, lever arm and
clock, as a posterior (issue #28 item 1).

Model
-----
The rig is rigid.  The reference IMU (label ``reference_imu``) defines the array frame through its
nominal orientation R₀ and its position (the origin) and its clock (o = d = 0).  The motion is a
continuous-time state in the array frame — angular rate ω(t), its derivative ω̇(t), and the
reference's specific force f(t) and its derivative — held at knots τ_j every h seconds (10 ms,
:data:`~.solve.DEFAULT_KNOT_SPACING`, whatever the rates: finer knots absorb each IMU's noise at its
own instants and the joint MAP reads it as timing, 3–12 std on the offsets of a concealed rig at
5 and 2.5 ms, ``experiments/rig_knot_spacing.md``) and interpolated by cubic Hermite polynomials
(:mod:`.model`).  A white-noise-on-jerk prior scores
consecutive knots (q_c: the mean squared ω̈, f̈ of the smoothed reference signals over 1 s; weak on
purpose).  IMU k's sample stamped s on its own clock was taken at t = t₀ + o_k + (s − t₀)/(1 + d_k)
(DESIGN §7.3), and reads

    y_g = R_k ω(t) + b_g,k + e_g          y_a = R_k [f(t) + ω̇(t)×r_k + ω(t)×(ω(t)×r_k)] + b_a,k + e_a

with Gaussian e: white noise of the recording's stated std plus, where the IMUs carry their own
stamps, the stamping error (a host's latency in stamping; the IMU itself ticks regularly) as a
timing error ε ~ N(0, σ_j,k²) of the whole sample, which moves its six readings along ∂y/∂t: the
sample's covariance is diag(σ_g², σ_a²) + σ_j,k² ẏ ẏᵀ.  σ_j,k is read off the stamps (their second
differences, :func:`~.model.stamp_jitter_std`); ẏ is evaluated at the start of each LM pass and held
fixed within it (iteratively reweighted), so each sample is whitened by (I + u uᵀ)^{-1/2},
u = σ_j ẏ/σ.  With one stamp column for all IMUs the error is common to every IMU and left out.  The reference has R₀ fixed, r = 0 and no
biases (its biases are absorbed in ω and f).  Unknowns per IMU k ≠ reference: R_k (3, right
box-plus), r_k (3, m), o_k (s), d_k (only where the IMU carries its own stamps: a NaN-union
recording or ``imu_time_offset``; else 0), and its gyro and acc biases b_g,k(t), b_a,k(t) relative
to the reference's, as random walks on a grid of bias knots of their own, H seconds apart (one grid
per sensor kind; globals, linear between bias knots), consecutive bias knots differing by
N(0, (K_k² + K_ref²) H) per axis, K the walk's density (rad/s/√s, m/s²/√s) — the reference's walk
enters through ω and f, so the relative bias walks with both.  H (:func:`~.solve.bias_knot_spacing`)
is the largest spacing at which the linear interpolant misses the walk (its Brownian bridge,
K√H/2 at mid-interval) by at most a quarter of a sample's white-noise std, at least 1 s (so each
bias knot is fixed by its second of samples rather than by the walk prior) and at most the
recording: on exp_1's 30 s window EuRoC's walks and the MIMU4444's noise give two 15 s acc
intervals and one 30 s gyro interval, the concealed rigs' small walks one interval over the
recording.  Why not at the motion knots: 6 bias numbers per IMU every 10 ms, each held by the walk
prior rather than by its few samples, left LM crawling along thousands of weakly determined
directions (exp_1's 30 s pairs stopped at the iteration limit on offsets of 1–88 ms).  Cost: the
bias knots are dense globals of the LM, 6·n(K−1) columns in every interval's Jacobian; a long
recording with walks fast against its noise (hundreds of bias knots) makes them the dominant
memory.  K per IMU and sensor comes from long rests (Allan deviation, the exports'
:func:`accel_bayes.data.export.random_walks`), else from the recording (``gyro_random_walk``,
``acc_random_walk`` of the array description or sensor.yaml), else EuRoC's ADIS16448 figures with a
one-line warning (:data:`~.solve.DEFAULT_RANDOM_WALK`).  The walks are marginalised (Schur
complement of the bias knots), so the clock, lever-arm and orientation stds include them (on 15 s concealed rigs a walk of
1e-4 m/s²/√s moves the offsets' z by ≤ 0.08, ``experiments/rig_offset_decomposition.md``; a walk
of the white noise's size over the recording widens the lever-arm and orientation stds by 9–32 %,
``tests/inference/test_rig_walk.py``).  A stated nominal orientation
(not the identity, which format v1 cannot tell from "absent") enters as a prior of 5° std; a fit
more than 3 prior std away draws a one-line warning.  The lever arm has a 1 m std prior about the
nominal position: proper, so LM cannot wander along an unexcited direction, and flat for anything
the data identify.  The lever arm is identified by the ω̇ and ω² terms, the orientation by ω (and
f), the clock by the timing of ω's and f's changes.

Optional sensor terms (off by default, :class:`RigSettings`): ``linear_errors`` — per
non-reference IMU and sensor kind a symmetric 3×3 linear error M (scale factors and
non-orthogonality relative to the reference; the antisymmetric part is R's), readings
(I + M) R ω and (I + M) R [f + …], each entry N(0, 3 %²) a priori; ``acc_delay`` — per non-reference
IMU its acc's own time offset δ_k against its gyro (relative to the reference's, which f absorbs):
the acc readings are predicted at t + δ_k, δ_k ~ N(0, (2 ms)²).  Both are marginalised like the
biases (M) or reported with a std (δ_k, ``RigResult.acc_delay``).  On the MIMU4444's exp_1 the
gyros' relative M reaches 2 %, and the offsets timed by the gyros alone and by both sensors differ
by up to 0.3 ms; neither term explains the pair/eight-IMU offset disagreement, which is the IMUs'
relative timing changing by up to 1 ms between moves (``experiments/rig_mimu_diagnose.md``).

Assumptions (what the model does not have): bias walks of the stated density (a walk faster than
stated makes the stds too small; bias instability (flicker) is read as a walk; the walk is the
linear interpolant of a Brownian motion between bias knots H apart, whose bridge, ≤ K√H/2, is
at most a quarter of the white noise, or more where the 1 s floor binds), no scale factors or misalignments inside an IMU
unless ``linear_errors`` asks for them and no nonlinearity (exp_1's final spin near the gyro range is
out of reach), the acc and gyro of an IMU sampled at the same instant unless ``acc_delay`` frees it
(a constant delay, not one that wanders), stamp errors independent between
samples, a constant drift, motion smooth on the scale of h (cubic between knots; impacts and
vibration above ~1/(4h) are not represented), the reference's nominal orientation exact.

Solve: the package's structured LM (:mod:`accel_bayes.inference.lm`), knots eliminated by the
block-tridiagonal Schur complement; a second pass re-buckets the samples at the first pass's clocks
where they moved by more than h/4.  Posterior: Laplace at the MAP with the exact Hessian (the
Gauss–Newton JᵀJ evaluates ∂r/∂o at the noise-fitted ω̇ and is 25–40 % optimistic for the clock),
Gauss–Newton where the exact one is indefinite (LM stopped on a ridge).  Beside it a
misspecification-robust std, the block sandwich H⁻¹ B H⁻¹ over 3 s blocks with the motion and bias
knots profiled out (:mod:`.robust`), and a rule fixed in advance for the reported std: the
sandwich where a 1 % test says the blocks' spread exceeds the model's, else the Laplace (one-line
warning; on exp_1's MIMU pairs the Laplace std was 20–65× below a jackknife's because the IMUs'
relative timing changes between moves, ``experiments/rig_mimu_pairs.md``).  Identifiability: a
direction of the information scaled by :data:`~.solve.IDENT_SCALE` with eigenvalue < 1 (std above
those scales) makes the parameters loading on it ``unidentified``; so does the lever arm along the
only axis the reference gyro turns about (:func:`~.solve.unexcited_axes`), which a noise-fitted
motion would otherwise credit with information.  Unidentified coordinates get no std (NaN, null in
positions.json) and ``calibrate`` exits with status 4.
"""
from .solve import IDENT_SCALE, RigResult, RigSettings, fit_rig, rig_samples

__all__ = ["RigResult", "RigSettings", "fit_rig", "rig_samples", "IDENT_SCALE"]
