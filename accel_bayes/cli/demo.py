"""``accel-bayes demo``: the whole pipeline on an embedded simulated default."""
from __future__ import annotations

from . import _options as opt


def register(sub) -> None:
    from ..data.output_sets import OVERWRITE_DIR_HELP

    p = sub.add_parser(
        "demo",
        help="run simulate → MAP → posterior → diagnostics on a built-in example",
        description="Simulate the 8-IMU MIMU4444 corner board under smooth hand-like motion, "
        "calibrate it (MAP, then the PmMH posterior), run the diagnostics and write a report. "
        "Exit status 4 (results written, marked in the report) when the posterior's chains have not converged.",
    )
    p.add_argument("--out", default="demo_out", metavar="DIR",
                   help="output directory (default: demo_out; written as one set, see the README)")
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_DIR_HELP)
    p.add_argument("--quick", action="store_true", help="a smaller, faster run (smoke test)")
    p.add_argument("--seed", type=opt.seed, default=1, help="random seed (default: 1)")
    p.add_argument("--no-progress", action="store_true", help="hide progress bars")
    p.set_defaults(func=_run)


def _run(args) -> int:
    import json
    from pathlib import Path

    from ..data.output_sets import OutputDir
    from ._status import EXIT_OK, untrusted

    OutputDir(args.out, overwrite=args.overwrite).check()  # refused before torch is imported; run_demo opens it
    from ..pipelines.demo import run_demo

    report = run_demo(args.out, quick=args.quick, progress=not args.no_progress, seed=args.seed,
                      overwrite=args.overwrite)
    # the posterior's positions.json (DESIGN §7.3) says whether its chains converged
    pos = Path(report).parent / "posterior" / "positions.json"
    if pos.is_file():
        d = json.loads(pos.read_text(encoding="utf-8"))["diagnostics"]
        if d.get("converged") is False:
            return untrusted("demo", d.get("warnings", []), str(pos))
    return EXIT_OK
