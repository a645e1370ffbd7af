"""Defaults of :func:`accel_bayes.pipelines.calibrate.calibrate`, importable without torch: the
command line builds ``calibrate --help`` from them before it decides whether to compute (issue #26).
"""
from __future__ import annotations

from ..constants import DEFAULT_MIN_ROTATION, DEFAULT_PRIOR_STD, DEFAULT_RATE_BINS, DEFAULT_THREADS, RHAT_MAX

__all__ = ["DEFAULTS"]

# Defaults.  Measured on the shared 2-core machine under heavy load (load average ≈ 15): a 32-IMU,
# T = 3000 simulated recording took 570 s in all (MAP, N choice, 4 × 2000 iterations, outputs);
# 8 IMUs at T = 1000 and 32 IMUs at T = 500 took 2.5–7 min.  With MAP-centred independence moves
# (independence_prob 0.8) 4 × 1000 draws gave R̂ ≤ 1.02 and bulk ESS ≥ 340 on those cases, where
# the random walk alone gave R̂ > 1.8 (21 and 93 coordinates: O(d) steps per independent draw).
# Real MIMU4444 recording (exp_1, T ≈ 5900 selected samples, estimated noise, N = 1): the whole
# pipeline took 3.5–4 min wall (≈ 2 min CPU) with R̂ ≤ 1.004 and bulk ESS ≥ 1600.
#
# Length of the chains (issue #15): ``draws`` None runs until converged — every coordinate with
# R̂ < rhat_max and bulk and tail ESS ≥ ess_min (Vehtari et al. 2021: 1.01, and 100 per chain, i.e.
# 400 for the 4 chains), checked every ``check_every`` kept draws per chain (a fixed count, never wall
# time, so where a run stops does not depend on the machine), up to ``max_draws`` per chain
# (20 000: 20× the 1000 that sufficed in the cases above; 4 × 21 000 iterations at the ≈ 30 ms per
# iteration measured for 8 IMUs, T = 600 on the loaded 2-core machine is ≈ 40 min) and
# ``max_seconds`` of sampling (3600 s, a safety stop above that; a run that hits it has a
# machine-dependent length and is reported as such).  An int ``draws`` runs exactly that many, as
# before.  The demo board (mimu4444_8, smooth, T = 600, seed 1) converged at the first check, 500
# draws per chain.
DEFAULTS = {
    "chains": 4,
    "draws": None,
    "warmup": 1000,
    "max_draws": 20_000,
    "check_every": 500,
    "rhat_max": RHAT_MAX,
    "ess_min": None,  # None: 100 per chain (diagnostics.ESS_PER_CHAIN), 400 for the 4 chains
    "max_seconds": 3600.0,
    "prior": "gaussian",
    "prior_std": DEFAULT_PRIOR_STD,
    "gyro_method": "auto",
    "target_accept_prob": 0.15,
    "independence_prob": 0.8,
    "correlation": "auto",
    "start_overdispersion": 1.5,
    "drop_clipped": True,
    "intrinsics": "auto",
    "drop_static": True,
    "min_rotation": DEFAULT_MIN_ROTATION,
    "noise": "auto",
    "noise_bins": DEFAULT_RATE_BINS,
    "noise_inflation": None,  # None: True without a model, False with one
    "phi_prior": "empirical",
    "threads": DEFAULT_THREADS,
    # with a model: the board's angular jerk in the per-sample likelihood, on since one log p̂ with it
    # meets issue #30's cost bar (≤ 4× the flat model's on exp_1; experiments/bench_likelihood_percov.md)
    "angular_jerk": True,
    # with a model whose report has accelerometer blocks: the triads' linear errors integrated out (their
    # deviations) and cut (the part they share), the tolerance by type-II ML (model.acc_block_marginal;
    # experiments/percov_blind_acc.md)
    "acc_blocks": "fit",
}
