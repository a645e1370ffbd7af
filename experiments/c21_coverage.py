#!/usr/bin/env python3
"""Coverage / simulation-based calibration study of the posterior (issue #3, MUST-SHOW "Coverage").

For each of ``--n`` data sets (default 100):

* θ_true is drawn from the prior the calibration uses (N(design, σ_r²) with σ_r = 3 mm, IMU 0 the
  reference), on a 4-IMU, 20 mm square board (A = 4, 9 free coordinates: small enough for many
  data sets);
* T = 30 samples of [C21] §IV-A-style i.i.d. motion (ω 500 °/s, ω̇ 5000 °/s², s 20 m/s² per
  axis), σ_a = 0.3 m/s², σ_g = 0.06 °/s (posterior std ≈ 0.2–0.7 mm: informative, not degenerate);
* the posterior is sampled by the package's PmMH kernel, set up as ``calibrate`` sets it up
  (MAP-centred Laplace shape for the random walk and the independence moves, automatic N), with
  **chains started from prior draws**, never from the truth or the MAP.

Which posterior?  [C21] puts a flat prior on φ_t = [ω̇_t; s_t]; no simulation can draw φ from
it, and the data-generating φ ~ N(0, F) is not harmless: under it the exact posterior has a
φ̂ᵀF⁻¹φ̂ term (ω̇̂ grows as the array shrinks) that offsets the flat model's −(T/2)·log|M(θ)|
(|M| grows like the squared array size).  ``--phi-model``:

* ``empirical`` (default) — the package default: a Gaussian prior on φ whose 6×6 covariance is
  estimated from each data set (:func:`accel_bayes.model.phi_prior.empirical_phi_prior`, at the
  design positions, as ``calibrate`` does).  Here the checks ask whether the default model is
  calibrated, F̂ from only T = 30 samples included;
* ``matched`` — the simulation's own Gaussian prior on φ (``RaoBlackwellLikelihood(phi_prior=…)``,
  M → M + F⁻¹, checked against a dense Gaussian in tests/model/test_likelihood.py), so the sampled
  posterior is exact for the generating process: this validates the likelihood estimator, the
  pseudo-marginal kernel and its adaptation together;
* ``flat`` — [C21] as published, on the same data: measures how much the flat prior shrinks the
  array when rotation is weak relative to the noise (a property of the model, not the sampler).

Checks (printed as a verdict, and asserted by ``tests/experiments/test_coverage.py -m slow``):

1. every data set reaches R̂ < 1.01 (max over the 9 coordinates);
2. the central 90 % interval of the pre-chosen coordinate x of IMU 1 (relative to IMU 0) covers the
   truth in a number of data sets inside the binomial(n, 0.9) central 99 % band;
3. simulation-based-calibration ranks: for each coordinate, the truth's rank among L = 99 thinned
   pooled draws is uniform on {0..99} if the posterior is right (Talts et al. 2018).  Tested by a
   χ² test on 10 bins per coordinate with a Bonferroni-corrected level 0.01/9, and pooled over all
   coordinates at level 0.01.

Results are appended to ``OUT/replicates.jsonl`` one line per data set, so an interrupted run
resumes where it stopped (same options → same data sets and seeds).  The rank histograms go to
``OUT/ranks.png``.

Usage::

    python experiments/c21_coverage.py                       # 100 data sets, the default (empirical) φ prior
    python experiments/c21_coverage.py --phi-model matched   # the simulation's own φ prior (exact posterior)
    python experiments/c21_coverage.py --phi-model flat      # [C21]'s flat prior on the same data sets
    python experiments/c21_coverage.py --n 10 --workers 2
"""
from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from _dask import add_dask_arguments, dask_client, map_tasks  # noqa: E402
from accel_bayes.constants import DEFAULT_PRIOR_STD, DEG_TO_RAD  # noqa: E402

COORDS = [(k, ax) for k in (1, 2, 3) for ax in "xyz"]
STUDY_COORD = (1, "x")
L_RANK = 99


def square_board(acc_std: float = 0.3):
    """4 IMUs at the corners of a 20 mm square, all with accelerometers and gyroscopes."""
    import torch

    from accel_bayes.physics.arrays import SensorArray

    K = 4
    pos = torch.tensor([[0, 0, 0], [0.02, 0, 0], [0, 0.02, 0], [0.02, 0.02, 0.0]], dtype=torch.float64)
    return SensorArray(positions=pos, orientations=torch.tensor([[1.0, 0, 0, 0]] * K, dtype=torch.float64),
                       has_acc=torch.ones(K, dtype=torch.bool), has_gyro=torch.ones(K, dtype=torch.bool),
                       acc_noise_std=torch.full((K,), acc_std, dtype=torch.float64),
                       gyro_noise_std=torch.full((K,), 0.06 * DEG_TO_RAD, dtype=torch.float64),
                       name="square4", package_size=4e-3)


OMEGA_STD = 500 * DEG_TO_RAD  # rad/s per axis
OMEGA_DOT_STD = 5000 * DEG_TO_RAD  # rad/s² per axis
S_STD = 20.0  # m/s² per axis (motion.iid_motion default)
PHI_MODELS = ("empirical", "matched", "flat")


def replicate(i: int, T: int = 30, prior_std: float = DEFAULT_PRIOR_STD, chains: int = 4, draws: int = 1000,
              warmup: int = 400, phi_model: str = "empirical") -> dict:
    """One data set: simulate from the prior, sample the posterior from prior draws, return
    ranks/coverage.  Seeds: θ_true from 10 000 + i, the recording from 20 000 + i, chains from i.

    phi_model : "empirical" — the package default (module docstring);
        "matched" — the likelihood carries the Gaussian prior on φ_t = [ω̇_t; s_t] the
        simulation draws from (``phi_prior``), so the sampled posterior is the exact one of
        the generating process and SBC must pass; "flat" — [C21]'s flat prior on φ, whose
        −(T/2)·log|M(θ)| factor is not compensated by the simulated φ and shrinks the array.

    The sampler is the package's PmMH kernel set up as :func:`accel_bayes.pipelines.calibrate.calibrate` sets it up:
    random walk shaped by the Laplace covariance at the mode, mixed 80 % with independence moves
    from that Laplace approximation; N chosen by :func:`accel_bayes.model.draw_tuning.choose_num_draws`.
    The mode is the package MAP of the same target (``fit_map(phi_prior=…)``).
    """
    import torch

    from accel_bayes.diagnostics import arviz_calls as dg_az
    from accel_bayes.inference.map import fit_map
    from accel_bayes.inference.mcmc import PMMHKernel, run_pmmh
    from accel_bayes.inference.mcmc.priors import GaussianPrior
    from accel_bayes.model.draw_tuning import choose_num_draws
    from accel_bayes.model.likelihood import RaoBlackwellLikelihood
    from accel_bayes.model.phi_prior import empirical_phi_prior
    from accel_bayes.simulate import simulate

    if phi_model not in PHI_MODELS:
        raise ValueError(f"phi_model: expected one of {PHI_MODELS}, got {phi_model!r}")
    arr = square_board()
    g = torch.Generator().manual_seed(10_000 + i)
    true = arr.positions.clone()
    true[1:] += prior_std * torch.randn(3, 3, generator=g, dtype=torch.float64)
    s = simulate(arr, "iid", T, seed=20_000 + i, true_positions=true, clip=False,
                 motion_kwargs=dict(omega_std=OMEGA_STD, omega_dot_std=OMEGA_DOT_STD, s_std=S_STD))
    t0 = time.perf_counter()
    lik = RaoBlackwellLikelihood.from_recording(
        s.recording, num_draws=1, gyro_method="calibrated",
        phi_prior=(OMEGA_DOT_STD, S_STD) if phi_model == "matched" else None)
    if phi_model == "empirical":
        lik = lik.with_phi_prior(empirical_phi_prior(lik.acc, lik.omega.mean, lik.acc_noise_std, arr.positions))
    prior = GaussianPrior(arr.positions, std=prior_std, reference=0)
    N, _ = choose_num_draws(lik, arr.positions, target=1.0)
    lik.num_draws = int(N)
    # The random walk's shape and the independence moves come from the Laplace covariance at the
    # MAP of the same target (its φ prior included), as in calibrate().  Chains start from the prior.
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        fit = fit_map(lik.acc, lik.omega.mean, lik.omega.cov, lik.acc_noise_std, reference=0,
                      prior_mean=arr.positions, prior_std=prior_std, on_divergence="ignore", phi_prior=lik.phi_prior)
    centre = torch.as_tensor(fit.theta, dtype=torch.float64)
    lap = torch.as_tensor(fit.laplace_cov, dtype=torch.float64)
    lap = 0.5 * (lap + lap.T)
    kernel = PMMHKernel(lik, prior, seed=i, proposal_cov=lap, independence_prob=0.8,
                        independence_mean=centre, independence_cov=lap)
    init = prior.sample((chains,), generator=torch.Generator().manual_seed(30_000 + i))
    run = run_pmmh(kernel, draws, warmup, chains, init, progress=False)
    idata = dg_az.to_inference_data(run.theta, [1, 2, 3], run.log_phat, log_prior=run.log_prior)
    post = idata.posterior["r"]
    ranks, covered = {}, None
    for k, ax in COORDS:
        x = post.sel(imu=k, axis=ax).values.ravel()
        t = float(true[k, "xyz".index(ax)] - true[0, "xyz".index(ax)])
        thin = x[:: max(1, len(x) // L_RANK)][:L_RANK]  # spaced draws: near-independent for SBC
        ranks[f"{k}{ax}"] = int((thin < t).sum())
        if (k, ax) == STUDY_COORD:
            lo, hi = np.quantile(x, [0.05, 0.95])
            covered = bool(lo <= t <= hi)
    return {"i": i, "ranks": ranks, "covered": covered, "rhat": dg_az.rhat_max(idata), "ess_bulk_min": dg_az.ess_bulk_min(idata),
            "num_draws": int(N), "seconds": time.perf_counter() - t0, "phi_model": phi_model,
            "acceptance": float(run.accepted.double().mean()),
            "T": T, "chains": chains, "draws": draws, "warmup": warmup}


def verdict(reps: list[dict], alpha: float = 0.01) -> dict:
    """The three checks of the module docstring on a list of :func:`replicate` results."""
    import scipy.stats

    n = len(reps)
    rh = np.array([r["rhat"] for r in reps], dtype=float)
    cov = int(sum(r["covered"] for r in reps))
    lo, hi = scipy.stats.binom.ppf([alpha / 2, 1 - alpha / 2], n, 0.9)
    names = [f"{k}{ax}" for k, ax in COORDS]
    counts = {c: np.bincount(np.array([r["ranks"][c] for r in reps]) * 10 // (L_RANK + 1), minlength=10)
              for c in names}
    p_coord = {c: float(scipy.stats.chisquare(counts[c]).pvalue) for c in names}
    pooled = sum(counts.values())
    p_pooled = float(scipy.stats.chisquare(pooled).pvalue)
    return {"n": n, "rhat_max": float(np.nanmax(rh)), "rhat_ok": bool((rh < 1.01).all()),
            "covered": cov, "band": (int(lo), int(hi)), "coverage_ok": bool(lo <= cov <= hi),
            "rank_counts": {c: v.tolist() for c, v in counts.items()}, "rank_p": p_coord,
            "rank_p_min": min(p_coord.values()), "ranks_ok": min(p_coord.values()) > alpha / len(names),
            "rank_p_pooled": p_pooled, "pooled_ok": p_pooled > alpha}


def plot_ranks(v: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(v["rank_counts"])
    fig, axes = plt.subplots(3, 3, figsize=(9, 7), sharex=True, sharey=True)
    n = v["n"]
    import scipy.stats

    lo, hi = scipy.stats.binom.ppf([0.005, 0.995], n, 0.1)
    for ax, c in zip(axes.ravel(), names):
        ax.bar(np.arange(10) * 10 + 5, v["rank_counts"][c], width=9, color="tab:blue")
        ax.axhspan(lo, hi, color="0.85", zorder=0)
        ax.set_title(f"IMU {c[0]} {c[1]}  (χ² p = {v['rank_p'][c]:.2f})", fontsize=9)
    for ax in axes[-1]:
        ax.set_xlabel(f"rank of truth among {L_RANK} draws")
    fig.suptitle(f"SBC rank histograms, {n} data sets (grey: binomial 99 % band per bin)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--n", type=int, default=100, help="data sets (default 100)")
    p.add_argument("--T", type=int, default=30, help="samples per data set (default 30)")
    p.add_argument("--chains", type=int, default=4)
    p.add_argument("--draws", type=int, default=1000)
    p.add_argument("--warmup", type=int, default=400)
    p.add_argument("--phi-model", choices=PHI_MODELS, default="empirical",
                   help="likelihood's prior on φ = [ω̇; s]: 'empirical' (the package default, estimated from each "
                        "data set), 'matched' (the simulation's Gaussian: exact SBC) or 'flat' ([C21]: measures its "
                        "scale shrinkage)")
    p.add_argument("--out", type=Path, default=None, help="default experiments/out/c21_coverage_<phi-model>")
    add_dask_arguments(p, default_workers=1)
    args = p.parse_args(argv)
    if args.out is None:
        args.out = HERE / "out" / f"c21_coverage_{args.phi_model}"
    args.out.mkdir(parents=True, exist_ok=True)
    store = args.out / "replicates.jsonl"
    settings = dict(T=args.T, chains=args.chains, draws=args.draws, warmup=args.warmup, phi_model=args.phi_model)
    done = {}
    if store.exists():
        for line in store.read_text().splitlines():
            r = json.loads(line)
            if all(r.get(k) == v for k, v in settings.items()):
                done[r["i"]] = r
    todo = [dict(i=i, **settings) for i in range(args.n) if i not in done]
    print(f"[c21_coverage] {len(done)} data sets already in {store}, {len(todo)} to run; settings {settings}")
    t0 = time.perf_counter()
    if todo:
        with dask_client(args) as client:
            # Submit in small batches so every finished batch is on disk before the next starts.
            for b in range(0, len(todo), 4):
                for r in map_tasks(client, replicate, todo[b:b + 4], desc=f"data sets {b + 1}–{b + len(todo[b:b + 4])}"):
                    with store.open("a") as fh:
                        fh.write(json.dumps(r) + "\n")
                    done[r["i"]] = r
    reps = [done[i] for i in sorted(done) if i < args.n]
    v = verdict(reps)
    plot_ranks(v, args.out / "ranks.png")
    (args.out / "verdict.json").write_text(json.dumps(v, indent=1))
    secs = np.array([r["seconds"] for r in reps])
    print(f"\n{v['n']} data sets (this run {time.perf_counter() - t0:.0f} s; calibrate {np.median(secs):.1f} s median each)")
    print(f"  R̂ < 1.01 on every data set: {'YES' if v['rhat_ok'] else 'NO'} (max {v['rhat_max']:.4f})")
    print(f"  90 % interval of r[1,x] covers the truth: {v['covered']}/{v['n']}, binomial 99 % band "
          f"{v['band'][0]}–{v['band'][1]}: {'YES' if v['coverage_ok'] else 'NO'}")
    print(f"  SBC ranks uniform per coordinate (χ², 10 bins, Bonferroni 0.01/9): "
          f"{'YES' if v['ranks_ok'] else 'NO'} (min p {v['rank_p_min']:.3f}); pooled p {v['rank_p_pooled']:.3f}")
    print(f"  rank histograms: {args.out / 'ranks.png'}")
    ok = v["rhat_ok"] and v["coverage_ok"] and v["ranks_ok"] and v["n"] >= 100
    print(f"SUMMARY c21_coverage: n={v['n']} covered={v['covered']} band={v['band'][0]}-{v['band'][1]} "
          f"rhat_max={v['rhat_max']:.4f} rank_p_min={v['rank_p_min']:.3f} pass={'yes' if ok else 'no'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
