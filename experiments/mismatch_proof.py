#!/usr/bin/env python3
"""Blind proof of the mismatch detector on data from an independent simulator.

Each data set comes from ``experiments/_conceal.py`` — a first-principles numpy forward model of
an IMU array on a rigid board in continuous motion, written without the package's signal model
— and hides at most one effect of the DESIGN §7.2 vocabulary on one random non-reference IMU
(and axis).  :func:`accel_bayes.mismatch.detect` sees only the :class:`Recording` (nominal
poses, stated noise); the truth stays with this script.  Printed:

* the confusion matrix, true effect × top-ranked finding ("none" = no finding reported);
* localisation: right IMU, and right IMU and axis where the effect has an axis;
* the false-alarm rate: ``mismatch_detected`` on clean data sets;
* fit figures: χ²/dof of the baseline and of the refined model, and the position error
  (RMS over the non-reference IMUs of |r̂_k − r_k|, positions relative to the reference IMU,
  µm) of the baseline fit and of the refined fit, relative to the clean-data error.  The
  clean-data error of a case is measured on its exact *clean twin*: the same seed with the
  effect switched off (same motion, true geometry and noise draws), fitted the same way
  (``--twin``: a full detect of the twin, whose false alarms also count; ``--twin-baseline``:
  only the detector's baseline fit of the twin — the fit it ends with on clean data unless it
  raises a false alarm — at ~5 % of the cost; ``--no-twin``: the median error of the board's
  clean sets, a much cruder reference because the error varies with T, noise and motion).

With ``--out DIR`` (or ``--fig PNG``) the same is drawn in ``DIR/summary.png``: the confusion
matrix, χ²/dof before → after refinement, and the position error before → after relative to
the clean-data error, one point per case.

MUST-SHOW targets, each printed with PASS/FAIL:

1. right effect ranked first in ≥ 90 % of the effect cases;
2. right IMU (and axis, where the effect has one) in ≥ 90 % of the effect cases;
3. ``mismatch_detected`` false on ≥ 95 % of the clean recordings (the dedicated clean sets and
   the clean twins together);
4. after refinement χ²/dof within 10 % of 1 in ≥ 90 % of the effect cases;
5. after refinement the position error within 1.5 × the clean-data error in ≥ 90 % of the
   effect cases.

Scoring rules.  The top finding is ``findings[0]`` (none if the list is empty).  IMU: the
finding's ``imu`` must equal the truth's.  Axis: scored for the effects applied to one sensing
axis (acc bias/scale/misalignment — the receiving axis —/nonlinearity, axis displacement, gyro
bias/scale/g-sensitivity); not for ``saturation`` (a whole triad has one range; the truth still
records the axis that clipped most), ``triad_orientation``, ``time_offset``, ``noise_level``.
A finding with ``axis`` null but a 3-vector parameter (the §7.2 g-sensitivity, displacement,
bias… vectors) points at the axis of its largest component.

Run::

    python experiments/mismatch_proof.py --quick             # mimu8, 2/effect, 4 clean, T=1500, no twins (~10–15 min)
    python experiments/mismatch_proof.py                     # 10/effect, 30 clean, three boards
    python experiments/mismatch_proof.py --per-effect 20 --clean 60 --out experiments/out/mismatch_proof
    python experiments/mismatch_proof.py --generate-only --save-cases /tmp/cases   # data only, no detector

Cases run as dask.distributed tasks (``_dask.py``: a LocalCluster of ``--workers`` single-thread
processes, default 1, or ``--scheduler ADDRESS``; ``--workers 0`` runs them in this process).

Resuming.  With ``--out DIR`` every finished case is appended at once as one row of
``DIR/cases.csv`` (fixed columns :data:`COLUMNS`), and the options that define the benchmark are
kept in ``DIR/options.json``.  Rerunning with the same options skips the cases already in the CSV
(a crashed case counts as done — and as a failure — unless ``--retry-errors``), so the full
benchmark accumulates over several runs or sessions; ``--max-cases N`` and ``--time-budget S``
bound one run.  One change of options is allowed on resume: a ``--no-twin`` store may continue
with ``--twin-baseline``; the stored rows then get their clean-twin reference computed first.
Other changes of options with the same ``DIR`` are refused (use another directory).
Cases are run interleaved (first case of every effect, then the second, …) so a partial run
covers every effect.  The summary — confusion matrix, localisation, false alarms, fits before
and after — is computed from all rows present and says how many of the cases the issue requires
(≥ 10 per effect, ≥ 30 clean) are done::

    nohup env OMP_NUM_THREADS=1 python3 experiments/mismatch_proof.py --twin-baseline --workers 2 \
        --out experiments/out/mismatch_proof_full > /tmp/mp_full.log 2>&1 &   # rerun = resume
    python experiments/mismatch_proof.py --rescore experiments/out/mismatch_proof_full/cases.csv
"""
from __future__ import annotations

import argparse
import csv
import json
import math
import os
import sys
import time
import traceback
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from _conceal import AXIS_EFFECTS, BOARDS, DEG, EFFECTS, make_case, oracle_noncentrality, save_case  # noqa: E402
from _dask import add_dask_arguments, dask_client  # noqa: E402

AXIS_SCORED = tuple(e for e in AXIS_EFFECTS if e != "saturation")
TARGETS = {"effect": 0.90, "localisation": 0.90, "clean_quiet": 0.95, "chi2_after": 0.90, "position_after": 0.90}
CHI2_TOL = 0.10
POS_FACTOR = 1.5
# A case is "above the detection limit" when its oracle non-centrality λ (see
# _conceal.oracle_noncentrality) is at least this many times the report's threshold: a detector
# that knew the effect's shape would then pass the threshold with probability ≳ 95 %.
DETECTABLE_FACTOR = 2.0
# What the issue requires of the concealed benchmark.
REQUIRED_PER_EFFECT = 10
REQUIRED_CLEAN = 30
# The columns of cases.csv, in order (a fixed header, so rows can be appended run after run).
COLUMNS = ("case", "board", "effect_true", "seed", "imu_true", "axis_true", "magnitude", "T", "rate", "sigma_a",
           "sigma_g_dps", "omega_rms_dps", "K", "lambda_oracle", "seconds", "mismatch_detected", "top_effect",
           "top_imu", "top_axis", "top_evidence", "top_axis_scored", "top_parameters", "param_ratio",
           "second_effect", "n_findings", "threshold", "chi2_before", "chi2_after", "findings",
           "pos_err_before_um", "pos_err_after_um", "seconds_twin", "twin_mismatch_detected", "pos_err_clean_um",
           "error")
# Options that define the cases and how they are scored: a rerun must match them to resume.
OPTION_KEYS = ("seed", "T", "rate", "boards", "twin", "detect_kwargs")


# ---------------------------------------------------------------------------- detector access

def _detector():
    """The detector function, or a clear SystemExit when it is not there yet."""
    try:
        from accel_bayes.mismatch import detect
    except ImportError as exc:
        raise SystemExit(
            "mismatch_proof: accel_bayes.mismatch.detect is not available "
            f"({exc}); the blind proof needs the detector. Data generation alone works: "
            "--generate-only [--save-cases DIR]") from None
    return detect


def _as_dict(report) -> dict:
    return report.to_dict() if hasattr(report, "to_dict") else dict(report)


_POS_KEYS_BEFORE = (("details", "positions_baseline"), ("positions", "before"), ("fitted_positions", "before"), ("positions_before",),
                    ("baseline", "positions"), ("baseline", "position"))
_POS_KEYS_AFTER = (("details", "positions_refined"), ("positions", "after"), ("fitted_positions", "after"), ("positions_after",),
                   ("refined", "positions"), ("refined", "position"))


def _lookup(d: dict, path):
    cur = d
    for k in path:
        if not isinstance(cur, dict) or k not in cur or cur[k] is None:
            return None
        cur = cur[k]
    return cur


def _positions(rep: dict, which: str, K: int, ref: int):
    """(K, 3) fitted positions relative to the reference IMU from the report, or None."""
    for path in (_POS_KEYS_BEFORE if which == "before" else _POS_KEYS_AFTER):
        v = _lookup(rep, path)
        if v is None:
            continue
        if isinstance(v, dict):  # e.g. {"imus": [{"imu": k, "mean": [...]}, ...]} (§7.3 style)
            rows = v.get("imus")
            if rows is None:
                continue
            arr = np.full((K, 3), np.nan)
            for r in rows:
                arr[int(r["imu"])] = r.get("mean", r.get("position"))
            v = arr
        arr = np.asarray(v, dtype=float)
        if arr.shape == (K, 3):
            return arr - arr[ref]
    return None


def _finding_axis(finding: dict):
    """The axis a finding points at: its ``axis``, or — for an effect reported per IMU with a
    3-vector parameter (e.g. a g-sensitivity vector) — the axis of the vector's largest
    component.  None if neither exists."""
    if finding.get("axis") is not None:
        return finding["axis"]
    for v in (finding.get("parameters") or {}).values():
        if isinstance(v, (list, tuple)) and len(v) == 3 and all(isinstance(x, (int, float)) for x in v):
            return "xyz"[int(np.argmax(np.abs(np.asarray(v, dtype=float))))]
    return None


_PARAM_KEY = {"acc_bias": "bias", "acc_scale": "scale", "acc_misalignment": "coupling", "acc_nonlinearity": "k2",
              "gyro_bias": "bias", "gyro_scale": "scale", "gyro_g_sensitivity": "sensitivity",
              "gyro_nonlinearity": "k2",
              "time_offset": "offset", "noise_level": "factor", "saturation": "limit",
              "axis_displacement": "displacement", "triad_orientation": "rotation_vector"}


def _param_ratio(finding: dict, truth: dict):
    """Fitted / true size of the concealed effect when the top finding names it: the component
    on the true axis for per-axis parameters, the projection on the true vector for the
    displacement and rotation vectors.  A ratio near −1 means a sign-convention disagreement."""
    e = truth["effect"]
    if finding.get("effect") != e or e not in _PARAM_KEY:
        return None
    est = (finding.get("parameters") or {}).get(_PARAM_KEY[e])
    tru = (truth.get("parameters") or {}).get(_PARAM_KEY[e])
    if est is None or tru is None:
        return None
    try:
        est, tru = np.asarray(est, dtype=float), np.asarray(tru, dtype=float)
        if e in ("axis_displacement", "triad_orientation"):
            return float(np.dot(est, tru) / np.dot(tru, tru)) if est.shape == (3,) else None
        if est.shape == (3,):
            est = est["xyz".index(truth["axis"])]
        if tru.shape == (3,):
            tru = tru["xyz".index(truth["axis"])]
        return float(est) / float(tru) if float(tru) != 0 else None
    except (TypeError, ValueError):
        return None


def _pos_error_um(est, true_rel, ref) -> float:
    if est is None:
        return float("nan")
    d = np.delete(est - true_rel, ref, axis=0)
    return float(np.sqrt((d * d).sum(-1).mean()) * 1e6)


# ---------------------------------------------------------------------------- one case (worker)

def twin_baseline_error(clean, ref: int, true_rel) -> float:
    """Position error (µm) of the detector's own baseline fit (its first stage:
    ``prepare`` + ``baseline_fit``, the nominal model's MAP) on a case's clean twin — the
    clean-data reference of ``--twin-baseline``, a fraction of the cost of a full detect."""
    from accel_bayes.mismatch import baseline_fit, prepare

    base, _ = baseline_fit(prepare(clean.recording), use_map=True, progress=False)
    pos = np.asarray(base.positions, dtype=float)
    return _pos_error_um(pos - pos[ref], true_rel, ref)


def run_case(case_id: str, board: str, effect: str, seed: int, settings: dict, twin: bool,
             detect_kwargs: dict, save_dir: str | None = None, generate_only: bool = False) -> dict:
    """Generate one blind case, run the detector on the recording alone, score it."""
    row = {"case": case_id, "board": board, "effect_true": effect, "seed": seed}
    try:
        case = make_case(board, effect, seed, **settings)
        tr, rec = case.truth, case.recording
        st = tr["settings"]
        row.update(imu_true=tr["imu"], axis_true=tr["axis"], magnitude=tr["magnitude"], T=st["T"],
                   rate=round(st["rate"], 3), sigma_a=st["sigma_a"], sigma_g_dps=st["sigma_g"] / DEG,
                   omega_rms_dps=st["omega_rms_achieved"] / DEG, K=rec.K)
        clean = make_case(board, "none", seed, **settings) if effect != "none" else case
        row["lambda_oracle"] = oracle_noncentrality(case, clean) if effect != "none" else 0.0
        if save_dir:
            save_case(case, Path(save_dir) / f"{case_id}.nc", overwrite=True)
        if generate_only:
            return row
        detect = _detector()
        t0 = time.perf_counter()
        rep = _as_dict(detect(rec, **detect_kwargs))
        row["seconds"] = time.perf_counter() - t0
        ref = int(rec.reference_imu)
        true_rel = np.asarray(tr["true_relative_position"])
        f = rep.get("findings") or []
        top = f[0] if f else {}
        row.update(
            mismatch_detected=bool(rep.get("mismatch_detected")),
            top_effect=top.get("effect", "none") if f else "none",
            top_imu=top.get("imu"), top_axis=top.get("axis"), top_evidence=top.get("evidence"),
            top_axis_scored=_finding_axis(top) if f else None,
            top_parameters=json.dumps(top.get("parameters")) if f else None,
            param_ratio=_param_ratio(top, tr) if f else None,
            second_effect=f[1].get("effect") if len(f) > 1 else None,
            n_findings=len(f), threshold=rep.get("threshold"),
            chi2_before=_lookup(rep, ("baseline", "chi2_per_dof")),
            chi2_after=_lookup(rep, ("refined", "chi2_per_dof")),
            findings=json.dumps([{k: x.get(k) for k in ("effect", "imu", "axis", "evidence", "alternatives")} for x in f]),
        )
        if row["chi2_after"] is None:  # nothing refined: the final model is the baseline
            row["chi2_after"] = row["chi2_before"]
        pb = _positions(rep, "before", rec.K, ref)
        pa = _positions(rep, "after", rec.K, ref)
        if pa is None and rep.get("refined") is None:
            pa = pb
        row["pos_err_before_um"] = _pos_error_um(pb, true_rel, ref)
        row["pos_err_after_um"] = _pos_error_um(pa, true_rel, ref)
        if twin == "baseline" and effect != "none":
            t1 = time.perf_counter()
            row["pos_err_clean_um"] = twin_baseline_error(clean, ref, true_rel)
            row["seconds_twin"] = time.perf_counter() - t1
        elif twin and effect != "none":
            t1 = time.perf_counter()
            rep0 = _as_dict(detect(clean.recording, **detect_kwargs))
            row["seconds_twin"] = time.perf_counter() - t1
            row["twin_mismatch_detected"] = bool(rep0.get("mismatch_detected"))
            # The clean-data error is the error of the fit the detector ends with on clean data
            # (the baseline unless it — wrongly — refined something).
            p0 = _positions(rep0, "after", rec.K, ref)
            if p0 is None:
                p0 = _positions(rep0, "before", rec.K, ref)
            row["pos_err_clean_um"] = _pos_error_um(p0, true_rel, ref)
        elif effect == "none":
            row["pos_err_clean_um"] = row["pos_err_after_um"]
    except SystemExit:
        raise
    except Exception as exc:  # a crash is a failed case, not a crashed benchmark
        row["error"] = f"{type(exc).__name__}: {exc}"
        row["traceback"] = traceback.format_exc(limit=6)
    return row


# ---------------------------------------------------------------------------- scoring

def _frac(xs):
    xs = [bool(x) for x in xs]
    return (sum(xs) / len(xs)) if xs else float("nan"), sum(xs), len(xs)


def _fmt_frac(f):
    v, k, n = f
    return f"{k}/{n} = {100 * v:.1f} %" if n else "n/a"


def _verdict(value, target):
    if value != value:  # nan
        return "n/a"
    return "PASS" if value >= target else "FAIL"


def score(rows: list[dict]) -> dict:
    eff_all = [r for r in rows if r["effect_true"] != "none"]
    clean_rows = [r for r in rows if r["effect_true"] == "none"]
    ok = lambda r: "error" not in r  # noqa: E731

    def detectable(r):
        thr = r.get("threshold")
        thr = 20.0 if thr is None or not math.isfinite(float(thr)) else float(thr)
        lam = r.get("lambda_oracle")
        return (math.inf if lam is None else float(lam)) >= DETECTABLE_FACTOR * thr

    for r in eff_all:
        r["above_detection_limit"] = detectable(r)
    sub = {"all": eff_all, "detectable": [r for r in eff_all if r["above_detection_limit"]]}
    res = {}
    for name, eff_rows in sub.items():
        res[name] = _score_effect_rows(eff_rows, ok)
    # Clean recordings: the dedicated clean sets and the clean twins of the effect cases (each an
    # independent clean recording of its own seed).
    quiet_dedicated = [ok(r) and not r.get("mismatch_detected") for r in clean_rows]
    # (rows read back from a CSV carry every column, None where a case has no twin)
    quiet_twins = [ok(r) and not r["twin_mismatch_detected"] for r in eff_all
                   if r.get("twin_mismatch_detected") is not None]
    quiet = quiet_dedicated + quiet_twins

    # Confusion matrix.
    truths = [e for e in EFFECTS if any(r["effect_true"] == e for r in rows)] + (["none"] if clean_rows else [])
    pred_of = lambda r: r.get("top_effect") if ok(r) else "error"  # noqa: E731
    preds = [p for p in list(EFFECTS) + ["none"] + sorted({pred_of(r) for r in rows} - set(EFFECTS) - {"none"})
             if any(pred_of(r) == p for r in rows)]
    conf = {t: {p: 0 for p in preds} for t in truths}
    for r in rows:
        conf[r["effect_true"]][pred_of(r)] += 1

    per_effect = {}
    for e in truths:
        rs = [r for r in rows if r["effect_true"] == e]
        fin = lambda k: [float(r[k]) for r in rs if ok(r) and r.get(k) is not None and math.isfinite(float(r[k]))]  # noqa: E731,E501
        med = lambda k: float(np.median(fin(k))) if fin(k) else None  # noqa: E731
        per_effect[e] = {
            "n": len(rs),
            "below_detection_limit": sum(not r.get("above_detection_limit", True) for r in rs) if e != "none" else 0,
            "lambda_oracle_median": med("lambda_oracle") if e != "none" else None,
            "right_effect": _frac([ok(r) and r.get("top_effect") == e for r in rs])[0] if e != "none" else None,
            "localised": _frac([_right_loc(r, ok) for r in rs])[0] if e != "none" else None,
            "detected": _frac([ok(r) and r.get("mismatch_detected") for r in rs])[0],
            "chi2_before_median": med("chi2_before"),
            "chi2_after_median": med("chi2_after"),
            "pos_err_before_um_median": med("pos_err_before_um"),
            "pos_err_after_um_median": med("pos_err_after_um"),
            "pos_err_clean_um_median": med("pos_err_clean_um"),
            "param_ratio_median": med("param_ratio") if e != "none" else None,
            "errors": sum(not ok(r) for r in rs),
        }
    return {
        "n_effect_cases": len(eff_all), "n_clean_cases": len(clean_rows),
        **res["all"], "detectable": res["detectable"],
        "clean_quiet": _frac(quiet), "clean_quiet_dedicated": _frac(quiet_dedicated),
        "clean_quiet_twins": _frac(quiet_twins),
        "false_alarm_rate": 1 - _frac(quiet)[0] if quiet else float("nan"),
        "confusion": conf, "per_effect": per_effect, "misnamed_with_alternative": _misnamed_alternatives(eff_all, ok),
        "errors": sum(not ok(r) for r in rows),
    }


def _misnamed_alternatives(eff_rows: list[dict], ok) -> dict:
    """Of the effect cases whose top finding names another effect, how many list the true effect
    (at the true IMU) among that finding's ``alternatives`` — i.e. the report said the recording
    could not tell the two apart.  Rows written before findings carried alternatives are left
    out (``n_without_record``)."""
    hit = n = missing = 0
    for r in eff_rows:
        if not ok(r) or r.get("top_effect") in (None, "none", r["effect_true"]):
            continue
        try:
            top = (json.loads(r.get("findings") or "[]") or [{}])[0]
        except (TypeError, ValueError):
            top = {}
        if "alternatives" not in top:
            missing += 1
            continue
        n += 1
        hit += any(a.get("effect") == r["effect_true"] and a.get("imu") == r.get("imu_true")
                   for a in top.get("alternatives") or [])
    return {"listed": hit, "n": n, "n_without_record": missing}


def _finite(x) -> bool:
    try:
        return x is not None and math.isfinite(float(x))
    except (TypeError, ValueError):
        return False


def _right_loc(r, ok):
    if r["effect_true"] == "none":
        return False
    if not ok(r) or r.get("top_imu") is None or int(r["top_imu"]) != int(r["imu_true"]):
        return False
    if r["effect_true"] in AXIS_SCORED:
        return r.get("top_axis_scored") == r["axis_true"]
    return True


def _score_effect_rows(eff_rows, ok) -> dict:
    right_effect = [ok(r) and r.get("top_effect") == r["effect_true"] for r in eff_rows]
    right_imu = [ok(r) and r.get("top_imu") is not None and int(r["top_imu"]) == int(r["imu_true"]) for r in eff_rows]
    loc = [_right_loc(r, ok) for r in eff_rows]
    right_axis = [_right_loc(r, ok) for r in eff_rows if r["effect_true"] in AXIS_SCORED]
    chi2_ok = [ok(r) and r.get("chi2_after") is not None and abs(float(r["chi2_after"]) - 1) <= CHI2_TOL
               for r in eff_rows]

    def pos_ok(r):
        if not ok(r):
            return False
        a, c = r.get("pos_err_after_um"), r.get("pos_err_clean_um")
        if c is None or a is None or not (math.isfinite(a) and math.isfinite(c)):
            return False
        return a <= POS_FACTOR * c

    # Position: scored where a clean-data reference exists (twin or clean sets); a crashed
    # case counts as a failure.
    pos = [pos_ok(r) for r in eff_rows if not ok(r) or _finite(r.get("pos_err_clean_um"))]

    return {"n": len(eff_rows), "right_effect": _frac(right_effect), "right_imu": _frac(right_imu),
            "localised": _frac(loc), "right_axis_where_scored": _frac(right_axis),
            "chi2_after_ok": _frac(chi2_ok), "position_after_ok": _frac(pos)}


def print_report(sc: dict, out=None) -> dict:
    out = sys.stdout if out is None else out  # looked up at call time (captured/redirected stdout)
    p = lambda *a: print(*a, file=out)  # noqa: E731
    conf = sc["confusion"]
    if conf:
        preds = list(next(iter(conf.values())).keys())
        short = {c: c.replace("acc_", "a.").replace("gyro_", "g.").replace("_", "")[:9] for c in preds}
        p("\nConfusion matrix (rows: concealed effect; columns: top-ranked finding, 'none' = no finding)")
        p(f"{'':>20}" + "".join(f"{short[c]:>10}" for c in preds))
        for t, row in conf.items():
            p(f"{t:>20}" + "".join(f"{row[c] or '.':>10}" for c in preds))
    p("\nPer effect: n (below detection limit), median oracle λ, detected, right effect, localised, "
      "median χ²/dof before → after, median position error µm before → after (clean reference), "
      "median fitted/true effect size")
    f = lambda x, fmt: ("–" if x is None else format(x, fmt))  # noqa: E731
    for e, d in sc["per_effect"].items():
        p(f"  {e:>18} {d['n']:>3} ({d['below_detection_limit']}) λ {f(d['lambda_oracle_median'], '.0f'):>7}  "
          f"det {f(d['detected'], '.0%'):>4}  eff {f(d['right_effect'], '.0%'):>4}  loc {f(d['localised'], '.0%'):>4}  "
          f"χ² {f(d['chi2_before_median'], '.3f')} → {f(d['chi2_after_median'], '.3f')}  "
          f"pos {f(d['pos_err_before_um_median'], '.1f')} → {f(d['pos_err_after_um_median'], '.1f')} "
          f"({f(d['pos_err_clean_um_median'], '.1f')})  fit/true {f(d['param_ratio_median'], '.2f')}"
          + (f"  ERRORS {d['errors']}" if d["errors"] else ""))
    dsc = sc["detectable"]
    p(f"\nLocalisation detail: right IMU {_fmt_frac(sc['right_imu'])}; right IMU and axis (axis effects only) "
      f"{_fmt_frac(sc['right_axis_where_scored'])}")
    mn = sc.get("misnamed_with_alternative")
    if mn and (mn["n"] or mn["n_without_record"]):
        p(f"Misnamed effect cases whose report lists the true effect as a not-ruled-out alternative: "
          f"{mn['listed']}/{mn['n']}" + (f" ({mn['n_without_record']} more from runs before alternatives were recorded)"
                                          if mn["n_without_record"] else ""))
    if sc["clean_quiet"][2]:
        p(f"False-alarm rate on clean recordings: {sc['false_alarm_rate']:.1%} (mismatch_detected on dedicated clean "
          f"sets: {sc['clean_quiet_dedicated'][2] - sc['clean_quiet_dedicated'][1]}/{sc['clean_quiet_dedicated'][2]}, "
          f"on clean twins: {sc['clean_quiet_twins'][2] - sc['clean_quiet_twins'][1]}/{sc['clean_quiet_twins'][2]})")
    else:
        p("No clean recordings run.")
    verdicts = {
        "right effect ranked first": ("right_effect", TARGETS["effect"]),
        "right IMU (and axis where it has one)": ("localised", TARGETS["localisation"]),
        "clean sets: mismatch_detected false": ("clean_quiet", TARGETS["clean_quiet"]),
        f"after refit |χ²/dof − 1| ≤ {CHI2_TOL:.0%}": ("chi2_after_ok", TARGETS["chi2_after"]),
        f"after refit position error ≤ {POS_FACTOR}× clean": ("position_after_ok", TARGETS["position_after"]),
    }
    p(f"\nMUST-SHOW (all cases; in brackets: the {dsc['n']} effect cases above the detection limit, "
      f"oracle λ ≥ {DETECTABLE_FACTOR:g} × threshold)")
    out_v = {}
    for name, (key, target) in verdicts.items():
        fr = sc[key]
        v = _verdict(fr[0], target)
        out_v[name] = v
        extra = "" if key == "clean_quiet" else f"   [{_fmt_frac(dsc[key])}: {_verdict(dsc[key][0], target)}]"
        p(f"  [{v}] {name}: {_fmt_frac(fr)} (target ≥ {target:.0%}){extra}")
    if sc["errors"]:
        p(f"\n{sc['errors']} case(s) raised an error (counted as failures; see the CSV).")
    return out_v


# ---------------------------------------------------------------------------- figure

_SHORT = {"acc_bias": "a.bias", "acc_scale": "a.scale", "acc_misalignment": "a.misal", "acc_nonlinearity": "a.nonlin",
          "axis_displacement": "displ", "triad_orientation": "orient", "gyro_bias": "g.bias", "gyro_scale": "g.scale",
          "gyro_g_sensitivity": "g.gsens", "time_offset": "t.offset", "saturation": "satur", "noise_level": "noise",
          "gyro_nonlinearity": "g.nonlin", "sampling_jitter": "s.jitter", "none": "none", "unexplained": "unexpl", "error": "error"}


def _scatter_by_limit(ax, x, y, above, color) -> None:
    """One point per case, filled above the detection limit and hollow below it."""
    for d in (True, False):
        sel = above == d
        ax.scatter(x[sel], y[sel], s=18, facecolors=color if d else "none", edgecolors=color,
                   label="above detection limit" if d else "below detection limit")


def plot_summary(rows: list[dict], sc: dict, path: Path) -> None:
    """Three panels: the confusion matrix (counts); χ²/dof before vs after refinement per case;
    position error before and after refinement relative to the clean-data error per case.
    Cases below the detection limit (oracle λ < 2 × threshold) are drawn hollow."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    conf = sc["confusion"]
    truths = list(conf)
    preds = list(next(iter(conf.values()))) if conf else []
    mat = np.array([[conf[t][p] for p in preds] for t in truths], dtype=float)
    fig, axes = plt.subplots(1, 3, figsize=(17, 5.5), gridspec_kw={"width_ratios": [1.25, 1, 1]})
    ax = axes[0]
    frac = mat / np.maximum(mat.sum(1, keepdims=True), 1)
    ax.imshow(frac, cmap="Blues", vmin=0, vmax=1)
    for i in range(len(truths)):
        for j in range(len(preds)):
            if mat[i, j]:
                ax.text(j, i, f"{int(mat[i, j])}", ha="center", va="center", fontsize=8,
                        color="white" if frac[i, j] > 0.6 else "black")
    ax.set_xticks(range(len(preds)), [_SHORT.get(p, p) for p in preds], rotation=60, fontsize=8)
    ax.set_yticks(range(len(truths)), [_SHORT.get(t, t) for t in truths], fontsize=8)
    ax.set_xlabel("top-ranked finding")
    ax.set_ylabel("concealed effect")
    ax.set_title("(a) confusion matrix (counts)")

    eff = [r for r in rows if r["effect_true"] != "none" and "error" not in r]
    det = np.array([bool(r.get("above_detection_limit", True)) for r in eff])
    ax = axes[1]
    cb = np.array([float(r["chi2_before"]) if _finite(r.get("chi2_before")) else np.nan for r in eff])
    ca = np.array([float(r["chi2_after"]) if _finite(r.get("chi2_after")) else np.nan for r in eff])
    _scatter_by_limit(ax, cb, ca, det, "C0")
    lo, hi = 0.8, max(2.0, float(np.nanmax(cb)) * 1.2) if len(cb) and np.isfinite(cb).any() else 2.0
    ax.plot([lo, hi], [lo, hi], "k:", lw=0.8, label="no change")
    ax.axhspan(1 - CHI2_TOL, 1 + CHI2_TOL, color="C2", alpha=0.15, label=f"target |χ²/dof − 1| ≤ {CHI2_TOL:.0%}")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("χ²/dof, nominal model")
    ax.set_ylabel("χ²/dof, refined model")
    ax.set_title("(b) fit before → after refinement")
    ax.legend(fontsize=7)

    ax = axes[2]
    rel = [(float(r["pos_err_before_um"]) / float(r["pos_err_clean_um"]),
            float(r["pos_err_after_um"]) / float(r["pos_err_clean_um"]), d)
           for r, d in zip(eff, det) if all(_finite(r.get(k)) for k in ("pos_err_before_um", "pos_err_after_um",
                                                                          "pos_err_clean_um"))]
    if rel:
        b_, a_, d_ = map(np.array, zip(*rel))
        _scatter_by_limit(ax, b_, a_, d_, "C1")
        hi = max(2.0, float(b_.max()) * 1.2)
        ax.plot([0.5, hi], [0.5, hi], "k:", lw=0.8, label="no change")
        ax.axhline(POS_FACTOR, color="C3", lw=1, label=f"target: ≤ {POS_FACTOR}× clean")
        ax.set_xscale("log")
        ax.set_yscale("log")
    ax.set_xlabel("position error / clean-data error, nominal model")
    ax.set_ylabel("position error / clean-data error, refined model")
    ax.set_title("(c) geometry before → after refinement")
    ax.legend(fontsize=7)
    fig.suptitle(f"Concealed-effect benchmark: {len(eff)} effect cases, "
                 f"{sum(r['effect_true'] == 'none' for r in rows)} clean")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ---------------------------------------------------------------------------- main

def build_cases(args) -> list[dict]:
    """The cases of a benchmark, interleaved: case 0 of every effect (and clean), then case 1, …
    (clean sets spread evenly among them), so a partial run covers every effect."""
    effects = args.effects or list(EFFECTS)
    bad = [e for e in effects if e not in EFFECTS]
    if bad:
        raise SystemExit(f"--effects: unknown {bad}; expected some of {list(EFFECTS)}")
    boards = args.boards
    bad = [b for b in boards if b not in BOARDS]
    if bad:
        raise SystemExit(f"--boards: unknown {bad}; expected some of {list(BOARDS)}")
    settings = {k: v for k, v in (("T", args.T), ("rate", args.rate)) if v is not None}
    # A case's seed depends only on (base seed, effect, index), so a subset of effects or a
    # smaller count reproduces the same data sets.
    seed_of = lambda e, j: args.seed * 1_000_003 + (EFFECTS.index(e) + 1 if e != "none" else 99) * 10_000 + j  # noqa: E731
    cases = []
    for e in list(effects) + ["none"]:
        n = args.per_effect if e != "none" else args.clean
        for j in range(n):
            cases.append(dict(case_id=f"{e}-{j:03d}", board=boards[j % len(boards)], effect=e,
                              seed=seed_of(e, j), settings=settings, _order=((j + 0.5) / n, len(cases))))
    cases.sort(key=lambda c: c.pop("_order"))
    return cases


def fill_clean_reference(rows: list[dict]) -> None:
    """Without twins, an effect case's clean-data position error is the median error of the clean
    sets of the same board (computed from every clean row present, so it is refreshed as clean
    cases accumulate); rows that already carry a twin's error keep it."""
    for b in set(r["board"] for r in rows):
        ce = [r.get("pos_err_after_um") for r in rows if r["board"] == b and r["effect_true"] == "none"
              and "error" not in r and _finite(r.get("pos_err_after_um"))]
        for r in rows:
            if r["board"] == b and r["effect_true"] != "none" and not _finite(r.get("pos_err_clean_um")):
                r["pos_err_clean_um"] = float(np.median(ce)) if ce else float("nan")


def progress(rows: list[dict], effects=None) -> dict:
    """How many of the cases the issue requires are done: per effect (≥ REQUIRED_PER_EFFECT each)
    and clean (≥ REQUIRED_CLEAN)."""
    effects = list(effects or EFFECTS)
    per = {e: sum(r["effect_true"] == e for r in rows) for e in effects}
    clean = sum(r["effect_true"] == "none" for r in rows)
    req = {e: min(n, REQUIRED_PER_EFFECT) for e, n in per.items()}
    done = sum(req.values()) + min(clean, REQUIRED_CLEAN)
    total = REQUIRED_PER_EFFECT * len(effects) + REQUIRED_CLEAN
    return {"per_effect": per, "clean": clean, "required_done": done, "required_total": total,
            "complete": done >= total}


def _progress_line(pg: dict) -> str:
    short = ", ".join(f"{e} {n}" for e, n in pg["per_effect"].items())
    return (f"required cases done: {pg['required_done']}/{pg['required_total']} "
            f"(≥ {REQUIRED_PER_EFFECT} per effect, ≥ {REQUIRED_CLEAN} clean; have: {short}, clean {pg['clean']})"
            + ("" if pg["complete"] else " — INCOMPLETE: the verdicts below cover the cases done so far"))


def read_rows(path) -> list[dict]:
    """Rows of a cases.csv written by this script, with the types :func:`score` needs."""
    def conv(k, v):
        if v in ("", "None"):
            return None
        if k in ("mismatch_detected", "twin_mismatch_detected"):
            return v == "True"
        if k in ("imu_true", "top_imu", "n_findings", "seed", "T", "K"):
            return int(float(v))
        try:
            return float(v)
        except ValueError:
            return v
    with open(path, newline="") as f:
        rows = [{k: conv(k, v) for k, v in r.items()} for r in csv.DictReader(f)]
    for r in rows:
        if r.get("error") is None:
            r.pop("error", None)
        for k in ("effect_true", "axis_true", "top_axis", "top_axis_scored", "top_effect"):
            if k in r and r[k] is not None:
                r[k] = str(r[k])
        if r.get("top_axis_scored") is None and r.get("top_effect") not in (None, "none"):
            top = {"axis": r.get("top_axis"),
                   "parameters": json.loads(r["top_parameters"]) if r.get("top_parameters") else None}
            r["top_axis_scored"] = _finding_axis(top)
    return rows


def _options(args, detect_kwargs) -> dict:
    twin = args.twin if args.twin == "baseline" else bool(args.twin)
    return {"seed": args.seed, "T": args.T, "rate": args.rate, "boards": list(args.boards), "twin": twin,
            "detect_kwargs": detect_kwargs}


def _open_store(out: Path, options: dict, retry_errors: bool) -> list[dict]:
    """Rows already in ``out/cases.csv`` (checked against ``out/options.json``); creates both
    files for a new benchmark.  With ``retry_errors`` the crashed rows are dropped (rewritten
    without them) so they run again."""
    out.mkdir(parents=True, exist_ok=True)
    csv_path, opt_path = out / "cases.csv", out / "options.json"
    if csv_path.exists():
        if not opt_path.exists():
            raise SystemExit(f"--out: {csv_path} exists without options.json (an older run); use another --out, "
                             f"or --rescore {csv_path}")
        old = json.loads(opt_path.read_text())
        new = json.loads(json.dumps(options))  # as stored (tuples → lists)
        if old.get("twin") is False and new["twin"] == "baseline" and {**old, "twin": "baseline"} == new:
            # adding baseline twins changes no detector result: the stored rows stay valid and
            # get their clean-data reference filled in by backfill_twin_baselines
            opt_path.write_text(json.dumps(options, indent=1))
            old = new
        if old != new:
            diff = {k: (old.get(k), new.get(k)) for k in OPTION_KEYS if old.get(k) != new.get(k)}
            raise SystemExit(f"--out: {out} holds a benchmark run with other options {diff} (stored, given); "
                             "rerun with the same options to resume, or use another --out")
        with open(csv_path, newline="") as f:
            header = next(csv.reader(f), None)
        if header != list(COLUMNS):
            raise SystemExit(f"--out: {csv_path} has other columns than this script writes; use another --out")
        rows = read_rows(csv_path)
        if retry_errors and any("error" in r for r in rows):
            rows = [r for r in rows if "error" not in r]
            _write_rows(csv_path, rows)
        return rows
    opt_path.write_text(json.dumps(options, indent=1))
    _write_rows(csv_path, [])
    return []


def backfill_twin_baselines(rows: list[dict], csv_path: Path, settings: dict) -> int:
    """Fill ``pos_err_clean_um`` (baseline fit of the clean twin) into the effect rows of a store
    that was run without twins; rewrites the CSV once per filled row (a kill loses nothing).
    Returns the number of rows filled."""
    n = 0
    for r in rows:
        if r["effect_true"] == "none" or "error" in r or _finite(r.get("pos_err_clean_um")):
            continue
        t1 = time.perf_counter()
        clean = make_case(r["board"], "none", int(r["seed"]), **settings)
        tr = clean.truth
        ref = int(clean.recording.reference_imu)
        r["pos_err_clean_um"] = twin_baseline_error(clean, ref, np.asarray(tr["true_relative_position"]))
        r["seconds_twin"] = time.perf_counter() - t1
        _write_rows(csv_path, rows)
        n += 1
        print(f"  {r['case']}: clean twin baseline error {r['pos_err_clean_um']:.2f} µm "
              f"({r['seconds_twin']:.0f} s)", flush=True)
    return n


def _write_rows(path: Path, rows: list[dict]) -> None:
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(COLUMNS), extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({c: r.get(c) for c in COLUMNS})


def _append_row(path: Path, row: dict) -> None:
    """One finished case → one line, flushed at once (a killed run loses only unfinished cases)."""
    with open(path, "a", newline="") as f:
        csv.DictWriter(f, fieldnames=list(COLUMNS), extrasaction="ignore").writerow({c: row.get(c) for c in COLUMNS})
        f.flush()
        os.fsync(f.fileno())


def run_cases(args, params: list[dict], on_row, budget_s: float | None = None) -> int:
    """Run ``run_case(**p)`` for every p, calling ``on_row(row)`` as each finishes (in this process
    with ``--workers 0``, else on dask workers, at most one task per worker in flight so that a
    time budget stops cleanly).  New cases are started only while ``budget_s`` (s) lasts.
    Returns the number of cases run."""
    t0 = time.perf_counter()
    within = lambda: budget_s is None or time.perf_counter() - t0 < budget_s  # noqa: E731
    fn = run_case
    done = 0
    with dask_client(args) as client:
        if client is None:
            from _dask import run_single_threaded

            for p in params:
                if not within():
                    break
                on_row(run_single_threaded(globals()["run_case"], p))
                done += 1
            return done
        from distributed import as_completed

        from _dask import run_single_threaded

        slots = max(1, len(client.nthreads()) if getattr(args, "scheduler", None) else int(args.workers))
        queue = list(params)
        ac = as_completed()
        for _ in range(min(slots, len(queue))):
            ac.add(client.submit(run_single_threaded, fn, queue.pop(0), pure=False))
        for fut in ac:
            on_row(fut.result())
            done += 1
            if queue and within():
                ac.add(client.submit(run_single_threaded, fn, queue.pop(0), pure=False))
    return done


def summarize(rows: list[dict], args, out: Path | None, extra: dict | None = None) -> int:
    """Score every row present, print the report and (with ``out``) write summary.json.
    Returns the exit code (1 if a verdict fails)."""
    if not rows:
        print("no finished cases yet")
        return 0
    if not args.twin:
        fill_clean_reference(rows)
    pg = progress(rows, args.effects)
    print("\n" + _progress_line(pg))
    sc = score(rows)
    verdicts = print_report(sc)
    fig = getattr(args, "fig", None) or (out / "summary.png" if out is not None else None)
    if fig is not None:
        plot_summary(rows, sc, Path(fig))
        print(f"figure: {fig}")
    secs = [r["seconds"] for r in rows if _finite(r.get("seconds"))]
    if secs:
        print(f"\ndetect(): median {np.median(secs):.1f} s per recording, max {max(secs):.1f} s "
              f"(over the {len(secs)} rows present)")
    errs = [r for r in rows if "error" in r]
    for r in errs[:3]:
        print(f"case {r['case']} failed: {r['error']}", file=sys.stderr)
    if out is not None:
        summary = {"settings": {k: v for k, v in vars(args).items() if k != "func"}, "progress": pg,
                   "verdicts": verdicts, **(extra or {}), **{k: v for k, v in sc.items()}}
        with open(out / "summary.json", "w") as f:
            json.dump(summary, f, indent=1, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o))
        print(f"rows in {out / 'cases.csv'}; summary in {out / 'summary.json'}")
    return 1 if any(v == "FAIL" for v in verdicts.values()) else 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--per-effect", type=int, default=10, help="data sets per concealed effect (default 10)")
    ap.add_argument("--clean", type=int, default=30, help="clean data sets (default 30)")
    ap.add_argument("--effects", nargs="+", default=None, help=f"effects to conceal (default all: {' '.join(EFFECTS)})")
    ap.add_argument("--boards", nargs="+", default=list(BOARDS), help="boards, used in turn (default all three)")
    ap.add_argument("--T", type=int, default=None, help="samples per recording (default random 1500–3000)")
    ap.add_argument("--rate", type=float, default=None, help="sample rate Hz (default random 100–250)")
    ap.add_argument("--seed", type=int, default=1, help="base seed (default 1)")
    ap.add_argument("--quick", action="store_true",
                    help="mimu8, 2 per effect, 4 clean, T=1500, no twins (explicit options still win); 28 "
                         "detect() calls, ~10 min on one quiet core at ~20 s per call")
    tw = ap.add_mutually_exclusive_group()
    tw.add_argument("--twin", dest="twin", action="store_true", default=None,
                    help="fit each effect case's clean twin too (default, except with --quick)")
    tw.add_argument("--twin-baseline", dest="twin", action="store_const", const="baseline",
                    help="for each effect case fit only the detector's baseline (nominal MAP) on its clean "
                         "twin: the clean-data position error without a second full detect (false alarms "
                         "then come from the dedicated clean sets alone)")
    tw.add_argument("--no-twin", dest="twin", action="store_false",
                    help="skip the clean twins (~40 %% cheaper; the clean-data position error is then the "
                         "median over the clean sets of the same board)")
    ap.add_argument("--alpha", type=float, default=0.01, help="detect(alpha=...) (default 0.01)")
    ap.add_argument("--max-findings", type=int, default=3)
    ap.add_argument("--no-refine", action="store_true", help="detect(refine=False)")
    ap.add_argument("--detect-opt", action="append", default=[], metavar="KEY=VALUE",
                    help="extra keyword for detect(), value parsed as JSON if it can be (repeatable), "
                         "e.g. --detect-opt n_twins=20")
    ap.add_argument("--out", default=None, help="directory for cases.csv (appended, resumable), options.json and "
                                                "summary.json")
    ap.add_argument("--max-cases", type=int, default=None, help="run at most N new cases this time")
    ap.add_argument("--time-budget", type=float, default=None, metavar="S",
                    help="start no new case after S seconds (running ones finish)")
    ap.add_argument("--retry-errors", action="store_true", help="rerun the cases that crashed in an earlier run")
    ap.add_argument("--save-cases", default=None, metavar="DIR", help="also write every recording + truth sidecar")
    ap.add_argument("--generate-only", action="store_true", help="generate (and save) the data, run no detector")
    ap.add_argument("--rescore", default=None, metavar="CSV", help="only score and print a cases.csv of an earlier run")
    ap.add_argument("--fig", default=None, metavar="PNG",
                    help="summary figure (confusion matrix, χ²/dof and position error before/after); default "
                         "OUT/summary.png with --out, none otherwise")
    add_dask_arguments(ap, default_workers=1)
    args = ap.parse_args(argv)
    if args.rescore:
        rows = read_rows(args.rescore)
        opt = Path(args.rescore).with_name("options.json")
        args.twin = json.loads(opt.read_text()).get("twin", True) if opt.exists() else \
            any(r.get("twin_mismatch_detected") is not None for r in rows)
        return summarize(rows, args, None)
    if args.quick:
        given = set(a.split("=")[0] for a in (argv if argv is not None else sys.argv[1:]))
        if "--per-effect" not in given:
            args.per_effect = 2
        if "--clean" not in given:
            args.clean = 4
        if "--boards" not in given:
            args.boards = ["mimu8"]
        if "--T" not in given:
            args.T = 1500
    if args.twin is None:
        args.twin = not args.quick
    if not args.generate_only:
        _detector()  # fail now, clearly, not inside a worker
    if args.save_cases:
        Path(args.save_cases).mkdir(parents=True, exist_ok=True)
    cases = build_cases(args)
    detect_kwargs = dict(alpha=args.alpha, max_findings=args.max_findings, refine=not args.no_refine, seed=0)
    for kv in args.detect_opt:
        if "=" not in kv:
            raise SystemExit(f"--detect-opt: expected KEY=VALUE, got {kv!r}")
        key, v = kv.split("=", 1)
        try:
            detect_kwargs[key] = json.loads(v)
        except ValueError:
            detect_kwargs[key] = v
    params = [dict(**c, twin=args.twin, detect_kwargs=detect_kwargs, save_dir=args.save_cases,
                   generate_only=args.generate_only) for c in cases]

    if args.generate_only:
        t0 = time.perf_counter()
        rows = []
        run_cases(args, params, rows.append)
        errs = [r for r in rows if "error" in r]
        if args.out:
            Path(args.out).mkdir(parents=True, exist_ok=True)
            _write_rows(Path(args.out) / "generated.csv", rows)
        print(f"generated {len(rows)} data sets in {time.perf_counter() - t0:.1f} s ({len(errs)} errors)"
              + (f"; saved to {args.save_cases}" if args.save_cases else ""))
        return 1 if errs else 0

    out = Path(args.out) if args.out else None
    rows = _open_store(out, _options(args, detect_kwargs), args.retry_errors) if out else []
    if out and args.twin == "baseline":
        backfill_twin_baselines(rows, out / "cases.csv", cases[0]["settings"] if cases else {})
    done_ids = {r["case"] for r in rows}
    wanted = {c["case_id"] for c in cases}
    pending = [p for p in params if p["case_id"] not in done_ids]
    if args.max_cases is not None:
        pending = pending[:max(0, int(args.max_cases))]
    print(f"mismatch_proof: {sum(c['effect'] != 'none' for c in cases)} effect cases "
          f"({args.per_effect} × {len(set(c['effect'] for c in cases if c['effect'] != 'none'))} effects), "
          f"{args.clean} clean, boards {args.boards}, "
          f"twins {'baseline fit' if args.twin == 'baseline' else 'on' if args.twin else 'off'}; "
          f"{len(wanted & done_ids)} already done, running {len(pending)} now", flush=True)

    def on_row(row):
        rows.append(row)
        if out:
            _append_row(out / "cases.csv", row)
        extra = f" ({row['error']})" if "error" in row else \
            f" → {row.get('top_effect')} [{row.get('top_imu')}, {row.get('top_axis')}] {row.get('seconds', 0):.0f} s"
        print(f"  {row['case']} ({row['board']}, T={row.get('T')}){extra}", flush=True)

    t0 = time.perf_counter()
    n_run = run_cases(args, pending, on_row, budget_s=args.time_budget)
    wall = time.perf_counter() - t0
    print(f"ran {n_run} case(s) in {wall:.0f} s", flush=True)
    # score the cases of this benchmark definition (rows of other ids, e.g. a larger earlier
    # --per-effect, are kept in the CSV but not scored here)
    mine = [r for r in rows if r["case"] in wanted]
    return summarize(mine, args, out, {"wall_seconds_this_run": wall, "cases_run_this_run": n_run})


if __name__ == "__main__":
    sys.exit(main())
