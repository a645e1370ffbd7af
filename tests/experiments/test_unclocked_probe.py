"""The unclocked-IMU probe (``experiments/unclocked_probe.py``): its three treatments are made on the
terms ``unresolved_terms`` returns, and only on the rows without a clock.  The probe itself runs
from the script (a calibrate per case and treatment)."""
from types import SimpleNamespace

import numpy as np
import torch

import accel_bayes.model.report_terms as rt
from experiments import unclocked_probe as up
from tests.model.test_calibrate_percov import UNRESOLVED, _clock, _report


def test_the_treatments_touch_only_the_unclocked_rows(monkeypatch):
    t = np.arange(500) / 62.5
    rep = _report(SimpleNamespace(K=4, T=500), [_clock(1, 0.8, 0.1), _clock(3, -2.3, 0.6), UNRESOLVED])
    args = (rep, t, [0, 1, 2, 3], [0, 1, 2, 3], np.full(500, 4.0))
    prior = rt.unresolved_terms(*args)
    unc = prior.age_var_acc > 0
    assert unc.tolist() == [True, False, True, False]
    for mode in up.MODES:
        orig, patched = up._patched_terms(mode)
        assert orig is rt.unresolved_terms
        got = patched(*args)
        # the clocked rows are the package's own in every treatment
        assert torch.equal(got.age_acc[:, ~unc], prior.age_acc[:, ~unc])
        assert torch.equal(got.age_gyro[:, ~unc], prior.age_gyro[:, ~unc])
        if mode == "prior":
            assert torch.equal(got.age_var_acc, prior.age_var_acc) and torch.equal(got.age_acc, prior.age_acc)
            continue
        assert not bool(got.age_var_acc.any()) and not bool(got.age_var_gyro.any())
        want = 0.0 if mode == "zero" else prior.age_acc[:, unc]
        np.testing.assert_array_equal(got.age_acc[:, unc].numpy(), np.broadcast_to(want, got.age_acc[:, unc].shape))
