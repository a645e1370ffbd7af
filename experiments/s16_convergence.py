"""[S16] Fig. 7 in simulation: success rate of the self-calibration vs the initial pose error.

Four motions (``s16_common.MOTIONS``): "sinusoid" (segments of sinusoidal rate about one axis
at a time, the paper's synthetic motion), "table1" (the slow three-axis table motion of
Table II, 5.4 s), "table2" (another table motion, 20 s = 2500 samples), "hand" (faster, with
translation).  One noisy recording per motion (σ = 0.02 m/s², states as a table logs them,
see ``s16_common``), the Table I plate with triad 1 fixed at its true pose and known triad
parameters.

Per error level and trial ([S16] §VI-B): every free triad starts either with its position moved by
the level in a uniformly random direction (orientation true), or rotated by the level about a
uniformly random axis (position true); the motion starts at zero.  Success = no divergence and,
for every free triad, final position error < 1 mm and orientation error < 0.5°.  The
self-calibration runs with ``rerun_from_estimate="auto"`` (the [S16] §VI-A re-run whenever the
first run misfits the data) and ``restart_on_divergence`` (default: a first run that diverges is
restarted once from the start positions with its own orientation estimate, which converges even
when its positions do not — see ``self_calibrate``).

Writes ``--out`` (CSV, one row per run) and ``--fig`` (PNG: success rate vs position error and vs
orientation error, one line per motion).  Usage::

    python experiments/s16_convergence.py [--quick] [--trials N] [--motions a,b] [--levels-pos CM,..]
        [--levels-rot DEG,..] [--variant V] [--process-noise {s16,estimate,estimate-snap}]
        [--scheduler ADDR] [--workers W]

Default: all four motions, 100 trials per level, 9 position levels (0.5–16 cm) and 9 orientation
levels (5–180°): 7 200 self-calibrations, many hours on two cores.  ``--quick`` (a smoke test of
a few minutes): 2 trials at 2 levels per axis (2, 16 cm; 20, 180°), all four motions.  ``--levels-pos`` /
``--levels-rot`` choose the levels (an empty string skips that axis) and ``--motions`` the
motions, e.g. the must-show subset of the issue (100 trials up to 2 cm / 20° on the table-like
motions)::

    python experiments/s16_convergence.py --motions table1,table2 --levels-pos 0.5,1,2 --levels-rot 5,10,20

The SUMMARY line states exactly which table-like levels and how many trials it covers.
``--first-trial N`` starts the trial numbering at N, so a later run adds new trials to the same
levels (each trial's start is seeded by motion, kind, level and trial number); the CSVs of
separate runs are merged by ``--replot a.csv,b.csv,...``.  ``--process-noise`` picks the motion
model of ``self_calibrate``: ``s16`` (default, the paper's fixed variances; the model of the stored
runs), ``estimate`` or ``estimate-snap`` (issue #12; the pipeline/CLI default); rows of a non-default
model are labelled ``MOTION [jerk]`` / ``MOTION [snap]`` (like ``--variant``'s) and get their own
SUMMARY line.  The start of trial k does not depend on the model, so the models are compared on the
same starts.  The committed figure
(``experiments/figures/s16_convergence.png``, numbers in ``experiments/s16_results.md``) merges
the runs kept in ``experiments/results/s16_convergence/``.
"""
from __future__ import annotations

import argparse
import csv
import math
import sys
import time
import zlib
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402
import torch  # noqa: E402

import s16_common as C  # noqa: E402
from _dask import add_dask_arguments, dask_client, map_tasks  # noqa: E402
from accel_bayes.constants import DEG_TO_RAD, RAD_TO_DEG  # noqa: E402

POS_LEVELS_CM = [0.5, 1, 2, 4, 6, 8, 10, 12, 16]
ROT_LEVELS_DEG = [5, 10, 20, 30, 45, 60, 90, 120, 180]
QUICK_POS_CM = [2, 16]
QUICK_ROT_DEG = [20, 180]
QUICK_TRIALS = 2
SUCCESS_POS, SUCCESS_ROT_DEG = 1e-3, 0.5

# What each --variant changes in self_calibrate: the package default, the default without the two
# divergence remedies, and the [S16] procedure (joint LM from zero motion, no remedies).
VARIANTS = {
    "default": {},
    "no-remedies": {"rerun_from_estimate": False, "restart_on_divergence": False},
    "s16": {"rerun_from_estimate": False, "restart_on_divergence": False, "warm_start_motion": False},
}
# --process-noise: the motion model of self_calibrate ("s16", the paper's fixed variances, is the default
# and the model of the stored runs); a non-default one tags the row's motion label, like a --variant
PROCESS_NOISE_TAGS = {"s16": None, "estimate": "jerk", "estimate-snap": "snap"}

_CACHE: dict = {}


def _recording(motion: str, seed: int):
    """(z, proto) for one motion, cached per worker process."""
    key = (motion, seed)
    if key not in _CACHE:
        proto = C.prototype()
        x = C.states_from_trace(C.motion_trace(motion))
        g = torch.Generator().manual_seed(seed)
        _CACHE[key] = (C.measurements(x, proto, 0.02, g), proto)
    return _CACHE[key]


def run_one(task: tuple) -> dict:
    """task = (motion, kind "position"/"orientation", level, trial, seed[, variant[, process_noise]])."""
    C.one_thread()
    from accel_bayes.physics.geometry import boxplus, rotation_angle
    from accel_bayes.inference.selfcal import self_calibrate

    motion, kind, level, trial, seed = task[:5]
    variant = task[5] if len(task) > 5 else "default"
    process_noise = task[6] if len(task) > 6 else "s16"
    opts = {"rerun_from_estimate": "auto", **VARIANTS[variant], "process_noise": process_noise}
    z, proto = _recording(motion, seed)
    # a deterministic seed per task (Python's str hash is salted per process)
    g = torch.Generator().manual_seed(zlib.crc32(f"{motion}|{kind}|{float(level)}|{trial}|{seed}".encode()))
    p0 = proto["positions"].clone()
    q0 = proto["orientations"].clone()
    v = torch.randn(5, 3, generator=g, dtype=torch.float64)
    v = v / v.norm(dim=-1, keepdim=True)
    v[0] = 0  # the fixed triad stays at its true pose
    if kind == "position":
        p0 = p0 + level * 1e-2 * v
    else:
        q0 = boxplus(q0, level * DEG_TO_RAD * v)
    t0 = time.perf_counter()
    r = self_calibrate(z, 1 / C.RATE, nominal_positions=p0, nominal_orientations=q0, fixed=0, acc_noise_std=0.02,
                       sensor_params=(proto["sens"], proto["offset"]), covariance=False, max_iter=100,
                       **opts)
    pe = ae = math.nan
    if r.ok:
        pe = float((r.positions[1:] - proto["positions"][1:]).norm(dim=-1).max())
        ae = float(rotation_angle(r.orientations[1:], proto["orientations"][1:]).max() * RAD_TO_DEG)
    success = bool(r.ok and pe < SUCCESS_POS and ae < SUCCESS_ROT_DEG)
    # a variant's or process model's rows carry it in the motion label, so plots and tables show it as its own line
    tags = [t for t in (None if variant == "default" else variant, PROCESS_NOISE_TAGS[process_noise]) if t]
    label = f"{motion} [{', '.join(tags)}]" if tags else motion
    return {"motion": label, "kind": kind, "level": level, "trial": trial, "success": success, "status": r.status,
            "reason": r.reason[:80], "max_pos_err_mm": pe * 1e3, "max_ang_err_deg": ae,
            "runs": len(r.runs), "iterations": sum(u["iterations"] for u in r.runs),
            "seconds": time.perf_counter() - t0}


def plot(rows: list[dict], path: Path, motions: list[str], pos_levels, rot_levels) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 5.6), sharey=True)
    for ax, kind, levels, unit in ((axes[0], "position", pos_levels, "initial position error (cm)"),
                                   (axes[1], "orientation", rot_levels, "initial orientation error (°)")):
        if not levels:
            ax.set_title(f"({kind}: not run)")
            continue
        for i, m in enumerate(motions):
            # only the levels run for this motion, so a line is not broken by levels it skipped
            lv_m, rate, counts = [], [], set()
            for lv in levels:
                s = [r["success"] for r in rows if r["motion"] == m and r["kind"] == kind and r["level"] == lv]
                if s:
                    lv_m.append(lv)
                    rate.append(100.0 * np.mean(s))
                    counts.add(len(s))
            if lv_m:
                # one colour and marker per motion; a --process-noise run (e.g. "[snap]") keeps its motion's
                # colour with hollow markers, a --variant gets its own colour; tagged rows are dashed
                base, _, tag = m.partition(" [")
                k = list(C.MOTIONS).index(base) if base in C.MOTIONS else i
                model_tag = tag.rstrip("]") in PROCESS_NOISE_TAGS.values()
                color = f"C{k % 10}" if (not tag or model_tag) else (f"C{4 + sorted(VARIANTS).index(tag.rstrip(']'))}"
                                                                   if tag.rstrip("]") in VARIANTS else f"C{(4 + i) % 10}")
                ax.plot(lv_m, rate, marker="os^Dv<>p"[(k if not tag or model_tag else i) % 8], color=color,
                        ls="--" if tag else "-", mfc="none" if model_tag else color,
                        label=f"{m} ({'/'.join(str(c) for c in sorted(counts))} trials / level)")
        if kind == "position":
            # [S16] §VI-B: beyond half the spacing of neighbouring triads (16.91 cm) a triad may
            # start nearer another triad's true position than its own
            ax.axvline(8.45, color="0.5", lw=0.8, ls=":", label="half the triad spacing (8.45 cm)")
        ax.set_xlabel(unit)
        ax.grid(True, alpha=0.3)
        ax.set_ylim(-3, 103)
    axes[0].set_ylabel("success rate (%)")
    for ax in axes:
        if ax.lines:
            ax.legend(fontsize=7.5, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2)
    fig.suptitle("[S16] Fig. 7 (simulation): self-calibration success vs initial pose error")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _read_rows(paths) -> list[dict]:
    rows = []
    for path in paths:
        with open(path, newline="") as fh:
            for r in csv.DictReader(fh):
                r["level"] = float(r["level"])
                r["trial"] = int(r["trial"])
                r["success"] = r["success"] == "True"
                for k in ("max_pos_err_mm", "max_ang_err_deg", "seconds"):
                    r[k] = float(r[k])
                rows.append(r)
    return rows


def replot(paths, fig: Path) -> int:
    """Merge per-run CSVs, print the tables and the SUMMARY line, write the figure."""
    rows = _read_rows(paths)
    motions = list(dict.fromkeys(r["motion"] for r in rows))
    order = {m: i for i, m in enumerate(C.MOTIONS)}
    motions.sort(key=lambda m: (" [" in m, order.get(m.split(" [")[0], 99), m))
    pos_levels = sorted({r["level"] for r in rows if r["kind"] == "position"})
    rot_levels = sorted({r["level"] for r in rows if r["kind"] == "orientation"})
    plot(rows, fig, motions, pos_levels, rot_levels)
    print(f"{len(rows)} self-calibrations from {', '.join(map(str, paths))}; figure {fig}")
    report(rows, motions, pos_levels, rot_levels)
    return 0


def report(rows, motions, pos_levels, rot_levels) -> None:
    """Success-rate tables (with the number of trials per cell), failures and the SUMMARY line."""
    for kind, lv_list, unit in (("position", pos_levels, "cm"), ("orientation", rot_levels, "°")):
        if not lv_list:
            continue
        print(f"\nsuccess rate (%) [trials] vs initial {kind} error ({unit})")
        print(f"{'motion':10s} " + " ".join(f"{lv:>12g}" for lv in lv_list))
        for m in motions:
            cells = []
            for lv in lv_list:
                s = [r["success"] for r in rows if r["motion"] == m and r["kind"] == kind and r["level"] == lv]
                cells.append(f"{100.0 * np.mean(s):6.1f} [{len(s):3d}]" if s else f"{'-':>12s}")
            print(f"{m:10s} " + " ".join(cells))
    fails = [r for r in rows if not r["success"]]
    kinds = {}
    for r in fails:
        key = "diverged" if r["status"] != "ok" else "converged elsewhere"
        kinds[key] = kinds.get(key, 0) + 1
    print(f"\nfailures: {kinds or 'none'}")
    for r in fails[:10]:
        print(f"  {r['motion']} {r['kind']} {r['level']:g} trial {r['trial']}: {r['status']} {r['reason']} "
              f"max pos err {r['max_pos_err_mm']:.3g} mm, max ang err {r['max_ang_err_deg']:.3g}°")
    print("mean time per self-calibration: "
          + ", ".join(f"{m} {np.mean([r['seconds'] for r in rows if r['motion'] == m]):.2f} s" for m in motions))
    small = [r for r in rows if (r["kind"] == "position" and r["level"] <= 2) or (r["kind"] == "orientation" and r["level"] <= 20)]
    # the must-show SUMMARY reads the untagged rows (the package default); each tag (a --variant or
    # --process-noise run) gets its own SUMMARY line
    tags = sorted({r["motion"].partition(" ")[2] for r in small if r["motion"].partition(" ")[0] in ("table1", "table2")})
    if "" in tags or not tags:
        _summary([r for r in small if r["motion"] in ("table1", "table2")], "")
    for tag in tags:
        if tag:
            _summary([r for r in small if r["motion"] in (f"table1 {tag}", f"table2 {tag}")], f" {tag}")


def _summary(table_rows, tag) -> None:
    if table_rows:
        cells = {}
        for r in table_rows:
            key = (r["motion"], r["kind"], r["level"])
            cells[key] = cells.get(key, 0) + 1
        cov_txt = "; ".join(f"{m} {'pos' if k == 'position' else 'rot'} {lv:g}{'cm' if k == 'position' else 'deg'} "
                            f"x{c}" for (m, k, lv), c in sorted(cells.items()))
        n_ok = sum(r["success"] for r in table_rows)
        table_ok = n_ok == len(table_rows)
        print(f"SUMMARY s16_convergence{tag}: table-like motions up to 2 cm / 20 deg: {n_ok}/{len(table_rows)} successful "
              f"({100.0 * n_ok / len(table_rows):.1f} %; runs per level: {cov_txt}): {'100% yes' if table_ok else 'NO'}")
    else:
        print("SUMMARY s16_convergence: no table-like level up to 2 cm / 20 deg was run")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="smoke test: 2 trials at 2 and 16 cm, 20 and 180°")
    ap.add_argument("--trials", type=int, default=None, help="trials per level (default 100; 6 with --quick)")
    ap.add_argument("--motions", default="sinusoid,table1,table2,hand")
    ap.add_argument("--levels-pos", default=None,
                    help="initial position errors, cm, comma separated ('' = none; default "
                         + ",".join(f"{v:g}" for v in POS_LEVELS_CM) + ")")
    ap.add_argument("--levels-rot", default=None,
                    help="initial orientation errors, degrees, comma separated ('' = none; default "
                         + ",".join(f"{v:g}" for v in ROT_LEVELS_DEG) + ")")
    ap.add_argument("--first-trial", type=int, default=0,
                    help="index of the first trial (default 0): a later run with --first-trial N adds new trials "
                         "to the same levels instead of repeating trials 0..N-1 (merge with --replot)")
    ap.add_argument("--variant", default="default", choices=sorted(VARIANTS),
                    help="default: the package's self_calibrate (warm start, re-run and restart remedies); "
                         "no-remedies: without the re-run and restart; s16: also without the motion-only warm "
                         "start (the paper's procedure). Non-default rows are labelled 'MOTION [VARIANT]'")
    ap.add_argument("--process-noise", default="s16", choices=list(PROCESS_NOISE_TAGS),
                    help="self-calibration motion model: s16 (the paper's fixed variances, default; the stored "
                         "runs), estimate (white noise on the jerk) or estimate-snap (white noise on the snap, the "
                         "pipeline/CLI default; issue #12). Non-s16 rows are labelled 'MOTION [jerk]' / 'MOTION [snap]'")
    ap.add_argument("--seed", type=int, default=1)
    add_dask_arguments(ap)
    ap.add_argument("--out", default="out/s16_convergence.csv")
    ap.add_argument("--fig", default="out/s16_convergence.png")
    ap.add_argument("--replot", default=None, metavar="CSV[,CSV...]",
                    help="run nothing: merge these per-run CSVs (e.g. subsets run separately), print the "
                         "tables and SUMMARY and write --fig")
    args = ap.parse_args(argv)
    if args.replot:
        return replot([Path(f) for f in args.replot.split(",") if f], Path(args.fig))
    motions = [m for m in args.motions.split(",") if m]
    for m in motions:
        if m not in C.MOTIONS:
            ap.error(f"--motions: unknown motion {m!r}; expected some of {sorted(C.MOTIONS)}")
    n = args.trials if args.trials is not None else (QUICK_TRIALS if args.quick else 100)

    def levels(text, default, name):
        if text is None:
            return list(default)
        try:
            vals = [float(v) for v in text.split(",") if v.strip()]
        except ValueError:
            ap.error(f"{name}: expected comma-separated numbers, got {text!r}")
        if any(not v > 0 for v in vals):
            ap.error(f"{name}: levels must be > 0")
        return sorted(vals)

    pos_levels = levels(args.levels_pos, QUICK_POS_CM if args.quick else POS_LEVELS_CM, "--levels-pos")
    rot_levels = levels(args.levels_rot, QUICK_ROT_DEG if args.quick else ROT_LEVELS_DEG, "--levels-rot")
    if not pos_levels and not rot_levels:
        ap.error("no levels to run (--levels-pos and --levels-rot both empty)")
    if args.first_trial < 0:
        ap.error("--first-trial: expected an integer >= 0")
    trials = range(args.first_trial, args.first_trial + n)
    tasks = [(m, "position", lv, k, args.seed, args.variant, args.process_noise) for m in motions
              for lv in pos_levels for k in trials]
    tasks += [(m, "orientation", lv, k, args.seed, args.variant, args.process_noise) for m in motions
              for lv in rot_levels for k in trials]
    # longest first (the 20 s motion), so the pool does not idle at the end
    tasks.sort(key=lambda t: -C.MOTIONS[t[0]]["T"])
    t0 = time.perf_counter()
    with dask_client(args, upload=("s16_common.py",)) as client:
        rows = map_tasks(client, run_one, [dict(task=t) for t in tasks], desc="self-calibrations")
    wall = time.perf_counter() - t0
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0].keys()))
        w.writeheader()
        w.writerows(rows)
    labels = list(dict.fromkeys(r["motion"] for r in rows))  # motion names, tagged with a non-default variant/model
    plot(rows, Path(args.fig), labels, pos_levels, rot_levels)
    print(f"{len(rows)} self-calibrations in {wall:.0f} s wall; CSV {out}, figure {args.fig}")
    report(rows, labels, pos_levels, rot_levels)
    return 0


if __name__ == "__main__":
    sys.exit(main())
