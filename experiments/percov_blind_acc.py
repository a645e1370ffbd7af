#!/usr/bin/env python3
"""The concealed clock recordings calibrated blind to the accelerometers' errors too (issue #30 item 4).

``experiments/percov_conceal.md`` calibrates clockgen's clock cases with the detector's own report, but
first inverts each accelerometer's generator 3×3 error and bias on the outputs
(``--acc-intrinsics known``, :func:`experiments.percov_conceal.known_acc_intrinsics`): clockgen's motion
rests in one orientation, so the preparation cannot calibrate the triads from rests, and that step was
the one oracle left in the chain.  Here it goes: the recording is given as generated, the detector runs
with its accelerometer linear stage (``DetectOptions(acc_linear=True)``, :mod:`accel_bayes.mismatch.acc_linear`)
and ``calibrate(rec, model=report.json)`` inverts the report's accelerometer blocks on the outputs
itself, beside everything else it reads from the report.  Nothing of the truth reaches either.

Per case (``clock`` seeds 0…N−1, the same recordings, mounting error and calibration settings as
percov_conceal; the calibration as ``accel-bayes calibrate REC --model report.json`` runs it, with the
angular jerk, untempered):

* ``blind`` — the raw recording, ``detect(acc_linear=True)``, ``calibrate(model=report)`` with its
  default ``acc_blocks="fit"``: the triads' deviations from their mean linear error integrated out of the
  likelihood and the error they share cut, the tolerance by type-II ML, the report's blocks its centre
  (:mod:`accel_bayes.model.acc_block_marginal`);
* ``blind_fixed`` — the same report, ``acc_blocks="fixed"``: the blocks inverted as exact (what
  ``calibrate --model`` did before the option; the records of the first two runs);
* ``oracle`` — percov_conceal's ``with_angjerk`` on today's code: the generator's accelerometer errors
  inverted first, ``detect`` with its defaults, the same calibration.

Scored as percov_conceal: z per free coordinate = (posterior mean − truth) / posterior std; issue #30's
bar with the model: RMS z within 0.8–1.25, none beyond 4.  The per-case records are committed in
``experiments/results/percov_blind_acc/`` (a rerun reuses them); the detector's reports they came from are cached in
``experiments/out/percov_blind_acc/`` (too large to commit).

    PYTHONPATH=. OMP_NUM_THREADS=1 nice -n 5 python3 experiments/percov_blind_acc.py --n 21
"""
from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT.parent))
DOC = ROOT / "percov_blind_acc.md"
VARIANTS = ("blind", "blind_fixed", "oracle")
OUT = ROOT / "results" / "percov_blind_acc"
REPORTS = ROOT / "out" / "percov_blind_acc"
#: percov_conceal's issue #30 run settings (its document's Regenerate line)
CALIB = {"chains": 2, "warmup": 300, "draws": 400, "seed": 0}


def run_case(seed: int, variant: str, out: Path, reports: Path = REPORTS, duration: float = 20.0,
             mount_std: float = 5e-4) -> dict:
    """The detector (``blind``: with the acc stage on the raw recording; ``oracle``: defaults on the recording
    with the generator's acc errors inverted), then the calibration with its report; cached in
    ``out/clock-SSS/{variant}.json``, the report in ``reports/clock-SSS/{variant}_report.json``."""
    from accel_bayes.data.outputs import write_json
    from accel_bayes.mismatch import DetectOptions, detect
    from experiments.acc_stage_budget import stage_blocks
    from experiments.percov_conceal import case_recording, run_variant, score

    d = out / f"clock-{seed:03d}"
    f = d / f"{variant}.json"
    if f.exists():
        return json.loads(f.read_text())
    blind = variant.startswith("blind")
    rec, truth, pos = case_recording(seed, duration, mount_std, acc_intrinsics="none" if blind else "known")
    rep = reports / f"clock-{seed:03d}" / f"{'blind' if blind else variant}_report.json"
    t0 = time.perf_counter()
    if not rep.exists():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            report = detect(rec, DetectOptions(seed=CALIB["seed"], acc_linear=blind))
        rep.parent.mkdir(parents=True, exist_ok=True)
        write_json(rep, report.to_dict())
    det_s = time.perf_counter() - t0
    doc = json.loads(rep.read_text())
    r = run_variant(rec, "with_angjerk", rep, CALIB["chains"], CALIB["draws"], CALIB["warmup"], CALIB["seed"],
                    **({"acc_blocks": "fixed"} if variant == "blind_fixed" else {}))
    res = {"variant": variant, "seed": seed, "board": truth["board"], "f_host": truth["f_host"], "K": int(rec.K),
           "detect_seconds": det_s, "calibrate_seconds": r["seconds"],
           "acc_blocks": stage_blocks(doc, int(rec.K))[2],
           "acc_stage": (doc["details"].get("acc_linear_stage") or {}).get("result"),
           "gyro_common": gyro_common(doc),
           "findings": [{"effect": x["effect"], "imu": x.get("imu")} for x in doc["findings"]],
           "used": [u["effect"] for u in (r.get("model") or {}).get("used", [])],
           "acc_blocks_record": ((r["positions"]["provenance"]["settings"].get("model") or {}).get("acc_blocks")),
           # the chains' target's sandwich (with blocks: the integrated target's, acc_block_marginal.marginal_scores)
           "sandwich": {k: v for k, v in ((r["positions"]["provenance"]["settings"].get("model") or {})
                                          .get("sandwich") or {}).items()
                        if k in ("std_ratio", "std_ratio_max", "std_ratio_median", "laplace_std_m", "sandwich_std_m",
                                 "cut_std_m", "coordinates")},
           "score": {**score(r["positions"], pos), "truth_m": true_coordinates(pos, score(r["positions"], pos))},
           "settings": CALIB}
    d.mkdir(parents=True, exist_ok=True)
    write_json(f, res)
    return res


def true_coordinates(pos: np.ndarray, sc: dict) -> list[float]:
    """The true value (m) of each scored coordinate of ``sc`` (:func:`experiments.percov_conceal.score`'s
    ``coordinates``, relative to its reference IMU), from the true positions ``pos`` (K, 3)."""
    ref = int(sc["reference_imu"])
    out = []
    for c in sc["coordinates"]:  # "r[k, a]"
        k, a = int(c[2:c.index(",")]), "xyz".index(c[-2])
        out.append(float(pos[k, a] - pos[ref, a]))
    return out


def gyro_common(doc: dict) -> dict:
    """What a report's gyro linear stage did with the common part (one array-frame 3×3 error of every gyro, seen
    through the accelerometers' lever arms): kept or not, and where kept its largest |entry| and isotropic part."""
    st = (doc["details"].get("gyro_linear_stage") or {})
    c = st.get("common")
    if not c:
        return {"kept": False}
    M = np.asarray(c["matrix"], dtype=np.float64)
    return {"kept": True, "max_abs": float(np.abs(M).max()), "isotropic": float(np.trace(M) / 3)}


def with_truth(rec_path: Path, seed: int, reports: Path = REPORTS) -> dict:
    """The record at ``rec_path`` with ``score.truth_m`` and ``gyro_common`` filled in (records written before
    they were kept: the true positions come from the generator again, seeded as the case, the gyro stage's common
    part from the cached report where there is one; the record is rewritten)."""
    from accel_bayes.data.outputs import write_json
    from experiments.percov_conceal import case_recording

    r = json.loads(rec_path.read_text())
    if "truth_m" not in r["score"]:
        _, _, pos = case_recording(seed, 20.0, 5e-4, acc_intrinsics="none")
        r["score"]["truth_m"] = true_coordinates(pos, r["score"])
        write_json(rec_path, r)
    rep = reports / rec_path.parent.name / f"{'blind' if r['variant'].startswith('blind') else r['variant']}_report.json"
    if "gyro_common" not in r and rep.exists():
        r["gyro_common"] = gyro_common(json.loads(rep.read_text()))
        write_json(rec_path, r)
    return r


def rescaled(sc: dict) -> tuple[float, np.ndarray]:
    """(geometry scale − 1, the z left after it): the isotropic rescale of the case's estimated coordinates that best
    fits the truth, Σ mean·truth / Σ truth², and each coordinate's z once the truth is rescaled by it.  Tells a
    whole-array size error (the accelerometers' common isotropic scale is the array's size gauge) from the rest."""
    t, e, sd = (np.asarray(sc[k]) for k in ("truth_m", "error_m", "std_m"))
    g = float((t + e) @ t / (t @ t))
    return g - 1.0, ((t + e) - g * t) / sd


def _common(r: dict) -> str:
    c = r.get("gyro_common")
    if c is None:
        return "?"
    return f"{c['max_abs']:.3f} ({100 * c['isotropic']:+.1f} %)" if c["kept"] else "—"


def _rms(z) -> float:
    return float(np.sqrt(np.mean(np.square(z))))


def _stats(z) -> dict:
    z = np.asarray(z, dtype=np.float64)
    return {"n": int(z.size), "rms": _rms(z), "max": float(np.abs(z).max()),
            "beyond4": int((np.abs(z) > 4).sum()), "mean": float(z.mean())}


def _fixed_cells(f: dict | None, b: dict) -> str:
    """The blocks-fixed record's z RMS / max |z| and the blind run's fitted tolerance (table cells)."""
    zf = np.asarray(f["score"]["z"]) if f else None
    rec = b.get("acc_blocks_record") or {}
    tol = (f"{100 * rec['tau_matrix']:.2f} / {rec['tau_bias_m_s2']:.3f}" if "tau_matrix" in rec else "—")
    return ("—" if zf is None else f"{_rms(zf):.2f} / {np.abs(zf).max():.2f}") + " | " + tol


def sandwich_z(rec: dict):
    """(n,) the errors over the recorded sandwich std of the chains' target, with the cut's spread where there is one
    (matched by coordinate name), or None when the record has no sandwich."""
    sw = rec.get("sandwich") or {}
    if not sw.get("sandwich_std_m"):
        return None
    sc = rec["score"]
    at = {c: i for i, c in enumerate(sw["coordinates"])}
    idx = [at[c] for c in sc["coordinates"]]
    s2 = np.asarray(sw["sandwich_std_m"])[idx] ** 2 + np.asarray(sw.get("cut_std_m") or np.zeros(len(at)))[idx] ** 2
    return np.asarray(sc["error_m"]) / np.sqrt(s2)


def markdown(rows: list[tuple], cmd: str, seconds: float) -> list[str]:
    """The document: pooled figures over the cases that have blind and oracle, then case by case.  ``rows``:
    (blind, oracle or None) or (blind, oracle or None, blind_fixed or None) records per case; the blocks-fixed
    column appears where every pooled case has one."""
    from experiments._stamp import run_stamp

    fixed = {r[0]["seed"]: r[2] for r in rows if len(r) > 2 and r[2] is not None}
    rows = [(r[0], r[1]) for r in rows]
    both = [(b, o["score"]) for b, o in rows if o is not None]
    showf = bool(both) and all(b["seed"] in fixed for b, _ in both)
    sf = _stats(np.concatenate([fixed[b["seed"]]["score"]["z"] for b, _ in both])) if showf else None
    fx = (lambda v: f" {v} |") if showf else (lambda v: "")  # noqa: E731
    fsc = [fixed[b["seed"]]["score"] for b, _ in both] if showf else []
    sb = _stats(np.concatenate([b["score"]["z"] for b, _ in both]))
    so = _stats(np.concatenate([o["z"] for _, o in both]))
    err = lambda s: 1e6 * _rms(np.concatenate([x["error_m"] for x in s]))  # noqa: E731
    std = lambda s: 1e6 * float(np.median(np.concatenate([x["std_m"] for x in s])))  # noqa: E731
    ok = lambda s: 0.8 <= s["rms"] <= 1.25 and s["beyond4"] == 0  # noqa: E731
    L = ["# percov_blind_acc — concealed clock recordings calibrated blind to the accelerometers' errors too (issue #30 item 4)",
         "", f"Regenerate: `{cmd}` ({run_stamp()}; this invocation {seconds:.0f} s; per-case records committed in "
         "`experiments/results/percov_blind_acc/`, the reports cached in `experiments/out/percov_blind_acc/`).", "",
         "What runs: the script's docstring. **blind**: the recording as generated, `detect(acc_linear=True)`, "
         "`calibrate(model=report)` (angular jerk, untempered; the triads' linear errors with a Gaussian tolerance centred "
         "by the report's blocks, the tolerance by type-II ML: their deviations from their mean integrated out of the "
         "likelihood, the positions moving the integral's weights too, the part they share cut: option "
         "`acc_blocks='fit'`, the default). "
         + ("**blind, blocks fixed**: the same with `acc_blocks='fixed'` (the report's blocks inverted as exact). " if showf
            else "") + "**oracle**: percov_conceal's `with_angjerk` on the same code (the generator's accelerometer errors "
         f"inverted first, `detect` defaults, the same calibration). Calibration {CALIB['chains']} chains × "
         f"({CALIB['warmup']} + {CALIB['draws']}), seed {CALIB['seed']}; z = (posterior mean − truth) / posterior std per "
         "free coordinate.", "",
         f"Cases: {len(both)} with both ({len(rows)} run).", "",
         "| | blind (acc stage) | oracle (generator's acc errors inverted) |" + fx("blind, blocks fixed"),
         "|---|---|---|" + fx("---"),
         f"| error/std RMS (must: 0.8–1.25) | {sb['rms']:.2f} | {so['rms']:.2f} |" + fx(showf and f"{sf['rms']:.2f}"),
         f"| max \\|z\\| (must: ≤ 4) | {sb['max']:.2f} | {so['max']:.2f} |" + fx(showf and f"{sf['max']:.2f}"),
         f"| coordinates beyond 4 std (must: 0) | {sb['beyond4']}/{sb['n']} | {so['beyond4']}/{so['n']} |"
         + fx(showf and f"{sf['beyond4']}/{sf['n']}"),
         f"| mean z | {sb['mean']:.2f} | {so['mean']:.2f} |" + fx(showf and f"{sf['mean']:.2f}"),
         f"| z RMS after each case's whole-array rescale | {_rms(np.concatenate([rescaled(b['score'])[1] for b, _ in both])):.2f} | "
         f"{_rms(np.concatenate([rescaled(o)[1] for _, o in both])):.2f} |"
         + fx(showf and f"{_rms(np.concatenate([rescaled(x)[1] for x in fsc])):.2f}"),
         f"| RMS error (µm) | {err([b['score'] for b, _ in both]):.1f} | {err([o for _, o in both]):.1f} |"
         + fx(showf and f"{err(fsc):.1f}"),
         f"| median posterior std (µm) | {std([b['score'] for b, _ in both]):.1f} | {std([o for _, o in both]):.1f} |"
         + fx(showf and f"{std(fsc):.1f}"),
         f"| bar met | {'YES' if ok(sb) else 'NO'} | {'YES' if ok(so) else 'NO'} |" + fx(showf and ('YES' if ok(sf) else 'NO')),
         "",
         "Per case: *size* = the geometry scale − 1 (Σ mean·truth / Σ truth² over the case's coordinates, in %); *z RMS "
         "rescaled* = what is left once the truth is rescaled by it (a whole-array size error taken out).", "",
         "*gyro common* = the largest \\|entry\\| of the common 3×3 error the report's gyro linear stage kept (its "
         "isotropic part in brackets; — where none was kept). The generator draws each gyro's 3×3 entries N(0, σ), σ "
         "0.5–3 % per gyro, on the even seeds; what all gyros share is their mean, about σ/√K.", "",
         "| case | board | read Hz | acc blocks (triads) | z RMS blind / oracle | max \\|z\\| blind / oracle | size % blind / oracle | z RMS rescaled blind / oracle | gyro common blind / oracle | detect s blind / oracle | calibrate s blind / oracle |"
         + fx("z RMS / max \\|z\\| blocks fixed | tolerance τ_M % / τ_b m/s²"),
         "|---|---|---|---|---|---|---|---|---|---|---|" + fx("---|---")]
    pair = lambda x, y, fmt: f"{x:{fmt}} / " + ("—" if y is None else f"{y:{fmt}}")  # noqa: E731
    for b, o in rows:
        zb = np.asarray(b["score"]["z"])
        zo = None if o is None else np.asarray(o["score"]["z"])
        gb, rb = rescaled(b["score"])
        go, ro = (None, None) if o is None else rescaled(o["score"])
        L.append(f"| clock-{b['seed']:03d} | {b['board']} | {b['f_host']:g} | {len(b['acc_blocks'])}/{b['K']} | "
                 + pair(_rms(zb), None if zo is None else _rms(zo), ".2f") + " | "
                 + pair(np.abs(zb).max(), None if zo is None else np.abs(zo).max(), ".2f") + " | "
                 + pair(100 * gb, None if o is None else 100 * go, "+.2f") + " | "
                 + pair(_rms(rb), None if o is None else _rms(ro), ".2f") + " | "
                 + _common(b) + " / " + ("—" if o is None else _common(o)) + " | "
                 + pair(b["detect_seconds"], None if o is None else o["detect_seconds"], ".0f") + " | "
                 + pair(b["calibrate_seconds"], None if o is None else o["calibrate_seconds"], ".0f") + " |"
                 + (fx(_fixed_cells(fixed.get(b["seed"]), b)) if showf else ""))
    worst = sorted(((abs(z), c, b["seed"]) for b, _ in both for z, c in zip(b["score"]["z"], b["score"]["coordinates"])),
                   reverse=True)[:5]
    L += ["", "Largest |z| blind: " + ", ".join(f"clock-{s:03d} {c} {z:.2f}" for z, c, s in worst) + "."]
    pairs = [(b, o) for b, o in rows if o is not None]
    zb_sw = [sandwich_z(b) for b, _ in pairs]
    if zb_sw and all(z is not None for z in zb_sw):
        mx = [b["sandwich"]["std_ratio_max"] for b, _ in pairs]
        md = [b["sandwich"]["std_ratio_median"] for b, _ in pairs]
        zo_sw = [sandwich_z(o) for _, o in pairs]
        zsw = np.concatenate(zb_sw)
        oracle = ""
        if all(z is not None for z in zo_sw):
            zo = np.concatenate(zo_sw)
            oracle = (f"; the oracle's (the per-sample likelihood's own sandwich) {_rms(zo):.2f} (max {np.abs(zo).max():.2f}, "
                      f"{int((np.abs(zo) > 4).sum())} beyond 4) against {so['rms']:.2f}")
        L += ["", f"The chains' own target's sandwich (the blocks integrated: `acc_block_marginal.marginal_scores`), per "
                  f"case: sandwich/Laplace std ratio max {min(mx):.2f}–{max(mx):.2f} (median over cases "
                  f"{np.median(mx):.2f}), median over coordinates {min(md):.2f}–{max(md):.2f}; the error over the "
                  f"sandwich std (with the cut's spread) has RMS {_rms(zsw):.2f} (max "
                  f"{np.abs(zsw).max():.2f}, {int((np.abs(zsw) > 4).sum())} beyond 4), "
                  f"where over the posterior std it is {sb['rms']:.2f}" + oracle + "."]
    return L


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=21, help="clock cases, seeds 0..n-1 (default 21, as percov_conceal's run)")
    ap.add_argument("--cases", default="", help="comma-separated seeds to compute (default all n); the document uses every cached one")
    ap.add_argument("--out", type=Path, default=OUT, help="the per-case records (default experiments/results/percov_blind_acc)")
    ap.add_argument("--reports", type=Path, default=REPORTS, help="the detector reports (default experiments/out/percov_blind_acc)")
    ap.add_argument("--variants", default=",".join(VARIANTS), help="comma-separated subset of blind,oracle to compute")
    ap.add_argument("--no-doc", action="store_true", help="run and cache the cases only")
    args = ap.parse_args(argv)
    t0 = time.time()
    seeds = [int(s) for s in args.cases.split(",") if s.strip()] or list(range(args.n))
    variants = [v for v in args.variants.split(",") if v]
    if any(v not in VARIANTS for v in variants):
        ap.error(f"--variants: expected a subset of {','.join(VARIANTS)}, got {args.variants!r}")
    for s in seeds:
        for v in variants:
            r = run_case(s, v, args.out, args.reports)
            z = np.asarray(r["score"]["z"])
            print(f"clock-{s:03d} {r['board']} {r['f_host']:g} Hz {v}: acc blocks {len(r['acc_blocks'])}/{r['K']}, z RMS "
                  f"{_rms(z):.2f}, max |z| {np.abs(z).max():.2f}", flush=True)
    if args.no_doc:
        return 0
    rows = []
    for s in range(args.n):
        f, h, g = (args.out / f"clock-{s:03d}" / f"{v}.json" for v in VARIANTS)
        if f.exists():
            rows.append((with_truth(f, s, args.reports), with_truth(g, s, args.reports) if g.exists() else None,
                         with_truth(h, s, args.reports) if h.exists() else None))
    from experiments._reading import write_with_reading

    cmd = "PYTHONPATH=. OMP_NUM_THREADS=1 nice -n 5 python3 experiments/percov_blind_acc.py" + (
        "" if args.n == 21 else f" --n {args.n}")
    write_with_reading(DOC, markdown(rows, cmd, time.time() - t0))
    print(f"wrote {DOC}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
