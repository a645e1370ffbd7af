"""Name a mismatch: which physical effect (and where) explains the excess of the residuals.

:func:`detect` is the public entry point (DESIGN §2 "mismatch", §7.2 report v1)::

    report = detect(recording)           # a Recording or a path to a format-v1 file
    report.mismatch_detected, report.findings[0].effect.name, report.to_dict(), report.write("out")

Procedure
---------
1. **Baseline**: the nominal model fitted jointly in geometry and motion
   (:func:`accel_bayes.mismatch.fit.baseline_fit`, started from the package's MAP), on the
   recording prepared as the calibration prepares it (:func:`accel_bayes.mismatch.prepared.prepare`
   through :func:`accel_bayes.prep.preprocess.preprocess`: intrinsics from the rests when it has
   them, rests, flagged-clipped and slowly rotating samples dropped by THE sample selection; a
   reading at the range is censored, not a measurement; unflagged clipping stays in and is the
   ``saturation`` effect's business).
2. **Locate** (:func:`accel_bayes.mismatch.locate.locate`): standardized residuals, excess per
   IMU/axis/regime, posterior predictive check.
3. **Candidates**: every location of every requested effect class
   (:meth:`Effect.candidates`; the identifiability rules are in
   :mod:`accel_bayes.physics.effects`).  m = their number.
3a. **Gyro linear stage** (:mod:`accel_bayes.mismatch.gyro_linear`): every gyroscope's whole
   linear error (3 × 3 scale/misalignment + offset, :class:`~accel_bayes.physics.effects.GyroLinear`,
   12 parameters per IMU) is tested as a group and per IMU, fitted in closed form alternating
   with the motion (its part common to all gyros through the accelerometer lever arms, judged by a
   heteroscedasticity-robust Wald statistic: :func:`~accel_bayes.mismatch.gyro_linear.robust_wald`), and the
   recording is corrected for the blocks that pass; the rounds below run on the corrected
   recording with the blocks held fixed, and never try a gyro scale/misalignment/bias term on
   an IMU that has a block.  Each block is a finding (vocabulary ``gyro_scale``, axis null,
   parameters {"scale": 3 × 3, "bias": 3}); ``max_findings`` counts the rounds' findings only.
   Why: raw MEMS gyros carry all twelve terms on every IMU, and one term per round leaves the
   rest in the residual, where a random timing effect explains them better (1/21 concealed
   multi-effect cases named right before this stage, experiments/mismatch_multi.md).  Skipped
   when ``effects`` does not name ``gyro_linear`` (the default names every effect).
3a'. **Accelerometer linear stage** (opt-in, ``DetectOptions(acc_linear=True)``;
   :mod:`accel_bayes.mismatch.acc_linear`): the same for every accelerometer triad
   (:class:`~accel_bayes.physics.effects.AccLinear`, vocabulary ``acc_scale`` axis null), regressed on
   the fitted specific force, without a common part, its spread tested by inverting the strongest
   triad's block alone; where ``prep`` calibrated the triads from the rests, on those outputs (what the
   rests leave: a chip's rotation on the board, offsets in motion).  The rounds then
   never try an acc bias/scale/misalignment term on a triad that has a block.
3b. **Clock stage** (:mod:`accel_bayes.mismatch.clock`): on every IMU with a gyroscope, a
   ``sampling_clock`` (:class:`~accel_bayes.physics.effects.SamplingClock`: the data age a sawtooth
   beating against the read rate, shared by the IMU's acc and gyro) found by a beat-frequency search
   on the gyro's restricted timing statistics (those ``timing_wander`` is fitted on), accepted where
   its evidence against no clock *and* against the best AR(1) instant error (``timing_wander``; its
   ρ = 0 end is white jitter) both exceed the stage threshold (the threshold below, or the χ²₄
   look-elsewhere quantile over the (beat, drift) cells searched if larger) and its width is
   physical.  The recording is corrected for the accepted clocks, which are held fixed from here
   on like the gyro blocks; one finding per IMU, not counted by ``max_findings``.  Skipped when
   ``effects`` does not name ``sampling_clock``.
3c. **Filter delay** (:mod:`accel_bayes.mismatch.filter_delay`): the accelerometer's filter delay
   beyond the gyroscope's, one for the clocked IMUs, reported where the data identify it (not
   applied to the recording); else ``filter_delay_acc_minus_gyro_s`` is reported null with the reason.
4. **Screen** every candidate cheaply at the current fit (:mod:`accel_bayes.mismatch.screens`: score
   tests of the mean effects, the restricted likelihood ratio of ``noise_level``, the profiled
   marginal of the random effects, the clamp gain of ``saturation``).
5. **Refit** the best screened candidates by LM and take their **evidence**; 6. **Accept** one per
   round, at most ``max_findings`` rounds, then recompute every finding's evidence with the
   others in the model (drop-one): the rules are in :mod:`accel_bayes.mismatch.choose`.  A refit is
   refused when its constant parameter is not constant across time segments, and a ``saturation``
   refit when fewer than 3 recorded outputs lie within 5σ of its limit
   (:data:`~accel_bayes.mismatch.choose.SATURATION_AT_LIMIT`: a clamp no output reaches cuts the
   model's overshooting peaks, not the data).
7. **Unexplained**: at the final model, the located-excess tests of
   :func:`accel_bayes.mismatch.locate.excess_cells` (free mean and variance per regime bin, χ²_2B),
   Bonferroni-corrected over the cells × schemes tested; a significant one that also exceeds the
   threshold is reported as an ``unexplained`` finding with its location.  The cells are ranked
   by a p-value that stays finite for any statistic (:func:`accel_bayes.mismatch.locate.log10_chi2_sf`;
   with SciPy's underflowing ``logsf`` every cell beyond χ² ≈ 1400 tied at −inf and the first
   cell enumerated — IMU 0, accelerometer x — was reported whatever the data).
7a. **Unresolved motion** (:mod:`accel_bayes.mismatch.unresolved_stage`): with accepted clocks on
   ≥ 2 IMUs, ``unresolved_motion`` — per-sample jerk and angular acceleration common to the board,
   loaded by the clocks' data ages, marginalised — tested per |ω| band and sensor at the final
   model and kept per sensor where it passes its permutation test, then fitted per |ω| × |ω̇|
   cell with the age error the clocks do not give; random timing effects it supersedes are
   withdrawn and the model refitted without them; a finding (imu null) when either sensor keeps
   it, its log-likelihood gain added to ``refined.loglik``, its predicted variance part of the
   budget's b.  Not capped by ``max_findings``.  Opt-in (``unresolved_angular_jerk``, CLI
   ``--unresolved-angular-jerk``): the accelerometer term also carries the board's unresolved angular
   jerk through each triad's lever arm (``experiments/budget_gap_probe.md`` measures it).
8. **Budget** (:func:`accel_bayes.mismatch.budget.residual_budget`, vocabulary 1.1): per sensor and
   per |ω| and |ω̇| quantile band of the baseline motion, the excess variance the baseline leaves
   (a, leverage-corrected squared residual minus the stated variance) and the part the final
   model accounts for (b, the squared residual its mean effects remove — both fits' residuals
   projected off the motion states in the stated noise's whitening, so the refit's weights do not
   count as a removal — plus the variance its variance effects predict); b = 0 when nothing was
   found.  Reported also with ``refine=False``.

Threshold rule (reported as ``threshold``): Bonferroni over the m tests made (the round
candidates, plus the gyro linear stage's group test and one test per gyro),

    threshold = χ²_{d_max} quantile at 1 − α/m,

with d_max the largest number of parameters of any candidate (3).  One number for every finding,
conservative for candidates with fewer parameters (and for ``sampling_jitter``, whose boundary
null ½χ²₀ + ½χ²₁ is not used to lower it).  The gyro linear stage holds its group to χ²_{12n}, each
block to χ²_12 and each block's terms to χ²_1, all at 1 − α/m.  Findings are ranked by the p-value of their
evidence under χ²_df (most supported first; equal to ranking by evidence for equal df).

Budget: one baseline fit, one screen per round (vectorised algebra, a few ms per candidate) and
at most ``n_refit`` LM refits per round (``noise_level`` ones only in a round that needs them);
every sample the prepared selection keeps is used.  ``experiments/bench_detect.py`` (one thread):
the whole real MIMU exp_1 (5885 samples kept, 8 IMUs; gyro linear stage, blocks on all eight gyros,
three rounds, each random effect refitted by GLS) in 64 s and a 32-IMU, T = 3000 recording in 27 s,
at load ≈ 1 on the shared 2-core machine (``experiments/bench_detect.md``; 7adf109: 123 s and 27 s).
The GLS refits of the random effects (a few more LM solves each) doubled the time on exp_1 (37 s
before them).
"""
from __future__ import annotations

import time as _time

import numpy as np

from ..data.io import load_recording
from ..constants import ACC_OUTPUTS
from ..errors import UserError
from ..physics.effects import Unexplained
from ..threads import torch_threads
from .budget import group_power, residual_budget
from .characterise import characterise, describe
from .choose import GYRO_LINEAR_TERMS, REFRESH_PASSES, SATURATION_AT_LIMIT, acc_timing_unidentified, alternatives, choose, evidence, pick, \
    random_channels
from .clock import clock_corrected, clock_stage
from .compare import compare_fits, posterior_comparison
from .filter_delay import filter_delay
from .fit import _effect_std, baseline_fit, fit_model
from .acc_linear import ACC_LINEAR_TERMS, acc_linear_stage, restage
from .gyro_linear import block_corrected_recording, gyro_linear_stage, refresh_blocks
from .linear_blocks import LinearStage, block_arrays, corrected_outputs
from .locate import locate, log10_chi2_sf, regime_concentration, regimes, time_window
from .options import DetectOptions
from .prepared import prepare
from .report import Finding, MismatchReport
from .screens import STATIONARITY_SEGMENTS, Screen, candidate_effects, log10_p, screen, stationarity, threshold_rule
from .unresolved_stage import supersede_random_timing, unresolved_stage

__all__ = ["detect"]


def _check_recording(rec) -> None:
    """Refuse (one line) a recording the detector cannot judge, before any fit."""
    from ..prep.selection import DEFAULT_MIN_ROTATION, rotation_rate

    if rec.T < 3:
        raise UserError(f"time: mismatch detection needs at least 3 samples, the recording has {rec.T}")
    w = rotation_rate(rec)
    # Without rotation ω = ω̇ = 0 and every effect that acts through the rotation (axis_displacement,
    # the lever arms, time_offset, gyro_scale, gyro_nonlinearity, sampling_jitter) leaves no trace:
    # "no mismatch detected" would be a verdict on effects that were never testable.
    if not np.nanmax(w) >= DEFAULT_MIN_ROTATION:
        raise UserError(f"gyro: the recording does not rotate (largest mean gyro rate |w| {np.nanmax(w):.3g} rad/s < "
                        f"{DEFAULT_MIN_ROTATION} rad/s); the rotation-dependent effects cannot be tested; "
                        "record the array in motion")


def detect(recording, options: DetectOptions | None = None, **keywords) -> MismatchReport:
    """Find, name and fix model mismatch in one recording (module docstring).

    recording : :class:`~accel_bayes.data.recording.Recording` or path to a format-v1 file (needs
        gyroscope data).
    options : a :class:`~accel_bayes.mismatch.options.DetectOptions` (every option, checked at
        construction; its docstring lists them).  Or the same options as keywords (``effects=…,
        alpha=…, max_findings=…, refine=…, posterior=…, seed=…, progress=…, n_twins=…, n_refit=…,
        use_map=…, loo_draws=…, unresolved_permutations=…, threads=…``), the 0.2 form, which builds
        the record; not both.

    Returns a :class:`~accel_bayes.mismatch.report.MismatchReport`.
    """
    if options is None:
        options = DetectOptions(**keywords)
    elif not isinstance(options, DetectOptions):
        raise UserError(f"options: expected a DetectOptions, got {type(options).__name__}")
    elif keywords:
        raise UserError(f"options: give a DetectOptions or keywords, not both (got {sorted(keywords)})")
    with torch_threads(options.threads):
        return _detect(recording, options)


def clock_explanation(c) -> str:
    """A clock finding's explanation: the effect's own, and where the clock stage searched the IMU a second
    time (:mod:`accel_bayes.mismatch.clock`, "Leaks") what its first pick was and whose copy."""
    text = c.explain()
    st = c.stats or {}
    if st.get("second_look"):
        text += (f" Searched a second time with the other clocks taken out: the first pick "
                 f"({st['first_look_beat_mid_hz']:+.3f} Hz at the recording's middle) sat on ± IMU "
                 f"{st['leak_of_imu']}'s beat, which leaks into every other IMU's residual through the fitted rate.")
    return text


def _stage_findings(prep, reg, stages, clock, fd) -> list[Finding]:
    """The findings of the stages held fixed in the rounds: one per accepted clock (its filter delay
    as :func:`~accel_bayes.mismatch.filter_delay.filter_delay` found it) and one per block of the
    linear ``stages`` (gyro, then accelerometer; None where a stage did not run)."""
    out = []
    for c in (clock.clocks if clock is not None else []):
        ev = float(c.stats["evidence"])
        out.append(Finding(effect=c, evidence=ev, df=c.df, log10_p=log10_chi2_sf(ev, 4),
                           where={"regime": "all regimes", "time_s": None}, explanation=clock_explanation(c),
                           screen_statistic=None, orientations=prep.q,
                           parameters_reported={"filter_delay_acc_minus_gyro_s": fd["value_s"]},
                           extra={"evidence_kind": "2·Δlog L of the gyro's restricted timing statistics, "
                                                   "white-noise factor profiled (mismatch.clock)",
                                  "evidence_vs_wander": float(c.stats["evidence_vs_wander"]),
                                  "filter_delay_acc_minus_gyro": fd,
                                  "units": {p.name: p.unit for p in c.parameters}}))
    for stage in stages:
        for e in (stage.blocks if stage is not None else []):
            ev = float(e.stats["statistic_robust"])
            kind = ("the block's conditional likelihood ratio at the final rates over max(1, P) (gyro linear stage)"
                    if stage.sensor == "gyro" else "the block's conditional likelihood ratio at the stage's specific "
                                                   "force over max(1, P) (accelerometer linear stage)")
            out.append(Finding(effect=e, evidence=ev, df=e.df, log10_p=log10_chi2_sf(ev, e.df),
                               where=regime_concentration(prep, reg, stage.gain_t), explanation=e.explain(),
                               screen_statistic=None, orientations=prep.q,
                               extra={"evidence_kind": kind, "evidence_raw": float(e.stats["statistic"])}))
    return out


def without_withdrawn(findings: list[Finding], withdrawn: list[dict]) -> list[Finding]:
    """``findings`` less those whose fitted effect a later step withdrew (``withdrawn``: dicts whose
    ``"effect"`` is the withdrawn effect's label, ``timing_wander[imu=2,sensor=acc]``).  A
    :class:`Finding`'s ``effect`` is its vocabulary *name*; the fitted effect, whose label locates
    it, is its ``model`` (until 2026-11-28 the filter read ``effect``, matched nothing, and the
    report kept superseded findings whose terms its refined model no longer had)."""
    gone = {g["effect"] for g in withdrawn}
    return [f for f in findings if not (hasattr(f.model, "label") and f.model.label() in gone)]


def _unexplained(prep, loc_final, characterisation, threshold, alpha) -> Finding | None:
    """Step 7: the strongest located excess at the final model, if significant (module docstring)."""
    from scipy.stats import chi2

    tests = loc_final.excess_tests
    if not tests:
        return None
    m_u = len(tests)
    top = tests[0]
    thr_u = float(chi2.isf(alpha / m_u, top["df"]))
    if not (top["statistic"] > thr_u and top["statistic"] > threshold):
        return None
    # the same cell's strongest regime bin and time window, where each is significant
    same = [t for t in tests if (t["imu"], t["sensor"], t["axis"]) == (top["imu"], top["sensor"], top["axis"])]
    sig = [t for t in same if t["statistic"] > float(chi2.isf(alpha / m_u, t["df"]))]
    reg_t = next((t for t in sig if t["scheme"] != "time"), None)
    time_t = next((t for t in sig if t["scheme"] == "time"), None)
    tw = time_window(prep, loc_final.reg, time_t["contributions"]) if time_t is not None else None
    where = {"regime": reg_t["bin"] if reg_t is not None else None, "time_s": tw,
             "scheme": top["scheme"], "bin": top["bin"]}
    char_u = characterisation.get(top["sensor"]) if top["sensor"] in ("acc", "gyro") else None
    imu_c = None if char_u is None else next((r for r in char_u["imus"] if r["imu"] == top["imu"]), None)
    u = Unexplained(imu=top["imu"], axis=top["axis"], sensor=top["sensor"], where=where,
                    excess={"chi2_ratio": top["chi2_ratio"], "mean_z": top["mean_z"],
                            "scheme": top["scheme"], "bin": top["bin"], "df": top["df"], "threshold": thr_u,
                            "scales_with": None if imu_c is None else imu_c["top_covariate"],
                            "lag1_autocorrelation": None if imu_c is None else imu_c["autocorrelation"].get("lag1"),
                            "anisotropy": None if imu_c is None else imu_c["anisotropy"]},
                    characterisation=None if imu_c is None else describe(char_u, top["sensor"], top["imu"]))
    return Finding(effect=u, evidence=float(top["statistic"]), df=int(top["df"]), log10_p=float(top["log10_p"]),
                   where=dict(u.where), explanation=u.explain(), screen_statistic=None)


def _detect(recording, o: DetectOptions) -> MismatchReport:
    t_start = _time.perf_counter()
    alpha, names, seed = o.alpha, None if o.effects is None else list(o.effects), o.seed
    loaded = load_recording(recording, require_gyro=True)
    rec, source = loaded.recording, None if loaded.path is None else str(loaded.path)
    _check_recording(rec)
    say = (lambda msg: print(f"[mismatch {(_time.perf_counter() - t_start):6.1f} s] {msg}", flush=True)) if o.progress \
        else (lambda msg: None)
    timings = {}
    prep = prepare(rec)
    t0 = _time.perf_counter()
    base, base_info = baseline_fit(prep, use_map=o.use_map, progress=False)
    timings["baseline_fit_s"] = _time.perf_counter() - t0
    say(f"baseline fit: χ²/dof = {base.chi2_per_dof:.4g} ({base_info['start']} start)")
    t0 = _time.perf_counter()
    loc0 = locate(prep, base, n_twins=o.n_twins, seed=seed)
    timings["locate_s"] = _time.perf_counter() - t0
    say(f"locate: {loc0.summary}")

    cands_all = candidate_effects(prep, names)
    n_gyro = int(np.asarray(prep.has_gyro).sum())
    gyro_stage = (names is None or "gyro_linear" in names) and n_gyro >= 2
    n_acc = int(np.asarray(prep.has_acc).sum())
    # the acc stage: opt-in; where prep calibrated the triads from the rests it estimates what they leave,
    # on the rest-calibrated outputs (acc_linear's docstring)
    acc_stage_on = o.acc_linear and (names is None or "acc_linear" in names) and n_acc >= 2
    # Bonferroni over every test: the round candidates, and the stages' group and per-block tests
    m = len(cands_all) + (n_gyro + 1 if gyro_stage else 0) + (n_acc + 1 if acc_stage_on else 0)
    df_max = max([c.df for c in cands_all] + [1])
    threshold = threshold_rule(m, df_max, alpha)
    say(f"{m} candidates, threshold {threshold:.4g} (χ²_{df_max}, 1 − {alpha}/{m})")

    current = base
    accepted: list[dict] = []
    rounds = []
    t0 = _time.perf_counter()
    stage = None
    prep0 = prep
    if gyro_stage:
        # step 3a: every gyro's linear error, held fixed from here on (the rounds run on the recording
        # corrected for it: accel_bayes.mismatch.gyro_linear)
        # (its common part, seen through the accelerometers' lever arms, waits for their stage when it runs)
        stage = gyro_linear_stage(prep, base, m=m, alpha=alpha, common=not acc_stage_on)
        prep0, prep, current = prep, stage.prep, stage.fit
        say(f"gyro linear stage: {stage.info['result']}")
    timings["gyro_linear_s"] = _time.perf_counter() - t0
    acc_stage = None
    if o.acc_linear and not acc_stage_on:  # asked for, not run: the report says why
        why = ("effects does not name acc_linear" if names is not None and "acc_linear" not in names
               else f"{n_acc} accelerometer triad(s): a block is relative to the others")
        acc_stage = LinearStage(prep, current, [], None, {"result": f"not run: {why}"}, "acc")
        say(f"acc linear stage: not run ({why})")
    if acc_stage_on:
        # step 3a': every accelerometer's linear error, held fixed from here on like the gyro blocks
        # (accel_bayes.mismatch.acc_linear)
        t0 = _time.perf_counter()
        acc_stage = acc_linear_stage(prep, current, m=m, alpha=alpha)
        if stage is not None and (acc_stage.blocks or stage.blocks):
            # the gyro stage's common part is seen through the accelerometers' lever arms: now that they are
            # corrected (or found without error), both stages again, the gyros' first with it (acc_linear.restage)
            stage, acc_stage = restage(prep0, acc_stage, m=m, alpha=alpha)
        if acc_stage.blocks:
            # prep0 (what the gyro blocks' refresh re-corrects) carries the acc correction too
            prep0 = corrected_outputs(prep0, *block_arrays(acc_stage.blocks, prep.K), "acc")
            if stage is not None:
                stage.prep, stage.fit = acc_stage.prep, acc_stage.fit
        if acc_stage.blocks or "restaged" in acc_stage.info:
            prep, current = acc_stage.prep, acc_stage.fit
        # which outputs the blocks act on: calibrate inverts them only on the same (model.report_terms)
        acc_stage.info["outputs"] = ACC_OUTPUTS[bool(prep.preparation["intrinsics"]["applied"])]
        say(f"acc linear stage: {acc_stage.info['result']}")
        timings["acc_linear_s"] = _time.perf_counter() - t0
    t0 = _time.perf_counter()
    clock = None
    fd = {"value_s": None, "std_s": None, "identified": False, "reason": "no clock stage"}
    if (names is None or "sampling_clock" in names) and prep.gyro_rate is not None:
        # step 3b: every IMU's sampling clock, held fixed from here on like the gyro blocks (not a
        # round candidate, so not capped by max_findings: accel_bayes.mismatch.clock)
        clock = clock_stage(prep, current, m=m, alpha=alpha, threshold=threshold)
        if clock.clocks:
            if stage is not None:  # the blocks' refresh re-corrects prep0: it must carry the clocks too
                prep0 = clock_corrected(prep0, current, clock.clocks)
                stage.prep, stage.fit = clock.prep, clock.fit
            prep, current = clock.prep, clock.fit
            # step 3c: the accelerometers' filter delay beyond the gyros', reported where identified
            # (not applied: accel_bayes.mismatch.filter_delay says why)
            fd = filter_delay(prep, current, [c.imu for c in clock.clocks])
        again = clock.info.get("second_look") or []
        say(f"clock stage: sampling_clock on IMUs {clock.info['accepted']}"
            + (f" (searched a second time, a pick on another IMU's copied beat: {again})" if again else "")
            + f"; filter delay {fd['value_s'] if fd['identified'] else 'not identified'}")
    timings["clock_s"] = _time.perf_counter() - t0
    blocked = {e.imu for e in stage.blocks} if stage is not None else set()
    acc_blocked = {e.imu for e in acc_stage.blocks} if acc_stage is not None else set()
    last_screens: list[Screen] = []
    for rnd in range(int(o.max_findings)):
        in_model = {e.label() for e in current.effects}
        taken = {(e.imu, ch) for e in current.effects if e.kind == "random" for ch in random_channels(e)}
        # one random effect per IMU and sensor: two would each be profiled as if alone and
        # count the same variance twice; no gyro scale/misalignment/bias term where a gyro_linear
        # block already holds all twelve
        pool = [c.copy() for c in cands_all if c.label() not in in_model
                and not (c.kind == "random" and any((c.imu, ch) in taken for ch in random_channels(c)))
                and not (c.name in GYRO_LINEAR_TERMS and c.imu in blocked)
                and not (c.name in ACC_LINEAR_TERMS and c.imu in acc_blocked)
                and not acc_timing_unidentified(c, current.effects, prep.K)]
        ts = _time.perf_counter()
        screens = screen(prep, current, pool)
        last_screens = screens
        chosen = choose(screens, threshold, o.n_refit)
        info = {"round": rnd + 1, "screen_s": _time.perf_counter() - ts,
                "screen_top": [s.to_dict() for s in screens[:10]], "refits": []}
        say(f"round {rnd + 1}: screened {len(screens)}; refitting {[s.effect.label() for s in chosen]}")
        h_cur = current.linear().h
        results = []

        def refit(sc):
            cand = sc.effect
            try:
                model_eff = [e.copy() for e in current.effects] + [cand]
                f = fit_model(prep, model_eff, init=current, laplace=False)
            except Exception as exc:  # a candidate that cannot be fitted is reported, not fatal
                info["refits"].append({"candidate": cand.label(), "error": f"{type(exc).__name__}: {exc}"})
                return
            ev = evidence(prep, f, current, cand)
            # noise-robust evidence of mean effects: the LR over the residual power left in the
            # effect's IMU/sensor group (an F-test-like guard: noise larger than stated inflates
            # every mean candidate's LR by the same factor)
            power = 1.0 if cand.kind in ("noise", "random") else group_power(prep, f, cand, h_cur)
            ev_r = ev / max(power, 1.0)
            lp = log10_p(ev_r, cand)
            row = {"candidate": cand.label(), "evidence": ev, "evidence_robust": ev_r,
                   "group_power_after": power, "df": cand.df, "log10_p": lp,
                   "screen_statistic": sc.statistic, "seconds": f.seconds}
            refused_why = None
            if cand.kind == "mean" and ev_r > threshold:
                # a constant parameter must be constant: the score test across time segments
                # (noise-robust like the evidence), at the same family-wise level
                q, q_df = stationarity(prep, f, f.effects[-1])
                q_r = q / max(power, 1.0)
                q_thr = threshold_rule(m, q_df, alpha)
                row.update({"stationarity": q_r, "stationarity_df": q_df, "stationarity_threshold": q_thr})
                if q_r > q_thr:
                    refused_why = (f"its parameter is not constant through the recording: stationarity score "
                                   f"{q_r:.4g} > {q_thr:.4g} (χ²_{q_df}, {STATIONARITY_SEGMENTS} time segments)")
            if cand.kind == "clip" and ev_r > threshold and refused_why is None:
                # a clip holds outputs at its limit; a fitted limit that none reaches cuts the model's own
                # overshooting peaks (choose.SATURATION_AT_LIMIT says how this was measured)
                y, sig, msk = ((prep.y_acc, prep.sigma_acc, prep.m_acc) if cand.which == "acc"
                               else (prep.y_gyro, prep.sigma_gyro, prep.m_gyro))
                n_at = f.effects[-1].outputs_at_limit(y, sig, SATURATION_AT_LIMIT[0], msk)
                row["outputs_at_limit"] = n_at
                if n_at < SATURATION_AT_LIMIT[1]:
                    refused_why = (f"{n_at} recorded output(s) within {SATURATION_AT_LIMIT[0]:g} σ of its limit "
                                   f"±{float(f.effects[-1].params['limit']):.4g} (a clip holds at least "
                                   f"{SATURATION_AT_LIMIT[1]}): it cuts the model's peaks, not the outputs")
            info["refits"].append(row)
            f.drop_linear()
            results.append({"effect": f.effects[-1], "fit": f, "evidence": ev, "evidence_robust": ev_r,
                            "log10_p": lp, "screen": sc, "without": current, "refused_why": refused_why})

        for sc in chosen:
            if sc.effect.kind != "noise":
                refit(sc)
        # noise_level is only considered in a round where no mean/clip candidate is acceptable
        # (choose.pick), so its refits are only done then: each one is up to ``noise_rounds`` + 1
        # LM solves, and on a badly fitting recording (real MIMU data, χ²/dof ~ 3000) they were
        # 3/4 of the detector's time while their result could not change the verdict.
        for r in [r for r in results if r.get("refused_why")]:
            info.setdefault("refused", []).append({"candidate": r["effect"].label(), "why": r["refused_why"]})
        results = [r for r in results if not r.get("refused_why")]
        mean_ok = any(r["effect"].kind not in ("noise", "random") and r["evidence_robust"] > threshold for r in results)
        for sc in chosen:
            if sc.effect.kind == "noise":
                if mean_ok:
                    info["refits"].append({"candidate": sc.effect.label(), "screen_statistic": sc.statistic,
                                           "skipped": "a mean/clip candidate is acceptable in this round"})
                else:
                    refit(sc)
        rounds.append(info)
        best = pick(results, threshold, alpha, info, lambda: characterise(prep, current))
        if best is None:
            say("no further candidate above the threshold")
            break
        say(f"accepted {best['effect'].label()} (evidence {best['evidence']:.4g})")
        best["alternatives"] = alternatives(best, results)
        accepted.append(best)
        current = best["fit"]
        if stage is not None and stage.blocks:
            # the blocks were fitted without this finding: re-estimate them given it (gyro_linear.refresh_blocks)
            for _ in range(REFRESH_PASSES):
                current = refresh_blocks(prep0, stage, current)
            prep = stage.prep
    timings["detection_s"] = _time.perf_counter() - t0

    # ---- evidence with all other findings in the model (drop-one); a finding whose evidence falls
    # to the threshold or below once the others are in the model is withdrawn and the model refitted
    t0 = _time.perf_counter()
    withdrawn = []
    while True:
        drops = []
        for i, acc_ in enumerate(accepted):
            eff = current.effects[i]
            if len(accepted) > 1:
                others = [e.copy() for j, e in enumerate(current.effects) if j != i]
                without = fit_model(prep, others, init=current, laplace=False)
                ev = evidence(prep, current, without, eff)
            else:
                without, ev = acc_["without"], acc_["evidence"]
            drops.append((ev, without))
        weakest = min(range(len(drops)), key=lambda i: drops[i][0]) if drops else None
        if weakest is None or drops[weakest][0] > threshold:
            break
        withdrawn.append({"effect": current.effects[weakest].label(), "evidence": drops[weakest][0]})
        say(f"withdrew {current.effects[weakest].label()} (evidence {drops[weakest][0]:.4g} with the others in the model)")
        current = drops[weakest][1]
        accepted.pop(weakest)
    if accepted:
        _effect_std(current, [e for e in current.effects if e.kind in ("mean", "clip")])
    reg = regimes(prep, current)
    findings: list[Finding] = []
    for i, acc_ in enumerate(accepted):
        eff = current.effects[i]
        ev, without = drops[i]
        gain = (current.loglik_t - without.loglik_t).numpy()
        where = {"regime": "all regimes", "time_s": None} if eff.kind == "noise" \
            else regime_concentration(prep, reg, gain)
        findings.append(Finding(effect=eff, evidence=float(ev), df=eff.df, log10_p=log10_p(ev, eff),
                                where=where, explanation=eff.explain(), screen_statistic=acc_["screen"].statistic,
                                orientations=prep.q,
                                extra={"evidence_when_added": acc_["evidence"],
                                       "evidence_noise_robust": acc_["evidence_robust"],
                                       "alternatives": acc_.get("alternatives", []),
                                       # a wander's estimated instants (jitter.random_offsets): mean, rms, s
                                       **({"instants_s": {"mean": eff.stats["instant_mean_s"],
                                                          "rms": eff.stats["instant_rms_s"]}}
                                          if "instant_mean_s" in eff.stats else {})}))
    findings += _stage_findings(prep, reg, (stage, acc_stage), clock, fd)
    fixed = list(stage.blocks) if stage is not None else []
    fixed += list(acc_stage.blocks) if acc_stage is not None else []
    fixed += list(clock.clocks) if clock is not None else []
    timings["evidence_s"] = _time.perf_counter() - t0

    # ---- step 7a: unresolved motion through the clocks' data ages, at the final model
    t0 = _time.perf_counter()
    unres = None
    if clock is not None and clock.clocks:
        kw = dict(threshold=threshold, alpha=alpha, m=m, n_permutations=o.unresolved_permutations, seed=seed + 2,
                  angular_jerk=o.unresolved_angular_jerk)
        unres = unresolved_stage(prep, current, clock.clocks, **kw)
        unres, current, gone = supersede_random_timing(prep, current, clock.clocks, unres, **kw)
        if gone:  # their findings leave the report; the refit without them is the final model
            withdrawn += gone
            findings = without_withdrawn(findings, gone)
            say("superseded by the unresolved motion's age error: " + ", ".join(g["effect"] for g in gone))
        say(f"unresolved motion: kept on {unres.info.get('kept', [])} (evidence {unres.evidence:.4g})")
        if unres.effect is not None:
            fixed.append(unres.effect)
            findings.append(Finding(effect=unres.effect, evidence=unres.evidence, df=unres.effect.df,
                                    log10_p=log10_chi2_sf(unres.evidence, unres.effect.df),
                                    where={"regime": "all |omega| bands", "time_s": None},
                                    explanation=unres.effect.explain(), screen_statistic=None,
                                    extra={"evidence_kind": "2·Δlog L of the marginal (scales per |omega| x |omega_dot| "
                                                            "cell, white variance per IMU, age error) against white "
                                                            "variances per IMU and |omega| band; the ages tested by "
                                                            "permuting them within bands (mismatch.unresolved_stage)",
                                           "loglik_gain": unres.loglik_gain}))
    timings["unresolved_s"] = _time.perf_counter() - t0

    # ---- unexplained located excess at the final model
    t0 = _time.perf_counter()
    loc_final = loc0 if current is base else locate(prep, current, n_twins=o.n_twins, seed=seed + 1)
    # what the final model leaves, described (item 2 of issue #11): what it scales with, white or
    # correlated in time, along the output's rate (timing-like) or isotropic
    t_c = _time.perf_counter()
    characterisation = characterise(prep, current, coupling=True)
    timings["characterise_s"] = _time.perf_counter() - t_c
    unexplained = _unexplained(prep, loc_final, characterisation, threshold, alpha)
    if unexplained is not None:
        findings.append(unexplained)
    timings["unexplained_s"] = _time.perf_counter() - t0
    findings.sort(key=lambda f: f.log10_p)

    # ---- refined model and comparison
    refined = comparison = post = None
    t0 = _time.perf_counter()
    if o.refine and (accepted or fixed):
        refined = current
        comparison = compare_fits(base, refined, draws=o.loo_draws, seed=seed)
        say(f"refined: χ²/dof {base.chi2_per_dof:.4g} → {refined.chi2_per_dof:.4g}")
        if o.posterior:
            lin = [e for st in (stage, acc_stage) if st is not None for e in st.blocks]
            fixed_src = None if stage is None and acc_stage is None else block_corrected_recording(prep.source, lin)
            post = posterior_comparison(prep.source, refined, o.posterior, seed=seed, progress=o.progress,
                                        corrected_base=fixed_src, index=prep.selection.index)
    timings["refine_s"] = _time.perf_counter() - t0
    # residual budget (vocabulary 1.1): against the model with the findings, also with
    # refine=False (it is fitted already); b = 0 where nothing was found
    extra = [unres.effect] if unres is not None and unres.effect is not None else []
    budget = residual_budget(prep, base, None if current is base and not extra else current, extra=extra)
    timings["total_s"] = _time.perf_counter() - t_start
    settings = o.to_settings()
    return MismatchReport(
        findings=findings, baseline_fit=base, refined_fit=refined, threshold=threshold, alpha=alpha, n_candidates=m,
        df_max=df_max, location=loc0, location_after=None if current is base else loc_final,
        comparison=comparison, posterior=post, settings=settings, timings=timings, rounds=rounds,
        withdrawn=withdrawn, budget=budget,
        screens=[s.to_dict() for s in last_screens[:20]], baseline_info=base_info, source=source,
        recording_info={"T": prep.T, "K": prep.K, "reference_imu": prep.ref, "description": rec.description,
                        "T_given": int(len(rec.time)), "dropped_clipped": int(prep.n_dropped_clipped),
                        "preparation": prep.preparation,
                        "sample_rate_hz": rec.sample_rate},
        prep=prep, characterisation=characterisation,
        gyro_linear=None if stage is None else stage.info,
        acc_linear=None if acc_stage is None else acc_stage.info,
        fixed_effects=fixed,
        clock=None if clock is None else {**clock.info, "filter_delay_acc_minus_gyro": fd},
        unresolved=None if unres is None else unres.info,
    )
