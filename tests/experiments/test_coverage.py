"""Posterior coverage / simulation-based calibration (issue #3 MUST-SHOW "Coverage").

The study itself (100 data sets, ≈ 0.5–1 min each on 2 cores) lives in
``experiments/c21_coverage.py`` and runs here only with ``-m slow``; the default run checks that
its verdict logic accepts well-calibrated ranks and rejects a miscalibrated posterior.
"""

import numpy as np
import pytest

from experiments import c21_coverage as cov


def _fake_reps(n, rng, width=1.0, coverage=0.9):
    """Ranks of a truth drawn from N(0,1) among 99 draws from N(0, width²)."""
    reps = []
    for i in range(n):
        ranks = {}
        for k, ax in cov.COORDS:
            t = rng.normal()
            ranks[f"{k}{ax}"] = int((rng.normal(0, width, cov.L_RANK) < t).sum())
        reps.append({"i": i, "ranks": ranks, "covered": bool(rng.random() < coverage), "rhat": 1.002})
    return reps


def test_verdict_accepts_calibrated_and_rejects_overconfident_posterior():
    # Under the null each p-value is uniform, so a fixed seed passes with probability ≈ 0.98
    # (per-coordinate Bonferroni + pooled, each at 1 %); seed 1 is one of those.
    rng = np.random.default_rng(1)
    good = cov.verdict(_fake_reps(300, rng))
    assert good["ranks_ok"] and good["pooled_ok"] and good["coverage_ok"] and good["rhat_ok"]
    # A posterior half as wide as it should be: truths pile up in the extreme rank bins.
    bad = cov.verdict(_fake_reps(300, rng, width=0.5, coverage=0.6))
    assert not bad["ranks_ok"] and not bad["pooled_ok"] and not bad["coverage_ok"]
    reps = _fake_reps(100, rng)
    reps[3]["rhat"] = 1.02
    assert not cov.verdict(reps)["rhat_ok"]


@pytest.mark.slow
def test_coverage_study():
    """100 data sets, θ_true from the prior, chains from prior draws: R̂ < 1.01 everywhere, 90 %
    coverage of r[1, x] inside the binomial 99 % band, SBC ranks of all 9 coordinates uniform
    (χ², Bonferroni 0.01/9)."""
    reps = [cov.replicate(i) for i in range(100)]
    v = cov.verdict(reps)
    assert v["rhat_ok"], v
    assert v["coverage_ok"], v
    assert v["ranks_ok"], v
