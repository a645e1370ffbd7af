"""``accel-bayes mismatch``: find, name and fix model mismatch in a recording (DESIGN §7.2).

    accel-bayes mismatch rec.nc --out DIR [--alpha A] [--effects a,b,...] [--no-refine]
                                          [--posterior] [--seed S]

writes ``DIR/report.json`` (format ``accel_bayes.mismatch/1``), ``DIR/report.md`` and its
figures, and prints one line per finding.  Exit status 0 whether or not a mismatch is found;
2 for bad input (unreadable recording, unknown effect name, bad option, fewer than 3 samples, or
a recording that does not rotate: the rotation-dependent effects could not be tested, so a
clean report would be unfounded).
"""
from __future__ import annotations

from . import _options as opt


def register(subparsers) -> None:
    from ..data.output_sets import OVERWRITE_DIR_HELP

    p = subparsers.add_parser(
        "mismatch",
        help="find where the model and a recording disagree, name the missing physics, refit",
        description="Fit the nominal array model, locate residual excess (IMU, axis, motion regime), test every "
        "candidate effect of vocabulary v1.2 (DESIGN §7.2; --effects names a subset, an unknown name is refused with the list) by "
        "its likelihood-ratio evidence against a Bonferroni threshold, add the supported ones, refit and compare. Writes DIR/report.json "
        "(accel_bayes.mismatch/1) and DIR/report.md with figures.",
    )
    p.add_argument("recording", metavar="REC", help="recording file (NetCDF format v1, with gyroscope data)")
    p.add_argument("--out", required=True, metavar="DIR",
                   help="output directory (created if missing; written as one set, see the README)")
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_DIR_HELP)
    p.add_argument("--alpha", type=opt.fraction(lo_open=True), default=0.01,
                   help="family-wise error rate of the Bonferroni-corrected threshold (default 0.01)")
    p.add_argument("--effects", default=None, metavar="A,B,...",
                   help="comma-separated effect names to try (default: all of vocabulary v1.2)")
    p.add_argument("--max-findings", type=opt.count(0), default=3, help="most effects added to the model (default 3)")
    p.add_argument("--no-refine", action="store_true", help="skip the refined-model comparison (refined = null)")
    p.add_argument("--posterior", action="store_true",
                   help="also run short PmMH calibrations before/after correcting for the findings (slow)")
    p.add_argument("--seed", type=opt.seed, default=0, help="random seed (PPC twins, Laplace draws; default 0)")
    p.add_argument("--twins", type=opt.count(1), default=100, help="posterior predictive twins (default 100)")
    p.add_argument("--unresolved-angular-jerk", action="store_true",
                   help="unresolved_motion also carries the board's angular jerk on the accelerometers, through "
                        "each triad's lever arm (opt-in; default off)")
    p.add_argument("--acc-linear", action="store_true",
                   help="run the accelerometer linear stage: every triad's 3x3 scale/misalignment and offset, "
                        "estimated as one block (on the rest-calibrated outputs where the rests calibrate the triads: "
                        "what they leave, e.g. each chip's rotation on the board) (opt-in; default off)")
    p.add_argument("--no-figures", action="store_true", help="write report.json and report.md without figures")
    p.add_argument("--progress", action="store_true", help="print stage messages")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..data.output_sets import OutputDir
    from ..data.paths import require_file
    from ..mismatch.options import DetectOptions

    # the options, the input and the target are checked before torch is imported
    options = DetectOptions.from_args(args)
    require_file(args.recording, "recording file")
    out = OutputDir(args.out, overwrite=args.overwrite, inputs=(args.recording,)).open()
    from ..mismatch import detect

    if args.posterior:
        import dataclasses

        from ..pipelines.calibrate import calibrate

        options = dataclasses.replace(options, posterior=calibrate)
    report = detect(args.recording, options)
    paths = report.write(out.staging, figures=not args.no_figures)
    out.commit()
    d = report.to_dict()
    if d["mismatch_detected"]:
        print(f"mismatch detected (threshold {d['threshold']:.4g}):")
        for i, f in enumerate(d["findings"], 1):
            loc = ", ".join(x for x in (None if f["imu"] is None else f"IMU {f['imu']}",
                                        None if f["axis"] is None else f"axis {f['axis']}") if x)
            print(f"  {i}. {f['effect']}" + (f" ({loc})" if loc else "") + f": evidence {f['evidence']:.4g}")
        if d["refined"]:
            print(f"  chi2/dof {d['baseline']['chi2_per_dof']:.4g} -> {d['refined']['chi2_per_dof']:.4g}")
    else:
        print(f"no mismatch detected (chi2/dof {d['baseline']['chi2_per_dof']:.4g}, threshold {d['threshold']:.4g})")
    print(f"wrote {out.final(paths['json'])} and {out.final(paths['markdown'])}")
    return 0
