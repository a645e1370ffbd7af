"""The fixed set of boards the posterior defaults are judged on (issue #15 items 3 and must-show 2).

Every recording comes from the independent simulator :mod:`_conceal` (first-principles numpy,
none of the package's numerics), with no concealed effect, so that a calibrated posterior must
cover its truth.  Seeds are fixed here, once:

* :func:`random_boards` — 20 random boards: 6–10 IMUs at random positions spanning 6–16 cm
  (a plate with a few mm of height, or a 3-D block on every fourth board), Haar-random mounting
  orientations, smooth random motion (RMS |ω| 250–600 °/s), 100–250 Hz, T = 2500,
  σ_a 0.01–0.04 m/s², no rests;
* :func:`regression_boards` — the two boards of the issues: an irregular plate (7 IMUs scattered
  over about 15 cm, T = 2641, σ_a = 0.02 m/s², smooth hand-like motion; issue #15) and a 5 cm cube
  with 8 randomly yawed IMUs (250 Hz, T = 2968, σ_a = 0.012 m/s²; issue #12).

Each entry is ``(name, ConcealedCase)``; ``case.truth["true_relative_position"]`` (K, 3) m is the
truth relative to the reference IMU.
"""
from __future__ import annotations

import math

import numpy as np

if __package__:  # imported as experiments._boards (tests, from the repository root)
    from . import _conceal as cc
else:  # imported by a script run as python3 experiments/X.py, with experiments/ on sys.path
    import _conceal as cc

SEED_BASE = 15_000  # issue #15; never change: the boards are the benchmark


def _quat_yaw(yaw: float) -> np.ndarray:
    return np.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])


def random_board(i: int) -> cc.Board:
    """Board ``i`` of the random set (positions in m, quaternions array → sensor)."""
    rng = np.random.default_rng(SEED_BASE + i)
    K = int(rng.integers(6, 11))
    span = float(rng.uniform(0.06, 0.16))
    height = span if i % 4 == 3 else float(rng.uniform(0.0, 0.006))
    pos = rng.uniform(-0.5, 0.5, size=(K, 3)) * np.array([span, span, height])
    # spread: the largest pairwise distance is the span (rescale the x-y footprint)
    d = np.linalg.norm(pos[:, None, :2] - pos[None, :, :2], axis=-1).max()
    pos[:, :2] *= span / d
    pos -= pos[0]
    q = rng.standard_normal((K, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 0] < 0] *= -1
    return cc.Board(f"random{i:02d}", pos, q, 0)


def random_boards(n: int = 20):
    """[(name, case)] for the ``n`` random boards (recordings generated here, seconds each)."""
    out = []
    for i in range(n):
        b = random_board(i)
        case = cc.make_case(b, "none", seed=SEED_BASE + 100 + i, T=2500)
        out.append((b.name, case))
    return out


def plate7() -> cc.Board:
    """The irregular plate of issue #15: 7 IMUs scattered over about 15 cm, random orientations."""
    rng = np.random.default_rng(SEED_BASE + 900)
    pos = np.column_stack([rng.uniform(-0.075, 0.075, 7), rng.uniform(-0.05, 0.05, 7), rng.uniform(-0.002, 0.002, 7)])
    pos -= pos[0]
    q = rng.standard_normal((7, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 0] < 0] *= -1
    return cc.Board("plate7", pos, q, 0)


def cube8() -> cc.Board:
    """The 5 cm cube of issue #12: 8 IMUs on the corners, each yawed at random."""
    rng = np.random.default_rng(SEED_BASE + 901)
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=float) * 0.05
    q = np.array([_quat_yaw(float(a)) for a in rng.uniform(-math.pi, math.pi, 8)])
    return cc.Board("cube8", corners, q, 0)


def regression_boards():
    """[(name, case)] for the two regression boards of the issues."""
    return [("plate7", cc.make_case(plate7(), "none", seed=SEED_BASE + 910, T=2641, rate=180.0, sigma_a=0.02)),
            ("cube8", cc.make_case(cube8(), "none", seed=SEED_BASE + 911, T=2968, rate=250.0, sigma_a=0.012))]


def all_boards(n: int = 20):
    return random_boards(n) + regression_boards()
