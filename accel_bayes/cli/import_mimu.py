"""``accel-bayes import-mimu DATA.bin[.gz] -o rec.nc [--overwrite]``.

Reads a MIMU4444 binary stream (:mod:`accel_bayes.data.mimu`), verifies every packet, finds the rests,
estimates the noise from them, writes a format-v1 recording (DESIGN §7.1) and prints a short
import report.
"""
from __future__ import annotations

from pathlib import Path

from . import _options as opt


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "import-mimu",
        help="import a MIMU4444 binary stream (.bin or .bin.gz) as a recording file",
        description=(
            "Import a MIMU4444 stream (command ack + 106-byte packets), verify checksums, detect the "
            "static segments, estimate the noise std from them and write a format-v1 recording."
        ),
    )
    p.add_argument("data", metavar="DATA.bin[.gz]", help="the raw stream (gzip recognised by its magic bytes)")
    p.add_argument("-o", "--output", required=True, metavar="FILE", help="recording file to write (.nc)")
    p.add_argument("--overwrite", action="store_true", help="replace FILE if it exists")
    p.add_argument("--tol-deg", type=opt.real(0.0, 180.0, lo_open=True, unit="degrees"), default=2.0,
                   help="rests whose gravity directions agree within this angle are one orientation (default 2)")
    p.add_argument("--min-static-s", type=opt.positive("s"), default=3.0,
                   help="shortest static segment kept, seconds (default 3)")
    p.add_argument("--max-fail-fraction", type=opt.fraction(), default=0.01,
                   help="refuse the file if more than this fraction of the stream is damaged: packets dropped for a "
                        "checksum, header, stamp or plausibility failure (duplicates not counted) plus the bytes "
                        "skipped to resynchronise, in packet units (default 0.01)")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..data.outputs import OutputFile
    from ..data.paths import require_file

    # The input first: a wrong input path is the likelier mistake than an existing output; both
    # before torch is imported.
    src, out = require_file(args.data, "MIMU stream file (.bin or .bin.gz)"), Path(args.output)
    target = OutputFile(out, overwrite=args.overwrite).open()
    from ..data.io import write_recording
    from ..data.mimu import import_mimu

    rec, report, _ = import_mimu(
        src, max_fail_fraction=args.max_fail_fraction, tol_deg=args.tol_deg,
        min_duration_s=args.min_static_s, return_report=True,
    )
    write_recording(rec, out, overwrite=args.overwrite)  # validates (DESIGN §7.1) before writing
    target.commit()
    for line in report.lines():
        print(line)
    print(f"noise std (pooled over static segments): acc {_fmt(rec.acc_noise_std)} m/s², "
          f"gyro {_fmt(rec.gyro_noise_std)} rad/s")  # rad/s, as `info` prints it
    print(f"wrote {out}")
    return 0


def _fmt(x) -> str:
    return "[" + ", ".join(f"{v:.3g}" for v in x) + "]"
