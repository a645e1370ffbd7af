"""``accel-bayes calibrate REC --out DIR``: posterior of the triad positions with PmMH ([C21]).

On an imported MIMU recording (``accel-bayes import-mimu``) the defaults run the whole real-data
pipeline: intrinsic calibration from the recording's rests, static / clipped / non-rotating
samples dropped, accelerometer noise estimated from the data (tempered by the sandwich factor),
MAP, PmMH.  Each step has a switch (``--intrinsics none``, ``--keep-static``, ``--keep-clipped``,
``--min-rotation 0``, ``--noise stated``, ``--no-noise-inflation``); what ran is printed and
recorded in ``positions.json`` (``provenance.settings.preprocess`` / ``noise_model``).

Writes DIR/posterior.nc (ArviZ InferenceData), DIR/summary.csv (R̂, ESS, MCSE per coordinate),
DIR/positions.json (DESIGN §7.3) and trace/rank/autocorr/ellipses plots; prints a short table.

Length of the chains: by default the chains run until converged — every coordinate with
R̂ < 1.01 (``--rhat-max``) and bulk and tail ESS ≥ 100 per chain, 400 for the 4 default chains
(``--ess-min``), checked every 500 draws per
chain (``--check-every``, a fixed count, so the result does not depend on the machine), up to
20 000 draws per chain (``--max-draws``) or 3600 s of sampling (``--max-seconds``, a safety stop
whose use makes the length machine-dependent and is reported).  ``--draws N`` runs exactly N draws
per chain instead (the fixed mode of earlier versions, same draws for the same seed).

Exit status (DESIGN §7.5): 0 converged; 2 refused (bad option, recording or checkpoint — checked
before any computation); 4 finished but the chains have not converged (some coordinate with
R̂ ≥ 1.01, bulk or tail ESS < 100 per chain, or not computable; in the default mode: within the budget):
the outputs are written, ``positions.json`` has ``diagnostics.converged: false`` and
``diagnostics.warnings`` (the coordinate, its value and the threshold of each failed criterion,
and the budget that stopped the run), and one line on stderr says why.
"""
from __future__ import annotations

import argparse
import sys

from . import _options as opt
from ._status import EXIT_OK, untrusted

# prep.preprocess.INTRINSICS_MODES, written out so that parsing imports no torch (a test keeps them equal)
INTRINSICS_MODES = ("auto", "estimate", "none")


def register(sub) -> None:
    from ..pipelines.calibrate_defaults import DEFAULTS
    from ..data.output_sets import OVERWRITE_DIR_HELP

    p = sub.add_parser(
        "calibrate",
        help="posterior of the accelerometer-triad positions (PmMH, [C21])",
        description="Sample the posterior of the accelerometer-triad positions relative to the reference IMU "
        "with pseudo-marginal Metropolis-Hastings and the Rao-Blackwellized likelihood of [C21]. "
        "Writes posterior.nc, summary.csv, positions.json and plots to --out.",
    )
    p.add_argument("recording", metavar="REC", help="recording file (.nc, format v1) with gyroscope data")
    p.add_argument("--out", required=True, metavar="DIR",
                   help="output directory (created if missing; written as one set, see the README)")
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_DIR_HELP)
    p.add_argument("--chains", type=opt.count(1), default=DEFAULTS["chains"],
                   help="number of chains (default %(default)s)")
    p.add_argument("--draws", type=opt.count(1), default=DEFAULTS["draws"], metavar="N",
                   help="run exactly N kept draws per chain (default: run until converged, see --max-draws)")
    p.add_argument("--warmup", type=opt.count(0), default=DEFAULTS["warmup"],
                   help="warm-up (adaptation) iterations per chain (default %(default)s)")
    c = p.add_argument_group(
        "run until converged (default; --draws N switches it off)",
        "The chains are continued from their current state (the same seed gives the draws of one long run) until "
        "every coordinate has R-hat < --rhat-max and bulk and tail ESS >= --ess-min, checked every --check-every "
        "draws per chain (fixed counts, never wall time), up to --max-draws draws per chain or --max-seconds of "
        "sampling. A run that stops unconverged exits with status 4 and says which criterion failed.")
    c.add_argument("--max-draws", type=opt.count(1), default=DEFAULTS["max_draws"], metavar="N",
                   help="most kept draws per chain (default %(default)s)")
    c.add_argument("--check-every", type=opt.count(1), default=DEFAULTS["check_every"], metavar="N",
                   help="kept draws per chain between convergence checks (default %(default)s)")
    c.add_argument("--max-seconds", type=opt.positive("s"), default=DEFAULTS["max_seconds"], metavar="S",
                   help="wall-clock safety stop of the sampling, seconds, tested after each check (default "
                        "%(default)s); a run stopped by it has a machine-dependent length and is reported so")
    c.add_argument("--rhat-max", type=opt.real(1.0, lo_open=True), default=DEFAULTS["rhat_max"], metavar="R",
                   help="R-hat threshold of every coordinate (default %(default)s; also decides exit status 4 "
                        "with --draws)")
    c.add_argument("--ess-min", type=opt.positive("draws"), default=DEFAULTS["ess_min"], metavar="E",
                   help="bulk and tail ESS threshold of every coordinate, all chains together (default 100 per "
                        "chain: 400 for 4 chains)")
    p.add_argument("--num-draws", type=opt.count(1), default=None, metavar="N",
                   help="Monte Carlo draws per likelihood estimate (default: chosen so Var[log p̂] ≈ 1)")
    p.add_argument("--seed", type=opt.seed, default=0, help="random seed (default %(default)s)")
    p.add_argument("--prior", choices=("gaussian", "box"), default=DEFAULTS["prior"],
                   help="prior on the positions (default %(default)s)")
    p.add_argument("--prior-std", type=opt.positive("m"), default=DEFAULTS["prior_std"], metavar="M",
                   help="prior standard deviation in metres (default %(default)s, [C21] §IV-A)")
    p.add_argument("--no-map", action="store_true",
                   help="do not fit the MAP first; chains start from prior draws")
    g = p.add_argument_group(
        "real-data preprocessing and noise",
        "Intrinsic calibration from the recording's rests, then dropping static, clipped and non-rotating samples; "
        "the accelerometer noise estimated from the data. 'auto' does this for a recording with rests (the real-data "
        "protocol) and skips it, with a note, for one without (e.g. simulated twisting).")
    g.add_argument("--intrinsics", default=DEFAULTS["intrinsics"], metavar="{auto,estimate,none,FILE.json}",
                   help="accelerometer bias/scale/misalignment and gyro bias: 'auto' (default) estimates them from the "
                        "recording's rests when it has any, 'estimate' insists, 'none' skips, or an intrinsics JSON "
                        "(accel-bayes intrinsics) to apply")
    g.add_argument("--keep-static", action="store_true", help="keep the samples of the rests (dropped by default)")
    g.add_argument("--keep-clipped", action="store_true",
                   help="keep samples where an accelerometer or gyroscope is at its range (dropped by default; a "
                        "warning on stderr counts the ones fitted)")
    g.add_argument("--min-rotation", type=opt.nonnegative("rad/s"), default=DEFAULTS["min_rotation"], metavar="RAD_S",
                   help="drop samples whose mean gyro rate |w| is below this, rad/s (default %(default)s = 29 deg/s; "
                        "0 keeps all)")
    g.add_argument("--select", choices=("rotation",), default=None,
                   help="(compatibility) drop samples without rotation even with --min-rotation 0")
    g.add_argument("--noise", choices=("auto", "stated", "estimate"), default=DEFAULTS["noise"],
                   help="accelerometer noise: the recording's stated std, or estimated from the data (a level per "
                        "IMU x a factor per gyro-rate bin, type-II ML at the MAP, inflated by the sandwich factor); "
                        "'auto' (default): estimate for recordings with rests or with a --model report that has an "
                        "'unexplained' finding, stated otherwise")
    g.add_argument("--noise-bins", type=opt.count(1), default=DEFAULTS["noise_bins"], metavar="B",
                   help="gyro-rate bins of the estimated noise model (default %(default)s; 1 = one level per IMU)")
    g.add_argument("--no-noise-inflation", action="store_true",
                   help="with estimated noise: do not apply the sandwich (misspecification) factor")
    p.add_argument("--model", default=None, metavar="REPORT.json",
                   help="a mismatch report of this recording (accel-bayes mismatch): its random gyroscope effects "
                        "(timing_wander, sampling_jitter) become per-sample gyro covariances in the likelihood; the "
                        "sandwich is then measured and recorded, not applied (refused if the report is for another "
                        "recording)")
    p.add_argument("--instant-error", action="store_true",
                   help="with --model: also project out each triad's own sampling-instant error times its output "
                        "rate (e by type-II ML; ~5x the cost of one flat likelihood evaluation); default off")
    p.add_argument("--angular-jerk", action=argparse.BooleanOptionalAction, default=None,
                   help="with --model: also project out the board's unresolved angular jerk (loaded by the data ages "
                        "times the lever arms, scale per band by type-II ML; ~2.3x the cost of one flat likelihood "
                        "evaluation, ~4.7x where the report leaves an IMU without a clock); default on with --model, --no-angular-jerk: the jerk alone")
    p.add_argument("--acc-blocks", default=DEFAULTS["acc_blocks"], metavar="{fit,fixed,TAU_M,TAU_B}",
                   help="with --model whose report has accelerometer blocks: 'fit' (default) integrates the "
                        "triads' linear errors out of the likelihood (the part they share drawn from its prior), "
                        "the tolerance by type-II ML; TAU_M,TAU_B that "
                        "tolerance (matrix entries, offsets m/s^2); 'fixed' inverts the blocks as exact")
    p.add_argument("--phi-prior", choices=("empirical", "flat"), default=DEFAULTS["phi_prior"],
                   help="prior on φ = [ω̇; s] that the likelihood integrates out: 'empirical' (default: a Gaussian "
                        "whose covariance is estimated from the recording; removes the flat prior's inward pull on "
                        "the array) or 'flat' ([C21] as published)")
    p.add_argument("--gyro-method", choices=("auto", "sample_cov", "sample_cov_mean", "calibrated"),
                   default=DEFAULTS["gyro_method"],
                   help="gyroscope posterior (default %(default)s: 'calibrated' with estimated noise, else "
                        "'sample_cov' = [C21] eq. 30)")
    p.add_argument("--proposal", choices=("auto", "rw", "mixture"), default="auto",
                   help="proposal: random walk, or random walk mixed with independence moves (default %(default)s)")
    p.add_argument("--correlation", type=_correlation, default=DEFAULTS["correlation"], metavar="{auto,RHO}",
                   help="correlated pseudo-marginal sampling: the chains carry the estimator's normals z and move "
                        "them by z' = RHO z + sqrt(1 - RHO^2) e. 'auto' (default): when fresh draws would need "
                        "N > 1 per estimate, N = 1 and RHO from the data (Var of the log-estimate change ~ 1); "
                        "0: fresh draws every iteration ([C21])")
    p.add_argument("--checkpoint-every", type=opt.count(0), default=0, metavar="K",
                   help="save the sampler state to DIR/checkpoint.pt every K iterations (kept if the run is "
                        "killed or interrupted)")
    p.add_argument("--resume", action="store_true",
                   help="continue from DIR/checkpoint.pt (a DIR holding it needs no --overwrite)")
    p.add_argument("--threads", type=opt.count(1), default=DEFAULTS["threads"], metavar="K",
                   help="torch CPU threads (default %(default)s: the tensors are small, and extra threads cost more "
                        "than they give on a shared machine)")
    p.add_argument("--device", type=_device, default=None, metavar="DEV",
                   help="run the chains on DEV, e.g. cuda (default: the CPU; loading, MAP and summary stay on the "
                        "CPU; another device draws other random numbers; no --checkpoint-every/--resume)")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=_run)


def _device(s: str):
    """--device: a torch device torch can allocate on here."""
    import argparse

    from ..errors import UserError
    from ..pipelines.calibrate import _device_option

    try:
        _device_option(s, None)
    except UserError as exc:
        raise argparse.ArgumentTypeError(str(exc).split(": ", 1)[1]) from None
    return s


def _correlation(s: str):
    """--correlation: 'auto' or a number in [0, 1)."""
    return "auto" if s == "auto" else opt.fraction()(s)


def _run(args) -> int:
    from pathlib import Path

    from ..data.output_sets import OutputDir
    from ..data.paths import require_file
    from ..pipelines.calibrate_options import CalibrateOptions

    # inputs, options and output target before the pipeline (and torch) is imported: refusals answer at once
    require_file(args.recording, "recording file")
    if args.intrinsics not in INTRINSICS_MODES:
        require_file(args.intrinsics, "intrinsics file (JSON)", flag="--intrinsics")
    if args.model is not None:
        require_file(args.model, "mismatch report (JSON)", flag="--model")
    # the checkpoint lives in DIR itself (a killed run keeps it) and joins the committed set
    ckpt = Path(args.out) / "checkpoint.pt" if args.checkpoint_every or args.resume else None
    options = CalibrateOptions.from_args(args, checkpoint=ckpt)
    out = OutputDir(args.out, overwrite=args.overwrite, resume=args.resume, keep=("checkpoint.pt",),
                    inputs=(args.recording, args.intrinsics, args.model)).open()
    from ._rig import calibrate_if_rig  # issue #28: a rig recording goes to the rig model, no flag
    status = calibrate_if_rig(args, out)
    if status is not None:
        return status
    from ..pipelines.calibrate import calibrate, write_outputs

    if ckpt is not None:
        out.ensure_target()
        if args.resume and not ckpt.exists():
            print(f"accel-bayes calibrate: no checkpoint at {ckpt}; starting afresh", file=sys.stderr)
    res = calibrate(args.recording, options, progress=not args.quiet)
    n_kept = res.settings["preprocess"]["samples"].get("clipped_kept", 0)
    if n_kept:  # stderr: the table below goes to stdout, which is often redirected
        print(f"accel-bayes calibrate: warning: --keep-clipped: {n_kept} samples with an accelerometer or gyroscope at "
              "its range are fitted; the model cannot explain them and the posterior may be biased", file=sys.stderr)
    paths = write_outputs(res, out.staging, plots=not args.no_plots)
    out.commit()
    print(format_table(res))
    print(f"files: {', '.join(str(out.final(p)) for p in paths.values())}")
    d = res.positions["diagnostics"]
    if not d["converged"]:
        return untrusted("calibrate", d["warnings"] + [_longer_hint(res.settings)], str(out.final(paths["positions"])))
    return EXIT_OK


def _longer_hint(settings) -> str:
    conv = settings.get("convergence") or {}
    if conv.get("mode") == "fixed draws":
        return "run longer (--draws/--warmup, or leave out --draws to run until converged)"
    return ("run longer (raise --max-draws/--max-seconds; with --checkpoint-every, --resume continues the same "
            "chains)")


def format_table(res) -> str:
    """IMU, posterior mean (mm), std (µm), worst R̂ and smallest bulk ESS over its 3 coordinates
    ("n/a" where they cannot be computed: one chain, a few draws)."""
    from ..diagnostics.stats import format_stat

    summ = res.summary
    doc = res.positions
    lines = []
    pre = (res.extra or {}).get("preprocess")
    if pre is not None:
        lines.extend(pre.lines())
    nm = res.settings.get("noise_model")
    if res.settings.get("noise") == "estimate" and nm:
        sw = nm.get("sandwich") or {}
        lines.append("noise: estimated (type-II ML at the MAP): level per IMU "
                     + ", ".join(f"{v:.3g}" for v in nm["std"]) + " m/s2 (stated "
                     + ", ".join(f"{v:.3g}" for v in nm["stated"]) + f"); rate factor over {len(nm['bin_scale'])} "
                     f"|w| bins {min(nm['bin_scale']):.2f}-{max(nm['bin_scale']):.2f}"
                     + (f"; sandwich inflation kappa {sw['applied']:.2f} (std x{sw['applied'] ** 0.5:.2f})"
                        if sw.get("applied") else ""))
    elif res.settings.get("noise"):
        lines.append(f"noise: {res.settings['noise']} (the recording's acc_noise_std); gyro posterior "
                     f"{res.settings['gyro_method']}")
    mod = res.settings.get("model")
    if mod:
        sw = mod.get("sandwich") or {}
        lines.append(f"model: {mod.get('source') or 'in memory'} (sha256 {mod['sha256'][:12]}): {len(mod['used'])} finding(s) "
                     f"in the likelihood, {len(mod['skipped'])} skipped"
                     + (f"; sandwich/Laplace std ratio at the mode max {sw['std_ratio_max']:.2f}, median "
                        f"{sw['std_ratio_median']:.2f} (kappa {sw['kappa']:.2f}, tempering {sw['tempering_applied']:.2f})"
                        if sw.get("kappa") is not None else ""))
        ab = mod.get("acc_blocks") or {}
        if ab.get("tau_matrix") is not None:
            cut = ab.get("common_shift_std_median_m")
            lines.append(f"model: accelerometer blocks of IMU(s) {', '.join(str(k) for k in ab.get('report_blocks') or [])}"
                         f" integrated out (tolerance {100 * ab['tau_matrix']:.2f} % / {ab['tau_bias_m_s2']:.3g} m/s2, "
                         f"{ab.get('tau_from')}); the part every triad shares cut"
                         + (f" (adds {cut * 1e6:.0f} µm std, median)" if cut is not None else "")
                         + "; the sandwich above is that target's")
        elif ab.get("how"):
            lines.append(f"model: accelerometer blocks {ab['how']}")
        unc = (mod.get("unresolved_motion") or {}).get("unclocked") or []
        if unc:
            imus = ", ".join(str(u["imu"]) for u in unc)
            lines.append(f"model: IMU(s) {imus} without a sampling clock in the report: expected data age "
                         f"{unc[0]['age_acc_s'] * 1e3:.3g} ms (acc) with a random age of std "
                         f"{unc[0]['age_std_s'] * 1e3:.3g} ms loading the unresolved motion")
    conv = res.settings.get("convergence") or {}
    how = ""
    if conv.get("mode") == "until converged":
        how = f" (run until converged: {conv['checks']} checks every {conv['check_every']}, {conv['stopped']})"
    lines += [f"PmMH: {res.settings['chains']} chains × {res.settings['draws']} draws{how} "
              f"(+{res.settings['warmup']} warm-up), N = {res.settings['num_draws']}, "
              + (f"correlated rho = {res.settings['correlation']:.4f}, " if res.settings.get("correlation") else "")
              + f"T = {res.settings['T']}, {res.seconds:.1f} s; positions relative to IMU {doc['reference_imu']}",
              f"{'IMU':>4} {'x mm':>9} {'y mm':>9} {'z mm':>9} {'sx µm':>8} {'sy µm':>8} {'sz µm':>8} "
              f"{'R-hat':>6} {'ESS':>7}"]
    for e in doc["imus"]:
        if e["mean"] is None:
            lines.append(f"{e['imu']:>4}  (no accelerometer)")
            continue
        m = [v * 1e3 for v in e["mean"]]
        s = [v * 1e6 for v in e["std"]]
        if e["imu"] == doc["reference_imu"]:
            rh, ess = "ref", ""
        else:
            rows = [f"r[{e['imu']}, {a}]" for a in "xyz"]
            rows = [r for r in rows if r in summ.index]
            rh = format_stat(summ.loc[rows, "r_hat"].max(), ".3f") if rows else ""
            ess = format_stat(summ.loc[rows, "ess_bulk"].min(), ".0f") if rows else ""
        lines.append(f"{e['imu']:>4} {m[0]:9.3f} {m[1]:9.3f} {m[2]:9.3f} {s[0]:8.1f} {s[1]:8.1f} {s[2]:8.1f} "
                     f"{rh:>6} {ess:>7}")
    d = doc["diagnostics"]
    lines.append(f"max R-hat {format_stat(d['rhat_max'], '.3f')}, "
                 f"min bulk ESS {format_stat(d['ess_bulk_min'], '.0f')}, "
                 f"min tail ESS {format_stat(d.get('ess_tail_min'), '.0f')}, "
                 f"acceptance {', '.join(f'{a:.2f}' for a in d['acceptance_rate'])}")
    if not d["converged"]:
        lines.append(f"warning: {'; '.join(d['warnings'])}: the chains have not mixed well enough "
                     f"for reliable moments; {_longer_hint(res.settings)} and check trace.png/rank.png")
    return "\n".join(lines)
