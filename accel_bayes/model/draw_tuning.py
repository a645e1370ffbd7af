"""Tuning the likelihood's Monte Carlo estimator for pseudo-marginal MH ([C21] §III-C, DESIGN §5):
the number of draws N (:func:`choose_num_draws`) and the correlation ρ of the correlated kernel
(:func:`choose_correlation`), each measured from seeded repeats at a central θ.
"""
from __future__ import annotations

import math

import torch

from ..errors import UserError
from .likelihood import RaoBlackwellLikelihood

__all__ = ["choose_num_draws", "choose_correlation"]


def choose_num_draws(
    likelihood,
    positions: torch.Tensor,
    target: float = 1.0,
    accept: tuple[float, float] = (0.1, 3.0),
    repeats: int = 40,
    start: int = 8,
    max_draws: int = 100_000,
    max_rounds: int = 4,
    seed: int = 0,
) -> tuple[int, list[dict]]:
    """Pick N so that Var[log p̂] at a central θ is ≈ ``target`` ([C21] §III-C; DESIGN §5).

    ``likelihood`` is a :class:`RaoBlackwellLikelihood` (its N is overridden per trial) or a
    factory ``N -> likelihood``; ``positions`` (A, 3) m is the central θ (e.g. the prior mean or
    the MAP).  Var[log p̂] is measured from ``repeats`` independent estimates (generator seeded
    with ``seed``) at N = ``start``; N is then extrapolated with the asymptotic 1/N law,
    N ← ceil(N · Var / target), and re-measured, until the measured variance is within a factor
    1.5 of ``target`` or ``max_rounds`` re-measurements are spent.  (The 1/N law only holds once
    Var ≲ 1; extrapolating from a tiny N overshoots, hence the re-measurement.)  [C21] aimed at
    Var ≈ 0.1; [43] of [C21] recommends ≈ 3.3 at 7 % acceptance; the default 1.0 sits between.

    Returns (N, table): N is, among the measured N whose variance lies in ``accept``, the one
    closest to ``target`` (log scale); if none did, the last N tried (check the table).
    ``table`` lists {"num_draws", "var", "repeats"} per measurement, in the order measured.
    The relative standard error of each variance is about sqrt(2/(repeats−1)) (0.23 at 40).
    """
    if not accept[0] <= target <= accept[1]:
        raise UserError(f"target: expected within accept={accept}, got {target}")
    if repeats < 3:
        raise UserError(f"repeats: expected >= 3, got {repeats}")
    is_lik = isinstance(likelihood, RaoBlackwellLikelihood)
    if not is_lik and not callable(likelihood):
        raise UserError("likelihood: expected a RaoBlackwellLikelihood or a callable N -> likelihood")

    def measure(N):
        lik = likelihood if is_lik else likelihood(N)
        gen = torch.Generator(device=lik.device)
        gen.manual_seed(int(seed) * 1_000_003 + N)
        vals = torch.stack([lik.log_phat(positions, generator=gen, num_draws=N) for _ in range(repeats)])
        return float(vals.var(0).max())

    table = []
    N = max(1, int(start))
    for _ in range(max_rounds + 1):
        v = measure(N)
        table.append({"num_draws": N, "var": v, "repeats": repeats})
        if abs(math.log(max(v, 1e-300) / target)) < math.log(1.5):
            break
        newN = int(min(max_draws, max(1, math.ceil(N * v / target))))
        if newN == N or any(row["num_draws"] == newN for row in table):
            break
        N = newN
    ok = [row for row in table if accept[0] <= row["var"] <= accept[1]]
    if not ok:
        return table[-1]["num_draws"], table
    best = min(ok, key=lambda row: abs(math.log(row["var"] / target)))
    return best["num_draws"], table


def choose_correlation(
    likelihood,
    positions: torch.Tensor,
    num_draws: int,
    target: float = 1.0,
    pairs: int = 32,
    seed: int = 0,
    min_gap: float = 1e-4,
) -> tuple[float, list[dict]]:
    """ρ of the correlated pseudo-marginal kernel (Deligiannidis, Doucet & Pitt 2018) such that
    Var[log p̂(θ, z') − log p̂(θ, z)] ≈ ``target`` at a central θ, z' = ρ z + √(1 − ρ²) ε.

    ``likelihood`` is a :class:`RaoBlackwellLikelihood` (or anything with ``sample_z`` and
    ``log_phat(positions, z=...)``); ``positions`` (A, 3) m the central θ (e.g. the MAP);
    ``num_draws`` N per estimate.  ``pairs`` seeded pairs (z, ε) (generator seeded with ``seed``,
    so the same seed gives the same ρ) are evaluated in one batch at a pilot gap
    1 − ρ = 2⁻⁸, where the variance of the difference is linear in the gap (z' − z ≈ −δz + √(2δ)ε
    for δ = 1 − ρ small: Var ≈ 2δ·E‖∇_z log p̂‖²); the gap is scaled to ``target`` by that law
    (clamped to [``min_gap``, 1]) and the variance re-measured there with the same pairs.

    Returns (ρ, table) with table rows {"rho", "var", "pairs"} in the order measured.  The
    relative standard error of each variance is about sqrt(2/(pairs−1)) (0.25 at 32).
    """
    if not target > 0:
        raise UserError(f"target: expected a variance > 0, got {target!r}")
    if int(pairs) < 3:
        raise UserError(f"pairs: expected >= 3, got {pairs!r}")
    gen = torch.Generator(device=likelihood.device)
    gen.manual_seed(int(seed) * 1_000_003 + 7 * int(num_draws) + 1)
    z = likelihood.sample_z((int(pairs),), int(num_draws), gen)
    eps = likelihood.sample_z((int(pairs),), int(num_draws), gen)
    pos = torch.as_tensor(positions, dtype=likelihood.dtype, device=likelihood.device)
    pos = pos.expand(int(pairs), *pos.shape[-2:])
    l0 = likelihood.log_phat(pos, z=z)

    def measure(gap):
        rho = 1.0 - gap
        zp = rho * z + math.sqrt(gap * (2.0 - gap)) * eps
        return float((likelihood.log_phat(pos, z=zp) - l0).var()), rho

    table = []
    pilot = 2.0 ** -8
    v, rho = measure(pilot)
    table.append({"rho": rho, "var": v, "pairs": int(pairs)})
    gap = 1.0 if not v > 0 else min(1.0, max(float(min_gap), pilot * float(target) / v))
    v, rho = measure(gap)
    table.append({"rho": rho, "var": v, "pairs": int(pairs)})
    return max(0.0, rho), table
