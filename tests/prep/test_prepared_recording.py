"""``prepare_recording`` (issue #26 item 1): one frozen record of a recording's fit inputs, made by
one function in ``prep/``; the likelihood's ``from_recording`` takes it (every other fit too:
``test_fits_take_prepared.py``)."""
import dataclasses

import numpy as np
import pytest
import torch

from accel_bayes.errors import UserError
from accel_bayes.model.gyro_posterior import gyro_posterior
from accel_bayes.model.likelihood import RaoBlackwellLikelihood
from accel_bayes.physics.arrays import mimu4444_8
from accel_bayes.prep.prepared import PreparedRecording, prepare_recording
from accel_bayes.simulate import simulate


@pytest.fixture(scope="module")
def rec():
    r = simulate(mimu4444_8(), "smooth", T=200, rate=100.0, seed=4, position_error_std=1e-4).recording
    r.reference_imu = 2
    return r


def test_prepared_recording_is_frozen_and_what_the_likelihood_is_built_from(rec):
    thr = float(rec.gyro_tensor("array").mean(1).norm(dim=-1).median())  # about half the samples
    p = prepare_recording(rec, select="rotation", min_rotation=thr)
    assert isinstance(p, PreparedRecording)
    with pytest.raises(dataclasses.FrozenInstanceError):
        p.reference = 0
    assert p.imu_labels == tuple(range(rec.K)) and p.imu_labels[p.reference] == 2
    assert p.acc.shape == (p.T, p.A, 3) and p.gyro.shape == (p.T, len(p.gyro_labels), 3)
    assert 0 < p.T < rec.T and np.array_equal(p.sample_index, p.selection.index)
    omega_bar = rec.gyro_tensor("array")[p.sample_index].mean(1).norm(dim=-1)
    assert bool((omega_bar >= thr - 1e-12).all())  # gyros of equal noise: ω̄ is the plain mean
    lik = RaoBlackwellLikelihood.from_recording(p, num_draws=4, gyro_method="calibrated")
    direct = RaoBlackwellLikelihood(p.acc, gyro_posterior(p.gyro, p.gyro_noise_std, "calibrated"), p.acc_noise_std,
                                    4, reference=p.reference)
    pos = p.nominal_positions + 1e-4
    z = lik.sample_z(generator=torch.Generator().manual_seed(1))
    assert torch.equal(lik.log_phat(pos, z=z), direct.log_phat(pos, z=z))
    assert lik.imu_labels == p.imu_labels and np.array_equal(lik.sample_index, p.sample_index)
    assert torch.equal(lik.nominal_positions, p.nominal_positions)


def test_prepare_recording_refusals_name_the_field(rec):
    with pytest.raises(UserError, match="^acc_imus: at least 3"):
        prepare_recording(rec, acc_imus=[2, 3])
    with pytest.raises(UserError, match="^reference_imu: IMU 2 is not among"):
        prepare_recording(rec, acc_imus=[0, 1, 3])
    sel = prepare_recording(rec).selection
    with pytest.raises(UserError, match="^selection: given together with"):
        prepare_recording(rec, selection=sel, drop_clipped=True)
    with pytest.raises(UserError, match="^select: expected None, .all., a mask"):
        prepare_recording(rec, select="static")
