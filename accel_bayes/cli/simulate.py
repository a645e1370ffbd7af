"""``accel-bayes simulate``: write a simulated recording and its truth sidecar.

    accel-bayes simulate --preset mimu32 --motion smooth -T 500 --rate 100 --seed 1 -o rec.nc

writes ``rec.nc`` (format v1, DESIGN §7.1) and ``rec.truth.json`` (true geometry, motion, noise,
seed and settings; ground truth never goes in the recording itself).
"""
from __future__ import annotations

from pathlib import Path

from ..constants import RAD_TO_DEG
from ..errors import UserError
from . import _options as opt

PRESET_NAMES = ("mimu32", "mimu8", "s16plate")
MOTION_NAMES = ("iid", "smooth", "table")


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "simulate",
        help="simulate an array recording with known geometry (+ truth sidecar)",
        description="Simulate a recording of a preset array under a chosen motion. Writes the "
        "recording (-o FILE, NetCDF format v1) and the ground truth beside it (FILE with suffix "
        ".truth.json). All values in SI units.",
    )
    p.add_argument("--preset", choices=PRESET_NAMES, default="mimu32", help="array design (default mimu32)")
    p.add_argument("--motion", choices=MOTION_NAMES, default="smooth",
                   help="iid: [C21] i.i.d. hand twist; smooth: continuous motion with gravity; table: [S16]-like rotation table (default smooth)")
    p.add_argument("-T", dest="T", type=opt.count(1), default=500, help="number of samples (default 500)")
    # An IMU output rate above 100 kHz is no physical sensor; without the bound a typo such as
    # 1e300 gave a file whose 1e-300 s steps every fit then fails on, far from the cause.
    p.add_argument("--rate", type=opt.real(0.0, 1e5, lo_open=True, unit="Hz"), default=100.0,
                   help="sample rate, Hz, in (0, 100000] (default 100)")
    p.add_argument("--seed", type=opt.seed, default=0, help="random seed; same seed, same files (default 0)")
    p.add_argument("--position-error", type=opt.nonnegative("m"), default=1e-4, metavar="M",
                   help="std of the true positions around the nominal ones, m per axis; the reference IMU stays exact (default 1e-4)")
    p.add_argument("--orientation-error", type=opt.nonnegative("rad"), default=0.0, metavar="RAD",
                   help="std of the true orientation error, rad per axis, as a rotation vector (default 0)")
    p.add_argument("--acc-noise", type=opt.positive("m/s^2"), default=None, metavar="X",
                   help="accelerometer noise std, m/s² (default: the preset's)")
    p.add_argument("--gyro-noise", type=opt.positive("rad/s"), default=None, metavar="X",
                   help="gyroscope noise std, rad/s (default: the preset's)")
    p.add_argument("--omega-rms", type=opt.nonnegative("rad/s"), default=None, metavar="RAD_S",
                   help="smooth motion only: RMS of |ω|, rad/s (default 400 °/s = 6.98 rad/s)")
    p.add_argument("--no-clip", action="store_true", help="do not clip outputs at the sensor ranges")
    p.add_argument("-o", "--output", required=True, metavar="FILE", help="recording to write (.nc)")
    p.add_argument("--overwrite", action="store_true", help="replace FILE and its sidecar if they exist")
    p.set_defaults(func=run)


def _physical_memory() -> int | None:
    """Bytes of RAM of this machine, or None where the OS does not say."""
    import os

    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (AttributeError, ValueError, OSError):
        return None


def _check(args) -> None:
    """The memory check of -T against the preset's size (single values are checked by their type=;
    this one needs the preset, so it runs after the output check)."""
    from ..physics.arrays import preset
    from ..simulate import BYTES_PER_IMU_SAMPLE, memory_estimate

    K = preset(args.preset).K
    need, have = memory_estimate(args.T, K), _physical_memory()
    # half the RAM: the recording is also held by xarray/netCDF while it is written
    if have is not None and need > have // 2:
        t_max = have // 2 // (K * BYTES_PER_IMU_SAMPLE)
        raise UserError(f"-T: {args.T} samples of the {args.preset} array ({K} IMUs) would need about "
                        f"{need / 2 ** 30:.3g} GiB of memory ({K * BYTES_PER_IMU_SAMPLE} B per sample); "
                        f"expected at most {t_max} samples on this machine ({have / 2 ** 30:.3g} GiB of RAM)")


def run(args) -> int:
    from ..data.outputs import OutputFile
    from ..data.paths import truth_path

    # what the arguments and the file system decide comes before torch is imported
    if args.omega_rms is not None and args.motion != "smooth":
        raise UserError(f"--omega-rms: applies to --motion smooth only, got --motion {args.motion}")
    out = Path(args.output)
    target = OutputFile(out, overwrite=args.overwrite, also=(truth_path(out),)).open()
    _check(args)
    from ..data import io
    from ..physics.arrays import preset
    from ..simulate import motion_rms, simulate

    arr = preset(args.preset)
    mkw = {"omega_rms": args.omega_rms} if args.omega_rms is not None else None
    res = simulate(arr, args.motion, T=args.T, rate=args.rate, seed=args.seed,
                   position_error_std=args.position_error, orientation_error_std=args.orientation_error,
                   acc_noise_std=args.acc_noise, gyro_noise_std=args.gyro_noise, clip=not args.no_clip,
                   motion_kwargs=mkw)
    io.write_recording(res.recording, out, overwrite=args.overwrite)
    side = io.write_truth(out, res.truth)  # after the recording: it records the recording's SHA-256
    target.commit()

    rec = res.recording
    w_rms, s_rms = motion_rms(res.motion)
    w_rms *= RAD_TO_DEG
    n_clip = 0 if rec.acc_clipped is None else int(rec.acc_clipped.sum())
    g_clip = 0 if rec.gyro_clipped is None else int(rec.gyro_clipped.sum())
    print(
        f"Simulated {rec.T} samples at {args.rate:g} Hz of the {args.preset} array ({rec.K} IMUs, "
        f"{int(rec.has_acc.sum())} accelerometer and {int(rec.has_gyro.sum())} gyroscope triads) under "
        f"{args.motion} motion (RMS |ω| {w_rms:.0f} °/s, RMS |s| {s_rms:.1f} m/s²), seed {args.seed}; "
        f"true positions off nominal by {args.position_error:g} m std per axis, orientations by "
        f"{args.orientation_error:g} rad; {n_clip} accelerometer and {g_clip} gyroscope samples clipped. "
        f"Recording written to {out}; ground truth written to the sidecar {side}."
    )
    return 0
