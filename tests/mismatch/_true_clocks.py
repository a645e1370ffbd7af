"""The true-clock setup the unresolved-motion tests share: clockgen's clock case 3 (mimu4444 at 62.5 Hz,
8 s, no linear errors, no drift) prepared and fitted, every IMU's clock known exactly from the generator, and
the clocks' mean effect taken off the outputs as the detector's clock stage does — so that a test is of the
unresolved term and the budget, not of the beat search."""
from __future__ import annotations

import dataclasses

import numpy as np
import torch

from accel_bayes.mismatch import baseline_fit, fit_model, prepare


class TrueClock:
    """An IMU's clock as the stage reads it (``imu``, ``age(t)``), from the generator's truth."""

    def __init__(self, imu, stamps, ages):
        self.imu, self._stamps, self._ages = imu, np.asarray(stamps), np.asarray(ages)

    def age(self, t):
        return torch.as_tensor(self._ages[np.searchsorted(self._stamps, np.asarray(t))], dtype=torch.float64)


def true_clock_case(**draw):
    """(prep, fit, truth, clocks) of the module docstring's case; ``draw``: further :func:`draw_case` switches
    (``vibration``, ``drop``)."""
    from experiments.clockgen import draw_case

    rec, truth = draw_case("clock", 3, duration=8.0, f_host=62.5, board_name="mimu4444", errors=False, drift=False,
                           **draw)
    prep = prepare(rec)
    fit, _ = baseline_fit(prep)
    clocks = [TrueClock(k, truth["pose"]["time"], truth["data_age"][:, k]) for k in range(prep.K)]
    # the clocks' mean effect off the outputs (the resolved motion seen late), as clock_corrected does
    age = torch.stack([c.age(prep.time) for c in clocks], 1)[..., None]
    prep = dataclasses.replace(prep, y_acc=(prep.y_acc + age * fit.ctx.acc_rate) * prep.m_acc,
                               y_gyro=(prep.y_gyro + age * fit.ctx.gyro_rate) * prep.m_gyro)
    return prep, fit_model(prep, [], init=fit, laplace=False), truth, clocks
