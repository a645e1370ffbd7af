"""[S16] self-calibration of accelerometer-only arrays: triad poses and motion, jointly — the driver.

:func:`self_calibrate` minimises F of [S16] eq. 15 over the motion states and the poses of all
triads but one, held at its nominal pose ([S16] eq. 16: it defines the array frame).  Unknowns are
the motion states x_i = [a_lin, ω, ω̇] (T, 9) — or, with the smoother continuous-time motion model
of issue #12 (``process_noise="estimate-snap"``), [a_lin, ω, ω̇, ω̈, ȧ_lin] (T, 15), whose extra
derivatives enter the process residuals only — local blocks, one per sample, coupled in a chain
by the process residuals, and the poses of the free triads (global blocks: a Euclidean position
and a unit quaternion).

It runs in steps, each returning a small record: the inputs checked
(:func:`.inputs.solve_inputs`), the motion prior read from the options
(:class:`SelfcalSolveOptions`, :func:`.motion_priors.motion_prior`), its start whitening
(:func:`.noise_em.initial_process_noise`), the LM runs — first, restart after a divergence, re-run
from the estimate — each a :class:`_Run` (:class:`_Solver`, :func:`_runs`), and the result with
its covariance and scale correction (:func:`_result`).
"""
from __future__ import annotations

import time as _time
from dataclasses import dataclass, field

import torch

from ...physics.geometry import quat_normalize
from .fitcheck import _whitened_rms, check_divergence
from .inputs import SolveInputs, solve_inputs
from .motion_priors import MotionPrior, continuous_process_whitening, motion_prior
from .motion_priors import process_variances as s16_variances
from .noise_em import _START_STIFFNESS, ProcessNoise, estimate_intensities, initial_process_noise
from .problem import _run_lm, build_problem
from .result import SelfCalDiverged, SelfCalResult, pose_covariance
from .scale import laplace_scale_correction, score_scale_correction

__all__ = ["SelfcalSolveOptions", "self_calibrate"]


@dataclass(frozen=True)
class SelfcalSolveOptions:
    """How :func:`self_calibrate` solves (its keywords of the same names, meanings and defaults),
    validated at construction: ``process_noise`` / ``process_variances`` are read into
    :attr:`prior` (a :class:`~.motion_priors.MotionPrior`; ValueError naming the option), and
    ``rerun_from_estimate`` must be True, False or "auto"."""

    process_noise: object = "s16"
    process_variances: dict | None = None
    marginal_scale: bool | str = True
    noise_max_iter: int = 30
    noise_rtol: float = 0.01
    max_iter: int = 200
    ftol: float = 1e-12
    xtol: float = 1e-12
    gtol: float = 1e-9
    progress: bool = False
    rerun_from_estimate: bool | str = True
    rerun_rms: float = 1.5
    covariance: bool = True
    raise_on_divergence: bool = False
    divergence_kwargs: dict | None = None
    warm_start_motion: bool = True
    restart_on_divergence: bool = True
    damping: object = None
    prior: MotionPrior = field(init=False, repr=False)

    def __post_init__(self):
        # frozen: the derived prior is set once, here
        object.__setattr__(self, "prior", motion_prior(self.process_noise, self.process_variances))
        if self.rerun_from_estimate not in (True, False, "auto"):
            raise ValueError(f"rerun_from_estimate: expected True, False or 'auto', got {self.rerun_from_estimate!r}")


def _initial_motion(init_motion, T: int, dim: int, dtype, device) -> torch.Tensor:
    """The start motion (T, dim): zeros ([S16] §VI-B), or ``init_motion`` ((T, 9) padded with zero
    extra derivatives)."""
    if init_motion is None:
        return torch.zeros(T, dim, dtype=dtype, device=device)
    x0 = torch.as_tensor(init_motion, dtype=dtype, device=device).clone()
    if x0.shape == (T, 9) and dim > 9:  # [a_lin, ω, ω̇] given: the extra derivatives start at zero
        x0 = torch.cat((x0, x0.new_zeros(T, dim - 9)), -1)
    if x0.shape != (T, dim):
        raise ValueError(f"init_motion: expected shape ({T}, 9) or ({T}, {dim}), got {tuple(x0.shape)}")
    return x0


@dataclass(frozen=True)
class _Run:
    """One LM run from a start: the LM result, its cost log, F (paper scaling), the divergence
    reason (None: not diverged), the summary that goes into ``SelfCalResult.runs``, and the
    process noise it ended with (intensities q or None, whitening W)."""

    res: object
    log: list
    F: float
    why: str | None
    summary: dict
    q: dict | None
    W: torch.Tensor


class _Solver:
    """The LM runs of one self-calibration: fixed inputs and options, and the process noise that
    the runs update in turn (the intensities' fixed point continues from run to run)."""

    def __init__(self, inp: SolveInputs, opts: SelfcalSolveOptions, noise: ProcessNoise):
        self.inp, self.opts, self.noise = inp, opts, noise
        self.n_total = inp.T * inp.A + inp.T - 1

    def _lm(self, problem, desc: str, ftol: float):
        o = self.opts
        return _run_lm(problem, max_iter=o.max_iter, ftol=ftol, xtol=o.xtol, gtol=o.gtol, progress=o.progress,
                       desc=desc, damping=o.damping)

    def _problem(self, p, q, x, poses_fixed: bool = False):
        inp = self.inp
        return build_problem(inp.acc, inp.dt, p, q, x, inp.fixed, inp.inv_std, self.noise.W, inp.S, inp.offset,
                             poses_fixed=poses_fixed)

    def run(self, p_start, q_start, x_start, label: str) -> _Run:
        """Motion-only warm start (optional), joint LM, the intensities' fixed point (estimated
        process noise), then the divergence check of the estimate."""
        inp, o, noise = self.inp, self.opts, self.noise
        log = []
        if o.prior.estimated and noise.q != noise.start:
            # every run from zero motion starts stiff again (continuation, see _START_STIFFNESS):
            # the re-run and the restart from the loose intensities let the poses run off.
            noise.q = {"acc": noise.q["acc"], "omega": noise.q["omega"] * _START_STIFFNESS}
            noise.W = continuous_process_whitening(inp.dt, noise.q, o.prior.dim)
        x_start = x_start.clone()
        if o.warm_start_motion:
            # Motion-only stage at the start poses (a well-posed problem in the states alone);
            # from zero motion it does not predetermine the sign of ω either ([S16] §VI-B).
            res0, log0 = self._lm(self._problem(p_start, q_start, x_start, poses_fixed=True),
                                  f"selfcal {label} (motion)", ftol=1e-10)
            for e in log0:
                e["stage"] = "motion"
            log.extend(log0)
            if bool(torch.isfinite(res0.locals).all()):
                x_start = res0.locals
        res, log1 = self._lm(self._problem(p_start, q_start, x_start), f"selfcal {label}", o.ftol)
        offset_it = log[-1]["iteration"] if log else 0
        for e in log1:
            e["stage"] = "joint"
            e["iteration"] += offset_it
        log.extend(log1[1:] if log else log1)
        if o.prior.estimated:
            def refit(p, q, x, k):  # at the noise.W that estimate_intensities just set
                return self._lm(self._problem(p, q, x), f"selfcal {label} (noise {k})", o.ftol)

            res = estimate_intensities(res, log, label, noise, refit, inp.dt, inp.inv_std, inp.S,
                                       max_steps=o.noise_max_iter, rtol=o.noise_rtol)
        for e in log:
            e["F"] = e["F_triad"] + e["F_process"]
            e["F_per_constraint"] = e["F"] / self.n_total
            e["run"] = label
        F = 2.0 * res.cost
        p, q, x = res.values["position"], res.values["rotation"], res.locals
        reason = res.reason
        rms = _whitened_rms(log[-1]["F_triad"], 3 * inp.T * inp.A)
        why = check_divergence(p, x, inp.p0, inp.fixed, F, rms_residual=rms, **(o.divergence_kwargs or {}))
        if why is None and reason == "non_finite":
            why = "the LM linearisation became non-finite"
        summary = {"label": label, "F": F, "rms_residual": rms, "n_iter": res.n_iter,
                   "iterations": len(log) - 1, "lm_reason": reason,
                   "converged": bool(res.converged), "diverged": why,
                   "positions": p.detach(), "orientations": q.detach(), "states": x.detach()}
        return _Run(res, log, F, why, summary, noise.q, noise.W)


@dataclass(frozen=True)
class _Runs:
    """The run whose estimate is returned, the summaries of all runs and their cost logs in order."""

    best: _Run
    runs: list
    full_log: list


def _runs(solver: _Solver, x0: torch.Tensor) -> _Runs:
    """The first run; a restart from its orientations when it diverged; the [S16] §VI-A re-run
    from the estimate; keep the best."""
    inp, o = solver.inp, solver.opts
    cur = solver.run(inp.p0, inp.q0, x0, "first")
    runs, full_log = [cur.summary], list(cur.log)
    q_div = cur.res.values["rotation"]
    if cur.why is not None and o.restart_on_divergence and bool(torch.isfinite(q_div).all()):
        r = solver.run(inp.p0, quat_normalize(q_div), torch.zeros_like(x0), "restart")
        runs.append(r.summary)
        full_log.extend(r.log)
        r.summary["kept"] = r.why is None
        if r.why is None:
            cur = r
    best = cur
    do_rerun = bool(o.rerun_from_estimate) if o.rerun_from_estimate != "auto" else cur.summary["rms_residual"] > o.rerun_rms
    if cur.why is None and do_rerun:
        r2 = solver.run(cur.res.values["position"], cur.res.values["rotation"], torch.zeros_like(x0), "rerun")
        runs.append(r2.summary)
        full_log.extend(r2.log)
        # Keep the re-run unless it is worse: on the global optimum both runs agree, while a
        # partial minimum of the first run has the higher cost.
        if r2.why is None and r2.F <= cur.F * (1 + 1e-9):
            best = r2
        r2.summary["kept"] = best is r2
    return _Runs(best, runs, full_log)


def _result(runs: _Runs, inp: SolveInputs, opts: SelfcalSolveOptions, noise: ProcessNoise) -> SelfCalResult:
    """The result of the kept run, with the Laplace covariance of the poses and, with an
    estimated process noise, the scale correction (both only when it did not diverge); the
    intensities reported and used are the kept run's, the history that of all runs."""
    best, prior = runs.best, opts.prior
    res, why = best.res, best.why
    status = "ok" if why is None else "diverged"
    out = SelfCalResult(
        status=status, reason=why or "", fixed=inp.fixed,
        raw_positions=res.values["position"].detach(), raw_orientations=res.values["rotation"].detach(),
        states=res.locals.detach(), cost=best.F, cost_log=best.log, full_cost_log=runs.full_log,
        n_constraints={"triad": inp.T * inp.A, "process": inp.T - 1}, runs=runs.runs,
        converged=bool(res.converged), lm_reason=res.reason, n_iter=res.n_iter,
        process_noise={"mode": prior.mode, "state_dim": prior.dim,
                       "intensities": None if best.q is None else dict(best.q),
                       "variances": s16_variances(prior.variances) if prior.mode == "s16" else None,
                       "history": noise.history},
    )
    if status == "ok" and opts.covariance:
        cov = pose_covariance(res, inp.A, inp.fixed)
        if cov is not None:
            out.position_cov, out.rotation_cov, out.covariance = cov
    if status == "ok" and prior.mode != "s16" and opts.marginal_scale:
        # the kept run's process noise, not the last run's: a re-run that was not kept ended at
        # intensities of its own
        if opts.marginal_scale == "score":
            corr = score_scale_correction(out, res, inp.A, inp.fixed, inp.dt, best.W, inp.inv_std, inp.S)
        else:
            corr = laplace_scale_correction(out, res, inp.A, inp.fixed, inp.acc, inp.dt, best.W, inp.inv_std, inp.S,
                                            inp.offset, opts.max_iter)
        if corr is not None:
            out.raw_positions, out.states = corr.positions, corr.states
            out.process_noise["scale_correction"] = corr.record
    return out


def self_calibrate(
    acc,
    time_or_dt,
    *,
    steps=None,
    nominal_positions,
    nominal_orientations=None,
    fixed: int = 0,
    acc_noise_std=0.02,
    process_variances: dict | None = None,
    process_noise="s16",
    marginal_scale: bool | str = True,
    noise_max_iter: int = 30,
    noise_rtol: float = 0.01,
    sensor_params=None,
    init_motion=None,
    max_iter: int = 200,
    ftol: float = 1e-12,
    xtol: float = 1e-12,
    gtol: float = 1e-9,
    progress: bool = False,
    rerun_from_estimate: bool | str = True,
    rerun_rms: float = 1.5,
    covariance: bool = True,
    raise_on_divergence: bool = False,
    divergence_kwargs: dict | None = None,
    warm_start_motion: bool = True,
    restart_on_divergence: bool = True,
    damping=None,
    dtype=torch.float64,
    device=None,
) -> SelfCalResult:
    """[S16] self-calibration: triad poses and motion from accelerometer triad outputs alone.

    Minimises F of [S16] eq. 15 — triad residuals (eq. 13) + process residuals (eq. 14, weights
    from eq. 8) — over the motion states x_1:T and the poses of all triads but ``fixed``
    (eq. 16), with the structured Levenberg–Marquardt of :mod:`accel_bayes.inference.lm`
    (motion eliminated by a block-tridiagonal Schur complement; quaternions on the manifold via
    q ⊞ δ = q ∘ exp(δ)).

    Parameters
    ----------
    acc : (T, A, 3) m/s² triad outputs, each in its sensor frame.
    time_or_dt : sample step Δt (s, scalar) or sample times (T,) s.
    steps : None (consecutive samples of the recording) or (T−1,) whole numbers ≥ 1: how many
        steps of the recording's sample grid lie between consecutive fitted samples, when some
        were left out (a sample selection).  The left-out samples' states are integrated out
        exactly (:func:`bridged_process_whitening`).
    nominal_positions : (A, 3) m — starting positions (the construction plan); the fixed
        triad's row defines the origin of the array frame.
    nominal_orientations : (A, 4) array → sensor quaternions (identity if None); likewise.
    fixed : index of the triad held at its nominal pose.
    acc_noise_std : m/s², scalar, (A,) or (A, 3); default 0.02 ([S16] §IV-B: σ² = 4·10⁻⁴).
    process_variances : dict acc / int / omega_dot of eq. 8 (default
        :data:`.motion_priors.S16_PROCESS_VARIANCES`, the paper's 10³, 10⁻⁷, 10³).
        Only with ``process_noise="s16"``.
    process_noise : the motion model.  ``"s16"`` (default; the paper's experiments): eq. 8 with the
        fixed ``process_variances``.  ``"estimate"`` (issue #12): the continuous-time white-noise-on-jerk model (:func:`wnoj_process_covariance`; same
        eq. 7 transition, ω the exact integral of ω̇) whose two intensities q_a, q_ω are estimated
        by the type-II ML fixed point q ← q · rss/(n − h) (:func:`process_noise_statistics`,
        :func:`update_process_intensities`) alternated with the joint LM; q_ω starts 10³ below the
        raw-output guess (stiff) and every LM run from zero motion starts stiff again.  A dict
        ``"estimate-snap"`` (issue #12; the default of the pipeline and the CLI): the smoother
        continuous-time model — white noise on the snap
        ω⃛ and on ä_lin, state x = [a_lin, ω, ω̇, ω̈, ȧ_lin] (T, 15), exact discretisation
        (:func:`continuous_process_covariance`, :func:`integrated_wiener_covariance`); ω̇ and a_lin
        are then smooth paths, as in hand motion, where the jerk model makes ω̇ a Brownian path.
        Intensities and scale as with "estimate"; the start intensities come from second
        differences of the outputs (:func:`initial_smooth_process_intensities`).  The triad residuals
        read only [a_lin, ω, ω̇]; ω̈, ȧ_lin enter the process residuals alone.
        ``{"acc": q_a, "omega": q_ω}`` (optionally ``"dim": 12 or 15``): that model with fixed
        intensities.
        ``result.process_noise`` records the mode, the intensities and the fixed-point history.
    marginal_scale : with the continuous-time model, move the joint MAP along the accelerometer-only
        scale orbit (:func:`scale_orbit`) to the maximum of the Laplace marginal likelihood of the
        poses (:func:`marginal_scale_score`): the joint MAP's scale is set by the motion prior alone
        and comes out too large (experiments/s16_handlike_map.md).  The covariance stays the MAP's.
        ``True`` (default): the Laplace marginal −log p(z | poses_c) ≈ ½F(x̂_c) + ½ log det H_xx(x̂_c)
        itself is minimised over the orbit parameter c (x̂_c the motion-only MAP at the orbit's
        poses; :func:`laplace_scale_nll`, safeguarded parabolic steps).  ``"score"``: the root of
        :func:`marginal_scale_score` instead (the earlier method; its trace term neglects how the
        triad Jacobians change with the motion, which on slow, weakly determined motion left the
        board 0.46 % large where the Laplace marginal's minimum is at the truth, issue #12).
    noise_max_iter, noise_rtol : iteration limit and relative tolerance of the intensity fixed point.
    sensor_params : known triad parameters ``(S, offset)`` or a dict with keys "S" and "offset";
        S (A, 3, 3) upper-triangular (or its 6 parameters (A, 6), [S16] eq. 21), offset (A, 3).
        Default: ideal triads (S = I, o = 0).
    init_motion : (T, 9) initial states ((T, 15) also accepted with "estimate-snap"; a (T, 9) start
        gets zero extra derivatives); default zeros ([S16] §VI-B: a non-zero start would
        predetermine the sign of ω).
    max_iter, ftol, xtol, gtol : LM stopping rules (:class:`~accel_bayes.inference.lm.StoppingRule`).
    progress : tqdm bar per LM run.
    rerun_from_estimate : after a run that did not diverge, run again from its poses with zero
        motion and keep the run with the lower cost ([S16] §VI-A remedy for partial minima,
        where ω took the wrong sign over part of the record).  ``"auto"``: re-run only when the
        first run's RMS whitened triad residual exceeds ``rerun_rms`` (a partial minimum misfits
        the data by many noise std; the global one fits to ≈ 1) — half the time on good data.
    covariance : compute the Laplace covariance (Schur complement of the Gauss–Newton matrix at
        the optimum, motion marginalised).
    raise_on_divergence : raise :class:`SelfCalDiverged` instead of returning a result with
        status "diverged" (whose poses cannot be read either way).
    divergence_kwargs : bounds passed to :func:`check_divergence`.
    warm_start_motion : first solve the motion alone with the poses held at their start values
        (from ``init_motion``, zero by default), then run the joint LM from that motion.  [S16]
        starts the joint LM from zero motion directly (``False``); the joint problem is then
        easily pulled into the diverged minima of Table III, even from the true poses, because
        the pose Jacobians vanish at zero motion and the first steps move poses and motion
        against each other.  The warm start keeps the zero-motion principle of [S16] §VI-B (the
        sign of ω is not predetermined: ω enters the motion-only stage through ω̇ and the
        integration constraint) and converges in ~20 iterations.
    restart_on_divergence : when the first run ends in a diverged minimum ([S16] Table III), run
        once more from the start positions with the diverged run's *orientations* and zero motion
        (label "restart"), and continue from that run if it does not diverge.  Orientations are
        fixed by the common (gravity-dominated) specific force that all triads see, so they
        converge even in the runs whose positions collapse or run off: with 20° initial
        orientation errors on the [S16] table motion, a run whose positions collapsed towards
        the fixed triad had brought the orientations to within 2–5°, and the restart from there
        converged to the global minimum.  The restart uses no information beyond the data and
        the start poses.
    damping : a zero-argument factory of LM damping strategies (each LM run needs a fresh one),
        or None: Marquardt's rule, diag(H) scaling, λ₀ = 10⁻⁶ (see ``_run_lm``).  A strategy
        instance is also accepted (it is then shared by the runs and re-initialised by each).

    Returns
    -------
    :class:`SelfCalResult`.
    """
    t_start = _time.perf_counter()
    opts = SelfcalSolveOptions(
        process_noise=process_noise, process_variances=process_variances, marginal_scale=marginal_scale,
        noise_max_iter=noise_max_iter, noise_rtol=noise_rtol, max_iter=max_iter, ftol=ftol, xtol=xtol, gtol=gtol,
        progress=progress, rerun_from_estimate=rerun_from_estimate, rerun_rms=rerun_rms, covariance=covariance,
        raise_on_divergence=raise_on_divergence, divergence_kwargs=divergence_kwargs,
        warm_start_motion=warm_start_motion, restart_on_divergence=restart_on_divergence, damping=damping)
    inp = solve_inputs(acc, time_or_dt, steps, nominal_positions, nominal_orientations, fixed, acc_noise_std,
                       sensor_params, dtype, device)
    noise = initial_process_noise(inp.acc, inp.dt, inp.steps, inp.p0, inp.q0, inp.fixed, inp.inv_std, opts.prior)
    x0 = _initial_motion(init_motion, inp.T, opts.prior.dim, dtype, inp.acc.device)
    out = _result(_runs(_Solver(inp, opts, noise), x0), inp, opts, noise)
    out.seconds = _time.perf_counter() - t_start
    if not out.ok and opts.raise_on_divergence:
        raise SelfCalDiverged(f"self-calibration diverged: {out.reason}", out)
    return out
