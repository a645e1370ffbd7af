"""The accelerometer's filter delay beyond the gyroscope's, ``filter_delay_acc_minus_gyro_s`` of
``sampling_clock`` (DESIGN §7.2 vocabulary 1.2; issue #27 item 2): estimated where the data
identify it, else reported null with the reason.

Physics.  Each IMU's digital low-pass delays its accelerometer by τ_a and its gyroscope by τ_g
(MPU-6050/9150 setting 2: 3.0 and 2.8 ms).  On a rigid board the common delay is absorbed by the
motion, and only Δ = τ_a − τ_g shows: linearised like the clock's age (:class:`SamplingClock`),
the accelerometer reads −Δ·ȧ more than the model, ȧ its fitted output rate.  The part of −Δ·ȧ common
to the IMUs is absorbed by each sample's specific force; what identifies Δ is the lever-arm part
(ω̇ × r_k + ω × ω × r_k differs between IMUs), small at slow motion.

Estimate.  One Δ for the board's clocked IMUs (one part type, one filter setting): the weighted
least-squares slope of the final fit's whitened accelerometer residuals on the regressor −ȧ, both
projected off the per-sample motion states (:func:`~accel_bayes.mismatch.model.project_off_states`,
the efficient information of :mod:`accel_bayes.mismatch.screens` without the geometry's small
share).  Its standard error is scaled by √max(1, P), P the mean leverage-corrected z² of those
residuals (the model misses far more than the stated noise on real data).  Identified when the
information is not singular (relative size ≥ 1e-8, as in the screens), the standard error is at
most :data:`IDENTIFIED_STD_S` — half the datasheet difference, so a value reported means the data
tell the datasheet's 0.2 ms from none — and the two halves of the recording agree (their
estimates within 3 combined standard errors).

Reported, not applied: the detector does not correct the recording for Δ.  Measured on the
first-principles generator (``experiments/clockgen``, seed 3, MIMU4444 at 62.5 Hz, 20 s; true Δ
+0.2 ms plus the filters' different group delays): with the true clocks taken off, the standard
error is 0.47 ms (no vibration) and 1.4 ms (with vibration) — not identified; inside ``detect``
(clocks on 5 of 8 IMUs, a wander on the others) the single estimate was −0.24 ms with a standard
error under 0.1 ms: the lever-arm signal is small enough for unmodelled timing on the other IMUs
to bias it, which the halves check is there to catch.
"""
from __future__ import annotations

import math

import torch

from .model import ModelFit, project_off_states
from .prepared import Prepared

__all__ = ["filter_delay", "IDENTIFIED_STD_S"]

#: the largest standard error (s) of an identified Δ: half the MPU-6050/9150 datasheet's 0.2 ms
IDENTIFIED_STD_S = 1.0e-4


def filter_delay(prep: Prepared, fit: ModelFit, imus) -> dict:
    """{"value_s", "std_s", "identified", "reason"} of Δ = τ_acc − τ_gyro (s, positive = the
    accelerometer lags) on the IMUs ``imus`` at ``fit`` (module docstring); ``value_s`` is None
    where not identified, and ``reason`` says why (else None)."""
    imus = sorted(int(k) for k in imus)
    if not imus:
        return {"value_s": None, "std_s": None, "identified": False, "reason": "no IMU with an accepted clock"}
    rate = fit.ctx.acc_rate
    if rate is None:
        return {"value_s": None, "std_s": None, "identified": False, "reason": "no accelerometer output rates"}
    lin = fit.linear()
    T, K = prep.T, prep.K
    sig = (prep.sigma_acc * fit.acc_factor)[None, :, None]
    E = torch.zeros(T, 2, K, 3, dtype=lin.r.dtype)
    sel = torch.zeros(K, dtype=torch.bool)
    sel[imus] = True
    E[:, 0] = -rate.to(lin.r.dtype) / sig * prep.m_acc * sel[None, :, None]
    E = E.reshape(T, -1)
    raw = float((E ** 2).sum())
    Et = project_off_states(lin.Jx, lin.Vinv, E)
    info = float((Et ** 2).sum())
    if raw <= 0 or info / raw < 1e-8:
        return {"value_s": None, "std_s": None, "identified": False,
                "reason": "the motion states absorb −Δ·ȧ entirely (no lever-arm signal)"}
    g_t = (Et * lin.r).sum(1)
    i_t = (Et ** 2).sum(1)
    u = float(g_t.sum())
    value = u / info
    z2 = (lin.r ** 2 / (1 - lin.h).clamp_min(1e-3)).reshape(T, 2, K, 3)[:, 0]
    m = prep.m_acc * sel[None, :, None]
    power = float((z2 * m).sum() / m.sum().clamp_min(1))
    std = math.sqrt(max(power, 1.0) / info)
    if std > IDENTIFIED_STD_S:
        return {"value_s": None, "std_s": std, "identified": False, "estimate_s": value,
                "reason": f"standard error {std * 1e3:.3g} ms > {IDENTIFIED_STD_S * 1e3:.3g} ms: the motion's lever-arm "
                          "part does not tell the datasheet's 0.2 ms difference from none"}
    # the two halves of the recording must agree: a bias from unmodelled timing elsewhere on the
    # board moves with the motion, a filter's delay does not
    halves = []
    for idx in torch.arange(T).chunk(2):
        ih = float(i_t[idx].sum())
        halves.append((float(g_t[idx].sum()) / ih, math.sqrt(max(power, 1.0) / ih)) if ih > 0 else (math.nan, math.inf))
    (v1, s1), (v2, s2) = halves
    if not abs(v1 - v2) <= 3 * math.hypot(s1, s2):
        return {"value_s": None, "std_s": std, "identified": False, "estimate_s": value, "halves_s": [v1, v2],
                "reason": f"the two halves of the recording disagree ({v1 * 1e3:+.3g} and {v2 * 1e3:+.3g} ms, > 3 "
                          "combined standard errors): the lever-arm signal is biased by other timing errors"}
    return {"value_s": value, "std_s": std, "identified": True, "reason": None, "halves_s": [v1, v2]}

