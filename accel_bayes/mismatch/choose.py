"""The detector's choices (:func:`accel_bayes.mismatch.detect`, steps 5–6): which screened candidates
are refitted, the evidence of a refit, which one a round accepts, and the alternatives reported
beside it.

5. **Refit** the best screened candidate of each effect class and the overall top three
   (at most ``n_refit``, only those with a screen statistic ≥ ½ of the threshold): the
   augmented model is re-optimised jointly with the geometry and the motion by the LM solver,
   and the **evidence** is the likelihood ratio 2·(log L with − log L without) at the two optima
   (for ``noise_level`` the restricted likelihood ratio of step 4 at the refitted model, because
   the plain one is biased by the leverage of the per-sample motion states).
6. **Accept** one candidate per round, repeat from step 4 with it in the model, at most
   ``max_findings`` times:

   * a mean (or clip) effect is acceptable when its *noise-robust* evidence — the evidence
     divided by max(1, P), P the mean leverage-corrected z² left in its IMU/sensor group after
     the refit — exceeds the threshold.  This F-test-like guard keeps noise larger than stated
     (which inflates every mean candidate's likelihood ratio on that IMU by the same factor)
     from being named as a bias or scale error; for a correctly named effect P ≈ 1.  It must
     also be *constant*: its score test across :data:`STATIONARITY_SEGMENTS` time segments
     (:func:`~accel_bayes.mismatch.screens.stationarity`, also over max(1, P)) must stay below the χ²_{(S−1)d} quantile at
     1 − α/m; a drifting bias that least squares projects onto a constant bias or a
     misalignment is refused there and left to the ``unexplained`` characterisation;
   * ``noise_level`` and the random effects (``sampling_jitter``) are considered only in a round
     where no mean/clip effect is acceptable: any unmodelled mean structure also raises the
     residual power, so the variance explanations come last.  They compete on equal terms
     (both a likelihood ratio of leverage-corrected residuals): ``noise_level`` predicts a
     constant variance factor on one sensor, ``sampling_jitter`` variance growing with the
     squared output rate on both sensors of the IMU.  ``noise_level`` is refused
     (:func:`heteroscedastic`) where its group's excess power varies more than 1.25× across the
     quintiles of a motion covariate (significant by the characteriser's F test): a constant
     factor does not describe such an excess, which is then left to a better variance model or
     to the characterised ``unexplained`` finding of step 7.  Exception to "mean first": a random
     effect whose evidence exceeds :data:`RANDOM_DOMINANCE` (10) × the best acceptable mean
     candidate's is taken first (a wandering timing error looks like structure to every mean
     candidate, each explaining a small part of it).  At most one random effect per IMU and
     sensor is in the model (each is profiled as if alone), none on an accelerometer where it would
     leave fewer than two IMUs without one (:func:`acc_timing_unidentified`), and a ``timing_wander`` only where its
     timing term alone (against the triad's best noise-only fit) passes the threshold.  ``noise_level`` refits of step 5
     are only done in a round where no mean/clip candidate is acceptable (elsewhere the
     round's ``refits`` list them as skipped);
   * among the acceptable ones the smallest p-value (χ²_df of the robust evidence) wins.

   With several findings, each one's evidence is recomputed with all the others in the model
   (drop-one refits).  Each finding lists as ``alternatives`` the other candidates refitted in
   its round whose Akaike relative likelihood against it, exp(−ΔAIC/2), is ≥ 5 %: effects this
   recording cannot tell apart from the named one (e.g. a quadratic response and a scale error
   on an axis whose specific force never changes sign).
"""
from __future__ import annotations

import math

from .jitter import jitter_evidence
from .model import ModelFit
from .screens import Screen, noise_evidence

__all__ = ["choose", "pick", "alternatives", "evidence", "heteroscedastic", "random_channels", "acc_timing_unidentified",
           "ACC_TIMING_ANCHORS",
           "ALTERNATIVE_MIN_RELATIVE_LIKELIHOOD", "HETEROSCEDASTIC_RATIO", "RANDOM_DOMINANCE", "REFRESH_PASSES", "SATURATION_AT_LIMIT",
           "GYRO_LINEAR_TERMS"]


def choose(screens: list[Screen], threshold: float, n_refit: int) -> list[Screen]:
    ok = [s for s in screens if s.identifiable and s.statistic >= 0.5 * threshold]
    chosen, seen = [], set()
    for s in ok:
        if s.effect.name not in seen:
            chosen.append(s)
            seen.add(s.effect.name)
    chosen = chosen[:n_refit]
    for s in ok[:3]:
        if all(s is not c for c in chosen):
            chosen.append(s)
    return chosen


# An alternative explanation is reported beside a finding when its Akaike relative likelihood
# exp(−ΔAIC/2) against the finding is at least this: the recording cannot rule it out.
ALTERNATIVE_MIN_RELATIVE_LIKELIHOOD = 0.05


def alternatives(best: dict, results: list[dict]) -> list[dict]:
    """The other candidates refitted in the round that accepted ``best`` whose fit is nearly as
    good: relative likelihood exp(((e_alt − 2 df_alt) − (e_best − 2 df_best)) / 2) ≥
    :data:`ALTERNATIVE_MIN_RELATIVE_LIKELIHOOD` (e = noise-robust evidence, both against the same
    model without them; AIC's penalty of 2 per parameter).  Example: on an axis whose specific
    force stays on one side of zero, a² is nearly a linear function of a, and a quadratic
    response is hard to tell from a scale error plus a bias."""
    e_b = best["evidence_robust"] - 2 * best["effect"].df
    out = []
    for r in results:
        if r is best or r["effect"].kind in ("noise", "random"):
            continue
        rel = math.exp(min(0.0, (r["evidence_robust"] - 2 * r["effect"].df - e_b) / 2))
        if rel >= ALTERNATIVE_MIN_RELATIVE_LIKELIHOOD:
            eff = r["effect"]
            out.append({"effect": eff.vocabulary_name or eff.name, "imu": eff.imu, "axis": eff.axis,
                        "evidence": float(r["evidence"]), "df": int(eff.df), "relative_likelihood": rel})
    return sorted(out, key=lambda a: -a["relative_likelihood"])


def evidence(prep, with_fit: ModelFit, without_fit: ModelFit, effect) -> float:
    if effect.kind == "noise":
        return noise_evidence(prep, with_fit, effect)[0]
    if effect.kind == "random":
        return jitter_evidence(prep, with_fit, effect)[0]
    return 2.0 * (with_fit.loglik - without_fit.loglik)



#: is refused (a concealed noise_level gives 1 ± 0.1 at T ≥ 1500 — sampling error only; the real MIMU data 10–40)
HETEROSCEDASTIC_RATIO = 1.25


#: a random effect is accepted in a round where mean effects are acceptable too when its evidence
#: exceeds this many times the best mean candidate's noise-robust evidence
RANDOM_DOMINANCE = 10.0


#: the vocabulary terms a gyro_linear block contains (never round candidates on an IMU that has one)
GYRO_LINEAR_TERMS = ("gyro_bias", "gyro_scale", "gyro_misalignment")

#: a ``saturation`` refit is refused unless at least [1] of its channel's recorded outputs lie within [0] stated
#: noise σ of its limit (:meth:`~accel_bayes.physics.effects.Saturation.outputs_at_limit`).  A clip flattens every
#: peak beyond the range: mismatch_proof's ten concealed clips hold 5–102 outputs at L.  On clockgen recordings
#: that never clip (|a| ≤ 53 m/s² against ±157) the detector accepted limits 16–35 σ above every output, or one
#: that cut a single peak: they clamp the model's overshooting peaks, not the data.  The count 3 was chosen after
#: seeing that single-peak case (``experiments/saturation_guard_probe.md``: 19/19 true kept, 7/7 false refused)
SATURATION_AT_LIMIT = (5.0, 3)

#: alternations of (gyro linear blocks | the rounds' findings) after each accepted finding: a block and
#: a finding on the same gyro share part of their signature (an offset and a second-order response), so
#: one re-estimate of the blocks leaves the finding's parameter biased; three settle it
REFRESH_PASSES = 3


def random_channels(effect) -> tuple:
    """The sensors a random effect's variance acts on ("acc", "gyro")."""
    which = getattr(effect, "which", None)
    if which in ("acc", "gyro"):
        return (which,)
    return ("acc", "gyro") if effect.sensor == "both" else (effect.sensor,)


#: IMUs an accelerometer timing error's common mode needs without a random timing term of their own
ACC_TIMING_ANCHORS = 2


def acc_timing_unidentified(effect, model_effects, K: int) -> bool:
    """True where a random effect on IMU ``effect.imu``'s accelerometer (``timing_wander`` on acc,
    ``sampling_jitter``) would leave fewer than :data:`ACC_TIMING_ANCHORS` of the board's K IMUs
    without one (``model_effects``: the effects already in the model).

    Why: an accelerometer timing error δ_k moves IMU k's output by δ_k·ȧ_k, ȧ_k = R_k(ṡ + ω̈ × r_k + …),
    and the per-sample motion states absorb the part common to the board (Δs = δ·ṡ, Δω̇ = δ·ω̈): after
    the projection only the differences of the δ_k are identified, against the IMUs that carry no
    term (they fix the reference, δ = 0).  With one such IMU left, its own timing error is handed to
    every term: the refit follows it exactly (its residual → 0, leverage → 1) and the termed IMUs
    carry δ_k − δ_ref, correlated where the terms are independent.  Concealed clockgen plate4 at
    100 Hz (clock-010, wanders on 3 of 4 accelerometers): the reference IMU's acc residual² fell to
    0.0003 (m/s²)² (stated noise 0.001), the termed ones rose 2–10×, and adding the third term took
    the §7.2 acc b/a from 0.30 to 0.10 with the top |ω| and |ω̇| bands negative
    (tests/mismatch/test_acc_timing_anchors.py, experiments/clock_budget.md).  With ≥ 2 left the reference is their mean and their own
    difference stays in the residual, where it is seen.  Binds only on boards with K ≤ 4 at the
    default three rounds."""
    if effect.kind != "random" or "acc" not in random_channels(effect):
        return False
    termed = {e.imu for e in model_effects if e.kind == "random" and "acc" in random_channels(e)}
    return len(termed | {effect.imu}) > K - ACC_TIMING_ANCHORS


def heteroscedastic(char: dict, effect, alpha: float) -> str | None:
    """Why a ``noise_level`` candidate contradicts the residuals' structure, or None.

    ``noise_level`` predicts the same excess power at every sample.  Refused when, in its group
    (one IMU's sensor; for imu=None the pooled sensor and each IMU, Bonferroni over the IMUs),
    the characteriser's top covariate
    (:func:`accel_bayes.mismatch.characterise.characterise`) both varies the mean z² by more than
    :data:`HETEROSCEDASTIC_RATIO` between its lowest and highest quintile and is significant at
    α / (number of covariates) by its F test."""
    c = char.get(effect.which)
    if not c:
        return None
    # imu=None claims the same factor for every IMU: any one IMU's structured excess refutes it
    groups = ([(None, c["covariates"], 1)] + [(x["imu"], x["covariates"], len(c["imus"])) for x in c["imus"]]
              if effect.imu is None else
              [(x["imu"], x["covariates"], 1) for x in c["imus"] if x["imu"] == effect.imu])
    for imu, rows, n_groups in groups:
        if not rows:
            continue
        top = rows[0]
        q = top["quintile_mean_z2"]
        lo, hi = min(q), max(q)
        ratio = hi / lo if lo > 0 else math.inf
        if not (ratio > HETEROSCEDASTIC_RATIO and top["log10_p"] < math.log10(alpha / (len(rows) * n_groups))):
            continue
        where = "" if imu is None else f" on IMU {imu}"
        return (f"the excess power{where} varies {ratio:.3g}× across the quintiles of {top['name']} "
                f"(F-test log10 p = {top['log10_p']:.3g}); a constant noise factor does not describe it")
    return None


def pick(results: list[dict], threshold: float, alpha: float, info: dict, characterised) -> dict | None:
    """The candidate a round accepts among its refits ``results`` (step 6), or None: mean and clip
    effects first, a random effect first only where it dominates, the variance explanations only
    where no structured one passes.  Refusals go to ``info["refused"]``; ``characterised()`` gives
    the characterisation of the current fit (computed only when a ``noise_level`` needs it)."""
    variance_kinds = ("noise", "random")
    ok = [r for r in results if r["effect"].kind not in variance_kinds and r["evidence_robust"] > threshold]
    dominant = [r for r in results if r["effect"].kind == "random" and ok
                and r["evidence"] > RANDOM_DOMINANCE * max(x["evidence_robust"] for x in ok)]
    # a timing_wander carries its triad's white-noise excess too: accept it only where the
    # timing term alone passes the threshold, otherwise it is noise_level under another name
    refused_w = [r for r in results if r["effect"].name == "timing_wander"
                 and r["effect"].stats.get("timing_evidence", math.inf) <= threshold]
    for r in refused_w:
        info.setdefault("refused", []).append({"candidate": r["effect"].label(),
                                               "why": f"its timing term alone has evidence "
                                                      f"{r['effect'].stats['timing_evidence']:.4g} <= threshold"})
    results_ok = [r for r in results if r not in refused_w]
    dominant = [r for r in dominant if r not in refused_w]
    if dominant:
        # a correlated timing error looks like structure to every mean candidate, yet each
        # explains a small part of it: a random effect far ahead of all of them goes first
        ok = dominant
    elif not ok:
        ok = [r for r in results_ok if r["effect"].kind in variance_kinds and r["evidence"] > threshold]
        if any(r["effect"].kind == "noise" for r in ok):
            # noise_level says "a constant factor": refuse it where the excess power varies
            # strongly with the motion (the characteriser's covariates), and leave that excess
            # to a better variance model or to the characterised ``unexplained`` finding
            char_now = characterised()
            keep = []
            for r in ok:
                why = heteroscedastic(char_now, r["effect"], alpha) if r["effect"].kind == "noise" else None
                if why is None:
                    keep.append(r)
                else:
                    info.setdefault("refused", []).append({"candidate": r["effect"].label(), "why": why})
            ok = keep
    return min(ok, key=lambda r: r["log10_p"]) if ok else None
