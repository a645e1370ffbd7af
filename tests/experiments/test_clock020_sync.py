"""The oracles of ``experiments/clock020_sync.py``: the synchronisation takes off exactly the data-age
effect it names (all orders, or the orders ≥ 2), checked on signals whose Taylor series is known, and
the case list parser."""
import numpy as np
from scipy.interpolate import CubicSpline

from experiments import clock020_sync as cs


def _splines(coef, grid):
    """Per IMU a cubic spline of the quadratic a + b t + c t² (3 axes), which a cubic spline reproduces exactly."""
    return [CubicSpline(grid, a + np.outer(grid, b) + np.outer(grid ** 2, c)) for a, b, c in coef]


def test_synchronised_takes_off_the_age_effect_to_the_order_it_names():
    rng = np.random.default_rng(3)
    K, T = 3, 40
    grid = np.linspace(-1.0, 2.0, 3001)
    coef = [tuple(rng.normal(size=(3, 3))) for _ in range(K)]
    S = _splines(coef, grid)
    tick = np.sort(rng.uniform(0.0, 1.0, T))[:, None] + rng.uniform(-1e-3, 1e-3, (T, K))
    tbar = tick.mean(1)
    Q = np.stack([np.linalg.qr(rng.normal(size=(3, 3)))[0] for _ in range(K)])
    every = cs.synchronised(S, tick, tbar, Q)
    higher = cs.synchronised(S, tick, tbar, Q, first_order=True)
    for k, (a, b, c) in enumerate(coef):
        d = tick[:, k] - tbar
        # F(tick) − F(t̄) of a quadratic: d (b + 2 c t̄) + d² c, in the sensor frame (rows @ Qᵀ)
        first = d[:, None] * (b + 2 * tbar[:, None] * c)
        second = (d ** 2)[:, None] * c
        np.testing.assert_allclose(every[:, k], (first + second) @ Q[k].T, atol=1e-10)
        np.testing.assert_allclose(higher[:, k], second @ Q[k].T, atol=1e-10)


def test_case_list():
    assert cs._cases("0-3,7") == [0, 1, 2, 3, 7]
    assert cs._cases("") == []
