"""The board's unresolved angular jerk in the per-sample likelihood (issue #30, angjerk_cal): triad k
read at centred age d_kt errs by d_kt(m_t + ω̈_t × (r_k − r̄)), ω̈_t ~ N(0, a_t² I₃) rad/s³, the
lever arms r_k a fixed covariate (accel_bayes.model.likelihood_percov, "Angular jerk").

References independent of the estimator's algebra: per sample a dense 3A × 3A covariance
σ²I + s²DDᵀ + a² Σ_axes (d ⊙ (e_j × r))(…)ᵀ built with numpy's cross product (and the instant error's
blocks), and the dense weighted projection (flat φ prior) or scipy's Gaussian (proper prior);
the angular jerk's scale recovered from data simulated with it (type-II ML).
"""
import math

import numpy as np
import pytest
import torch

from accel_bayes.errors import UserError
from accel_bayes.model.gyro_posterior import gyro_posterior
from accel_bayes.model.likelihood import RaoBlackwellLikelihood
from accel_bayes.model.likelihood_percov import PerSampleCovLikelihood, with_unresolved_motion
from accel_bayes.model.unresolved_fit import fit_unresolved_scales
from accel_bayes.physics.models import specific_force
from tests.model.test_instant_error import _rate
from tests.model.test_likelihood_percov import POS5, SIG, _case, _dense_marginal, _kinematic_H

DT = torch.float64
LEVER = POS5 + torch.tensor([0.003, -0.002, 0.001], dtype=DT)  # nominal positions: not the θ evaluated


def _dense(pos, acc, omega, age, jerk_std, ang_std, lever, rate=None, e=0.0, F=None):
    """Per sample log p(y_t | ω_t, θ) (T,), constants included, from the naive dense covariance."""
    A = pos.shape[0]
    n = 3 * A
    H = _kinematic_H(pos)
    lev = lever.numpy() - lever.numpy().mean(0)
    out = []
    for t in range(acc.shape[0]):
        mean = specific_force(pos, omega[t:t + 1], torch.zeros(1, 3, dtype=DT), torch.zeros(1, 3, dtype=DT))
        r = (acc[t] - mean[0]).reshape(-1).numpy()
        d = (age[t] - age[t].mean()).numpy()
        Sig = SIG ** 2 * np.eye(n) + float(jerk_std[t]) ** 2 * np.kron(np.outer(d, d), np.eye(3))
        for j in range(3):  # the column of unit angular jerk about axis j: d_k (e_j × r_k) on triad k
            col = (d[:, None] * np.cross(np.eye(3)[j], lev)).reshape(-1)
            Sig += float(ang_std[t]) ** 2 * np.outer(col, col)
        if rate is not None:
            for k in range(A):
                rho = rate[t, k].numpy()
                Sig[3 * k:3 * k + 3, 3 * k:3 * k + 3] += e ** 2 * np.outer(rho, rho)
        out.append(_dense_marginal(r, Sig, H, F))
    return np.array(out)


def _const(lik, A, F=None):
    c = lik.T * (-(3 * A - 6) / 2 * math.log(2 * math.pi) - 3 * A * math.log(SIG))
    if F is not None:  # the base class omits −½ log|F| and −3 log 2π of the proper prior too
        c += lik.T * (-0.5 * np.linalg.slogdet(F)[1] - 3 * math.log(2 * math.pi))
    return c


@pytest.mark.parametrize("prior", [None, "proper"])
@pytest.mark.parametrize("instant", [False, True])
def test_given_omega_equals_the_dense_gaussian_with_the_angular_jerk(prior, instant):
    acc, omega, age, s = _case(T=6, seed=4)
    ang = torch.linspace(2e4, 9e4, 6, dtype=DT)
    rate = _rate(6, 5) if instant else None
    F = None if prior is None else np.diag([30.0, 20.0, 25.0, 9.0, 16.0, 4.0])
    lik = PerSampleCovLikelihood(acc, omega, SIG, 3, age, s, phi_prior=None if F is None else torch.as_tensor(F),
                                 angjerk_std=ang, lever=LEVER, rate=rate, instant_std=2e-4 if instant else None)
    w = omega.mean + 0.1
    for pos in (POS5, POS5 * 1.3):
        want = _dense(pos, acc, w, age, s, ang, LEVER, rate, 2e-4, F=F)
        per = lik.log_lik_per_sample(pos, w).detach().numpy() + _const(lik, 5, F) / lik.T
        assert np.allclose(per, want, rtol=1e-10, atol=1e-8)
    # the term is not negligible in this case: without it the value differs by nats
    plain = PerSampleCovLikelihood(acc, omega, SIG, 3, age, s, phi_prior=lik.phi_prior, rate=rate,
                                   instant_std=2e-4 if instant else None)
    assert abs(float(plain.log_lik_given_omega(POS5, w)) - float(lik.log_lik_given_omega(POS5, w))) > 1.0


def test_log_phat_equals_the_dense_monte_carlo_average_and_zero_scale_is_the_jerk_model():
    acc, omega, age, s = _case(T=5, seed=9)
    ang = torch.full((5,), 5e4, dtype=DT)
    for N in (1, 7):
        lik = PerSampleCovLikelihood(acc, omega, SIG, N, age, s, angjerk_std=ang, lever=LEVER)
        z = lik.sample_z((), N, torch.Generator().manual_seed(N))
        om = lik.omega_draws(z)
        per = np.stack([_dense(POS5, acc, om[:, n], age, s, ang, LEVER) for n in range(N)], -1)
        want = (torch.logsumexp(torch.as_tensor(per), -1) - math.log(N)).sum().item()
        assert float(lik.log_phat(POS5, z=z)) + _const(lik, 5) == pytest.approx(want, rel=1e-9, abs=1e-8)
    # scale 0: the general path gives the closed-form jerk-only value
    zero = PerSampleCovLikelihood(acc, omega, SIG, 7, age, s, angjerk_std=0.0, lever=LEVER)
    jerk = PerSampleCovLikelihood(acc, omega, SIG, 7, age, s)
    assert float(zero.log_phat(POS5, z=z)) == pytest.approx(float(jerk.log_phat(POS5, z=z)), rel=1e-12, abs=1e-9)


def test_the_angular_jerk_scale_is_recovered_by_type2_ml_and_the_inputs_are_checked():
    """Data simulated with a known ω̈ (2e4 rad/s³ per axis) on the lever arms: the fitted scale
    lands within 25 % of it, and the fit gains nats over the jerk-only model; without ω̈ in the data
    the fitted scale is far below it."""
    T, A = 1500, 5
    g = torch.Generator().manual_seed(21)
    pos = POS5
    w = 3 * torch.randn(T, 3, generator=g, dtype=DT)
    wd = 3 * torch.randn(T, 3, generator=g, dtype=DT)
    sv = 3 * torch.randn(T, 3, generator=g, dtype=DT)
    age = 2e-3 * torch.rand(T, A, generator=g, dtype=DT)
    d = age - age.mean(-1, keepdim=True)
    wdd = 2e4 * torch.randn(T, 3, generator=g, dtype=DT)
    lev = pos - pos.mean(0)
    omega = gyro_posterior(w[:, None, :] + 1e-3 * torch.randn(T, 4, 3, generator=g, dtype=DT),
                           torch.full((4,), 1e-3, dtype=DT), "calibrated")
    band = torch.zeros(T, dtype=torch.long)
    for truth in (2e4, 0.0):
        rot = torch.cross(truth / 2e4 * wdd[:, None, :].expand(T, A, 3), lev.expand(T, A, 3), dim=-1)  # ω̈ × r
        acc = (specific_force(pos, w, wd, sv) - d[..., None] * rot
               + SIG * torch.randn(T, A, 3, generator=g, dtype=DT))
        base = RaoBlackwellLikelihood(acc, omega, SIG, 1)
        fit = fit_unresolved_scales(base, age, band, pos, w, lever=pos)
        if truth:
            assert float(fit.angjerk_rms[0]) == pytest.approx(truth, rel=0.25)
            assert fit.gain_angjerk > 20.0
        else:
            assert float(fit.angjerk_rms[0]) < 0.3 * 2e4
    with pytest.raises(UserError, match="angjerk_std, lever"):
        with_unresolved_motion(base, age, 1.0, angjerk_std=1.0)
    with pytest.raises(UserError, match="lever: expected"):
        with_unresolved_motion(base, age, 1.0, angjerk_std=1.0, lever=pos[:3])
    with pytest.raises(UserError, match="angjerk_std: expected"):
        with_unresolved_motion(base, age, 1.0, angjerk_std=-1.0, lever=pos)


def test_the_option_is_on_by_default_enters_the_fingerprint_and_the_cli_switches_it():
    """``angular_jerk`` is on by default (it acts only with a model); on, it is part of the checkpoint
    fingerprint (a checkpoint made without it is not resumed with it) and a model run switched off
    keeps the request of the runs before it; ``--no-angular-jerk`` switches it off, ``--angular-jerk``
    is accepted, and asked for explicitly without a model it is refused naming the option."""
    from accel_bayes.cli import build_parser
    from accel_bayes.pipelines.calibrate_options import CalibrateOptions

    assert CalibrateOptions().angular_jerk is True and CalibrateOptions(model="r.json").angular_jerk is True
    on = CalibrateOptions(model="r.json").fingerprint("rec", model_sha256="m")["options"]
    off = CalibrateOptions(model="r.json", angular_jerk=False).fingerprint("rec", model_sha256="m")["options"]
    assert on["angular_jerk"] is True and "angular_jerk" not in off
    assert {k: v for k, v in on.items() if k != "angular_jerk"} == off
    assert "angular_jerk" not in CalibrateOptions().fingerprint("rec")["options"]  # no model: no term
    parse = lambda *extra: build_parser().parse_args(["calibrate", "rec.nc", "--out", "o", *extra])  # noqa: E731
    assert CalibrateOptions.from_args(parse("--model", "r.json")).angular_jerk is True
    assert CalibrateOptions.from_args(parse("--model", "r.json", "--angular-jerk")).angular_jerk is True
    assert CalibrateOptions.from_args(parse("--model", "r.json", "--no-angular-jerk")).angular_jerk is False
    assert CalibrateOptions.from_args(parse("--no-angular-jerk")).angular_jerk is False
    with pytest.raises(UserError, match="^angular_jerk: .*needs a model"):
        CalibrateOptions.from_args(parse("--angular-jerk"))
