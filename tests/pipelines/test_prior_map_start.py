"""The noise step's MAP under the proper φ prior on a recording whose flat-φ MAP collapses (issue #30
item 4, ``experiments/vibgeom_probe.md``): concealed clock case clock-019 (plate4, 62.5 Hz) with the
generator's vibration and impacts, whose fitted accelerometer noise (≈ 0.3 m/s²) is as large as the
centripetal signal.  Before the fix the refit started at the collapsed flat MAP (θ ≈ 0) and stopped
in a reflected mode (geometry scale −0.60 against the generator's truth)."""
import warnings

import numpy as np
import torch

from accel_bayes.model.likelihood import RaoBlackwellLikelihood
from accel_bayes.pipelines.calibrate_options import CalibrateOptions
from accel_bayes.pipelines.calibrate_steps import _estimate_noise, _prepare_step
from accel_bayes.prep.prepared import prepare_recording
from experiments.percov_conceal import case_recording


def _scale(positions, truth, ref):
    """Σ estimate·truth / Σ truth² over the free coordinates (1: right size; < 0: reflected)."""
    est = np.delete(positions - positions[ref], ref, 0).ravel()
    tru = np.delete(truth - truth[ref], ref, 0).ravel()
    return float(est @ tru / (tru @ tru))


def test_noise_step_map_keeps_the_geometry_where_the_flat_map_collapses():
    rec, _, pos = case_recording(19, 20.0, 5e-4, "known")
    pre = _prepare_step(rec, CalibrateOptions())
    lik = RaoBlackwellLikelihood.from_recording(prepare_recording(pre.recording, selection=pre.selection),
                                                num_draws=1, gyro_method="calibrated")
    nominal = torch.as_tensor(pre.recording.nominal_position, dtype=torch.float64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        opts = CalibrateOptions()
        step = _estimate_noise(lik, nominal, opts.prior_std, opts.noise_bins, False, phi_prior=opts.phi_prior)
    res = step.map.result
    assert res is not None
    scale = _scale(np.asarray(res.positions), pos, lik.reference)
    assert 0.95 < scale < 1.05, scale
    # the nominal start won here: the warm start from the collapsed flat MAP is the failure
    start = step.phi_prior["map_start"]
    assert start["start"] == "nominal"
    assert start["log_posterior"]["nominal"] > start["log_posterior"]["flat_map"] + 1.0
