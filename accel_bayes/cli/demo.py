"""``accel-bayes demo``: the whole pipeline on an embedded simulated default."""
from __future__ import annotations

from . import _options as opt


def register(sub) -> None:
    p = sub.add_parser(
        "demo",
        help="run simulate → MAP → posterior → diagnostics on a built-in example",
        description="Simulate the 8-IMU MIMU4444 corner board under smooth hand-like motion, "
        "calibrate it (MAP, then the PmMH posterior), run the diagnostics and write a report.",
    )
    p.add_argument("--out", default="demo_out", help="output directory (default: demo_out)")
    p.add_argument("--quick", action="store_true", help="a smaller, faster run (smoke test)")
    p.add_argument("--seed", type=opt.seed, default=1, help="random seed (default: 1)")
    p.add_argument("--no-progress", action="store_true", help="hide progress bars")
    p.set_defaults(func=_run)


def _run(args) -> int:
    from ..demo import run_demo

    run_demo(args.out, quick=args.quick, progress=not args.no_progress, seed=args.seed)
    return 0
