#!/usr/bin/env python3
"""What in clock-020's rotational impacts biases r[5, y]?  Two physical explanations tested (issue #30).

``experiments/clock020_oracle.md`` found that clockgen's clock-020 (cube6, 125 Hz read) fails issue
#30's concealed bar (r[5, y] at z ≈ 5 with ``calibrate --model``) because of its three rotational
impacts: without their 186 samples the same report calibrates to z RMS 0.98.  The clocks are not the
cause (the truth's clocks make it worse).  Here two further candidates, each calibrated as
percov_conceal's ``with_angjerk`` (the default ``calibrate --model``: angular jerk on, untempered) on
the same recording (:func:`experiments.percov_conceal.case_recording`) with the case's own report:

* ``as_drawn`` — the recording as drawn (the reference row);
* ``rectification_removed`` — the accelerometer outputs with the DLPF's rectification of fast rotation
  taken off, with the truth: the centripetal term ω×(ω×r) is quadratic in ω, so the accelerometer's
  low-pass of it is not the centripetal term of the low-passed ω that the [C21] model evaluates (the
  difference is the within-window covariance of ω: a positive, systematic term ∝ r — a candidate
  for a *bias*, not a variance).  Δ₁ = F_acc[ω×(ω×r_k)] − F_acc[ω]×(F_acc[ω]×r_k), each IMU's own
  acc DLPF on its own internal ticks, the true ω and r_k, taken at the register's tick of each read
  and subtracted (sensor frame);
* ``rect_and_filter_removed`` — as above with the gyro's filter in the second term,
  Δ₂ = F_acc[ω×(ω×r_k)] − F_gyro[ω]×(F_gyro[ω]×r_k): the rectification plus the acc/gyro DLPF
  difference in the centripetal term (what the model gets wrong by using the gyro's ω);
* ``omega_dot_cells`` — no change to the data; the unresolved-motion scales fitted per cell of the
  report's |ω| band × a quantile band of |ω̇| (0–25–50–75–90–100 %, ω̇ the central difference of the
  gyro posterior mean): impacts are bursts of angular acceleration whose unresolved part one scale per
  |ω| band (the default) spreads over every sample of the band.  (An exploratory covariate, not the
  report's |ω̇| — the detector's comes from its own fitted motion states.)
* ``impact_cells_oracle`` — as ``omega_dot_cells`` with the second covariate the truth's impact windows
  (in / out, :func:`experiments.clock020_oracle.impact_windows`): an oracle of what a per-sample scale
  could reach if it knew where the bursts are — the unresolved motion's scale is intermittent, not a
  function of |ω|.

Each variant for each sampler seed in ``--seeds`` (their spread is the Monte Carlo error of z).  The
generator's internals (its clocks and filters) are read by recording the objects ``draw_case``
builds (this script's own oracle; it changes nothing in the draw).

    PYTHONPATH=. OMP_NUM_THREADS=1 nice -n 5 python3 experiments/clock020_impacts.py
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT.parent))
DOC = ROOT / "clock020_impacts.md"
SEED = 20
VARIANTS = ("as_drawn", "rectification_removed", "rect_and_filter_removed", "omega_dot_cells", "impact_cells_oracle")
#: the |ω̇| quantile edges of the exploratory cells (the budget's bands)
OMEGA_DOT_QUANTILES = (0.25, 0.5, 0.75, 0.9)


def case_with_internals(seed: int):
    """(rec, truth, pos, clocks, acc DLPFs, gyro DLPFs): percov_conceal's recording of the case and the
    generator's own clock and filter objects of each IMU (recorded as ``draw_case`` builds them)."""
    import experiments.clockgen.cases as cases
    from experiments.percov_conceal import case_recording

    made = {"dlpf": [], "clock": []}
    DLPF, Clock = cases.DLPF, cases.Clock

    class _DLPF(DLPF):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            made["dlpf"].append(self)

    class _Clock(Clock):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            made["clock"].append(self)

    cases.DLPF, cases.Clock = _DLPF, _Clock
    try:
        rec, truth, pos = case_recording(seed, 20.0, 5e-4, "known")
    finally:
        cases.DLPF, cases.Clock = DLPF, Clock
    K = len(pos)
    # draw_case builds the clocks, then the acc filters of IMUs 0..K-1, then the gyro filters
    return rec, truth, pos, made["clock"][-K:], made["dlpf"][-2 * K:-K], made["dlpf"][-K:]


def centripetal_error(seed: int, gyro_filter: bool):
    """(rec, truth, pos, Δ (T, K, 3) m/s² sensor frame): the accelerometer's low-passed centripetal term
    minus the centripetal term of the low-passed ω (the acc's filter, or with ``gyro_filter`` the
    gyro's), at each read's register tick (module docstring)."""
    import experiments.clockgen.cases as cases
    from experiments.clockgen.sensing import HostReader

    rec, truth, pos, clocks, f_acc, f_gyro = case_with_internals(seed)
    motion = cases.motion_of({"seed": seed, "duration": 20.0, "vibration": True, "drop": []})
    Q = np.array([cases.quat_to_matrix(q) for q in truth["orientation"]])
    reads = np.asarray(truth["read_time"])
    out = np.zeros_like(np.asarray(rec.acc, dtype=np.float64))
    for k in range(len(pos)):
        ticks = clocks[k].ticks(-cases.T_PRE, reads[-1, k] + 0.01)
        w = motion.at(ticks)["w"]
        r = np.asarray(pos[k], dtype=np.float64)[None]
        cent = np.cross(w, np.cross(w, r))
        wf = (f_gyro if gyro_filter else f_acc)[k](w)
        d = f_acc[k](cent) - np.cross(wf, np.cross(wf, r))
        idx, _ = HostReader.read(ticks, reads[:, k])
        out[:, k] = d[idx] @ Q[k].T
    return rec, truth, pos, out


def omega_dot_cells_step(build, impacts=None):
    """A wrapper of ``pipelines.calibrate._model_percov_step`` (``build``) whose scale bands are the
    report's |ω| bands × quantile bands of |ω̇| (module docstring), passed to ``build`` as one band
    index per sample with the report's per-band scales repeated per cell as the starting values.
    ``impacts`` [(onset s, end s)]: the second covariate is in/out of those windows instead of |ω̇|."""
    import torch

    def step(lik, terms, omega_norm, sample_scale, *args, **kw):
        p = dict(terms.parameters)
        band = torch.bucketize(torch.as_tensor(omega_norm, dtype=torch.float64),
                               torch.as_tensor(p["omega_edges"], dtype=torch.float64), right=True)
        B = len(p["omega_edges"]) + 1
        w = lik.omega.mean.detach().to(torch.float64)
        t = torch.as_tensor(np.asarray(terms.time, dtype=np.float64))
        dw = torch.empty_like(w)
        dw[1:-1] = (w[2:] - w[:-2]) / (t[2:] - t[:-2])[:, None]
        dw[0], dw[-1] = dw[1], dw[-2]
        n = dw.norm(dim=-1)
        if impacts is None:
            Qn = len(OMEGA_DOT_QUANTILES) + 1
            q = torch.bucketize(n, torch.quantile(n, torch.tensor(OMEGA_DOT_QUANTILES, dtype=torch.float64)), right=True)
        else:
            Qn = 2
            q = torch.zeros(len(t), dtype=torch.long)
            for a, b in impacts:
                q[(t >= a) & (t <= b)] = 1
        p["omega_edges"] = [c + 0.5 for c in range(B * Qn - 1)]
        for key in ("jerk_rms", "angular_acc_rms"):
            p[key] = [float(v) for v in p[key] for _ in range(Qn)]
        return build(lik, dataclasses.replace(terms, parameters=p), (band * Qn + q).to(torch.float64),
                     sample_scale, *args, **kw)

    return step


def run_one(variant: str, seed: int, report: Path, args) -> dict:
    import accel_bayes.pipelines.calibrate as cal
    from experiments.percov_conceal import case_recording, run_variant, score

    delta = None
    if variant in ("rectification_removed", "rect_and_filter_removed"):
        rec, truth, pos, delta = centripetal_error(SEED, gyro_filter=variant == "rect_and_filter_removed")
        rec = rec.copy()
        rec.acc = np.asarray(rec.acc, dtype=np.float64) - delta
    else:
        rec, truth, pos = case_recording(SEED, 20.0, 5e-4, "known")
    build = cal._model_percov_step
    if variant == "omega_dot_cells":
        cal._model_percov_step = omega_dot_cells_step(build)
    if variant == "impact_cells_oracle":
        from experiments.clockgen.cases import motion_of

        b = motion_of(truth).rot_imp
        margin = 0.02  # clock020_oracle.impact_windows' margin (the DLPFs' few ms)
        cal._model_percov_step = omega_dot_cells_step(
            build, impacts=[(t0 - margin, t0 + 40 * tau + margin) for t0, tau in zip(b.onset, b.tau)])
    try:
        r = run_variant(rec, "with_angjerk", report, args.chains, args.draws, args.warmup, seed)
    finally:
        cal._model_percov_step = build
    s = score(r["positions"], pos)
    row = {"variant": variant, "seed": seed, "z": s["z"], "coordinates": s["coordinates"], "error_m": s["error_m"],
           "std_m": s["std_m"], "seconds": r["seconds"]}
    if delta is not None:
        mag = np.linalg.norm(delta, axis=-1)
        row["delta_rms_per_triad"] = np.sqrt((mag ** 2).mean(0)).tolist()
        row["delta_max"] = float(mag.max())
    return row


def markdown(rows: list[dict], cmd: str, secs: float, args) -> str:
    from experiments._stamp import run_stamp

    coords = rows[0]["coordinates"]
    L = [f"# clock020_impacts — what in clock-020's impacts biases r[5, y]? (issue #30)", "",
         f"Regenerate: `{cmd}` ({run_stamp()}; this invocation {secs:.0f} s; cached in `experiments/out/clock020_impacts/`).",
         "", "What runs: the script's docstring (clockgen clock-020, cube6, 125 Hz, its own `detect` report, "
             f"`calibrate --model` with the angular jerk, {args.chains} chains × ({args.warmup} + {args.draws}) as percov_conceal).", "",
         "| variant | seed | z RMS | max \\|z\\| (where) | r[5, y] z | r[5, y] error / std µm | RMS error µm | median std µm | Δ rms per triad m/s² (max) |",
         "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        z = np.asarray(r["z"])
        i = int(np.abs(z).argmax())
        j = coords.index("r[5, y]")
        d = ("—" if "delta_rms_per_triad" not in r else
             ", ".join(f"{v:.4f}" for v in r["delta_rms_per_triad"]) + f" ({r['delta_max']:.3f})")
        L.append(f"| {r['variant']} | {r['seed']} | {np.sqrt(np.mean(z ** 2)):.2f} | {abs(z[i]):.2f} ({coords[i]}) | "
                 f"{z[j]:.2f} | {1e6 * r['error_m'][j]:.0f} / {1e6 * r['std_m'][j]:.0f} | "
                 f"{1e6 * np.sqrt(np.mean(np.square(r['error_m']))):.0f} | {1e6 * np.median(r['std_m']):.0f} | {d} |")
    return "\n".join(L) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0,1", help="sampler seeds (default 0,1)")
    ap.add_argument("--chains", type=int, default=2)
    ap.add_argument("--warmup", type=int, default=300)
    ap.add_argument("--draws", type=int, default=400)
    ap.add_argument("--report", type=Path, default=ROOT / "out" / "percov_conceal" / "clock-020" / "report.json",
                    help="clock-020's detect report (percov_conceal's cached stage; computed there if missing)")
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "clock020_impacts")
    ap.add_argument("--doc", type=Path, default=DOC)
    args = ap.parse_args(argv)
    if not args.report.exists():
        ap.error(f"--report: {args.report} not found; run experiments/percov_conceal.py --n 21 --first 20 first "
                 "(its clock-020 report stage) or give the report's path")
    args.out.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    rows = []
    for v in VARIANTS:
        for s in (int(x) for x in args.seeds.split(",")):
            f = args.out / f"{v}.seed{s}.json"
            if f.exists():
                rows.append(json.loads(f.read_text()))
                continue
            row = run_one(v, s, args.report, args)
            f.write_text(json.dumps(row))
            rows.append(row)
            z = np.asarray(row["z"])
            print(f"{v} seed {s}: z RMS {np.sqrt(np.mean(z ** 2)):.2f}, max |z| {np.abs(z).max():.2f}", flush=True)
    cmd = "PYTHONPATH=. OMP_NUM_THREADS=1 nice -n 5 python3 experiments/clock020_impacts.py" + (
        "" if args.report == ap.get_default("report") else f" --report {args.report}")
    text = markdown(rows, cmd, time.time() - t0, args)
    from accel_bayes.data.outputs import write_text
    from experiments._reading import READING_MARKER, kept_reading

    write_text(args.doc, text + "\n" + READING_MARKER + (kept_reading(args.doc) or "\n"))
    print(f"wrote {args.doc}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
