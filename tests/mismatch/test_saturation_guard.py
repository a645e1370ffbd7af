"""The detector refuses a ``saturation`` refit whose limit holds fewer than 3 recorded outputs
(``choose.SATURATION_AT_LIMIT``; experiments/saturation_guard_probe.md).

``Saturation.outputs_at_limit`` is checked against hand counts on made-up outputs; the refusal on a
clockgen recording that never clips (clock_budget's clock-013, where the detector without the guard
accepted a limit above every output) runs the whole detector (~30 s).
"""
import warnings

import numpy as np
import torch

from accel_bayes.mismatch.choose import SATURATION_AT_LIMIT
from accel_bayes.physics.effects import Saturation


def test_outputs_at_limit_counts_the_channel_outputs_within_n_sigma_of_the_limit():
    rng = np.random.default_rng(0)
    y = rng.normal(0.0, 5.0, (300, 3, 3))
    y[:, 1, 2] = np.clip(y[:, 1, 2], -6.0, 6.0)
    y[7, 1, 2] = np.nan
    sigma = np.array([0.02, 0.05, 0.01])
    mask = np.ones_like(y)
    mask[np.isnan(y)] = 0.0
    mask[0:5, 1, 2] = 0.0  # missing outputs do not count
    yt = torch.as_tensor(y)
    one = Saturation(imu=1, axis="z", sensor="acc", params={"limit": 6.0})
    ch = np.abs(y[5:, 1, 2])
    ch = ch[np.isfinite(ch)]
    assert one.outputs_at_limit(yt, torch.as_tensor(sigma), 5.0, torch.as_tensor(mask)) == \
        int((np.abs(ch - 6.0) <= 5 * 0.05).sum()) > 10
    every = Saturation(sensor="acc", params={"limit": 6.0})
    hand = sum(int((np.abs(np.abs(y[:, k][mask[:, k] > 0]) - 6.0) <= 5 * sigma[k]).sum()) for k in range(3))
    assert every.outputs_at_limit(yt, torch.as_tensor(sigma), 5.0, torch.as_tensor(mask)) == hand
    above = Saturation(imu=0, axis="x", sensor="acc", params={"limit": float(np.abs(y[:, 0, 0]).max()) + 0.2})
    assert above.outputs_at_limit(yt, torch.as_tensor(sigma), 5.0) == 0  # 10 σ above the largest output


def test_a_limit_no_output_reaches_is_refused_on_a_recording_that_never_clips():
    from accel_bayes.mismatch import detect
    from experiments.clockgen import draw_case

    rec, _ = draw_case("clock", 13, duration=20.0)
    assert np.nanmax(np.abs(rec.acc)) < 0.5 * 157  # never near the range
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        rep = detect(rec)
    assert not any(f.effect == "saturation" for f in rep.findings)
    refused = [r for rnd in rep.rounds for r in rnd.get("refused", []) if r["candidate"].startswith("saturation")]
    assert refused and f"within {SATURATION_AT_LIMIT[0]:g} σ of its limit" in refused[0]["why"]
