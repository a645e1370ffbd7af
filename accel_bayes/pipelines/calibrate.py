"""Posterior calibration of the accelerometer-triad positions with PmMH ([C21]; DESIGN §2, §5, §7.3).

:func:`calibrate` strings the stages together for one recording:

0. real-data preprocessing (:mod:`accel_bayes.prep.preprocess`): intrinsic calibration from the
   recording's own rests, then dropping static, clipped and non-rotating samples; and, for such
   recordings, the accelerometer noise model estimated from the data (:mod:`accel_bayes.model.noise`:
   a level per triad × a factor per gyro-rate bin, type-II ML at the MAP, and the sandwich
   inflation for what the model still misses).  On a recording without rests (e.g. simulated
   twisting) the intrinsics are skipped with a note and the stated noise is used;
1. the Rao-Blackwellized likelihood (:class:`~accel_bayes.model.likelihood.RaoBlackwellLikelihood`,
   [C21] eq. 26 with the −½ power of DESIGN §4) with the chosen gyro posterior and sample
   selection;
2. the prior on θ (Gaussian, σ_r = 3 mm by default, [C21] §IV-A; or a box of the same std);
3. optionally the MAP and its Laplace covariance (:mod:`accel_bayes.inference.map`): a central
   θ for choosing N, over-dispersed chain starts, the random-walk shape and an independence
   proposal;
4. N, the number of Monte Carlo draws per likelihood estimate, chosen so that Var[log p̂] ≈ 1
   at the central θ ([C21] §III-C, accepted range 0.1–3); where that needs N > 1, instead the
   correlated pseudo-marginal kernel with N = 1 and a correlation ρ of successive estimates
   measured at the central θ (Deligiannidis, Doucet & Pitt 2018);
5. C chains of :class:`~accel_bayes.inference.mcmc.PMMHKernel` (warm-up adaptation, then a
   fixed exact kernel), crash-safe when a checkpoint file is given; by default continued until
   every coordinate has R̂ < 1.01 and bulk and tail ESS ≥ 400, checked every 500 draws per chain,
   up to 20 000 draws per chain (:func:`~accel_bayes.inference.mcmc.run_pmmh_until`), or a fixed
   number of draws when ``draws`` is given;
6. ArviZ diagnostics and the DESIGN §7.3 ``positions.json``.

:func:`write_outputs` writes ``posterior.nc``, ``summary.csv``, ``positions.json`` and the plots.
The steps and the records they return are in :mod:`accel_bayes.pipelines.calibrate_steps`.
"""
from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from .. import __version__
from ..diagnostics import arviz_calls as dg_az, plots as dg_plots, stats as dg_stats
from ..data import positions as _positions_mod
from ..data.outputs import to_jsonable, write_text
from ..errors import UserError
from ..inference.mcmc import PMMHRun
from ..inference.mcmc.priors import BoxPrior, GaussianPrior
from ..model.likelihood import RaoBlackwellLikelihood
from ..prep.prepared import prepare_recording
from ..threads import torch_threads
from .calibrate_defaults import DEFAULTS
from .calibrate_options import CalibrateOptions
# The steps and the records they return (split out to keep each file under 600 lines);
# _recording_hash and _model_gyro_step are imported from here by tests/ and experiments/.
from .calibrate_model import (_block_sandwich_record, _common_cut_step, _model_block_step, _model_gyro_step,
                              _model_percov_step, _percov_sandwich_record, _sandwich_record)
from .calibrate_steps import (  # noqa: F401
    _central_step, _chains_fingerprint, _chains_step, _check_resume, _convergence_settings, _coordinate_names,
    _load_step, _map_step, _model_option, _noise_step, _prepare_step, _recording_hash, _start_step)

__all__ = ["calibrate", "CalibrateOptions", "CalibrationResult", "write_outputs", "positions_document", "DEFAULTS"]

# Defaults: pipelines/calibrate_defaults.py (torch-free: the command line's --help shows them).


@dataclass
class CalibrationResult:
    """What :func:`calibrate` returns.

    idata : ``az.InferenceData`` (posterior ``r`` (chain, draw, imu, axis), m, relative to the
        reference triad; sample stats; log-likelihood estimates).
    summary : pandas DataFrame from :func:`accel_bayes.diagnostics.arviz_calls.summarize` (R̂, ESS, MCSE).
    positions : the DESIGN §7.3 ``positions.json`` document (a dict).
    settings : every setting used (including the N chosen and its variance table).
    seconds : wall time of the whole calibration.
    run : the :class:`~accel_bayes.inference.mcmc.PMMHRun` (draws and per-draw statistics).
    map_result : the MAP result when one was used, else None.
    array : the :class:`~accel_bayes.physics.arrays.SensorArray` of the recording (for plots).
    """

    idata: object
    summary: object
    positions: dict
    settings: dict
    seconds: float
    run: PMMHRun
    map_result: object = None
    array: object = None
    input_sha256: str | None = None
    extra: dict = field(default_factory=dict)


# ---------------------------------------------------------------------------- options

def _device_option(device, checkpoint):
    """The chains' device: None (the default path, on the CPU), else a usable ``torch.device``;
    refused with a one-line error when torch cannot allocate there."""
    if device is None:
        return None
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError, ValueError):
        raise UserError(f"device: expected a torch device such as 'cpu' or 'cuda', got {device!r}") from None
    try:
        torch.empty(1, device=dev)
    except Exception as exc:  # noqa: BLE001 — whatever torch raises, the device is not usable here
        raise UserError(f"device: {str(dev)!r} is not usable here ({str(exc).splitlines()[0]})") from None
    # an explicit "cpu" takes the device path too (its draws equal the default path's, bit for bit:
    # tests/test_device.py), and keeps checkpoints
    if checkpoint is not None and dev.type != "cpu":
        raise UserError(f"checkpoint: not supported with device={str(dev)!r} (checkpoints hold CPU chain states)")
    return dev


# ---------------------------------------------------------------------------- main entry

def calibrate(recording, options: CalibrateOptions | None = None, *, progress: bool = True, callback=None,
              **keywords) -> CalibrationResult:
    """Sample the posterior of the accelerometer-triad positions of one recording with PmMH.

    recording : a :class:`~accel_bayes.data.recording.Recording` or a path to a format-v1 file.
    options : a :class:`~accel_bayes.pipelines.calibrate_options.CalibrateOptions` (None: every
        default), checked when it was built, before the recording is read; its docstring gives
        each option's meaning and unit.
    progress : tqdm bars (stderr) with the acceptance rate.
    callback : ``callback(chain, iteration, kernel)`` after every iteration.
    keywords : (kept for 0.2 only; prefer ``options``) the options as keywords, e.g.
        ``calibrate(rec, chains=2)``: ``options`` with these fields replaced.

    Returns a :class:`CalibrationResult`.
    """
    opts = options if options is not None else CalibrateOptions()
    if keywords:
        opts = dataclasses.replace(opts, **keywords)
    with torch_threads(opts.threads):  # small tensors: one thread is faster on a shared machine (accel_bayes.threads)
        t0 = time.perf_counter()
        # Steps: options (checked when the record was built: DESIGN §7.5 refuses early), 1 load,
        # 2 prepare, 3 noise, 4 MAP, 5 central θ and N, 6 posterior, 7 summary; writing the files
        # is :func:`write_outputs`.  Each step returns a record; the settings are assembled here.
        device = _device_option(opts.device, opts.checkpoint)
        cmodel = _model_option(opts.model)
        raw, sha, src = _load_step(recording)
        if cmodel is not None:
            cmodel.check_recording(raw)
            if cmodel.unresolved and opts.inflate_noise:
                raise UserError("noise_inflation: the model's per-sample covariance (its unresolved_motion finding) "
                                "replaces the tempering; expected no noise inflation with this report")
        request = _check_resume(raw, sha, opts, None if cmodel is None else cmodel.sha256)
        # step 2, prepare: intrinsics and sample selection; then the likelihood, the prior and the settings
        pre = _prepare_step(raw, opts)
        rec = pre.recording
        if cmodel is not None:
            cmodel.match_acc_outputs(bool(pre.summary["intrinsics"]["applied"]))
        noise_mode = opts.noise_mode(pre.has_rests, cmodel is not None and cmodel.unexplained)
        gm = ("calibrated" if noise_mode == "estimate" else "sample_cov") if opts.gyro_method == "auto" \
            else opts.gyro_method
        if cmodel is not None:
            gm = "calibrated"  # the model's fused posterior generalises it (model.report_terms)
        lik = RaoBlackwellLikelihood.from_recording(prepare_recording(rec, selection=pre.selection), num_draws=1,
                                                    gyro_method=gm)
        gyro_info = terms = blk = None
        if cmodel is not None:
            omega_norm = lik.omega.mean.norm(dim=-1)  # the "calibrated" |ω̄|: the report's bands are of it
            lik, gyro_info, terms = _model_gyro_step(lik, rec, cmodel)
            model_norm = lik.omega.mean.norm(dim=-1)  # what the noise model's per-sample scale is read at
            gm = "model"
        array = raw.sensor_array()
        labels = list(lik.imu_labels)
        ref_label = labels[lik.reference]
        free_labels = [k for i, k in enumerate(labels) if i != lik.reference]
        nominal_acc = torch.as_tensor(np.asarray(rec.nominal_position)[labels], dtype=torch.float64)
        ps = opts.prior_std
        if opts.prior == "gaussian":
            pri = GaussianPrior(nominal_acc, std=ps, reference=lik.reference)
        else:
            pri = BoxPrior.with_std(nominal_acc, std=ps, reference=lik.reference)

        settings = {
            **opts.to_settings(gyro_method=gm, noise=noise_mode, min_rotation=pre.summary["samples"]["min_rotation"]),
            "T": lik.T, "A": lik.A, "imu_labels": labels, "reference_imu": ref_label,
            "samples": {"recording": int(rec.T), "used": int(lik.T)},
            "target_accept_prob": opts.target_accept_prob,
            "preprocess": pre.summary,
        }
        if src is not None:
            settings["input"] = src
        extra = {"preprocess": pre}
        if opts.noise == "auto" and noise_mode == "estimate" and not pre.has_rests:
            # the one case the mode is not the recording's own: say where it came from (provenance)
            settings["noise_auto"] = "estimate: no rests, but the model's report has an 'unexplained' finding"

        noise = _noise_step(lik, nominal_acc, ps, noise_mode, opts)
        settings.update(noise.settings())
        if noise.noise is not None:
            extra["noise"] = noise.noise
        lik = noise.lik
        mstep = _map_step(lik, nominal_acc, ps, noise_mode, opts.use_map, noise.map)
        settings.update(mstep.settings())
        map_res = mstep.result
        if cmodel is not None:
            settings["model"] = {**cmodel.describe(), "gyro_posterior": gyro_info,
                                 "sandwich": _sandwich_record(lik, map_res, nominal_acc, ps, free_labels)}
            # the noise model's per-sample scale the likelihood's outputs were divided by (the model's steps' input)
            scale = (np.ones(lik.T) if noise.noise is None
                     else noise.noise.sample_scale(model_norm.cpu().numpy()))
        if terms is not None:
            # the per-sample covariance: the chains' likelihood from here on; the flat model's sandwich kept beside
            pc = _model_percov_step(lik, terms, omega_norm, scale, map_res, nominal_acc, ps,
                                    instant_error=opts.instant_error, angular_jerk=opts.angular_jerk)
            lik = pc.lik
            extra["percov"] = pc
            settings["model"]["sandwich_flat"] = settings["model"]["sandwich"]
            settings["model"]["sandwich"] = _percov_sandwich_record(pc, free_labels)
            settings["model"]["unresolved_motion"] = {
                **pc.record, "mode_positions_m": pc.positions.tolist(),
                "chains_centre": "this likelihood's mode at omega-bar and its Laplace covariance (central theta, "
                                 "proposal, independence proposal and starts), not the flat MAP's"}
            if map_res is not None:
                # the flat MAP sits ~2 of its std off this target's mode (percov_honesty_probe.md): an
                # independence proposal there would leave the target's tails to the random walk alone
                map_res = _recentred(map_res, pc.positions, pc.laplace_cov, lik.reference)
        if cmodel is not None and cmodel.acc_linear:
            if opts.acc_blocks == "fixed":
                settings["model"]["acc_blocks"] = {"how": "fixed: the report's blocks inverted as exact (option "
                                                          "acc_blocks)"}
            else:
                pos0 = nominal_acc if map_res is None else map_res.positions
                blk = _model_block_step(lik, rec, cmodel, pos0, nominal_acc, ps, scale, opts.acc_blocks,
                                        prev_cov=None if map_res is None else map_res.laplace_cov)
                lik = blk.lik
                settings["model"]["acc_blocks"] = blk.record
                # the chains' target is ℓ + Δ now: its own sandwich (Fisher's identity), the one before it kept
                settings["model"]["sandwich_before_blocks"] = settings["model"]["sandwich"]
                settings["model"]["sandwich"] = _block_sandwich_record(blk, free_labels)
                if map_res is not None:  # the chains centre on this target's mode, as for the per-sample covariance
                    map_res = _recentred(map_res, blk.positions, blk.laplace_cov, lik.reference)
        draws = _central_step(lik, pri, map_res, opts)
        lik.num_draws = int(draws.num_draws)
        settings.update(draws.settings())
        start = _start_step(lik, pri, draws, opts)
        settings.update(start.settings())
        fingerprint = _chains_fingerprint(settings, lik, request)
        # after the fingerprint: CPU checkpoints of earlier versions stay resumable (a device run has none)
        settings["device"] = "cpu" if device is None else str(device)
        names = _coordinate_names(labels, lik.reference)
        run = _chains_step(lik, pri, draws, start, opts, device=device, fingerprint=fingerprint, names=names,
                           progress=progress, callback=callback)
        if blk is not None:  # the accelerometers' common error, cut: drawn from its prior onto the draws
            run = _common_cut_step(run, blk, lik, opts.seed, settings["model"]["acc_blocks"])

        # step 7, summary: ArviZ diagnostics and the positions document
        N = draws.num_draws
        idata = dg_az.to_inference_data(
            run.theta, free_labels, run.log_phat, log_prior=run.log_prior, accepted=run.accepted,
            accept_prob=run.accept_prob, step_size=run.step_size, reference_imu=ref_label,
            attrs={"method": "pmmh", "num_draws": int(N), "seed": opts.seed, "accel_bayes_version": __version__},
        )
        summary = dg_az.summarize(idata)
        seconds = time.perf_counter() - t0
        settings.update(_convergence_settings(run, opts))
        settings["acceptance_rate"] = [float(a) for a in run.acceptance_rate]
        settings["step_size"] = [float(s) for s in run.step_size]
        settings["divergences"] = int(sum(len(d.get("divergences", [])) for d in run.diagnostics))
        positions = positions_document(idata, K=rec.K, reference_imu=ref_label, seconds=seconds, settings=settings,
                                       input_sha256=sha, seed=opts.seed)
        return CalibrationResult(idata=idata, summary=summary, positions=positions, settings=settings, seconds=seconds,
                                 run=run, map_result=map_res, array=array, input_sha256=sha, extra=extra)


def _recentred(map_res, positions, laplace_cov, reference: int):
    """``map_res`` centred on another target's mode instead: its positions (A, 3) m (reference row zero),
    θ (the free rows) and Laplace covariance (m²) — where the chains' central θ, proposals and starts go."""
    free = [i for i in range(positions.shape[0]) if i != reference]
    return dataclasses.replace(map_res, positions=positions, theta=positions[free], laplace_cov=laplace_cov)


def positions_document(idata, *, K: int, reference_imu: int, seconds: float, settings: dict,
                       input_sha256: str | None, seed: int) -> dict:
    """The DESIGN §7.3 document for a PmMH posterior (built by :mod:`accel_bayes.data.positions`, the
    one writer of the format): every IMU sorted by label, posterior mean/std/cov of its triad
    position relative to the reference IMU (array frame, m; zeros for the reference), R̂/ESS
    diagnostics (``converged`` and ``warnings`` by :func:`accel_bayes.diagnostics.stats.convergence_check`
    with the criteria of ``settings["convergence"]`` (default R̂ < 1.01, bulk and tail ESS ≥ 400);
    R̂/ESS are null where they cannot be computed; the draws per chain, the number of checks and
    why the run stopped) and provenance.  IMUs without an accelerometer triad get null moments."""
    mom = dg_stats.posterior_moments(idata)
    means = np.zeros((int(K), 3))
    covs = np.zeros((int(K), 3, 3))
    estimated = set(mom["imu"]) | {int(reference_imu)}
    for i, lab in enumerate(mom["imu"]):
        means[lab] = mom["mean"][i]
        covs[lab] = mom["cov"][i]
    for k in range(int(K)):
        if k not in estimated:  # no accelerometer triad: nothing to report (null in JSON)
            means[k] = np.nan
            covs[k] = np.nan
    conv = settings.get("convergence") or {}
    crit = conv.get("criteria") or {}
    x = idata.posterior[dg_az.VAR]
    names = [f"r[{int(i)}, {a}]" for i in x.coords["imu"].values for a in x.coords["axis"].values]
    chk = dg_stats.convergence_check(x.values, rhat_max=crit.get("rhat_max", dg_stats.RHAT_MAX),
                               ess_min=crit.get("ess_bulk_min", dg_stats.ESS_MIN), names=names)
    reasons = list(chk.failed)
    if reasons and conv.get("stopped") in ("max_draws", "max_seconds"):
        reasons.append(f"stopped unconverged after {conv.get('draws')} draws per chain and {conv.get('checks')} "
                       f"checks: {conv.get('why')}")
    diagnostics = {
        "rhat_max": to_jsonable(float(chk.rhat_max), nonfinite="null"),
        "ess_bulk_min": to_jsonable(float(chk.ess_bulk_min), nonfinite="null"),
        # added keys (§7.3 allows them): False with the reasons when R̂/ESS fail the rule, DESIGN §7.5 status 4
        "ess_tail_min": to_jsonable(float(chk.ess_tail_min), nonfinite="null"),
        "converged": not reasons,
        "warnings": reasons,
        "criteria": {"rhat_max": chk.rhat_limit, "ess_min": chk.ess_min},
        "draws_per_chain": int(x.sizes["draw"]),
        "checks": conv.get("checks"),
        "stopped": conv.get("stopped"),
        "seconds": float(seconds),
        "acceptance_rate": settings.get("acceptance_rate"),
        "num_draws": settings.get("num_draws"),
    }
    provenance = {"version": __version__, "input_sha256": input_sha256, "seed": int(seed),
                  "settings": json.loads(json.dumps(settings, default=str))}
    return _positions_mod.positions_document(method="pmmh", reference_imu=int(reference_imu), means=means,
                                             covs=covs, diagnostics=diagnostics, provenance=provenance)


def write_outputs(result: CalibrationResult, out_dir, *, plots: bool = True, truth=None) -> dict:
    """Write ``posterior.nc``, ``summary.csv``, ``positions.json`` and (``plots``) trace.png,
    rank.png, autocorr.png, ellipses.png into ``out_dir``, each file atomically; returns
    {name: path}.  ``truth``: (K, 3) true positions relative to the reference, m, drawn in
    ellipses.png where known (a simulation's).  The CLI passes the staging directory of an
    :class:`accel_bayes.data.output_sets.OutputDir`, so that the files appear in ``--out`` as one set."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise UserError(f"--out: {out} exists and is not a directory")
    out.mkdir(parents=True, exist_ok=True)
    paths = {}
    paths["posterior"] = dg_az.save(result.idata, out / "posterior.nc")
    paths["summary"] = write_text(out / "summary.csv", result.summary.to_csv())
    paths["positions"] = _positions_mod.write_positions(result.positions, out / "positions.json")
    if plots and result.array is not None:
        for q in dg_plots.save_plots(result.idata, result.array, out, prior_std=result.settings.get("prior_std"),
                               truth=truth):
            paths[q.stem] = q
    return paths
