"""Type-II ML of the unresolved jerk's scales per band and of ν (accel_bayes.model.unresolved_fit):
recovery on data drawn from the model with known scales, and ν large on Gaussian data."""

import math

import pytest
import torch

from accel_bayes.errors import UserError
from accel_bayes.model.gyro_posterior import gyro_posterior
from accel_bayes.model.likelihood import RaoBlackwellLikelihood
from accel_bayes.model.unresolved_fit import fit_unresolved_scales
from accel_bayes.physics.models import specific_force

DT = torch.float64
# 8 corners of a 5 × 4 × 1 cm board, row 0 the origin
POS8 = torch.tensor([[x, y, z] for x in (0.0, 0.05) for y in (0.0, 0.04) for z in (0.0, 0.01)], dtype=DT)
SIG = 0.2


def _data(T, scales, nu=None, seed=0, stated=SIG):
    """Data drawn from the per-sample model: two |ω| bands (first/second half), jerk scale per band,
    optional Gamma(ν/2, ν/2) precision scale per sample on noise and jerk together."""
    g = torch.Generator().manual_seed(seed)
    A = POS8.shape[0]
    w = 4 * torch.randn(T, 3, generator=g, dtype=DT)
    wd = 3 * torch.randn(T, 3, generator=g, dtype=DT)
    s = 3 * torch.randn(T, 3, generator=g, dtype=DT)
    band = (torch.arange(T) >= T // 2).long()
    age = 1e-3 * torch.rand(T, A, generator=g, dtype=DT)
    jerk = torch.as_tensor(scales, dtype=DT)[band][:, None] * torch.randn(T, 3, generator=g, dtype=DT)
    err = -age[..., None] * jerk[:, None, :] + SIG * torch.randn(T, A, 3, generator=g, dtype=DT)
    if nu is not None:
        lam = torch.distributions.Gamma(torch.full((T,), nu / 2, dtype=DT), torch.full((T,), nu / 2, dtype=DT))
        torch.manual_seed(seed)
        err = err / lam.sample().sqrt()[:, None, None]
    acc = specific_force(POS8, w, wd, s) + err
    omega = gyro_posterior(w[:, None, :] + 1e-4 * torch.randn(T, 3, 3, generator=g, dtype=DT),
                           torch.full((3,), 1e-4, dtype=DT), "calibrated")
    return RaoBlackwellLikelihood(acc, omega, stated, 1), age, band, w


def test_band_scales_are_recovered_and_gain_over_the_flat_model():
    lik, age, band, w = _data(3000, [2000.0, 6000.0])
    fit = fit_unresolved_scales(lik, age, band, POS8, w)
    # 1500 samples per band: the relative std of a variance from ~1500·3 draws is ~3 %
    assert fit.jerk_rms[0].item() == pytest.approx(2000.0, rel=0.06)
    assert fit.jerk_rms[1].item() == pytest.approx(6000.0, rel=0.05)
    assert fit.nu is None and fit.gain > 100.0


def test_nu_is_recovered_on_heavy_tails_and_large_on_gaussian_data():
    lik, age, band, w = _data(3000, [3000.0, 3000.0], nu=4.0, seed=1)
    fit = fit_unresolved_scales(lik, age, band, POS8, w, fit_nu=True)
    assert 3.0 < fit.nu < 5.5
    assert fit.jerk_rms[0].item() == pytest.approx(3000.0, rel=0.08)
    lik, age, band, w = _data(3000, [3000.0, 3000.0], seed=2)
    assert fit_unresolved_scales(lik, age, band, POS8, w, fit_nu=True).nu > 30.0


def test_the_noise_factor_finds_the_mixture_scale_under_a_stated_rms():
    """t noise with ν = 4 has rms √2 × its scale: stated at the rms, the factor 1/√2 fits best."""
    lik, age, band, w = _data(3000, [3000.0, 3000.0], nu=4.0, seed=3, stated=SIG * math.sqrt(2))
    fit = fit_unresolved_scales(lik, age, band, POS8, w, fit_nu=True, noise_factors=(0.5, 1 / math.sqrt(2), 1.0))
    assert fit.noise_factor == pytest.approx(1 / math.sqrt(2)) and 3.0 < fit.nu < 5.5
    assert fit.gain > 0


def test_band_must_be_integer_labels():
    lik, age, band, w = _data(20, [1.0, 1.0])
    with pytest.raises(UserError, match="^band: expected"):
        fit_unresolved_scales(lik, age, band.double(), POS8, w)
