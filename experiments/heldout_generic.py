#!/usr/bin/env python3
"""Held-out scoring of the clock + unresolved-motion physics against strong generic models on the
six real MIMU4444 experiments (DESIGN §7.2.1; issue #27 item 4).

For each experiment (loaded as ``experiments/mimu_mismatch.py`` loads it: the raw import, the
package's preparation — intrinsics from the rests, the one sample selection — and the nominal
fit), the residuals of :func:`accel_bayes.mismatch.heldout.residuals_of`.  Each IMU's clock (beat,
phase, drift) is acquired by the detector's own beat search on its gyro timing statistics
(:func:`accel_bayes.mismatch.heldout.clocks_from`, i.e. :func:`accel_bayes.mismatch.clock.estimate_clock`
on :func:`accel_bayes.mismatch.clock.clock_ab`): on the whole recording (used when the experiment is
the source; a diagnostic on the target), on its first ``--acquire-s`` seconds of contiguous motion
(:func:`~accel_bayes.mismatch.heldout.motion_window`, every sample, the window's own fit: the
protocol's acquisition), and by the causal tracker (:func:`~accel_bayes.mismatch.heldout.tracked_clocks`:
blocks of ``--block-s`` s, each with the clock acquired on the target's samples before it); each with
every acquired clock and with the evidence rule (an IMU whose clock does not pass the clock stage's
look-elsewhere threshold or width range gets none).  Every model is scored on the target's kept
samples after the window.  For all ordered pairs source → target, per sensor, in nats per sample on
the same residuals: banded white noise, Student-t per triad, multivariate t per sample, full
cross-IMU covariance per band, the physics model (clock-age mean + unresolved motion, white
remainder) and the physics model with each generic remainder; every parameter from the source.
Headline: the physics-specific gain = best physics variant − best generic model (both chosen on the
target's scores), with a moving-block bootstrap standard error (blocks of 2 s) of that difference, for
the protocol's physics: the 30 s acquisition with each IMU's data age marginalised over its predictive
(:func:`~accel_bayes.mismatch.heldout.clock_posteriors` on the window, carried forward with the source's
forecast noise :func:`~accel_bayes.mismatch.age_predictive.fit_forecast_noise`, fitted on its own phase
forecast errors;
:func:`~accel_bayes.mismatch.heldout.marginal_age`).  Beside it: the deterministic 30 s age (scored as
if certain), the tracker, the whole-target clock and no clock at all (every age uniform) as diagnostics.
The per-experiment cache is reused; the acquisition window's statistics and its regressor scale λ are
recomputed from the raw recording (seconds) into ``CACHE/exp_I_window.pt``.

    python experiments/heldout_generic.py --cache-only --experiments 1 2 3 &  # optional: load in two
    python experiments/heldout_generic.py --cache-only --experiments 4 5 6    # processes (cache)
    python experiments/heldout_generic.py                      # all six, whole recordings
    python experiments/heldout_generic.py --experiments 1 2    # a subset (the document says so)
    python experiments/heldout_generic.py --from-results       # rewrite the document from results.json

Writes ``--out`` (default ``experiments/results/heldout_generic``): ``results.json``, and the
document ``experiments/heldout_generic.md``.
"""
from __future__ import annotations

import argparse
import io
import datetime
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(HERE))

from _data import data_dir  # noqa: E402
from _reading import READING_MARKER, kept_reading  # noqa: E402
from _stamp import machine_note  # noqa: E402
from mimu_mismatch import load_recording  # noqa: E402

from accel_bayes.data import outputs  # noqa: E402
from accel_bayes.mismatch import baseline_fit, prepare  # noqa: E402
from accel_bayes.mismatch.clock import MIN_CYCLES  # noqa: E402
from accel_bayes.mismatch.age_predictive import (beat_walk_rate, fit_forecast_noise, forecast_errors,  # noqa: E402
                                                 phase_predictive)
from accel_bayes.mismatch.heldout import (GENERIC, PHYSICS, acquired_age, block_bootstrap_se,  # noqa: E402
                                          clock_posteriors, clocks_from, clocks_of, describe_source, fit_source,
                                          marginal_age, motion_window, residuals_of, score, tracked_age,
                                          tracked_clocks, window_statistics, with_rate_scale)

SENSORS = ("acc", "gyro")
#: s after the acquisition window's centre where a recording's phase forecast is checked against its local
#: phase (10 s blocks): the scored stretch spans τ ≈ 15–90 s
FORECAST_TAUS = np.arange(20.0, 90.1, 5.0)


def load(i, args):
    """Experiment i's residuals and its clock acquisitions: whole recording (as a source, and a
    diagnostic), the first ``acquire_s`` of contiguous motion (all samples, the window's own fit),
    and the causal tracker from there on.  Cached in ``CACHE/exp_{i}.pt`` (``--fresh`` recomputes)."""
    cache = args.cache / f"exp_{i}.pt"
    waited = 0.0
    while not cache.exists() and waited < args.wait_cache:  # another --cache-only process is writing it
        time.sleep(10.0)
        waited += 10.0
    if waited:
        time.sleep(10.0)
    if cache.exists() and not args.fresh:
        return torch.load(cache, weights_only=False)
    t0 = time.perf_counter()
    rec, info = load_recording(i, args.data, args.max_samples)
    prep = prepare(rec)
    fit, _ = baseline_fit(prep)
    res = residuals_of(prep, fit)
    window = motion_window(prep, args.acquire_s)
    t_src = np.asarray(prep.source.time, float)
    after = float(t_src[window][-1]) + 0.5 / res.f_read
    stats = window_statistics(prep, window)
    c_all = clocks_of(res)
    blocks = tracked_clocks(res, stats, after=after, block_s=args.block_s)
    first = res.time.numpy() < after
    info.update(T_kept=int(len(res.time)), f_read=res.f_read, span_s=float(res.time[-1] - res.time[0]),
                window_start_s=float(t_src[window][0]), window_end_s=after, n_window=int(window.sum()),
                n_window_used=int(len(stats[0])), n_kept_before=int(first.sum()), n_scored_max=int((~first).sum()),
                clock_whole={k: v.tolist() for k, v in c_all.items()},
                tracker_blocks=[{"start_s": b0, **{k: v.tolist() for k, v in c.items()},
                                 "beat_at_start_hz": (c["beat_hz"] + c["drift_hz_per_s"] * b0).tolist()}
                                for b0, c in blocks], load_seconds=time.perf_counter() - t0)
    out = {"res": res, "first": first, "info": info, "clock_whole": c_all, "blocks": blocks}
    buf = io.BytesIO()
    torch.save(out, buf)
    outputs.write_bytes(cache, buf.getvalue())
    return out


def load_window(i, d, args):
    """Experiment i's acquisition window statistics and each IMU's regressor scale λ on the window's
    own fit (:func:`~accel_bayes.mismatch.heldout.window_statistics`), cached in
    ``CACHE/exp_{i}_window.pt`` (``--fresh`` recomputes): the raw import and preparation again (a few
    seconds), not the whole-recording fit.  Checks that the window reproduces the cached
    acquisition's beats (the main cache's tracker was acquired on the same statistics)."""
    cache = args.cache / f"exp_{i}_window.pt"
    if cache.exists() and not args.fresh:
        return torch.load(cache, weights_only=False)
    t0 = time.perf_counter()
    rec, _ = load_recording(i, args.data, args.max_samples)
    prep = prepare(rec)
    stats, lam = window_statistics(prep, motion_window(prep, args.acquire_s), rate_scales=True)
    beat = clocks_from(*stats)["beat_hz"]
    out = {"stats": stats, "rate_scale": lam, "seconds": time.perf_counter() - t0,
           "max_beat_change_hz": float(np.max(np.abs(beat - d["blocks"][0][1]["beat_hz"])))}
    buf = io.BytesIO()
    torch.save(out, buf)
    outputs.write_bytes(cache, buf.getvalue())
    return out


def with_ages(d, args):
    """The cached experiment ``d`` with its ages: whole-recording clock, the plain 30 s acquisition and
    the causal tracker, each with every acquired clock and with the evidence rule
    (:func:`accel_bayes.mismatch.heldout.acquired_age`); the acquisition window's phase/beat posteriors
    (:func:`~accel_bayes.mismatch.heldout.clock_posteriors`, for the marginalised age) and, as a source,
    its beat walk's rate (:func:`~accel_bayes.mismatch.age_predictive.beat_walk_rate`: its beats tracked
    over blocks of ``--acquire-s`` from its window's start: the previous forecast) and its forecast noise
    (:func:`~accel_bayes.mismatch.age_predictive.fit_forecast_noise` on its own phase forecast errors from its
    window, :func:`~accel_bayes.mismatch.age_predictive.forecast_errors` at ``FORECAST_TAUS``)."""
    t0 = time.perf_counter()
    res = d["res"]
    # the cached clocks carry the fitted width; the evidence rule reads the data age's (fitted / λ, λ of
    # the window's fit — the tracker's later statistics are the whole fit's, whose λ is not cached)
    d["blocks"] = [(b0, with_rate_scale(c, d["window"]["rate_scale"])) for b0, c in d["blocks"]]
    blocks = d["blocks"]
    for acc, tag in ((None, ""), ("evidence", "_ev")):
        d[f"age_whole{tag}"] = acquired_age(res, d["clock_whole"], accept=acc)
        d[f"age_first{tag}"] = acquired_age(res, blocks[0][1], accept=acc)
        d[f"age_tracked{tag}"] = tracked_age(res, blocks, block_s=args.block_s, accept=acc)
        d[f"posts{tag}"] = clock_posteriors(d["window"]["stats"], blocks[0][1], accept=acc)
    t, A, B = res.time.numpy(), res.timing_a.numpy(), res.timing_b.numpy()
    d["walk"] = beat_walk_rate(t, A, B, d["clock_whole"], start=d["info"]["window_start_s"], block_s=args.acquire_s)
    # the recording's own forecast errors from its acquisition window (as a source: what its forecast
    # noise is fitted on; as a target: only the calibration table reads them, never a score)
    d["errors"] = [None if p is None else forecast_errors(t, A[:, k], B[:, k], p, taus=FORECAST_TAUS)
                   for k, p in enumerate(d["posts"])]
    d["noise"] = fit_forecast_noise(d["errors"], d["posts"])
    d["predictive_seconds"] = time.perf_counter() - t0
    return d


def pair_result(src, tgt, args, seed):
    """Scores of every model of ``src`` on ``tgt``'s kept samples after its acquisition window, per
    sensor: mean nats/sample, gains over white, the headline (physics with the target clock
    acquired on its first ``acquire_s`` of motion) and its bootstrap SE; the same with the causal
    tracker's clock (prequential: each block's clock from target samples before it); and, as a
    diagnostic that uses the scored samples for the clock (not a held-out number), with the target
    clock acquired on its whole recording."""
    keep = ~tgt["first"]
    out = {}
    q = src["noise"]  # the forecast noise is the source's: nothing of the target's scored data
    K = tgt["res"].timing_a.shape[1]
    point = [None if p is None else dict(p, cov=np.zeros((2, 2))) for p in tgt["posts"]]
    ages = {v: (marginal_age(tgt["res"], tgt["posts"], src["walk"]["q_hz2_per_s"]) if v == "marg_walk"
                else marginal_age(tgt["res"], tgt["posts" + v[4:]], q) if v.startswith("marg")
                else marginal_age(tgt["res"], [None] * K, q) if v == "lost"
                else marginal_age(tgt["res"], point, 0.0) if v == "point" else tgt[f"age_{v}"])
            for v, _, _ in VARIANTS}
    scores = {v: score(src["models"], tgt["res"], ages[v], keep) for v, _, _ in VARIANTS}
    for s in SENSORS:
        ll = scores["first"][s]["ll"]
        mean = {k: float(np.mean(v)) for k, v in ll.items()}
        best_g = max(GENERIC, key=lambda k: mean[k])
        r = {"n": scores["first"][s]["n"], "mean": mean, "best_generic": best_g,
             "gain_over_white": {k: mean[k] - mean["white"] for k in mean}}
        for v, tag, _ in VARIANTS:
            llv = scores[v][s]["ll"]
            mv = {k: float(np.mean(x)) for k, x in llv.items()}
            best_p = max(PHYSICS, key=lambda k: mv[k])
            diff = llv[best_p] - ll[best_g]  # generic scores do not depend on the clock
            r[f"best_physics{tag}"] = best_p
            r[f"physics_over_white{tag}"] = mv["physics"] - mean["white"]
            if tag:  # the deterministic 30 s clock's ("") are in gain_over_white with the generic models'
                r[f"gain_over_white{tag}"] = {k: mv[k] - mean["white"] for k in PHYSICS}
            r[f"physics_over_white_se{tag}"] = block_bootstrap_se(llv["physics"] - ll["white"], block=args.block,
                                                                  n_boot=args.boot, seed=seed)
            r[f"specific_gain{tag}"] = float(np.mean(diff))
            r[f"specific_se{tag}"] = block_bootstrap_se(diff, block=args.block, n_boot=args.boot, seed=seed)
            # the same remainder on both sides (physics + the best generic model against it): what the
            # physics adds to that model, not what another remainder family does better
            fam = "physics" if best_g == "white" else f"physics+{best_g}"
            same = llv[fam] - ll[best_g]
            r[f"same_family_gain{tag}"] = float(np.mean(same))
            r[f"same_family_se{tag}"] = block_bootstrap_se(same, block=args.block, n_boot=args.boot, seed=seed)
        out[s] = r
    return out


#: (age key, result suffix, name): the target clock's acquisitions scored; "_ev": the evidence rule
VARIANTS = (("marg", "_marg", "30 s acquisition, age marginalised (the protocol)"),
            ("marg_ev", "_marg_ev", "30 s acquisition, age marginalised, evidence rule"),
            ("marg_walk", "_marg_walk", "30 s acquisition, age marginalised, previous forecast (Brownian beat at "
             "the block-increment rate; diagnostic)"),
            ("first", "", "30 s acquisition, deterministic age"),
            ("first_ev", "_ev", "30 s acquisition, deterministic age, evidence rule"),
            ("tracked", "_tracked", "causal tracker (protocol extension)"),
            ("tracked_ev", "_tracked_ev", "causal tracker, evidence rule"),
            ("whole", "_clock_whole_target", "clock from the whole target (diagnostic, not held out)"),
            ("lost", "_lost", "no clock: every age uniform (the covariance part alone; diagnostic)"),
            ("point", "_point", "30 s posterior mean, drift 0, as if certain (diagnostic)"))


def _local_beats(c, t0) -> list:
    """The beats β₀ + d·t0 (Hz) of a clock dict as strings, starred where the evidence rule drops it."""
    from accel_bayes.mismatch.clock import WIDTH_RANGE_S

    out = []
    for b, d, e, th, w in zip(c["beat_hz"], c["drift_hz_per_s"], c["evidence"], c["threshold"], c["width_s"]):
        ok = e > th and WIDTH_RANGE_S[0] <= w <= WIDTH_RANGE_S[1]
        out.append(f"{b + d * t0:+.3f}" + ("" if ok else "*"))
    return out


def _z(r, tag):
    return r[f"specific_gain{tag}"] / r[f"specific_se{tag}"]


def _counts(R, s, tag):
    """(gains (P,), z (P,)) of the physics-specific gain of variant ``tag`` over the pairs."""
    rows = [R["pairs"][p][s] for p in R["pair_order"]]
    return np.array([r[f"specific_gain{tag}"] for r in rows]), np.array([_z(r, tag) for r in rows])


def summary_markdown(R) -> str:
    """The results document's body from ``results.json``'s content."""
    exps = R["experiments"]
    K = len(R["info"][str(exps[0])]["clock_whole"]["beat_hz"])
    L = ["## Headline: physics-specific gain (best physics variant − best generic model), nats/sample", "",
         "| sensor | clock | median | range | pairs > +3 SE | pairs < −3 SE |", "|---|---|---|---|---|---|"]
    for s in SENSORS:
        for _, tag, name in VARIANTS:
            g, z = _counts(R, s, tag)
            L.append(f"| {s} | {name} | {np.median(g):+.3f} | {g.min():+.3f} to {g.max():+.3f} | "
                     f"**{int((z > 3).sum())}/{len(g)}** | {int((z < -3).sum())} |")
    if "same_family_gain_marg" in R["pairs"][R["pair_order"][0]]["acc"]:
        L += ["", "The same with the physics on the best generic model's own remainder (physics + that model − that "
              "model: what the physics adds to it, with no change of remainder family):", "",
              "| sensor | clock | median | range | pairs > +3 SE | pairs < −3 SE |", "|---|---|---|---|---|---|"]
        for s in SENSORS:
            for _, tag, name in VARIANTS:
                rows = [R["pairs"][p][s] for p in R["pair_order"]]
                g = np.array([r[f"same_family_gain{tag}"] for r in rows])
                z = g / np.array([r[f"same_family_se{tag}"] for r in rows])
                L.append(f"| {s} | {name} | {np.median(g):+.3f} | {g.min():+.3f} to {g.max():+.3f} | "
                         f"**{int((z > 3).sum())}/{len(g)}** | {int((z < -3).sum())} |")
    L += ["", "## Clock acquisition (the detector's beat search): beat frequency per IMU (Hz)", "",
          "Whole recording / first 30 s of motion / the tracker's last block (acquired on the target's data "
          "before that block), each the local beat β₀ + d·t at the window's start (comparable across "
          "acquisitions); `*`: under the evidence rule's threshold or outside the width range (the IMU gets "
          "no clock under the rule). Acquired by `accel_bayes.mismatch.clock.estimate_clock` on each IMU's gyro "
          "timing statistics (`clock.clock_ab`); the sign says which way the sawtooth ramps. A "
          f"{R['acquire_s']:g} s window holds fewer than {MIN_CYCLES:g} cycles of a beat under "
          f"{MIN_CYCLES / R['acquire_s']:.2f} Hz, which the search does not consider (`clock.MIN_CYCLES`).", "",
          "| exp | " + " | ".join(f"IMU {k}" for k in range(K)) + " |", "|---|" + "---|" * K]
    for i in exps:
        inf = R["info"][str(i)]
        t0 = inf["window_start_s"]
        cols = [_local_beats(c, t0) for c in (inf["clock_whole"], inf["tracker_blocks"][0], inf["tracker_blocks"][-1])]
        L.append(f"| {i} | " + " | ".join(" / ".join(c[k] for c in cols) for k in range(K)) + " |")
    L += ["", "Acquisition window per experiment (the first stretch of " f"{R['acquire_s']:g} s without rests; "
          "samples of the window used: all but the clipped/flagged ones) and the scored samples (kept samples "
          "after the window):", "",
          "| exp | kept samples | window start (s) | window samples (used) | kept samples before the window end (not scored) "
          "| scored samples (max) | tracker blocks |", "|---|---|---|---|---|---|---|"]
    for i in exps:
        inf = R["info"][str(i)]
        L.append(f"| {i} | {inf['T_kept']} | {inf['window_start_s']:.1f} | {inf['n_window']} ({inf['n_window_used']}) | "
                 f"{inf['n_kept_before']} | {inf['n_scored_max']} | {len(inf['tracker_blocks'])} |")
    L += _predictive_section(R)
    for s in SENSORS:
        rows = [R["pairs"][p][s] for p in R["pair_order"]]
        L += ["", f"## {s}: held-out nats per sample, per pair (target's kept samples after its acquisition window)", "",
              "Gains over banded white noise (nats/sample), medians over the pairs: generic "
              + ", ".join(f"{k} {np.median([r['gain_over_white'][k] for r in rows]):+.3f}" for k in GENERIC)
              + "; physics with the age marginalised "
              + ", ".join(f"{k} {np.median([r['gain_over_white_marg'][k] for r in rows]):+.3f}" for k in PHYSICS)
              + "; physics with the deterministic 30 s age "
              + ", ".join(f"{k} {np.median([r['gain_over_white'][k] for r in rows]):+.3f}" for k in PHYSICS)
              + ". Specific gain ± SE (z) per clock variant; the best physics variant is named for the protocol's.", "",
              "| pair | n | best generic (gain over white) | physics over white ± SE (marginalised) | marginalised: best physics variant, "
              "specific gain ± SE (z) | marginalised, evidence rule | no clock (diagnostic) | posterior mean as if certain "
              "(diagnostic) | 30 s deterministic | tracker | whole-target clock (diagnostic) |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]

        def g(r, tag):
            return f"{r['specific_gain' + tag]:+.3f} ± {r['specific_se' + tag]:.3f} ({_z(r, tag):+.1f})"

        for p, r in zip(R["pair_order"], rows):
            L.append(f"| {p} | {r['n']} | {r['best_generic']} ({r['gain_over_white'][r['best_generic']]:+.3f}) | "
                     f"{r['physics_over_white_marg']:+.3f} ± {r['physics_over_white_se_marg']:.3f} | "
                     f"{r['best_physics_marg']}: {g(r, '_marg')} | {g(r, '_marg_ev')} | {g(r, '_lost')} | {g(r, '_point')} | {g(r, '')} | "
                     f"{g(r, '_tracked')} | {g(r, '_clock_whole_target')} |")
    L += ["", "## Source fits", "", "Per source and sensor: the clock-age mean's coefficient c (1 if the "
          "acquired age is the data age and the rate regressor the resolved motion's), the unresolved "
          "scales per |ω| band (m/s³ for acc, rad/s² for gyro) of the physics model, and the fitted degrees "
          "of freedom of the t models.", "",
          "| source | sensor | c | unresolved scale per band (physics) | ν triad-t (per IMU) | ν sample-t |",
          "|---|---|---|---|---|---|"]
    for i in exps:
        d = R["sources"][str(i)]
        for s in SENSORS:
            m = d[s]
            L.append(f"| {i} | {s} | {m['c']:.3f} | " + ", ".join(f"{x:.3g}" for x in m["physics"]["unresolved_scale"])
                     + " | " + ", ".join(f"{x:.2g}" for x in m["triad_t"]["nu"]) + f" | {m['sample_t']['nu']:.3g} |")
    return "\n".join(L)


PROTOCOL = """## Protocol

DESIGN §7.2.1, with these choices stated:

- **Acquisition window.** The MIMU experiments open with ~500 s of rests in 20 orientations (for the
  intrinsic calibration) joined by ~1.5 s turns; the recording's first 30 s hold one turn, and a rest
  carries no timing information (ω̇ = 0, so the timing statistic a_t = 0). The window is therefore the
  first 30 s of *contiguous motion*: from the first sample after which the board does not rest for 30 s
  (`heldout.motion_window`). Every sample of the window is used (the position fit's rotation test
  dropped ~20 % of them; only clipped/flagged samples go), with the window's own nominal fit (positions
  and motion fitted on the window alone, `heldout.window_statistics`), so the acquisition sees no
  scored sample. Every model is scored on the target's kept samples *after* the window; the kept
  samples of the turns before it are scored by no model.
- **The rate regressor** of the clock's mean −c·d·ẏ is the `sampling_clock` effect's: R_k ω̇ of the
  fitted motion for the gyro, and the timing statistics are the detector's clock stage's
  (`clock.clock_ab`); the accelerometer's is the finite difference of the fitted outputs
  (`prep.acc_rate`), as in the effect. All scales, ν and c from the source.
- **Causal tracker (protocol extension).** The beats drift with temperature, and a beat acquired on
  30 s is extrapolated over the following ~75 s (phase error Δβ·t). The tracker scores
  prequentially: the scored stretch is cut into blocks of {block_s:g} s; each block's clock is acquired
  by the same beat search on every target sample *before the block* (the window, then the scored
  samples already scored). Each block's score uses only data that precede it — an honest
  held-out score (prequential, as a filter's one-step-ahead prediction), not fitted to the block.
  The generic models have no target-specific parameter in §7.2.1 (all from the source), so there is
  nothing of theirs to track; both sides see the same target data before each block.
- **The age marginalised (the protocol's physics, the headline).** The physics model predicts its own
  clock: each IMU's phase and beat at the window's centre have the acquisition's posterior (the beat
  search's sawtooth likelihood on a grid, drift 0 inside the window — a drift fitted on 30 s and
  extrapolated ½dτ² is what lost the phase); after the window the beat walks (rate q) and drifts
  linearly at a random rate (variance σ²_d), both fitted on the *source*: maximum likelihood of the
  source's own phase forecast errors, its window's posterior forecast against its local phase on 10 s
  blocks at τ = 20–90 s (jointly Gaussian over τ per IMU; `age_predictive.fit_forecast_noise`). The
  phase at τ after the window's centre is N(φ̂ + β̂τ, σ²_φ + 2τσ_φβ + τ²σ²_β + qτ³/3 + σ²_dτ⁴/4) and
  the age W·frac(ψ) has exact moments (the sawtooth's
  Fourier series damped by the Gaussian characteristic function). The physics is scored with the age
  marginalised: mean −c·E[d]·ẏ, covariance + s²(E d E dᵀ + Σ_d)⊗I₃ + c²Σ_d∘ẏẏᵀ (the Gaussian with the
  marginal's exact first two moments; `accel_bayes/mismatch/age_predictive.py`). Where the phase is lost
  the mean vanishes and the unresolved motion is loaded by the age variance W²/12. Nothing of the
  target after the window enters; s, c, ν, covariances, q and σ²_d are the source's. (Before this run
  the forecast was a Brownian beat alone at the rate of the source's block-to-block beat increments: the
  "previous forecast" row, kept as a diagnostic.) Under the evidence rule an
  IMU whose clock fails it gets a uniform age (phase unknown).
"""

CAVEATS = """## Caveats (what this study does not settle)

{headline}
{short}
- What the marginalisation changed, per part (gyro physics with a white remainder over banded white
  noise, median over the pairs): {pw_first:+.2f} with the deterministic 30 s clock (the search's fitted
  drift extrapolated ½dτ², scored as if certain), {pw_point:+.2f} with the posterior mean and drift 0 as if
  certain, {pw_marg:+.2f} with the age marginalised, {pw_lost:+.2f} with no clock at all (every age uniform:
  the unresolved motion loaded by the age variance W²/12 and the mean term's variance), {pw_tracked:+.2f} with
  the tracker, {pw_whole:+.2f} with the whole target's clock as if certain. The evidence rule now reads the
  data age's width (fitted / λ) — smallest evidence / threshold of any acquired clock {ev_ratio:.1f}.
- The predictive is the Gaussian with the marginal's exact first two moments (for a t remainder, the t
  with that scale matrix), not the marginal itself (a continuous mixture over the ages); the acquisition
  posterior takes the timing statistics' noise as white at the profiled ĉ² (ĉ² is the statistics' total
  variance, not the residual's); the forecast noise (beat walk + drift variance) is one source's, pooled
  over its IMUs, and the recordings differ in how fast their beats drift; the source's models (s, c,
  remainders) were fitted with the source's whole-recording clock as if certain.
- The accelerometer's clock-mean coefficient c is {acc_c} over the sources (gyro: {gyro_c}): its rate
  regressor (the finite difference of the fitted outputs, `prep.acc_rate`, the effect's own) folds the
  board's 30–95 Hz vibration like the gyro's finite difference did; there is no per-sample board jerk
  state to replace it with. The accelerometer's clock physics is the unresolved-motion term, loaded on
  the ages in the covariance.
- Only the clock acquisition is causal: the target's residuals and, after the window, the timing
  statistics the tracker reads are the target's whole-recording nominal fit's (positions fitted on
  all its kept samples), the same for every model; the window's own statistics come from a fit on
  the window alone. The tracker's evidence rule uses the window fit's λ for its later blocks too.
- The clock is acquired on the nominal fit's residuals, not the detector's (no gyro linear blocks
  removed first); a constant per-IMU lateness (read skew, filter-delay differences) is left out of
  the loading (the sawtooth's offset is dropped); the sawtooth width is the nominal 1 ms.
- Residuals are the nominal fit's: no mean effect (e.g. the gyro scale errors the detector finds)
  is removed before scoring, for any model. The best physics variant and the best generic model are
  each chosen on the target's scores.
- On the first-principles generator (`tests/mismatch/test_unresolved_motion.py`, slow, 10 s case) the
  unresolved-motion scale was over-stated 1.2–1.9× (acc) and 1.6–1.9× (gyro) with the finite-difference
  regressor; with the gyro's R_k ω̇ the gyro's fitted scale is 0.33–0.39× the test's truth (exact
  angular acceleration less the finite-difference rate), and 0.24–0.33× the exact less the fitted ω̇
  state: that slow test fails on this branch, unexplained (the mean term now takes the resolved
  vibration; what the remainder's truth is needs working out).
"""


def _predictive_section(R) -> list:
    """The age predictive's inputs per experiment: λ and widths on the acquisition window, the phase and
    beat posterior's standard deviations, (as a source) the previous and the fitted forecast noise with the
    phase spread each implies, and the predictive's calibration before/after."""
    exps = R["experiments"]
    L = ["", "## The age's predictive (`accel_bayes/mismatch/age_predictive.py`)", "",
         "Per experiment as a target: the acquisition window's regressor scale λ (`clock.rate_scale` on the window's "
         "own fit), the data age's sawtooth width per IMU (fitted / λ, `clock.physical_width`, ms; the evidence rule "
         "reads it), and the posterior standard deviation of each IMU's phase (cycles) / beat (mHz) at the window's "
         "centre (`phase_posterior`: the beat search's likelihood on a grid, drift 0 inside the window). As a "
         "source: the previous forecast's beat walk rate q (maximum likelihood over the increments of its beats "
         f"tracked in {R['acquire_s']:g} s blocks from its window's start, all IMUs pooled), and the fitted forecast "
         "noise (`fit_forecast_noise`: beat walk q and drift variance σ²_d, maximum likelihood of its own phase forecast "
         "errors from its window at τ = 20–90 s), each as the phase spread it adds τ = 30 / 60 / 85 s after the "
         "target's window centre (√(qτ³/3); √(qτ³/3 + σ²_dτ⁴/4)); the scored stretch spans τ ≈ 15–90 s.", "",
         "| exp | λ | width (ms) per IMU | sd phase (cycles) / beat (mHz) per IMU | evidence rule drops | previous: q (Hz²/s) "
         "(increments); spread at 30 / 60 / 85 s | fitted: q (Hz²/s), σ_d (Hz/s); spread at 30 / 60 / 85 s |",
         "|---|---|---|---|---|---|---|"]
    for i in exps:
        inf = R["info"][str(i)]
        old, new = _noise(inf, "walk"), _noise(inf, "fitted")
        lam = sorted(set(round(x, 3) for x in inf["rate_scale"]))
        post = ", ".join("—" if p is None else f"{p['sd_phase']:.3f}/{1e3 * p['sd_beat_hz']:.2f}" for p in inf["posterior"])
        taus = np.array([30.0, 60.0, 85.0])
        L.append(f"| {i} | {', '.join(map(str, lam))} | {', '.join(f'{1e3 * w:.2f}' for w in inf['width_phys_s'])} | "
                 f"{post} | {inf['posterior_ev_none'] or 'none'} | {old.q:.2e} ({inf['walk_increments']}); "
                 + " / ".join(f"{x:.2f}" for x in np.sqrt(old.var(taus))) + f" | {new.q:.2e}, {np.sqrt(new.drift_var):.1e}; "
                 + " / ".join(f"{x:.2f}" for x in np.sqrt(new.var(taus))) + " |")
    L += ["", "Calibration of the phase predictive (nominal coverage 68 % / 95 %), over every pair (the source's "
          "forecast noise) and every IMU: the wrapped phase error e and the predictive sd σ τ s after the target's window "
          "centre, against two references, both estimates: the target's *local* phase (the same beat likelihood on "
          "10 s of the target around t_c + τ, its variance added to σ; `age_predictive.forecast_errors`) and its "
          "whole-recording clock (the beat search on the whole recording, quadratic drift). *Previous*: the Brownian "
          "beat at the rate q of the source's block-to-block beat increments (`beat_walk_rate`); *fitted*: the "
          "source's `ForecastNoise` (beat walk q + drift variance, maximum likelihood of the source's own forecast "
          "errors from its own window, `fit_forecast_noise`). The references are read only here, never by a score "
          "(at large σ the wrapping to ±½ cycle shrinks abs(e)).", "",
          "| τ (s) | reference | n | median abs(e) (cycles) | median σ previous / fitted | abs(e) < σ previous / fitted | "
          "abs(e) < 2σ previous / fitted |", "|---|---|---|---|---|---|---|"]
    for ref in ("local", "whole"):
        old, new = _calibration(R, "walk", ref), _calibration(R, "fitted", ref)
        for tau in old:
            (e, so), (_, sn) = old[tau], new[tau]
            L.append(f"| {tau:g} | {ref} | {len(e)} | {np.median(e):.3f} | {np.median(so):.3f} / {np.median(sn):.3f} | "
                     f"{np.mean(e < so):.0%} / {np.mean(e < sn):.0%} | {np.mean(e < 2 * so):.0%} / {np.mean(e < 2 * sn):.0%} |")
    reuse = [f"exp {i}: window {R['info'][str(i)].get('window_seconds', float('nan')):.0f} s, beats "
             f"{'reproduced' if R['info'][str(i)]['window_max_beat_change_hz'] < 1e-9 else 'CHANGED by %.2g Hz' % R['info'][str(i)]['window_max_beat_change_hz']}"
             for i in exps]
    L += ["", "Reused from the cache (`--cache`): each experiment's residuals, timing statistics, whole-recording and "
          "tracker clocks (the 55 min part). Recomputed: the acquisition window's statistics and λ (raw import, "
          "preparation, the window's own fit; cached beside as `exp_I_window.pt`), checked against the cached 30 s "
          "acquisition (the beat search on the recomputed statistics gives the cached beats): " + "; ".join(reuse) + "."]
    return L


def _noise(inf, which):
    """A source's forecast noise from its results ``inf``: "walk" the previous (Brownian beat at the block-increment
    rate q), "fitted" :func:`~accel_bayes.mismatch.age_predictive.fit_forecast_noise`'s."""
    from accel_bayes.mismatch.age_predictive import ForecastNoise

    if which == "walk":
        return ForecastNoise(q=inf["walk_q_hz2_per_s"])
    f = inf["forecast_noise"]
    return ForecastNoise(q=f["q_hz2_per_s"], drift_var=f["drift_var_hz2_per_s2"])


def _calibration(R, which, reference, taus=(30.0, 60.0, 85.0)) -> dict:
    """{τ: (abs wrapped phase error (n,), predictive sd (n,))} of the target's phase predictive τ s after its
    window's centre with each pair's source noise ``which`` (:func:`_noise`), over the pairs and IMUs, against
    ``reference``: "whole" the target's whole-recording clock (quadratic drift), "local" the target's local
    phase on 10 s around t_c + τ (:func:`~accel_bayes.mismatch.age_predictive.forecast_errors`; its variance
    added to the predictive's)."""
    out = {}
    for tau in taus:
        e, sd = [], []
        for p in R["pair_order"]:
            i, j = p.split("->")
            inf, noise = R["info"][j], _noise(R["info"][i], which)
            cw = inf["clock_whole"]
            for k, post in enumerate(inf["posterior"]):
                if post is None:
                    continue
                t = post["t_c"] + tau
                mean, s = phase_predictive(np.array([t]), dict(post, cov=np.array(post["cov"])), noise)
                if reference == "whole":
                    psi, v = cw["phase"][k] + cw["beat_hz"][k] * t + 0.5 * cw["drift_hz_per_s"][k] * t * t, 0.0
                else:
                    err = inf["forecast_errors"][k]
                    hit = [n for n, x in enumerate(err["tau"]) if abs(x - tau) < 1e-6] if err else []
                    if not hit:
                        continue
                    psi, v = mean[0] + err["e"][hit[0]], err["var"][hit[0]]
                e.append(abs((psi - mean[0] + 0.5) % 1.0 - 0.5))
                sd.append(float(np.sqrt(s[0] ** 2 + v)))
        out[tau] = (np.array(e), np.array(sd))
    return out


def _ev_ratio(R) -> float:
    """The smallest evidence/threshold of any acquired clock (30 s and tracker blocks)."""
    r = [e / t for i in R["experiments"] for b in R["info"][str(i)]["tracker_blocks"]
         for e, t in zip(b["evidence"], b["threshold"]) if t > 0]
    return min(r) if r else float("nan")


def _short(R) -> str:
    """The pairs where the protocol's (marginalised) gain is not above 3 SE, per sensor, with the others."""
    L = []
    for s in SENSORS:
        for p in R["pair_order"]:
            r = R["pairs"][p][s]
            if _z(r, "_marg") <= 3:
                L.append(f"- Marginalised, {s}, pair {p}: gain {r['specific_gain_marg']:+.3f} ± "
                         f"{r['specific_se_marg']:.3f} ({_z(r, '_marg'):+.1f} SE; {r['best_physics_marg']} "
                         f"against {r['best_generic']}); tracker {r['specific_gain_tracked']:+.3f} ({_z(r, '_tracked'):+.1f} SE); "
                         f"no clock {r['specific_gain_lost']:+.3f} ({_z(r, '_lost'):+.1f} SE).")
    return "\n".join(L) if L else "- The marginalised gain is above 3 SE on every pair for both sensors."


def _c_range(R, s) -> str:
    """The range of the sources' clock-mean coefficient c for sensor s, as text."""
    c = [R["sources"][str(i)][s]["c"] for i in R["experiments"]]
    return f"{min(c):+.3f} to {max(c):+.3f}"


def _headline(R) -> str:
    """The caveat on the headline (30/30 pairs above 3 SE per sensor), from the results."""
    parts = []
    for _, tag, name in [v for v in VARIANTS if v[0] not in ("whole", "lost", "point", "marg_walk")]:
        c = {s: int((_counts(R, s, tag)[1] > 3).sum()) for s in SENSORS}
        n = len(R["pair_order"])
        parts.append(f"{name}: {'met' if all(v == n for v in c.values()) else 'not met'} "
                     f"(acc {c['acc']}/{n}, gyro {c['gyro']}/{n})")
    best = sorted({R["pairs"][p][s]["best_generic"] for p in R["pair_order"] for s in SENSORS})
    return (f"- The headline (above 3 SE on every pair, per sensor): {'; '.join(parts)}.  Best generic models "
            f"chosen on the targets: {', '.join(best)}.")


def write_document(args, R, when) -> None:
    """The results document from ``R`` (the content of results.json)."""
    cmd = "python experiments/heldout_generic.py" + (
        f" --experiments {' '.join(map(str, args.experiments))}" if list(args.experiments) != [1, 2, 3, 4, 5, 6] else "") + (
        f" --max-samples {args.max_samples}" if args.max_samples else "")
    head = ["# Held-out scoring against strong generic models: the clock + unresolved-motion physics (issue #27 item 4)",
            "", f"Generated by `OMP_NUM_THREADS=1 PYTHONPATH=. {cmd}` (finished {when}), "
            f"{machine_note()}: the per-experiment cache "
            f"(residuals, clocks: {sum(R['info'][str(i)]['load_seconds'] for i in R['experiments']):.0f} s to build, "
            "2026-11-27 by two `--cache-only` processes) reused, the acquisition windows recomputed once "
            f"({sum(R['info'][str(i)].get('window_seconds', 0.0) for i in R['experiments']):.0f} s, cached beside), "
            f"{R['seconds']:.0f} s for this run in all (windows, predictives, fitting, scoring; cache in `--cache`, "
            "default experiments/out/heldout_generic; `--fresh` recomputes it; `--from-results` rewrites this document "
            "from results.json, keeping the hand-written reading below its marker). " + ("Whole recordings." if not args.max_samples else
                                      f"Last {args.max_samples} raw samples of each recording only."), "",
            "Method: `accel_bayes/mismatch/heldout.py` (module docstring). Every model scores the same residuals "
            "(the nominal fit's, leverage-corrected, array frame; samples with all 8 triads of the sensor observed). "
            "Best generic and best physics variant are chosen on the target's scores (so the generic side gets its "
            "best model). SE: moving-block bootstrap (2 s blocks) of the per-sample difference.", "",
            PROTOCOL.format(block_s=R.get("block_s", 15.0))]
    outputs.write_text(args.doc, "\n".join(head) + "\n" + summary_markdown(R) + "\n\n"
                       + CAVEATS.format(headline=_headline(R), short=_short(R), ev_ratio=_ev_ratio(R),
                                        **{f"pw_{v}": float(np.median([R["pairs"][p]["gyro"][f"physics_over_white{t}"]
                                                                        for p in R["pair_order"]]))
                                           for v, t in (("first", ""), ("tracked", "_tracked"), ("marg", "_marg"),
                                                        ("point", "_point"), ("lost", "_lost"),
                                                        ("whole", "_clock_whole_target"))},
                                        **{f"{s}_c": _c_range(R, s) for s in SENSORS})
                       + "\n" + READING_MARKER + kept_reading(args.doc))
    print(f"written {args.doc}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--experiments", type=int, nargs="+", default=[1, 2, 3, 4, 5, 6])
    ap.add_argument("--data", type=Path, default=data_dir())
    ap.add_argument("--out", type=Path, default=HERE / "results" / "heldout_generic")
    ap.add_argument("--cache", type=Path, default=HERE / "out" / "heldout_generic",
                    help="per-experiment cache folder (git-ignored)")
    ap.add_argument("--doc", type=Path, default=HERE / "heldout_generic.md")
    ap.add_argument("--acquire-s", type=float, default=30.0, help="target clock acquisition window (s of contiguous motion)")
    ap.add_argument("--max-samples", type=int, default=None, help="last N raw samples only (off: whole recordings)")
    ap.add_argument("--block-s", type=float, default=15.0, help="causal tracker's block length (s)")
    ap.add_argument("--cache-only", action="store_true",
                    help="only load the experiments into the cache (to run them in two processes), no scoring")
    ap.add_argument("--wait-cache", type=float, default=0.0,
                    help="seconds to wait for a missing cache file that a --cache-only process is writing")
    ap.add_argument("--fresh", action="store_true", help="recompute the per-experiment cache CACHE/exp_I.pt")
    ap.add_argument("--block", type=int, default=125, help="bootstrap block length (samples)")
    ap.add_argument("--boot", type=int, default=400, help="bootstrap resamples")
    ap.add_argument("--from-results", action="store_true", help="only rewrite the document from OUT/results.json")
    args = ap.parse_args(argv)
    if args.from_results:
        R = json.loads((args.out / "results.json").read_text())
        args.experiments, args.max_samples = R["experiments"], R.get("max_samples")
        write_document(args, R, R.get("finished_utc", "unknown date"))
        return 0
    torch.manual_seed(0)
    args.out.mkdir(parents=True, exist_ok=True)
    args.cache.mkdir(parents=True, exist_ok=True)  # before the long computation, so the results can be written
    t_start = time.perf_counter()
    data, R = {}, {"acquire_s": args.acquire_s, "block_s": args.block_s, "experiments": args.experiments, "info": {}, "sources": {},
                   "pairs": {}, "pair_order": [], "max_samples": args.max_samples}
    for i in args.experiments:
        t0 = time.perf_counter()
        d = load(i, args)
        d["window"] = load_window(i, d, args)
        data[i] = with_ages(d, args)
        t1 = time.perf_counter()
        if args.cache_only:
            print(f"exp_{i}: cached ({t1 - t0:.0f} s)", flush=True)
            continue
        data[i]["models"] = fit_source(data[i]["res"], data[i]["age_whole"], progress=lambda m: print(m, flush=True))
        w, walk = data[i]["window"], data[i]["walk"]
        R["info"][str(i)] = dict(data[i]["info"], fit_seconds=time.perf_counter() - t1,
                                 window_seconds=w["seconds"], window_max_beat_change_hz=w["max_beat_change_hz"],
                                 rate_scale=w["rate_scale"].tolist(), predictive_seconds=data[i]["predictive_seconds"],
                                 walk_q_hz2_per_s=walk["q_hz2_per_s"], walk_increments=walk["n_increments"],
                                 forecast_noise={"q_hz2_per_s": data[i]["noise"].q,
                                                 "drift_var_hz2_per_s2": data[i]["noise"].drift_var},
                                 forecast_errors=[None if e is None else {k: v.tolist() for k, v in e.items()}
                                                  for e in data[i]["errors"]],
                                 walk_blocks=walk["blocks"],
                                 posterior=[None if p is None else {"phase": p["phase"], "beat_hz": p["beat_hz"],
                                                                    "sd_phase": float(np.sqrt(p["cov"][0, 0])),
                                                                    "sd_beat_hz": float(np.sqrt(p["cov"][1, 1])),
                                                                    "cov": p["cov"].tolist(),
                                                                    "t_c": p["t_c"]} for p in data[i]["posts"]],
                                 posterior_ev_none=[k for k, p in enumerate(data[i]["posts_ev"]) if p is None],
                                 width_phys_s=data[i]["blocks"][0][1]["width_s"].tolist(),
                                 width_fit_s=data[i]["blocks"][0][1]["width_fit_s"].tolist())
        R["sources"][str(i)] = describe_source(data[i]["models"])
        print(f"exp_{i}: {data[i]['info']['T_kept']} kept samples; loaded {t1 - t0:.0f} s, models fitted "
              f"{time.perf_counter() - t1:.0f} s; beats {np.round(data[i]['clock_whole']['beat_hz'], 3)}", flush=True)
    if args.cache_only:
        return 0
    for n, i in enumerate(args.experiments):
        for j in args.experiments:
            if i == j:
                continue
            key = f"{i}->{j}"
            R["pairs"][key] = pair_result(data[i], data[j], args, seed=100 * i + j)
            R["pair_order"].append(key)
            print(key, {s: (R["pairs"][key][s]["best_generic"], R["pairs"][key][s]["best_physics"],
                            round(R["pairs"][key][s]["specific_gain"], 3), round(R["pairs"][key][s]["specific_se"], 3))
                        for s in SENSORS}, flush=True)
    R["seconds"] = time.perf_counter() - t_start
    R["finished_utc"] = f"{datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC"
    outputs.write_json(args.out / "results.json", outputs.to_jsonable(R))
    write_document(args, R, R["finished_utc"])
    print(f"written {args.doc} ({R['seconds']:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
