"""The covariates the per-sample-covariance likelihood (:mod:`.likelihood_percov`) reads from the
data and from a report, fixed before any θ: each triad's data age from the sampling clocks
(:func:`ages_from_clocks`), a per-sample scale from a per-|ω|-band one (:func:`band_scale`) and the
rate of each triad's output (:func:`triad_rates`).  Re-exported by :mod:`.likelihood_percov`."""
from __future__ import annotations

import numpy as np
import torch

from ..errors import UserError

__all__ = ["ages_from_clocks", "band_scale", "triad_rates"]


def band_scale(omega_norm, edges, rms, field: str = "jerk_rms") -> torch.Tensor:
    """s_t (T,) per sample from a per-|ω|-band scale: ``edges`` the B − 1 inner band edges
    (rad/s, ascending, as the ``unresolved_motion`` finding's ``omega_edges``), ``rms`` (B,) the
    band's scale (``jerk_rms`` m/s³ or ``angular_acc_rms`` rad/s², named by ``field`` in errors),
    ``omega_norm`` (T,) rad/s.  Band b holds edges[b−1] ≤ |ω| < edges[b]."""
    w = torch.as_tensor(np.asarray(omega_norm, dtype=np.float64))
    try:
        e = torch.as_tensor(np.asarray(edges, dtype=np.float64)).reshape(-1)
        v = torch.as_tensor(np.asarray(rms, dtype=np.float64)).reshape(-1)
    except (TypeError, ValueError):
        raise UserError(f"{field}: expected numbers per |omega| band and numeric omega_edges") from None
    if len(v) != len(e) + 1:
        raise UserError(f"{field}: expected {len(e) + 1} values for {len(e)} band edges, got {len(v)}")
    if not bool(torch.isfinite(v).all()) or bool((v < 0).any()):
        raise UserError(f"{field}: expected finite values >= 0")
    if not bool(torch.isfinite(e).all()) or bool((e[1:] < e[:-1]).any()):
        raise UserError("omega_edges: expected finite band edges in ascending order (rad/s)")
    return v[torch.bucketize(w, e, right=True)]


def ages_from_clocks(time, clocks: dict, labels, sensor: str = "acc") -> torch.Tensor:
    """The data ages (T, len(labels)) s of the rows ``labels`` (IMU labels) at the read times
    ``time`` (T,) s (the recording's own time axis), from ``clocks`` {IMU label:
    :class:`~accel_bayes.physics.effects.clock.SamplingClock`}.  ``sensor="acc"`` adds each
    clock's acc − gyro filter delay.  IMUs without a clock get age 0 here; a report's calibration
    gives them an age prior instead (:func:`.report_terms.unresolved_terms`)."""
    if sensor not in ("acc", "gyro"):
        raise UserError(f"sensor: expected 'acc' or 'gyro', got {sensor!r}")
    t = torch.as_tensor(np.asarray(time, dtype=np.float64))
    out = torch.zeros(len(t), len(labels), dtype=torch.float64)
    for j, k in enumerate(labels):
        clock = clocks.get(int(k))
        if clock is None:
            continue
        out[:, j] = clock.physical_age(t)  # the hold's sawtooth: what the report's scales were fitted on
        if sensor == "acc":
            out[:, j] += float(clock.params["filter_delay_acc_minus_gyro_s"])
    return out


def triad_rates(acc, time, sample_scale=None) -> torch.Tensor:
    """ρ (T, A, 3) m/s³: the rate of each triad's output ``acc`` (T, A, 3) m/s² (any one frame) at
    the read times ``time`` (T,) s, by the second-order differences of
    :func:`~accel_bayes.physics.effects.output_rates` within each run of contiguous samples (the
    rates the clocks' mean correction uses).  ``sample_scale`` (T,): the data were divided by it
    (a noise model's per-sample scale); the rate is taken in physical units and divided again.

    Why the outputs' own rate is the instant error's loading: a triad read at t + ε errs by ε times
    the rate of its specific force — the board's jerk, ω̈ × r_k and the rotation terms, which grow
    with |ω| and |ω̇| and differ by triad — and the outputs at 62.5 Hz resolve that rate to their
    noise (σ√2/(2Δt) ≈ 70 m/s³ against rates of 10³–10⁴ m/s³); an interior central difference does
    not use the sample itself, so the loading is independent of that sample's white noise."""
    from ..physics.effects import output_rates

    acc = torch.as_tensor(acc, dtype=torch.float64)
    sc = torch.ones(acc.shape[0], dtype=acc.dtype) if sample_scale is None else \
        torch.as_tensor(np.asarray(sample_scale, dtype=np.float64))
    phys = acc * sc[:, None, None]
    return output_rates(torch.as_tensor(np.asarray(time, dtype=np.float64)), phys, phys[:, :1])[0] / sc[:, None, None]
