"""The held-out study's target clock acquisition (accel_bayes/mismatch/heldout.py): the window of
contiguous motion, and the causal tracker's prequential blocks."""
from __future__ import annotations

import types

import numpy as np
import pytest
import torch

from accel_bayes.errors import UserError
from accel_bayes.mismatch import heldout


def _prep_with_rests(monkeypatch, T, rests, f=62.5):
    """A stand-in prepared recording of T samples at f Hz whose rests are ``rests`` (index pairs)."""
    import accel_bayes.prep.intrinsics as intr

    monkeypatch.setattr(intr, "rest_segments", lambda rec, seg=None: list(rests))
    src = types.SimpleNamespace(T=T, time=np.arange(T) / f)
    return types.SimpleNamespace(source=src)


def test_motion_window_starts_after_the_last_rest_before_a_long_enough_stretch(monkeypatch):
    """Rests with 2 s turns between them, then motion from sample 2875 on: the 30 s window starts
    there (not at the first turn), holds 30 s of samples and no rest sample."""
    rests = [(0, 1400), (1525, 2875)]
    prep = _prep_with_rests(monkeypatch, 6000, rests)
    w = heldout.motion_window(prep, 30.0)
    idx = np.flatnonzero(w)
    assert idx[0] == 2875
    assert np.all(np.diff(idx) == 1)
    assert (idx[-1] - idx[0]) / 62.5 == pytest.approx(30.0, abs=0.05)


def test_motion_window_refuses_a_recording_without_a_long_enough_stretch(monkeypatch):
    prep = _prep_with_rests(monkeypatch, 3000, [(0, 1400), (1525, 2875)])
    with pytest.raises(UserError, match="acquire_s"):
        heldout.motion_window(prep, 30.0)


def _synthetic(seed, T=3750, f=62.5, beat=(1.3,)):
    """Residuals-like timing statistics of IMUs with sawtooth ages and a slowly drifting beat:
    b = −a·age + N(0, a) (clock.py's model), a the motion's excitation."""
    g = np.random.default_rng(seed)
    t = np.arange(T) / f
    K = len(beat)
    a = g.uniform(0.5, 2.0, (T, K)) * 1e8
    beat_t = np.asarray(beat)[None, :] + 2e-3 * t[:, None]   # 2e-3 Hz/s: the phase runs off a fixed beat
    x = np.cumsum(beat_t / f, 0) + g.random(K)[None, :]
    age = 1e-3 * (x - np.floor(x))
    b = -a * age + np.sqrt(a) * g.normal(size=(T, K))
    res = types.SimpleNamespace(time=torch.as_tensor(t), timing_a=torch.as_tensor(a), timing_b=torch.as_tensor(b),
                                f_read=f)
    return res, age


def test_tracker_is_causal_and_follows_the_clock():
    """Each block's age depends only on samples before the block: changing the statistics from a
    block on leaves the earlier blocks' ages unchanged.  With a beat drifting as the search's model
    allows, the tracked ages correlate with the truth (r > 0.8) on every block."""
    res, age = _synthetic(1)
    n_win = int(30 * 62.5)
    window = (res.time[:n_win].numpy(), res.timing_a[:n_win], res.timing_b[:n_win], 62.5)
    after = float(res.time[n_win - 1]) + 0.008
    blocks = heldout.tracked_clocks(res, window, after=after, block_s=10.0)
    tr = heldout.tracked_age(res, blocks, block_s=10.0)
    assert tr[:n_win].abs().max() == 0
    t = res.time.numpy()
    for b0, _ in blocks:
        cur = (t >= b0) & (t < b0 + 10.0)
        for k in range(age.shape[1]):
            assert np.corrcoef(tr[cur, k].numpy(), age[cur, k])[0, 1] > 0.8
    # corrupt everything from the second block on: the first block's ages do not move, the last one's do
    cut = blocks[1][0]
    bad = res.time.numpy() >= cut
    res2 = types.SimpleNamespace(**vars(res))
    res2.timing_b = res.timing_b.clone()
    res2.timing_b[bad] = torch.as_tensor(np.random.default_rng(9).normal(size=(int(bad.sum()), 1)) * 1e4)
    tr2 = heldout.tracked_age(res2, heldout.tracked_clocks(res2, window, after=after, block_s=10.0), block_s=10.0)
    torch.testing.assert_close(tr2[~bad], tr[~bad])
    assert not torch.allclose(tr2[bad], tr[bad])
    # the evidence rule keeps these clocks (they stand far above the look-elsewhere threshold)
    assert all((c["evidence"] > c["threshold"]).all() for _, c in blocks)
    torch.testing.assert_close(heldout.tracked_age(res, blocks, block_s=10.0, accept="evidence"), tr)


def test_evidence_rule_drops_clocks_under_threshold_or_out_of_width():
    """acquired_age(accept="evidence"): an IMU whose clock is under its look-elsewhere threshold, or
    whose sawtooth width is unphysical, gets the accepted IMUs' mean age (no clock after centring);
    without the rule every clock loads; with no clock accepted, no IMU has an age."""
    res = types.SimpleNamespace(time=torch.arange(0, 4, 1 / 62.5, dtype=torch.float64))
    clock = {"beat_hz": np.array([1.0, -0.5, 2.0]), "phase": np.array([0.1, 0.5, 0.9]),
             "drift_hz_per_s": np.zeros(3), "width_s": np.array([1e-3, 1e-3, 1e-5]),
             "evidence": np.array([200.0, 10.0, 500.0]), "threshold": np.full(3, 40.0)}
    every = heldout.acquired_age(res, clock)
    ruled = heldout.acquired_age(res, clock, accept="evidence")
    torch.testing.assert_close(ruled[:, 0], every[:, 0])
    torch.testing.assert_close(ruled[:, 1], every[:, 0])
    torch.testing.assert_close(ruled[:, 2], every[:, 0])
    assert not torch.allclose(every[:, 1], every[:, 0])
    assert float(heldout.centred(ruled).abs().max()) < 1e-15
    clock["evidence"][:] = 1.0
    assert float(heldout.acquired_age(res, clock, accept="evidence").abs().max()) == 0.0
