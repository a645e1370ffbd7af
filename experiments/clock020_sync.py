#!/usr/bin/env python3
"""Which sensor's asynchrony carries clock-020's r[5, y] bias, and is it in the model's span?  (issue #30)

``experiments/clock020_oracle.md`` traced clockgen clock-020's failure of issue #30's concealed bar
(r[5, y] at z ≈ 5 under ``calibrate --model``) to its three rotational impacts, and
``experiments/clock020_impacts.md`` ruled out the DLPF's rectification and a larger unresolved-motion
scale.  Here each piece of the sampling asynchrony is taken off with the generator's truth (this
script's own oracle, written apart from the package), or one modelling choice changed, and the case
calibrated as percov_conceal's ``with_angjerk`` (the default ``calibrate --model``, untempered) with
the case's own ``detect`` report unless said:

* ``as_drawn`` — the reference row;
* ``twin`` — clockgen's synchronised twin of the case (every internal tick on a read, no read skew;
  same motion, errors and noise), with its own ``detect`` report;
* ``acc_synchronised`` — each accelerometer's output replaced by its own DLPF output at t̄, the mean
  over the IMUs of the register ticks of that read (a cubic spline of the filter output on the IMU's
  ~1 kHz ticks), i.e. the accelerometers' data-age effect taken off to all orders;
* ``acc_first_order_kept`` — as above plus d_k·F_k'(t̄) (d_k = tick_k − t̄): only the orders ≥ 2 of
  the age effect taken off;
* ``gyro_synchronised`` — the same for the gyros (the accelerometers as drawn);
* ``lever_truth`` / ``lever_map`` — the angular jerk's lever arms (a covariate, nominal positions by
  default) from the true positions / from the flat MAP;
* ``acc_clock_correction_off`` — the clocks' mean correction of the accelerometer outputs
  (+age·ẏ, ẏ by differences of the 125 Hz outputs, which the impacts alias) skipped, the gyros' kept;
* ``windows_projected`` — the unresolved jerk's and angular jerk's scales set to 10⁵ m/s³ and 10⁷ rad/s³
  on the samples of the impacts (onset − 5 ms to onset + 40τ + 5 ms), about 20–100 × the impacts' own
  (rms over the windows 1.0·10³ m/s³ and 1.4·10⁵ rad/s³, max 5.6·10³ and 9.0·10⁵, by differences of
  the generator's truth), which projects the age loadings out there (the type-II scales elsewhere);
* ``windows_projected_true_ages`` — as above with the report's clocks replaced by the generator's
  (:func:`experiments.clock020_oracle.variant_report`, ``d_oracle_acc_timing``: true beat, phase,
  drift and each accelerometer's filter delay and read skew);
* ``true_acc_delays`` / ``windows_projected_true_acc_delays`` — the report's clocks (beat, phase, drift)
  kept, each clocked IMU's accelerometer delay beyond its gyro (``filter_delay_acc_minus_gyro_s``, one
  board value in the report) replaced by the generator's own per IMU (DLPF difference − read skew,
  :func:`experiments.clock020_oracle.true_acc_delay`), without / with the windows' scales as above;
* ``windows_projected_true_clocks_0_2`` — the windows' scales with the report's four clocks kept and the
  generator's clocks given to the two IMUs the report leaves unclocked (0 and 2; the report's board
  delay, ``clock020_oracle``'s ``b_oracle_0_2``);
* ``mixture_true_ages`` — ``--mixture``'s plug-in with the widest set (×{1 … 10⁴}) on the generator's clocks;
* ``impact_cells_true_ages`` / ``omega_dot_cells_true_ages`` — ``clock020_impacts.md``'s type-II scales per
  |ω| band × in/out of the impact windows (an oracle of where they are) / × |ω̇| quantile band, with the
  generator's clocks as above: do accurate ages let the evidence pick the scale the windows need?

``--scan``: no sampling; at ``calibrate --model``'s per-sample mode θ̂ (type-II scales), with the
generator's clocks and with the case's report, the log-likelihood of the impact windows' samples at θ̂ and
at the true positions when the fitted scales there are multiplied by c (:data:`SCAN_MULTIPLIERS`): which c
the data's own evidence prefers, and how much the windows favour θ̂ over the truth at that c.

``--mixture``: a non-oracle attempt at the first ingredient the oracles point to (a per-sample scale of the
unresolved motion large enough in the impacts) on all of percov_conceal's cases: after the default type-II fit,
each sample's jerk and angular-jerk scales multiplied by one of a discrete set (:data:`MIXTURE_SETS`), the
weights by EM on the per-sample log-likelihoods at the model's mode (ω = ω̄), each sample at its most probable
multiplier (a plug-in, not marginalised in the chains), the mode refitted; compared with percov_conceal's
``with_angjerk`` run of the same case (``--baseline``).  The drop variant (:data:`DROP_SET`) instead removes
the samples the widest set's EM puts at ≥ ×100 (an outlier component that carries no information on θ)
and calibrates the rest with the defaults.

Also a span check with the truth, no calibration: the accelerometers' first-order age effect
d_k·F_k'(t̄) and the all-order one F_k(tick_k) − F_k(t̄), per sample projected on the columns of the
motion states φ (−[r_k]×, I) and of the age loadings (d_k I, d_k [r_k − r̄]×) at the true positions
and ages; the rms of what is left, in and out of the impact windows (m/s²).

    PYTHONPATH=. OMP_NUM_THREADS=1 nice -n 5 python3 experiments/clock020_sync.py
"""
from __future__ import annotations

import argparse
import contextlib
import json
import math
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT.parent))
DOC = ROOT / "clock020_sync.md"
SEED = 20
VARIANTS = ("as_drawn", "twin", "acc_synchronised", "acc_first_order_kept", "gyro_synchronised", "lever_truth",
            "lever_map", "acc_clock_correction_off", "windows_projected", "windows_projected_true_ages",
            "impact_cells_true_ages", "omega_dot_cells_true_ages", "true_acc_delays", "windows_projected_true_acc_delays",
            "windows_projected_true_clocks_0_2", "mixture_true_ages")
#: the impact windows' margins (s) and length in decay times; the scales set there (m/s³, rad/s³; in the noise
#: model's scaled samples): about 20–100 × the impacts' own jerk and angular jerk, which projects their loadings out
WINDOW_MARGIN, WINDOW_TAUS, WINDOW_JERK, WINDOW_ANGJERK = 0.005, 40.0, 1e5, 1e7
#: the ``--scan``'s multipliers of the fitted scales in the impact windows
SCAN_MULTIPLIERS = (1.0, 10.0, 100.0, 1e3, 1e4, 1e5)
#: the ``--mixture`` study's sets of scale multipliers
MIXTURE_SETS = ((1.0, 10.0, 100.0, 1e3, 1e4), (1.0, 10.0, 100.0), (1.0, 3.0, 10.0, 30.0))
#: the ``--mixture`` study's drop variant (its index after the sets): the first set's EM at the mode, then the
#: samples it puts at ≥ DROP_FROM × dropped from a default ``calibrate --model`` (``select``)
DROP_SET, DROP_FROM = len(MIXTURE_SETS), 100.0


def truth_timing():
    """(rec, truth, pos, tick (T, K) s, t̄ (T,) s, acc splines, gyro splines, Q (K, 3, 3), windows): the case
    as percov_conceal sees it and, per IMU, its register's tick of each read and cubic splines of its own
    DLPF outputs (array frame) on its internal ticks; Q[k] the array → sensor rotation."""
    from scipy.interpolate import CubicSpline

    import experiments.clockgen.cases as cases
    from experiments.clock020_impacts import case_with_internals
    from experiments.clockgen.sensing import HostReader

    rec, truth, pos, clocks, f_acc, f_gyro = case_with_internals(SEED)
    motion = cases.motion_of({"seed": SEED, "duration": 20.0, "vibration": True, "drop": []})
    Q = np.array([cases.quat_to_matrix(q) for q in truth["orientation"]])
    reads = np.asarray(truth["read_time"])
    T, K = reads.shape
    tick, sa, sg = np.zeros((T, K)), [], []
    for k in range(K):
        ticks = clocks[k].ticks(-cases.T_PRE, reads[-1, k] + 0.01)
        f, w = motion.specific_force(ticks, pos[k:k + 1])
        sa.append(CubicSpline(ticks, f_acc[k](f[:, 0])))
        sg.append(CubicSpline(ticks, f_gyro[k](w)))
        idx, _ = HostReader.read(ticks, reads[:, k])
        tick[:, k] = ticks[idx]
    b = motion.rot_imp
    windows = [(t0 - WINDOW_MARGIN, t0 + WINDOW_TAUS * tau + WINDOW_MARGIN) for t0, tau in zip(b.onset, b.tau)]
    return rec, truth, pos, tick, tick.mean(1), sa, sg, Q, windows


def synchronised(splines, tick, tbar, Q, first_order: bool = False) -> np.ndarray:
    """(T, K, 3) sensor frame: what to subtract from the outputs to read every IMU at t̄ (all orders), or
    with ``first_order`` only the orders ≥ 2 of F_k(tick_k) − F_k(t̄)."""
    out = np.zeros(tick.shape + (3,))
    for k, S in enumerate(splines):
        ex = S(tick[:, k]) - S(tbar)
        if first_order:
            ex = ex - (tick[:, k] - tbar)[:, None] * S(tbar, 1)
        out[:, k] = ex @ Q[k].T
    return out


@contextlib.contextmanager
def patched(variant: str, pos, windows):
    """The package's functions this variant changes, restored on exit (the script's own interception)."""
    import torch

    import accel_bayes.model.likelihood_percov as lp
    import accel_bayes.model.report_terms as rt
    import accel_bayes.model.unresolved_fit as uf
    import accel_bayes.pipelines.calibrate as cal
    import accel_bayes.pipelines.calibrate_model as cm

    saved = [(cm, "_model_percov_step"), (cal, "_model_percov_step"), (lp, "with_unresolved_motion"),
             (uf, "with_unresolved_motion"), (uf, "fit_unresolved_scales"), (rt, "clock_corrected")]
    old = [getattr(m, n) for m, n in saved]
    state = {}
    step0, wum0, fit0, cc0 = cm._model_percov_step, lp.with_unresolved_motion, uf.fit_unresolved_scales, rt.clock_corrected

    def step(lik, terms, omega_norm, sample_scale, map_res, nominal_acc, prior_std, **kw):
        state["time"] = torch.as_tensor(np.asarray(terms.time, dtype=np.float64))
        if variant == "lever_truth":
            state["lever"] = torch.as_tensor(pos, dtype=torch.float64)[torch.as_tensor(list(lik.imu_labels))]
        elif variant == "lever_map":
            state["lever"] = torch.as_tensor(map_res.positions, dtype=torch.float64)
        state["final"] = False
        return step0(lik, terms, omega_norm, sample_scale, map_res, nominal_acc, prior_std, **kw)

    def fit(*a, lever=None, **k):
        return fit0(*a, lever=None if lever is None else state.get("lever", lever), **k)

    def wum(lik, age, jerk_std, *a, lever=None, angjerk_std=None, **k):
        lever = None if lever is None else state.get("lever", lever)
        if variant.startswith("windows_projected") and angjerk_std is not None and "time" in state:
            t = state["time"]
            m = torch.zeros(t.shape, dtype=torch.bool)
            for a0, b0 in windows:
                m |= (t >= a0) & (t <= b0)
            state["inflated"] = int(m.sum())
            state["fitted_max"] = (float(torch.as_tensor(jerk_std).detach().max()),
                                   float(torch.as_tensor(angjerk_std).detach().max()))
            jerk_std = torch.where(m, torch.full_like(torch.as_tensor(jerk_std), WINDOW_JERK), torch.as_tensor(jerk_std))
            angjerk_std = torch.where(m, torch.full_like(torch.as_tensor(angjerk_std), WINDOW_ANGJERK),
                                      torch.as_tensor(angjerk_std))
        return wum0(lik, age, jerk_std, *a, lever=lever, angjerk_std=angjerk_std, **k)

    def cc(acc, gyro, time_s, age_acc, age_gyro):
        a, g = cc0(acc, gyro, time_s, age_acc, age_gyro)
        return (torch.as_tensor(acc, dtype=torch.float64), g) if variant == "acc_clock_correction_off" else (a, g)

    cm._model_percov_step = cal._model_percov_step = step
    lp.with_unresolved_motion = uf.with_unresolved_motion = wum
    uf.fit_unresolved_scales, rt.clock_corrected = fit, cc
    try:
        yield state
    finally:
        for (m, n), o in zip(saved, old):
            setattr(m, n, o)


def twin_case(out: Path):
    """(rec, pos, report path): clockgen's synchronised twin of the case, as percov_conceal prepares a case,
    and its ``detect`` report (defaults, seed 0), cached in ``out``."""
    from accel_bayes.data.outputs import write_json
    from accel_bayes.mismatch import detect
    from experiments.clockgen import draw_case
    from experiments.percov_conceal import known_acc_intrinsics, mounted

    rec, truth = draw_case("twin", SEED, duration=20.0)
    rec, pos = mounted(known_acc_intrinsics(rec, truth), truth, 5e-4, SEED)
    rep = out / "twin_report.json"
    if not rep.exists():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            write_json(rep, detect(rec, seed=0).to_dict())
    return rec, pos, rep


def true_ages_report(report: Path, rec, truth, out: Path) -> Path:
    """The case's report with its clocks replaced by the generator's (``d_oracle_acc_timing``), written to ``out``."""
    from accel_bayes.data.outputs import write_json
    from experiments.clock020_oracle import variant_report

    rep = out / "report_true_ages.json"
    write_json(rep, variant_report(json.loads(report.read_text()), truth, np.asarray(rec.time, dtype=np.float64),
                                   "d_oracle_acc_timing"))
    return rep


def true_delays_report(report: Path, truth, out: Path) -> Path:
    """The case's report with each clock's ``filter_delay_acc_minus_gyro_s`` the generator's own (module docstring)."""
    from accel_bayes.data.outputs import write_json
    from experiments.clock020_oracle import true_acc_delay

    doc = json.loads(report.read_text())
    for f in doc["findings"]:
        if f["effect"] == "sampling_clock":
            f["parameters"]["filter_delay_acc_minus_gyro_s"] = true_acc_delay(truth, int(f["imu"]))
    rep = out / "report_true_acc_delays.json"
    write_json(rep, doc)
    return rep


def evidence_scan(report: Path, out: Path, chains: int) -> dict:
    """``--scan`` (module docstring) with ``report``: per multiplier c of the fitted jerk and angular-jerk scales
    in the impact windows, the windows' log-likelihood (nats, ω at the gyro mean) at θ̂ and at the truth, and the
    whole recording's at θ̂; θ̂ is the mode at c = 1 (no chains are run)."""
    import torch

    import accel_bayes.pipelines.calibrate as cal
    import accel_bayes.pipelines.calibrate_model as cm
    from accel_bayes.model.likelihood import RaoBlackwellLikelihood
    from accel_bayes.model.likelihood_percov import with_unresolved_motion
    from experiments.percov_conceal import run_variant

    rec, truth, pos, tick, tbar, sa, sg, Q, windows = truth_timing()
    inner, found = cm._model_percov_step, {}

    class _Done(Exception):
        pass

    def step(lik, terms, omega_norm, sample_scale, *a, **kw):
        pc = inner(lik, terms, omega_norm, sample_scale, *a, **kw)
        L = pc.lik
        t = torch.as_tensor(np.asarray(terms.time, dtype=np.float64))
        m = torch.zeros(t.shape, dtype=torch.bool)
        for a0, b0 in windows:
            m |= (t >= a0) & (t <= b0)
        base = RaoBlackwellLikelihood(L.acc, L.omega, L.acc_noise_std, 1, reference=L.reference, phi_prior=L.phi_prior)
        extra = {} if L.age_var is None else {"age_var": L.age_var, "age_rate": L.age_rate}
        true_p = torch.as_tensor(pos, dtype=torch.float64)[torch.as_tensor(list(lik.imu_labels))]
        s_t = torch.as_tensor(np.asarray(sample_scale, dtype=np.float64)) * torch.ones(len(t), dtype=torch.float64)
        rows = []
        for c in SCAN_MULTIPLIERS:
            f = torch.where(m, torch.tensor(float(c), dtype=torch.float64), torch.tensor(1.0, dtype=torch.float64))
            lk = with_unresolved_motion(base, L.age, L.jerk_std * f, angjerk_std=L.angjerk_std * f, lever=L.lever,
                                        **extra)
            with torch.no_grad():
                at_mode = lk.log_lik_per_sample(pc.positions, L.omega.mean)
                at_truth = lk.log_lik_per_sample(true_p, L.omega.mean)
            rows.append({"c": c, "window_mode": float(at_mode[m].sum()), "window_truth": float(at_truth[m].sum()),
                         "total_mode": float(at_mode.sum())})
        found.update(rows=rows, n_window=int(m.sum()), jerk_window=float((L.jerk_std * s_t)[m].median()),
                     angjerk_window=float((L.angjerk_std * s_t)[m].median()),
                     jerk_max_outside=float((L.jerk_std * s_t)[~m].max()),
                     angjerk_max_outside=float((L.angjerk_std * s_t)[~m].max()))
        raise _Done

    cm._model_percov_step = cal._model_percov_step = step
    try:
        run_variant(rec, "with_angjerk", report, chains, 1, 1, 0)
    except _Done:
        pass
    finally:
        cm._model_percov_step = cal._model_percov_step = inner
    return found


def run_one(variant: str, seed: int, report: Path, args) -> dict:
    from experiments.percov_conceal import run_variant, score

    rec, truth, pos, tick, tbar, sa, sg, Q, windows = truth_timing()
    rep = report
    if variant == "twin":
        rec, pos, rep = twin_case(args.out)
    elif variant in ("acc_synchronised", "acc_first_order_kept"):
        rec = rec.copy()
        rec.acc = np.asarray(rec.acc, dtype=np.float64) - synchronised(sa, tick, tbar, Q, variant == "acc_first_order_kept")
    elif variant == "gyro_synchronised":
        rec = rec.copy()
        rec.gyro = np.asarray(rec.gyro, dtype=np.float64) - synchronised(sg, tick, tbar, Q)
    elif variant.endswith("_true_ages"):
        rep = true_ages_report(report, rec, truth, args.out)
    elif variant == "windows_projected_true_clocks_0_2":
        from accel_bayes.data.outputs import write_json
        from experiments.clock020_oracle import variant_report

        rep = args.out / "report_true_clocks_0_2.json"
        write_json(rep, variant_report(json.loads(report.read_text()), truth, np.asarray(rec.time, dtype=np.float64),
                                       "b_oracle_0_2"))
    elif variant.endswith("true_acc_delays"):
        rep = true_delays_report(report, truth, args.out)
    with patched(variant, pos, windows) as state, (
            mixture_step(MIXTURE_SETS[0], state) if variant == "mixture_true_ages" else contextlib.nullcontext()):
        if variant in ("impact_cells_true_ages", "omega_dot_cells_true_ages"):
            import accel_bayes.pipelines.calibrate as cal
            from experiments.clock020_impacts import omega_dot_cells_step

            # wraps patched()'s step; patched() restores the package's on exit
            cal._model_percov_step = omega_dot_cells_step(
                cal._model_percov_step, impacts=windows if variant.startswith("impact") else None)
        r = run_variant(rec, "with_angjerk", rep, args.chains, args.draws, args.warmup, seed)
    s = score(r["positions"], pos)
    return {"variant": variant, "seed": seed, "z": s["z"], "coordinates": s["coordinates"], "error_m": s["error_m"],
            "std_m": s["std_m"], "seconds": r["seconds"], "inflated_samples": state.get("inflated"),
            "fitted_max": state.get("fitted_max"), "mixture_counts": state.get("counts"),
            "findings": [f["effect"] for f in json.loads(Path(rep).read_text())["findings"]]}


@contextlib.contextmanager
def mixture_step(multipliers, info: dict):
    """``calibrate``'s per-sample-covariance step followed by the plug-in scale mixture (module docstring,
    ``--mixture``); what it chose goes into ``info``."""
    import torch

    import accel_bayes.pipelines.calibrate as cal
    import accel_bayes.pipelines.calibrate_model as cm
    from accel_bayes.model.likelihood import RaoBlackwellLikelihood
    from accel_bayes.model.likelihood_percov import with_unresolved_motion
    from accel_bayes.model.unresolved_fit import fixed_omega_mode

    inner = cm._model_percov_step
    mult = torch.as_tensor(multipliers, dtype=torch.float64)

    def step(lik, terms, omega_norm, sample_scale, map_res, nominal_acc, prior_std, **kw):
        pc = inner(lik, terms, omega_norm, sample_scale, map_res, nominal_acc, prior_std, **kw)
        L = pc.lik
        if L.angjerk_std is None:
            return pc
        base = RaoBlackwellLikelihood(L.acc, L.omega, L.acc_noise_std, 1, reference=L.reference, phi_prior=L.phi_prior)
        extra = {} if L.age_var is None else {"age_var": L.age_var, "age_rate": L.age_rate}

        def build(c):
            return with_unresolved_motion(base, L.age, L.jerk_std * c, angjerk_std=L.angjerk_std * c, lever=L.lever,
                                          **extra)

        with torch.no_grad():
            ll = torch.stack([build(torch.full((L.T,), float(c), dtype=torch.float64))
                              .log_lik_per_sample(pc.positions, L.omega.mean) for c in mult])  # (J, T)
        logpi = torch.full((len(mult),), -math.log(len(mult)), dtype=torch.float64)
        for _ in range(200):  # EM for the weights; the likelihoods at the mode are fixed
            resp = torch.softmax(logpi[:, None] + ll, 0)
            logpi = torch.log(resp.mean(1).clamp_min(1e-12))
        j = resp.argmax(0)
        info.update(weights=logpi.exp().tolist(), counts=[int((j == i).sum()) for i in range(len(mult))], choice=j.tolist(),
                    gain_nats=float(torch.logsumexp(logpi[:, None] + ll, 0).sum() - ll[0].sum()))
        new = build(mult[j])
        P, cov = fixed_omega_mode(new, pc.positions, prior_mean=nominal_acc, prior_std=prior_std)
        return cm.PercovStep(new, P, cov, pc.record)

    cm._model_percov_step = cal._model_percov_step = step
    try:
        yield
    finally:
        cm._model_percov_step = cal._model_percov_step = inner


def run_mixture(case: int, which: int, args) -> dict:
    """percov_conceal's case ``case`` with the plug-in mixture of :data:`MIXTURE_SETS` [which] (its cached report),
    or with ``which`` = :data:`DROP_SET` the drop variant (module docstring)."""
    from experiments.percov_conceal import case_recording, run_variant, score

    rec, truth, pos = case_recording(case, 20.0, 5e-4, "known")
    if which == DROP_SET:
        return run_mixture_drop(case, rec, pos, args)
    info = {}
    with mixture_step(MIXTURE_SETS[which], info):
        r = run_variant(rec, "with_angjerk", args.baseline / f"clock-{case:03d}" / "report.json", args.chains,
                        args.draws, args.warmup, 0)
    info.pop("choice", None)  # per sample; the counts summarise it
    return {"case": case, "set": which, "z": score(r["positions"], pos)["z"], **info}


def run_mixture_drop(case: int, rec, pos, args) -> dict:
    """:data:`DROP_SET` on one case: the EM's choice at the mode (no chains), then ``calibrate --model`` without
    the samples put at ≥ :data:`DROP_FROM` ×; a case without the angular jerk's scales drops nothing."""
    import accel_bayes.pipelines.calibrate as cal
    import accel_bayes.pipelines.calibrate_model as cm
    from experiments.percov_conceal import run_variant, score

    report = args.baseline / f"clock-{case:03d}" / "report.json"
    info = {}

    class _Chosen(Exception):
        pass

    with mixture_step(MIXTURE_SETS[0], info):
        mixed = cm._model_percov_step

        def step(lik, terms, *a, **k):
            mixed(lik, terms, *a, **k)
            info["time"] = np.asarray(terms.time, dtype=np.float64)
            raise _Chosen

        cm._model_percov_step = cal._model_percov_step = step
        try:
            run_variant(rec, "with_angjerk", report, args.chains, 1, 1, 0)
        except _Chosen:
            pass
        finally:
            cm._model_percov_step = cal._model_percov_step = mixed
    t = np.asarray(rec.time, dtype=np.float64)
    keep = np.ones(t.size, dtype=bool)
    if "choice" in info:
        flagged = info["time"][np.asarray(MIXTURE_SETS[0])[np.asarray(info["choice"])] >= DROP_FROM]
        keep[np.searchsorted(t, flagged).clip(0, t.size - 1)] = False
    r = run_variant(rec, "with_angjerk", report, args.chains, args.draws, args.warmup, 0, select=keep)
    n = int(info["time"].size) if "time" in info else None
    return {"case": case, "set": DROP_SET, "z": score(r["positions"], pos)["z"], "dropped": int((~keep).sum()),
            "counts": [None if n is None else n - int((~keep).sum()), int((~keep).sum())]}


def span_check() -> list[dict]:
    """The accelerometers' age effect against the columns of φ and of the age loadings (module docstring)."""
    rec, truth, pos, tick, tbar, sa, _, _, windows = truth_timing()
    T, K = tick.shape
    d = tick - tbar[:, None]
    first = np.stack([d[:, k, None] * sa[k](tbar, 1) for k in range(K)], 1)
    every = np.stack([sa[k](tick[:, k]) - sa[k](tbar) for k in range(K)], 1)

    def hat(v):
        return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])

    rc = pos - pos.mean(0)
    fixed = np.vstack([np.hstack([-hat(pos[k]), np.eye(3)]) for k in range(K)])        # (3K, 6)
    rot = np.stack([hat(rc[k]) for k in range(K)])                                       # (K, 3, 3)
    cols = np.concatenate([np.broadcast_to(fixed, (T, 3 * K, 6)),
                           (d[:, :, None, None] * np.eye(3)).reshape(T, 3 * K, 3),
                           (d[:, :, None, None] * rot).reshape(T, 3 * K, 3)], -1)       # (T, 3K, 12)
    t = np.asarray(truth["read_time"])[:, 0]
    win = np.zeros(T, dtype=bool)
    for a, b in windows:
        win |= (t >= a) & (t <= b)
    rows = []
    for name, x in (("first order d_k F_k'(t̄)", first), ("all orders F_k(tick_k) − F_k(t̄)", every)):
        y = x.reshape(T, 3 * K, 1)
        c = np.linalg.pinv(cols) @ y
        res = (y - cols @ c).reshape(T, K, 3)
        rms = lambda v, m: float(np.sqrt(np.mean(np.sum(v[m] ** 2, -1))))  # noqa: E731
        rows.append({"term": name, "in": rms(x, win), "out": rms(x, ~win), "res_in": rms(res, win),
                     "res_out": rms(res, ~win), "res_max": float(np.abs(res).max()), "n_in": int(win.sum())})
    return rows


def mixture_markdown(mix: list[dict], args) -> list[str]:
    """The ``--mixture`` table: z RMS / max |z| per case, percov_conceal's baseline and each multiplier set."""
    base = {}
    for f in sorted(args.baseline.glob("clock-*/with_angjerk.json")):
        base[int(f.parent.name.split("-")[1])] = np.asarray(json.loads(f.read_text())["score"]["z"])
    cases = sorted({m["case"] for m in mix})
    sets = sorted({m["set"] for m in mix})
    by = {(m["case"], m["set"]): m for m in mix}
    head = ["baseline (with_angjerk)"] + [
        f"×{{1 … 10⁴}}, ≥ ×{DROP_FROM:g} dropped" if i == DROP_SET else
        "×{" + ", ".join(f"{c:g}" for c in MIXTURE_SETS[i]) + "}" for i in sets]
    L = ["", f"## `--mixture`: the plug-in scale mixture on percov_conceal's {len(cases)} cases (sampler seed 0)", "",
         "z RMS / max \\|z\\| per case; the last rows pool the coordinates of all the cases; the final row counts, per "
         "set, the samples the EM moved off ×1 (for the drop variant: the samples dropped), summed over the cases.", "",
         "| case | " + " | ".join(head) + " |", "|---|" + "---|" * len(head)]
    pooled = {h: [] for h in head}
    for c in cases:
        cells = []
        zb = base.get(c)
        cells.append("—" if zb is None else f"{np.sqrt(np.mean(zb ** 2)):.2f} / {np.abs(zb).max():.2f}")
        if zb is not None:
            pooled[head[0]].append(zb)
        for h, i in zip(head[1:], sets):
            m = by.get((c, i))
            if m is None:
                cells.append("—")
                continue
            z = np.asarray(m["z"])
            pooled[h].append(z)
            cells.append(f"{np.sqrt(np.mean(z ** 2)):.2f} / {np.abs(z).max():.2f}")
        L.append(f"| clock-{c:03d} | " + " | ".join(cells) + " |")
    moved = {h: sum(sum(by[(c, i)].get("counts", [0])[1:]) for c in cases if (c, i) in by) for h, i in zip(head[1:], sets)}
    for name, fn in (("z RMS (bar 0.8–1.25)", lambda z: f"{np.sqrt(np.mean(z ** 2)):.2f}"),
                     ("max \\|z\\| (bar ≤ 4)", lambda z: f"{np.abs(z).max():.2f}"),
                     ("beyond 4 std", lambda z: f"{int((np.abs(z) > 4).sum())}/{z.size}")):
        L.append(f"| **{name}** | " + " | ".join(fn(np.concatenate(pooled[h])) if pooled[h] else "—" for h in head)
                 + " |")
    L.append("| samples moved off ×1 | — | " + " | ".join(str(moved[h]) for h in head[1:]) + " |")
    return L


def scan_markdown(scans: dict) -> list[str]:
    """The ``--scan`` tables, one per set of clocks."""
    L = []
    for name, title in (("report", "the case's report"), ("true_ages", "the generator's clocks")):
        sc = scans.get(name)
        if not sc:
            continue
        L += ["", f"`--scan` with {title}: {sc['n_window']} samples in the impact windows, fitted scales there (median, "
                  f"physical) {sc['jerk_window']:.3g} m/s³ and {sc['angjerk_window']:.3g} rad/s³ (outside at most "
                  f"{sc['jerk_max_outside']:.3g} and {sc['angjerk_max_outside']:.3g}); log-likelihood in nats, θ̂ the "
                  "mode at ×1:", "",
              "| scales in the windows | windows at θ̂ | windows at the truth | θ̂ − truth | whole recording at θ̂ |",
              "|---|---|---|---|---|"]
        best = max(sc["rows"], key=lambda r: r["window_mode"])["c"]
        for r in sc["rows"]:
            mark = " (best)" if r["c"] == best else ""
            L.append(f"| ×{r['c']:g}{mark} | {r['window_mode']:.1f} | {r['window_truth']:.1f} | "
                     f"{r['window_mode'] - r['window_truth']:+.1f} | {r['total_mode']:.1f} |")
    return L


def markdown(rows, span, cmd: str, secs: float, args, mix=(), scans=None) -> str:
    from experiments._stamp import run_stamp

    coords = rows[0]["coordinates"]
    j = coords.index("r[5, y]")
    L = ["# clock020_sync — which sensor's asynchrony carries clock-020's r[5, y] bias? (issue #30)", "",
         f"Regenerate: `{cmd}` ({run_stamp()}; this invocation {secs:.0f} s; cached in `{args.out.relative_to(ROOT.parent)}/`).",
         "", "What runs: the script's docstring (clockgen clock-020, cube6, 125 Hz, 20 s, known acc intrinsics, 0.5 mm "
             f"mounting error; `calibrate --model` with the angular jerk, {args.chains} chains × ({args.warmup} + "
             f"{args.draws}) as percov_conceal).", "",
         "| variant | seed | z RMS | max \\|z\\| (where) | r[5, y] z | r[5, y] error / std µm | RMS error µm | median std µm | samples inflated |",
         "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        z = np.asarray(r["z"])
        i = int(np.abs(z).argmax())
        L.append(f"| {r['variant']} | {r['seed']} | {np.sqrt(np.mean(z ** 2)):.2f} | {abs(z[i]):.2f} ({r['coordinates'][i]}) | "
                 f"{z[j]:.2f} | {1e6 * r['error_m'][j]:.0f} / {1e6 * r['std_m'][j]:.0f} | "
                 f"{1e6 * np.sqrt(np.mean(np.square(r['error_m']))):.0f} | {1e6 * np.median(r['std_m']):.0f} | "
                 f"{r.get('inflated_samples') or '—'} |")
    L += ["", f"Span check (truth, no calibration; {span[0]['n_in']} samples in the impact windows), m/s² rms:", "",
          "| accelerometer age effect | in windows | outside | left after φ and the age loadings: in | outside | max |",
          "|---|---|---|---|---|---|"]
    for s in span:
        L.append(f"| {s['term']} | {s['in']:.4f} | {s['out']:.4f} | {s['res_in']:.4f} | {s['res_out']:.4f} | {s['res_max']:.3f} |")
    L += scan_markdown(scans or {})
    if mix:
        L += mixture_markdown(list(mix), args)
    return "\n".join(L) + "\n"


def _cases(text: str) -> list[int]:
    """"0-3,7" → [0, 1, 2, 3, 7]."""
    out = []
    for part in (p for p in text.split(",") if p):
        a, _, b = part.partition("-")
        out += list(range(int(a), int(b or a) + 1))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0", help="sampler seeds (default 0)")
    ap.add_argument("--variants", default=",".join(VARIANTS), help="comma-separated subset (default: all)")
    ap.add_argument("--chains", type=int, default=2)
    ap.add_argument("--warmup", type=int, default=300)
    ap.add_argument("--draws", type=int, default=400)
    ap.add_argument("--report", type=Path, default=ROOT / "out" / "percov_conceal" / "clock-020" / "report.json",
                    help="clock-020's detect report (percov_conceal's cached stage)")
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "clock020_sync")
    ap.add_argument("--doc", type=Path, default=DOC)
    ap.add_argument("--no-doc", action="store_true", help="run and cache the variants only")
    ap.add_argument("--mixture", default="", help="comma-separated percov_conceal case seeds for the plug-in mixture "
                                                 "study (e.g. 0-20; default none)")
    ap.add_argument("--mixture-sets", default=",".join(str(i) for i in range(len(MIXTURE_SETS) + 1)),
                    help=f"indices into MIXTURE_SETS, {DROP_SET} the drop variant (default all)")
    ap.add_argument("--scan", action="store_true", help="also the evidence scan of the impact windows' scale (no chains)")
    ap.add_argument("--baseline", type=Path, default=ROOT / "out" / "percov_conceal",
                    help="percov_conceal's --out (its reports and with_angjerk runs)")
    args = ap.parse_args(argv)
    if not args.report.exists():
        ap.error(f"--report: {args.report} not found; run experiments/percov_conceal.py --n 21 --first 20 first "
                 "or give the report's path")
    names = [v for v in args.variants.split(",") if v]
    bad = [v for v in names if v not in VARIANTS]
    if bad:
        ap.error(f"--variants: {bad} not among {list(VARIANTS)}")
    args.out.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    rows = []
    for v in names:
        for s in (int(x) for x in args.seeds.split(",")):
            f = args.out / f"{v}.seed{s}.json"
            if not f.exists():
                row = run_one(v, s, args.report, args)
                f.write_text(json.dumps(row))
                z = np.asarray(row["z"])
                print(f"{v} seed {s}: z RMS {np.sqrt(np.mean(z ** 2)):.2f}, max |z| {np.abs(z).max():.2f}", flush=True)
            rows.append(json.loads(f.read_text()))
    mix = []
    for c in _cases(args.mixture):
        for i in (int(x) for x in args.mixture_sets.split(",") if x):
            f = args.out / "mixture" / f"clock-{c:03d}.set{i}.json"
            if not f.exists():
                f.parent.mkdir(parents=True, exist_ok=True)
                m = run_mixture(c, i, args)
                f.write_text(json.dumps(m))
                z = np.asarray(m["z"])
                print(f"mixture clock-{c:03d} set {i}: z RMS {np.sqrt(np.mean(z ** 2)):.2f}, max |z| {np.abs(z).max():.2f}",
                      flush=True)
            mix.append(json.loads(f.read_text()))
    scans = {}
    if args.scan or (args.out / "scan.report.json").exists():
        for name in ("report", "true_ages"):
            f = args.out / f"scan.{name}.json"
            if not f.exists():
                rep = args.report
                if name == "true_ages":
                    rec, truth = truth_timing()[:2]
                    rep = true_ages_report(args.report, rec, truth, args.out)
                f.write_text(json.dumps(evidence_scan(rep, args.out, args.chains)))
            scans[name] = json.loads(f.read_text())
    if args.no_doc:
        return 0
    if not mix:  # the document keeps the study's cached runs
        mix = [json.loads(f.read_text()) for f in sorted((args.out / "mixture").glob("clock-*.set*.json"))]
    sf = args.out / "span.json"
    if not sf.exists():
        sf.write_text(json.dumps(span_check()))
    cmd = "PYTHONPATH=. OMP_NUM_THREADS=1 nice -n 5 python3 experiments/clock020_sync.py" + (
        "" if args.report == ap.get_default("report") else f" --report {args.report}")
    if mix:
        cmd += f" --mixture {args.mixture or '0-20'}" + ("" if args.baseline == ap.get_default("baseline")
                                                         else f" --baseline {args.baseline}")
    if scans:
        cmd += " --scan"
    text = markdown(rows, json.loads(sf.read_text()), cmd, time.time() - t0, args, mix, scans)
    from accel_bayes.data.outputs import write_text
    from experiments._reading import READING_MARKER, kept_reading

    write_text(args.doc, text + "\n" + READING_MARKER + (kept_reading(args.doc) or "\n"))
    print(f"wrote {args.doc}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
