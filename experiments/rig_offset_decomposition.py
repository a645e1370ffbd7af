"""Why the rig's time-offset std was too small (issue #28 item 1): the same concealed rigs with the
generator's effects switched off one at a time → ``experiments/rig_offset_decomposition.md``.

    PYTHONPATH=. python3 experiments/rig_offset_decomposition.py [--seeds 19 26 2 4] [--duration 15]
        [--variants full "no bias walk" ...]

Each seed is drawn as in ``experiments/rig_proof.py`` (``draw_rig(seed, n_imu=2 + seed % 3)``) with
the white noise of every variant the same (the generator draws it from its own stream), and fitted
by ``fit_rig`` (stamp jitter modelled unless the variant says otherwise).  Variants: ``full`` (as
in the proof), ``full, jitter not modelled`` (the fit of main c03e6a6), ``no bias walk`` (jitter
kept), ``no jitter, no walk`` (white noise only), ``noise-free`` (no noise, no quantisation: the
motion model's own error).  Per variant: z = error/std of every time offset and clock drift, and
the time-offset errors in µs.  The fit models the bias walks at the density the recording states
(the generator's, in every variant: only the data change).

Until issue #28's third round the generator drew the walk from the white-noise stream, so that
``no bias walk`` also redrew the gyro noise and the stamp jitter: the 2.50 → 1.38 of that
comparison was two noise realisations, not the walk (``tests/experiments/test_rig_generator.py``).
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from accel_bayes.data import outputs  # noqa: E402
from accel_bayes.inference.rig import RigSettings, fit_rig  # noqa: E402
from experiments.clockgen.rig import draw_rig  # noqa: E402
from experiments._stamp import run_stamp  # noqa: E402

VARIANTS = {
    "full": ({}, RigSettings()),
    "full, jitter not modelled": ({}, RigSettings(stamp_jitter=False)),
    "no bias walk": ({"bias_walk": False}, RigSettings()),
    "no jitter, no walk": ({"jitter": False, "bias_walk": False}, RigSettings()),
    "noise-free": ({"jitter": False, "bias_walk": False, "noise": False, "quantised": False}, RigSettings()),
}


def run(seed, duration, variant):
    """z of every non-reference IMU's time offset and drift, and the offset errors (s)."""
    gen, settings = VARIANTS[variant]
    rec, truth = draw_rig(seed, duration=duration, n_imu=2 + seed % 3, **gen)
    res = fit_rig(rec, settings)
    d = np.asarray(truth["clock_drift"], float)
    o = np.asarray(truth["time_offset"], float) - float(rec.time[0]) * d / (1 + d)
    eo, ed = res.time_offset[1:] - o[1:], res.clock_drift[1:] - d[1:]
    return eo / res.time_offset_std[1:], ed / res.clock_drift_std[1:], eo, res.seconds


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[19, 26, 2, 4])
    ap.add_argument("--duration", type=float, default=15.0)
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    t_all = time.time()
    rows, pooled = [], {v: [] for v in args.variants}
    for seed in args.seeds:
        for v in args.variants:
            zo, zd, eo, sec = run(seed, args.duration, v)
            pooled[v] += list(zo) + list(zd)
            rows.append(f"| {seed} | {2 + seed % 3} | {v} | {', '.join(f'{z:+.2f}' for z in zo)} | "
                        f"{', '.join(f'{z:+.2f}' for z in zd)} | {', '.join(f'{1e6 * e:+.2f}' for e in eo)} | {sec:.0f} |")
            print(rows[-1], flush=True)
    lines = ["# Time-offset z on concealed rigs, effect by effect (issue #28 item 1)", "",
             f"Regenerate: `PYTHONPATH=. python3 experiments/rig_offset_decomposition.py --seeds "
             f"{' '.join(map(str, args.seeds))} --duration {args.duration:g} --variants "
             f"{' '.join(repr(v) if ' ' in v else v for v in args.variants)}` "
             f"({run_stamp()}, {time.time() - t_all:.0f} s).", "",
             "Seeds as in `rig_proof.py`; the white noise is the same draw in every variant of a seed.", "",
             "| seed | K | variant | z time offset | z clock drift | offset error (µs) | fit s |",
             "|---|---|---|---|---|---|---|"] + rows + ["", "| variant | RMS z (offsets and drifts pooled) | n |",
                                                           "|---|---|---|"]
    for v, z in pooled.items():
        lines.append(f"| {v} | {float(np.sqrt(np.mean(np.square(z)))):.2f} | {len(z)} |")
    outputs.write_text(REPO / "experiments" / "rig_offset_decomposition.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
