"""``accel-bayes export REC --positions positions.json [--intrinsics intrinsics.json]
[--mismatch report.json] [--format kalibr|openvins] -o FILE [--overwrite]``.

Writes a calibration as a Kalibr-style IMU chain YAML, or as OpenVINS' ``kalibr_imu_chain.yaml``
(``%YAML:1.0`` header, intrinsic fields); frames and conventions in :mod:`accel_bayes.data.export`.
"""
from __future__ import annotations

from pathlib import Path


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "export",
        help="export a calibration as a Kalibr IMU chain / OpenVINS kalibr_imu_chain.yaml",
        description=(
            "Write a Kalibr-style IMU chain YAML from a recording and its positions.json: per IMU T_i_b "
            "(4x4, takes a point from the reference IMU's frame to IMU i's frame), noise densities "
            "(sigma/sqrt(rate)), random walks where known, update rate, time offset where estimated, and "
            "the posterior covariance as extra keys. With --intrinsics (accel-bayes intrinsics) the "
            "OpenVINS fields Ta = T^-1 (lower-triangular, model kalibr) and R_IMUtoACC = I are written; "
            "with --mismatch the gyro couplings (Tw, R_IMUtoGYRO, Tg) and time offsets of the report. "
            "--format openvins adds OpenCV's %YAML:1.0 header and writes the intrinsic fields always "
            "(identity where not estimated, said so in a comment)."
        ),
    )
    p.add_argument("recording", metavar="REC", help="the recording the calibration was made from (.nc, format v1)")
    p.add_argument("--positions", required=True, metavar="JSON", help="positions.json of map / calibrate / selfcal")
    p.add_argument("--intrinsics", default=None, metavar="JSON", help="intrinsics.json of accel-bayes intrinsics (optional)")
    p.add_argument("--mismatch", default=None, metavar="JSON",
                   help="report.json of accel-bayes mismatch: gyro_scale, gyro_g_sensitivity, time_offset (optional)")
    p.add_argument("--format", choices=("kalibr", "openvins"), default="kalibr",
                   help="'kalibr': plain YAML (default); 'openvins': %%YAML:1.0 header for cv::FileStorage, "
                        "intrinsic fields always present")
    p.add_argument("-o", "--output", required=True, metavar="FILE", help="YAML file to write")
    p.add_argument("--overwrite", action="store_true", help="replace FILE if it exists")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..data.outputs import OutputFile
    from ..data.paths import require_file

    out = Path(args.output)
    for flag, path in (("REC", args.recording), ("--positions", args.positions), ("--intrinsics", args.intrinsics),
                       ("--mismatch", args.mismatch)):
        if path is not None:
            require_file(path, "file", flag=flag)
    target = OutputFile(out, overwrite=args.overwrite).open()
    from ..data.export import export_imu_chain  # torch: after every refusal the file system decides
    export_imu_chain(args.recording, args.positions, out, intrinsics=args.intrinsics, report=args.mismatch,
                     fmt=args.format, overwrite=args.overwrite)
    target.commit()
    print(f"wrote {out} ({args.format} IMU chain)")
    return 0
