"""Benchmark: one Rao-Blackwellized log-likelihood evaluation (DESIGN §4, §7.4).

Ours (:meth:`RaoBlackwellLikelihood.log_phat`: per-sample projection once, O(1)-in-A work per
draw) against the straightforward dense form of [C21] eq. 26: S formed densely (3A × 3A), every
‖y_t − G u(ω_t^(n))‖²_S as a dense quadratic form (batched matrix products over the draws,
chunked over t to bound memory), with the correct −½ log|M|.  Both include drawing the
3·T·N standard normals (same sampler), both use the same thread count, and both are checked to
give the same value on the same draws.

Setting: 32-IMU MIMU4444 (arrays.mimu4444_32), T = 500, N = 1000, [C21] §IV-A i.i.d. motion
(ω 1000 °/s, ω̇ 35000 °/s², s 20 m/s²), σ_a = 0.04 m/s², σ_g = 0.06 °/s, no clipping,
calibrated-gyro posterior N(mean of 32 gyros, Q_g/32), θ = the true (nominal) positions.

Also prints Var[log p̂] at N = 1 for σ_a = 0.79 and 0.04 m/s² (DESIGN §4 quotes ~4e-4 and ~0.09).

    python experiments/bench_likelihood.py [--threads 1] [--reps 9] [--dense-reps 3]
"""
from __future__ import annotations

import argparse
import math
import statistics
import time

import torch

from accel_bayes.physics.arrays import mimu4444_32
from accel_bayes.model.likelihood import RaoBlackwellLikelihood
from accel_bayes.physics.models import G_matrix, H_matrix, u_of_omega
from accel_bayes.simulate import simulate


def dense_eq26(lik: RaoBlackwellLikelihood, positions: torch.Tensor, z: torch.Tensor, chunk: int = 25) -> torch.Tensor:
    """[C21] eq. 26 with the −½ power, the straightforward way (the peer)."""
    r = positions - positions[lik.reference]
    H, G = H_matrix(r), G_matrix(r)
    Lam = torch.diag(lik.lam)
    M = H.T @ Lam @ H
    S = Lam - Lam @ H @ torch.linalg.solve(M, H.T @ Lam)  # 3A × 3A
    N = z.shape[-2]
    total = torch.zeros((), dtype=lik.dtype)
    for t0 in range(0, lik.T, chunk):
        t1 = min(lik.T, t0 + chunk)
        om = lik.omega.mean[t0:t1, None, :] + z[t0:t1] @ lik.omega_chol[t0:t1].transpose(-1, -2)
        res = lik.y[t0:t1, None, :] - u_of_omega(om) @ G.T  # (τ, N, 3A)
        q = ((res @ S) * res).sum(-1)
        total = total + (torch.logsumexp(-0.5 * q, -1) - math.log(N)).sum()
    return total - 0.5 * lik.T * torch.linalg.slogdet(M)[1]


def timed(fn, reps):
    """(last output, wall-clock seconds, process CPU seconds) of ``reps`` calls."""
    out, wall, cpu = None, [], []
    for _ in range(reps):
        c0, t0 = time.process_time(), time.perf_counter()
        out = fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return out, wall, cpu


def make_lik(sigma_a, T, N, seed):
    arr = mimu4444_32()
    sim = simulate(arr, "iid", T=T, seed=seed, position_error_std=0.0, acc_noise_std=sigma_a, clip=False)
    lik = RaoBlackwellLikelihood.from_recording(sim.recording, num_draws=N, gyro_method="calibrated")
    pos = sim.true_positions[list(lik.imu_labels)]
    return lik, pos


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--threads", type=int, default=1, help="torch threads for both (default 1)")
    ap.add_argument("--T", type=int, default=500)
    ap.add_argument("--N", type=int, default=1000)
    ap.add_argument("--reps", type=int, default=9, help="repetitions of ours (median reported)")
    ap.add_argument("--dense-reps", type=int, default=3, help="repetitions of the dense peer")
    ap.add_argument("--var-reps", type=int, default=400, help="replicates for Var[log p̂] at N = 1")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    print(f"threads={torch.get_num_threads()}  T={args.T}  N={args.N}  A=32  torch {torch.__version__}")

    lik, pos = make_lik(0.04, args.T, args.N, args.seed)
    gen = torch.Generator().manual_seed(args.seed + 1)

    # correctness on common draws
    z = lik.sample_z(generator=torch.Generator().manual_seed(args.seed + 2))
    v_ours = float(lik.log_phat(pos, z=z))
    v_dense = float(dense_eq26(lik, pos, z))
    print(f"value on common draws: ours {v_ours:.9f}  dense {v_dense:.9f}  |diff| {abs(v_ours - v_dense):.2e}"
          f"  (relative {abs(v_ours - v_dense) / abs(v_dense):.1e})")
    assert abs(v_ours - v_dense) <= 1e-9 * abs(v_dense) + 1e-6, "ours and the dense form disagree"

    lik.log_phat(pos, generator=gen)  # warm-up
    # Interleaved (one dense run, then a block of ours) so both see the same machine load.
    t_ours, c_ours, t_dense, c_dense = [], [], [], []
    per = max(1, math.ceil(args.reps / args.dense_reps))
    for _ in range(args.dense_reps):
        _, w, c = timed(lambda: dense_eq26(lik, pos, lik.sample_z(generator=gen)), 1)
        t_dense += w
        c_dense += c
        _, w, c = timed(lambda: lik.log_phat(pos, generator=gen), per)
        t_ours += w
        c_ours += c
    _, t_z, _ = timed(lambda: lik.sample_z(generator=gen), args.reps)
    _, t_fixed, _ = timed(lambda: lik.log_phat(pos, z=z), args.reps)
    P8 = pos + 1e-4 * torch.randn(8, *pos.shape, generator=gen, dtype=pos.dtype)
    _, t_b8, _ = timed(lambda: lik.log_phat(P8, generator=gen), max(3, args.reps // 3))
    med = lambda ts: 1e3 * statistics.median(ts)  # noqa: E731
    print(f"ours  (draws + estimate):   median {med(t_ours):8.1f} ms  (min {1e3 * min(t_ours):.1f}, "
          f"{len(t_ours)} reps; CPU time median {med(c_ours):.1f} ms)")
    print(f"  of which drawing z:       median {med(t_z):8.1f} ms")
    print(f"  estimate on given z:      median {med(t_fixed):8.1f} ms")
    print(f"  8 positions, shared z:    median {med(t_b8):8.1f} ms  ({med(t_b8) / 8:.1f} ms per θ)")
    print(f"dense eq. 26 (draws + est): median {med(t_dense):8.1f} ms  (min {1e3 * min(t_dense):.1f}, "
          f"{len(t_dense)} reps; CPU time median {med(c_dense):.1f} ms)")
    print(f"speedup by CPU time: {med(c_dense) / med(c_ours):.1f}x  (wall clock below)")

    # Var[log p̂] at N = 1, calibrated gyro posterior (32 gyros averaged)
    for sigma_a in (0.79, 0.04):
        lk, ps = make_lik(sigma_a, args.T, 1, args.seed)
        vals = lk.log_phat(ps.expand(args.var_reps, *ps.shape), generator=torch.Generator().manual_seed(7),
                           independent_draws=True)
        v = float(vals.var())
        se = v * math.sqrt(2 / (args.var_reps - 1))
        print(f"Var[log p̂] at N=1, sigma_a={sigma_a}: {v:.3g} (± {se:.1g}, {args.var_reps} replicates, T={args.T})")

    ours_ms, dense_ms = med(t_ours), med(t_dense)
    print(f"RESULT likelihood_eval_A32_T{args.T}_N{args.N}: ours {ours_ms:.1f} ms, dense_eq26 {dense_ms:.1f} ms, "
          f"speedup {dense_ms / ours_ms:.1f}x")


if __name__ == "__main__":
    main()
