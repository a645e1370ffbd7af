#!/usr/bin/env python3
"""Blind proof of the mismatch detector on MIMU-like multi-effect data (issue #11 item 6).

Each case comes from :func:`_conceal.make_multi_case` — the independent first-principles
simulator, not the package's signal model — and mimics the real MIMU4444 recordings
(``experiments/mimu_mismatch.md``): the mimu8 board at 62.5 Hz, vigorous shaking (RMS |ω|
600–1200 °/s, 0.5–7 Hz), rest noise levels, **linear gyro errors on every IMU** (scale and
cross-axis couplings up to 1.5–2.7 %, biases 0.05–0.5 °/s) and **one new effect** on a random
non-reference IMU: ``sampling_jitter`` (width 0.1–1 ms), ``gyro_nonlinearity`` (k₂ω² = 2–6 σ_g at
the rate peaks) or ``timing_wander`` on the gyro (width 1.1–1.35 ms, correlation 0.70–0.87).
:func:`accel_bayes.mismatch.detect` runs with its defaults on the recording alone.  Per case
three recordings are run:

* the **effect case** (linear gyro errors + the new effect);
* its **clean twin**: the same seed without the new effect (same motion, geometry, linear
  errors and noise draws);
* with ``--control`` (default on), the **control**: the same seed with the new effect but
  without the linear gyro errors — what the new effect alone gives on the same motion.

What counts as the right answer.  The linear gyro errors are vocabulary effects (DESIGN §7.2:
``gyro_scale`` is the "scale-factor / misalignment error", ``gyro_bias`` the offset; the
package's ``gyro_misalignment`` term is reported as ``gyro_scale``), present on every IMU, so a
``gyro_scale``/``gyro_bias`` finding at any IMU is a *correct* finding, never a false one.  The
new effect is then scored on the findings that are not such linear-gyro terms:

* **right effect first** — the first finding that is not ``gyro_scale``/``gyro_bias`` names the
  new effect (``timing_wander``: the extension's name, the detector's own; scored for its IMU
  only — the sensor is the gyro); ``strict`` also demands it is ``findings[0]``;
* **right IMU (and axis)** — that finding sits on the true IMU (and, for ``gyro_nonlinearity``,
  the true gyro axis);
* **false findings** — findings that are neither the new effect at its IMU nor a linear gyro
  term, e.g. a ``timing_wander`` on an IMU without one;
* **clean twin flagged** — the twin's report has a finding other than ``gyro_scale``/
  ``gyro_bias`` (``mismatch_detected`` itself is *expected* on the twins: they do have errors);
* **noise_level ↔ sampling_jitter confusion** — a jitter case whose first non-linear finding is
  ``noise_level`` at the jitter IMU, or a ``sampling_jitter`` finding on a case/twin/IMU without
  jitter;
* **refined χ²/dof within 10 % of 1** — the report's ``refined.chi2_per_dof`` (the baseline's
  where nothing was refined).

Detection limit: a case is above it when its oracle non-centrality λ (Σ over all outputs of
((case − twin)/σ)², ``_conceal.oracle_noncentrality``: what the new effect alone adds, the
twin sharing everything else) is at least 2 × the report's threshold (the rule of
``mismatch_proof.py``).

Run (resumable: finished cases are appended to ``OUT/cases.csv`` at once, a rerun skips them)::

    OMP_NUM_THREADS=1 python3 experiments/mismatch_multi.py --cases 15 --workers 1
    python3 experiments/mismatch_multi.py --rescore   # score the stored rows, rewrite the .md

One detect takes ~25–40 s here (T 3000–5000, 8 IMUs, one thread), so a case with its twin and
control ~1.5–2 min.
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

from _conceal import DEG, MULTI_EFFECTS, MULTI_RANGES, make_multi_case, oracle_noncentrality  # noqa: E402
from _dask import add_dask_arguments, dask_client, run_single_threaded  # noqa: E402
from mismatch_proof import DETECTABLE_FACTOR, _as_dict, _finding_axis, _lookup  # noqa: E402

OUT_DEFAULT = HERE / "results" / "mismatch_multi"
DOC_DEFAULT = HERE / "mismatch_multi.md"
LINEAR_NAMES = ("gyro_scale", "gyro_bias")  # the vocabulary names of the linear gyro errors
CHI2_TOL = 0.10
TARGETS = {"right_first": 0.90, "right_loc": 0.90, "confusion": 0.10, "twin_flagged": 0.05, "chi2": 0.90}
RUNS = ("", "twin_", "control_")  # column prefixes: effect case, clean twin, control
_RUN_COLS = ("seconds", "mismatch_detected", "threshold", "chi2_before", "chi2_after", "chi2_after_stated", "findings")
COLUMNS = ("case", "seed", "effect_true", "imu_true", "axis_true", "magnitude", "correlation", "T", "sigma_a",
           "sigma_g_dps", "omega_rms_dps", "lambda_oracle", "lambda_oracle_control") + \
    tuple(p + c for p in RUNS for c in _RUN_COLS) + ("error",)
CLEAN_COLUMNS = ("case", "seed", "T") + _RUN_COLS + ("error",)
OPTION_KEYS = ("seed", "T", "control", "linear", "detect_kwargs")
MARKER = "<!-- reading: hand-written below this line, kept when the document is regenerated -->"


# ---------------------------------------------------------------------------- one case

def _short_findings(rep: dict) -> list[dict]:
    """The findings as stored: name, IMU, axis (a 3-vector parameter's largest component where
    the finding has no axis), evidence and the scalar parameters."""
    out = []
    for f in rep.get("findings") or []:
        par = {k: v for k, v in (f.get("parameters") or {}).items() if isinstance(v, (int, float, str))}
        out.append({"effect": f.get("effect"), "imu": f.get("imu"), "axis": _finding_axis(f),
                    "evidence": f.get("evidence"), "parameters": par})
    return out


def _run_detect(rec, detect_kwargs: dict, prefix: str, row: dict) -> None:
    from accel_bayes.mismatch import detect

    t0 = time.perf_counter()
    rep = _as_dict(detect(rec, **detect_kwargs))
    row[prefix + "seconds"] = time.perf_counter() - t0
    row[prefix + "mismatch_detected"] = bool(rep.get("mismatch_detected"))
    row[prefix + "threshold"] = rep.get("threshold")
    row[prefix + "chi2_before"] = _lookup(rep, ("baseline", "chi2_per_dof"))
    after = _lookup(rep, ("refined", "chi2_per_dof"))
    row[prefix + "chi2_after"] = row[prefix + "chi2_before"] if after is None else after
    row[prefix + "chi2_after_stated"] = _lookup(rep, ("refined", "chi2_per_dof_stated"))
    row[prefix + "findings"] = json.dumps(_short_findings(rep))


def run_case(case_id: str, seed: int, effect: str, T: int | None, control: bool, detect_kwargs: dict,
             linear: float = 1.0) -> dict:
    """Generate the effect case, its clean twin (and the control), detect on each blind, store.
    ``linear`` scales the linear gyro errors of the effect case and the twin (1 = real size)."""
    row = {"case": case_id, "seed": seed, "effect_true": effect}
    try:
        case = make_multi_case(seed, effect, T=T, gyro_linear=linear)
        twin = make_multi_case(seed, "none", T=T, gyro_linear=linear)
        tr, st = case.truth, case.truth["settings"]
        row.update(imu_true=tr["imu"], axis_true=tr["axis"], magnitude=tr["magnitude"],
                   correlation=tr["parameters"].get("correlation"), T=st["T"], sigma_a=st["sigma_a"],
                   sigma_g_dps=st["sigma_g"] / DEG, omega_rms_dps=st["omega_rms_achieved"] / DEG,
                   lambda_oracle=oracle_noncentrality(case, twin))
        _run_detect(case.recording, detect_kwargs, "", row)
        _run_detect(twin.recording, detect_kwargs, "twin_", row)
        if control:
            ctl = make_multi_case(seed, effect, T=T, gyro_linear=False)
            ctl0 = make_multi_case(seed, "none", T=T, gyro_linear=False)
            row["lambda_oracle_control"] = oracle_noncentrality(ctl, ctl0)
            _run_detect(ctl.recording, detect_kwargs, "control_", row)
    except Exception as exc:  # a crash is a failed case, not a crashed benchmark
        row["error"] = f"{type(exc).__name__}: {exc}"
        row["traceback"] = traceback.format_exc(limit=6)
    return row


def run_clean(case_id: str, seed: int, T: int | None, detect_kwargs: dict) -> dict:
    """The truly clean set of a seed: no linear gyro errors, no new effect (the control's twin)."""
    row = {"case": case_id, "seed": seed}
    try:
        rec = make_multi_case(seed, "none", T=T, gyro_linear=False).recording
        row["T"] = rec.T
        _run_detect(rec, detect_kwargs, "", row)
    except Exception as exc:
        row["error"] = f"{type(exc).__name__}: {exc}"
    return row


# ---------------------------------------------------------------------------- scoring

def _hit(f: dict, r: dict) -> bool:
    """Whether finding ``f`` names the case's new effect where it is."""
    if f.get("effect") != r["effect_true"] or f.get("imu") is None or int(f["imu"]) != int(r["imu_true"]):
        return False
    return r["effect_true"] != "gyro_nonlinearity" or f.get("axis") == r["axis_true"]


def _nonlinear(fs: list[dict]) -> list[dict]:
    return [f for f in fs if f.get("effect") not in LINEAR_NAMES]


def score_run(r: dict, prefix: str) -> dict | None:
    """Scores of one recording (effect case: prefix ''; control: 'control_') of row ``r``."""
    if r.get(prefix + "findings") is None:
        return None
    fs = json.loads(r[prefix + "findings"])
    nl = _nonlinear(fs)
    first = nl[0] if nl else None
    eff = r["effect_true"]
    loc_ok = first is not None and first.get("imu") is not None and int(first["imu"]) == int(r["imu_true"]) and \
        (eff != "gyro_nonlinearity" or first.get("axis") == r["axis_true"])
    # the must-show confusion: jitter named noise_level (no case hides a noise_level, so the
    # other direction cannot occur here); spurious jitter findings are counted separately
    jitter_conf = eff == "sampling_jitter" and any(
        f.get("effect") == "noise_level" and f.get("imu") is not None and int(f["imu"]) == int(r["imu_true"])
        for f in fs)
    spurious_jitter = any(f.get("effect") == "sampling_jitter" and not _hit(f, r) for f in fs)
    # an ``unexplained`` finding on the effect's own IMU is the rest of that effect (not a false
    # name); elsewhere it is a false finding
    own = lambda f: f.get("imu") is not None and int(f["imu"]) == int(r["imu_true"])  # noqa: E731
    chi2 = r.get(prefix + "chi2_after")
    return {
        "first_nonlinear": None if first is None else f"{first['effect']}[{first.get('imu')}]",
        "right_first": first is not None and _hit(first, r),
        "right_first_strict": bool(fs) and _hit(fs[0], r),
        "right_loc": loc_ok,
        "found": any(_hit(f, r) for f in fs),
        "rank": next((j + 1 for j, f in enumerate(fs) if _hit(f, r)), None),
        "linear_imus": sorted({int(f["imu"]) for f in fs if f.get("effect") in LINEAR_NAMES and f.get("imu") is not None}),
        "false": [f"{f['effect']}[{f.get('imu')}]" for f in nl
                  if not _hit(f, r) and not (f.get("effect") == "unexplained" and own(f))],
        "unexplained_own_imu": any(f.get("effect") == "unexplained" and own(f) for f in fs),
        "confusion": bool(jitter_conf),
        "spurious_jitter": spurious_jitter,
        "chi2_ok": chi2 is not None and abs(float(chi2) - 1.0) <= CHI2_TOL,
    }


def score_twin(r: dict) -> dict | None:
    if r.get("twin_findings") is None:
        return None
    fs = json.loads(r["twin_findings"])
    nl = _nonlinear(fs)
    chi2 = r.get("twin_chi2_after")
    return {"flagged": bool(nl), "false": [f"{f['effect']}[{f.get('imu')}]" for f in nl],
            "linear_imus": sorted({int(f["imu"]) for f in fs if f.get("effect") in LINEAR_NAMES}),
            "confusion": any(f.get("effect") == "noise_level" for f in fs),
            "spurious_jitter": any(f.get("effect") == "sampling_jitter" for f in fs),
            "chi2_ok": chi2 is not None and abs(float(chi2) - 1.0) <= CHI2_TOL}


def _frac(xs) -> tuple:
    xs = [bool(x) for x in xs]
    return (sum(xs) / len(xs) if xs else float("nan"), sum(xs), len(xs))


def _fmt(fr) -> str:
    v, k, n = fr
    return f"{k}/{n} = {100 * v:.0f} %" if n else "n/a"


def _above(r: dict, lam_key: str = "lambda_oracle") -> bool:
    thr = r.get("threshold") or 24.0
    lam = r.get(lam_key)
    return lam is None or float(lam) >= DETECTABLE_FACTOR * float(thr)


def summarize(rows: list[dict]) -> dict:
    """Every must-show figure, per effect and overall, for the effect cases, the controls and the
    twins."""
    ok = [r for r in rows if r.get("error") is None]
    out = {"n_rows": len(rows), "errors": len(rows) - len(ok), "groups": {}}
    for which, prefix, lam in (("effect cases (linear gyro errors + new effect)", "", "lambda_oracle"),
                               ("controls (new effect alone, same motion)", "control_", "lambda_oracle_control")):
        g = {}
        for eff in list(MULTI_EFFECTS) + ["all"]:
            rs = [r for r in ok if (eff == "all" or r["effect_true"] == eff) and r.get(prefix + "findings") is not None]
            above = [r for r in rs if _above(r, lam)]
            sc = [score_run(r, prefix) for r in above]
            g[eff] = {"n": len(rs), "below_limit": len(rs) - len(above),
                      "right_first": _frac(s["right_first"] for s in sc),
                      "right_first_strict": _frac(s["right_first_strict"] for s in sc),
                      "right_loc": _frac(s["right_loc"] for s in sc),
                      "found": _frac(s["found"] for s in sc),
                      "with_false": _frac(bool(s["false"]) for s in sc),
                      "confusion": _frac(score_run(r, prefix)["confusion"] for r in rs
                                         if r["effect_true"] == "sampling_jitter"),
                      "spurious_jitter": _frac(score_run(r, prefix)["spurious_jitter"] for r in rs),
                      "unexplained_own_imu": _frac(s["unexplained_own_imu"] for s in sc),
                      "chi2_ok": _frac(score_run(r, prefix)["chi2_ok"] for r in rs)}
        out["groups"][which] = g
    tw = [score_twin(r) for r in ok if r.get("twin_findings") is not None]
    out["twins"] = {"n": len(tw), "flagged": _frac(s["flagged"] for s in tw),
                    "mismatch_detected": _frac(r.get("twin_mismatch_detected") for r in ok
                                               if r.get("twin_findings") is not None),
                    "confusion": _frac(s["confusion"] for s in tw),
                    "spurious_jitter": _frac(s["spurious_jitter"] for s in tw), "chi2_ok": _frac(s["chi2_ok"] for s in tw)}
    return out


def summarize_clean(rows: list[dict]) -> dict:
    ok = [r for r in rows if r.get("error") is None]
    return {"n": len(ok), "errors": len(rows) - len(ok), "flagged": _frac(r.get("mismatch_detected") for r in ok),
            "chi2_ok": _frac(r.get("chi2_after") is not None and abs(float(r["chi2_after"]) - 1) <= CHI2_TOL
                             for r in ok),
            "findings": [f"{r['case']}: {_cell(r.get('findings'))}" for r in ok if r.get("mismatch_detected")]}


def _verdict(v: float, target: float, upper: bool = False) -> str:
    if v != v:
        return "n/a"
    return "PASS" if (v <= target if upper else v >= target) else "FAIL"


# ---------------------------------------------------------------------------- store

def read_rows(path: Path) -> list[dict]:
    def conv(k, v):
        if v in ("", "None"):
            return None
        if k.endswith("mismatch_detected"):
            return v == "True"
        if k in ("seed", "imu_true", "T"):
            return int(float(v))
        if k in ("case", "effect_true", "axis_true", "error") or k.endswith("findings"):
            return v
        try:
            return float(v)
        except ValueError:
            return v
    if not path.exists():
        return []
    with open(path, newline="") as f:
        return [{k: conv(k, v) for k, v in r.items()} for r in csv.DictReader(f)]


def _append_row(path: Path, row: dict, columns=COLUMNS) -> None:
    new = not path.exists()
    with open(path, "a", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(columns), extrasaction="ignore")
        if new:
            w.writeheader()
        w.writerow({c: row.get(c) for c in columns})
        f.flush()
        os.fsync(f.fileno())


def build_cases(n: int, base_seed: int) -> list[dict]:
    """Case j hides MULTI_EFFECTS[j mod 3] (interleaved, so a partial run covers every effect);
    its seed depends only on (base seed, j)."""
    return [dict(case_id=f"{MULTI_EFFECTS[j % 3]}-{j:03d}", seed=base_seed * 1_000_003 + 700_000 + j,
                 effect=MULTI_EFFECTS[j % 3]) for j in range(n)]


# ---------------------------------------------------------------------------- document

def _cell(fs_json, limit: int = 4) -> str:
    if fs_json is None:
        return "–"
    fs = json.loads(fs_json)
    if not fs:
        return "none"
    parts = []
    for f in fs[:limit]:
        ax = f"{f['axis']}" if f.get("axis") else ""
        parts.append(f"{f['effect']}[{f.get('imu')}{ax}] {float(f['evidence']):.2g}")
    return "; ".join(parts)


def _rel(p: Path) -> str:
    try:
        return str(Path(p).resolve().relative_to(HERE.parent))
    except ValueError:
        return str(p)


def _settings_line() -> str:
    """The generator's ranges in the units people read them in."""
    R = MULTI_RANGES
    return (f"Settings (`_conceal.MULTI_RANGES`): mimu8, {R['rate']} Hz, T {R['T'][0]}–{R['T'][1]}; σ_a "
            f"{R['sigma_a'][0]}–{R['sigma_a'][1]} m/s², σ_g {R['sigma_g'][0]}–{R['sigma_g'][1]} rad/s; RMS |ω| "
            f"{R['omega_rms'][0] / DEG:.0f}–{R['omega_rms'][1] / DEG:.0f} °/s from {R['freq_range'][0]}–"
            f"{R['freq_range'][1]} Hz sinusoids, RMS origin acceleration {R['acc_rms'][0]:g}–{R['acc_rms'][1]:g} m/s²; "
            f"every IMU: gyro error matrix with largest entry {100 * R['gyro_linear_max'][0]:.1f}–"
            f"{100 * R['gyro_linear_max'][1]:.1f} %, biases {R['gyro_bias'][0] / DEG:g}–{R['gyro_bias'][1] / DEG:g} °/s; "
            f"new effect: sampling_jitter width {1e3 * R['sampling_jitter'][0]:g}–{1e3 * R['sampling_jitter'][1]:g} ms, "
            f"gyro_nonlinearity k2·max ω² = {R['gyro_nonlinearity'][0]:g}–{R['gyro_nonlinearity'][1]:g} σ_g, "
            f"timing_wander (gyro) width {1e3 * R['timing_wander'][0]:g}–{1e3 * R['timing_wander'][1]:g} ms, "
            f"correlation {R['timing_wander_correlation'][0]}–{R['timing_wander_correlation'][1]}.")


def _wander_lines(rows: list[dict]) -> list[str]:
    """What the detector calls the linear gyro errors: the ``timing_wander`` findings of the clean
    twins (which have no timing error at all), their parameters beside the real data's, and
    whether they sit on the IMUs whose gyro error differs most from the board's mean error
    (‖E_k − Ē‖_F, E regenerated from the seed: the part of the errors a common rate cannot
    absorb — a heuristic, the fit's rate is a weighted estimate)."""
    widths, rhos, hits, n_tw = [], [], 0, 0
    for r in rows:
        if r.get("error") or r.get("twin_findings") is None:
            continue
        tw = [f for f in json.loads(r["twin_findings"]) if f.get("effect") == "timing_wander"]
        widths += [float(f["parameters"]["width"]) for f in tw if "width" in f["parameters"]]
        rhos += [float(f["parameters"]["correlation"]) for f in tw if "correlation" in f["parameters"]]
        if tw:
            E = np.asarray(make_multi_case(int(r["seed"]), "none", T=200).truth["gyro_linear"]["matrix"])
            dev = np.linalg.norm(E - E.mean(0), axis=(1, 2))
            top = set(np.argsort(-dev)[:len(tw)].tolist())
            hits += sum(int(f["imu"]) in top for f in tw)
            n_tw += len(tw)
    if not widths:
        return []
    return [f"**The linear gyro errors, as the detector names them.** The clean twins (linear gyro errors only, no "
            f"timing error) get {n_tw} `timing_wander` findings: width {1e3 * min(widths):.2f}–{1e3 * max(widths):.2f} ms "
            f"(median {1e3 * float(np.median(widths)):.2f}), correlation {min(rhos):.2f}–{max(rhos):.2f} (median "
            f"{float(np.median(rhos)):.2f}) — the real MIMU data gave 1.11–1.35 ms and 0.70–0.87. {hits}/{n_tw} of them "
            "sit on the IMUs whose error matrix differs most from the board's mean (‖E_k − Ē‖_F, as many top IMUs as "
            "wander findings).", ""]


def write_doc(rows: list[dict], sm: dict, doc: Path, command: str, options: dict, csv_path: Path,
              clean: list[dict] | None = None) -> None:
    old = doc.read_text() if doc.exists() else ""
    reading = old[old.index(MARKER):] if MARKER in old else MARKER + "\n"
    L = ["# Blind multi-effect proof on MIMU-like data (issue #11 item 6)", "",
         f"Generated by `{command}` (rows in `{_rel(csv_path)}`; the same command with `--rescore` regenerates "
         "this file from them). "
         "Data: `experiments/_conceal.py:make_multi_case` (independent first-principles simulator); detector: "
         f"`accel_bayes.mismatch.detect` with its defaults ({json.dumps(options['detect_kwargs'])}), blind. "
         f"Linear gyro errors of the effect cases and twins: {options.get('linear', 1.0):g} × the real size.", "",
         _settings_line() + " Scoring rules: the script's docstring (linear gyro terms `gyro_scale`/`gyro_bias` are correct "
         f"findings; detection limit: oracle λ ≥ {DETECTABLE_FACTOR:g} × threshold).", ""]
    L += ["## Must-show verdicts", ""]
    for which, g in sm["groups"].items():
        a = g["all"]
        L += [f"**{which}** — {a['n']} cases, {a['below_limit']} below the detection limit:", "",
              "| effect | n (below limit) | right effect first (non-linear-gyro findings) | strict: findings[0] | "
              "right IMU (axis) | new effect named anywhere | with a false finding | `unexplained` on the effect's "
              "IMU | jitter named noise_level (jitter cases) | a spurious sampling_jitter | refined χ²/dof within 10 % |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
        for eff, d in g.items():
            L.append(f"| {eff} | {d['n']} ({d['below_limit']}) | {_fmt(d['right_first'])} | "
                     f"{_fmt(d['right_first_strict'])} | {_fmt(d['right_loc'])} | {_fmt(d['found'])} | "
                     f"{_fmt(d['with_false'])} | {_fmt(d['unexplained_own_imu'])} | {_fmt(d['confusion'])} | "
                     f"{_fmt(d['spurious_jitter'])} | {_fmt(d['chi2_ok'])} |")
        L.append("")
        L += [f"- [{_verdict(a['right_first'][0], TARGETS['right_first'])}] right effect first ≥ 90 % "
              f"(per effect above: " + ", ".join(f"{e} {_fmt(g[e]['right_first'])}" for e in MULTI_EFFECTS) + ")",
              f"- [{_verdict(a['right_loc'][0], TARGETS['right_loc'])}] right IMU (and axis) ≥ 90 %: "
              f"{_fmt(a['right_loc'])}",
              f"- [{_verdict(a['confusion'][0], TARGETS['confusion'], upper=True)}] noise_level ↔ sampling_jitter "
              f"confusions ≤ 10 %: jitter named noise_level {_fmt(a['confusion'])} of the jitter cases (no case hides "
              f"a noise_level); besides, a sampling_jitter finding where there is none in {_fmt(a['spurious_jitter'])}",
              f"- [{_verdict(a['chi2_ok'][0], TARGETS['chi2'])}] refined χ²/dof within 10 % of 1 in ≥ 90 %: "
              f"{_fmt(a['chi2_ok'])}", ""]
    t = sm["twins"]
    L += [f"**Clean twins** (linear gyro errors only) — {t['n']}: flagged (a finding other than "
          f"`gyro_scale`/`gyro_bias`) {_fmt(t['flagged'])} "
          f"[{_verdict(t['flagged'][0], TARGETS['twin_flagged'], upper=True)}, target ≤ 5 %]; "
          f"`mismatch_detected` {_fmt(t['mismatch_detected'])} (expected: they have errors); a noise_level "
          f"finding {_fmt(t['confusion'])}, a sampling_jitter finding {_fmt(t['spurious_jitter'])}; refined χ²/dof within 10 % {_fmt(t['chi2_ok'])}.", ""]
    if clean:
        c = summarize_clean(clean)
        L += [f"**Truly clean sets** (the controls' twins: no linear gyro errors, no new effect) — {c['n']}: "
              f"`mismatch_detected` {_fmt(c['flagged'])} "
              f"[{_verdict(c['flagged'][0], TARGETS['twin_flagged'], upper=True)}, target ≤ 5 %]"
              + (f" ({'; '.join(c['findings'])})" if c["findings"] else "")
              + f"; refined χ²/dof within 10 % {_fmt(c['chi2_ok'])}.", ""]
    L += _wander_lines(rows)
    secs = [float(r[p + "seconds"]) for r in rows for p in RUNS if r.get(p + "seconds") is not None]
    if secs:
        L += [f"detect(): median {np.median(secs):.0f} s per recording (max {max(secs):.0f} s, {len(secs)} "
              "recordings, one thread on the shared 2-core machine).", ""]
    L += ["## Per case", "",
          "Findings as `effect[IMU axis] evidence`, ranked; λ = oracle non-centrality of the new effect (effect "
          "case vs twin; control vs its own twin).", "",
          "| case | IMU (axis) | size | T | RMS \\|ω\\| °/s | σ_g °/s | λ | effect case: findings | χ²/dof before → "
          "after | clean twin: findings | twin χ²/dof after | control: findings | control χ²/dof after |",
          "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if r.get("error"):
            L.append(f"| {r['case']} | error: {r['error']} |||||||||||| ")
            continue
        size = (f"w {1e3 * float(r['magnitude']):.2f} ms" + (f", ρ {float(r['correlation']):.2f}"
                                                            if r.get("correlation") is not None else "")
                if r["effect_true"] != "gyro_nonlinearity" else f"k2 {float(r['magnitude']):.2e}")
        f2 = lambda x: "–" if x is None else f"{float(x):.3g}"  # noqa: E731
        L.append(f"| {r['case']} | {r['imu_true']}{r.get('axis_true') or ''} | {size} | {r['T']} | "
                 f"{float(r['omega_rms_dps']):.0f} | {float(r['sigma_g_dps']):.3f} | {float(r['lambda_oracle']):.3g} | "
                 f"{_cell(r.get('findings'))} | {f2(r.get('chi2_before'))} → {f2(r.get('chi2_after'))} | "
                 f"{_cell(r.get('twin_findings'))} | {f2(r.get('twin_chi2_after'))} | "
                 f"{_cell(r.get('control_findings'))} | {f2(r.get('control_chi2_after'))} |")
    L += ["", reading.rstrip() + "\n"]
    doc.write_text("\n".join(L))


def print_summary(sm: dict) -> None:
    for which, g in sm["groups"].items():
        print(f"\n{which}")
        for eff, d in g.items():
            print(f"  {eff:>18} n {d['n']:>2} (below {d['below_limit']})  first {_fmt(d['right_first']):>13}  "
                  f"strict {_fmt(d['right_first_strict']):>13}  loc {_fmt(d['right_loc']):>13}  "
                  f"found {_fmt(d['found']):>13}  false {_fmt(d['with_false']):>13}  conf {_fmt(d['confusion']):>13}  "
                  f"spur.jit {_fmt(d['spurious_jitter']):>13}"
                  f"  χ² {_fmt(d['chi2_ok']):>13}")
    t = sm["twins"]
    print(f"\nclean twins {t['n']}: flagged {_fmt(t['flagged'])}; mismatch_detected {_fmt(t['mismatch_detected'])}; "
          f"χ² ok {_fmt(t['chi2_ok'])}")


# ---------------------------------------------------------------------------- main

def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", type=int, default=15, help="effect cases (interleaved over the three effects; "
                                                          "default 15)")
    ap.add_argument("--seed", type=int, default=1, help="base seed (default 1)")
    ap.add_argument("--T", type=int, default=None, help="samples per recording (default random 3000–5000)")
    ap.add_argument("--no-control", dest="control", action="store_false",
                    help="skip the controls (the new effect without the linear gyro errors)")
    ap.add_argument("--linear", type=float, default=1.0,
                    help="factor on the linear gyro errors of the effect cases and twins (default 1: the real "
                         "magnitudes; e.g. 0.1 to see how small they must be for the detector to cope; use "
                         "another --out and --doc)")
    ap.add_argument("--clean", type=int, default=0, metavar="N",
                    help="also run N truly clean sets (seeds of cases 0..N-1 without linear gyro errors or new "
                         "effect; OUT/clean.csv), after the cases")
    ap.add_argument("--out", default=str(OUT_DEFAULT), help="directory of cases.csv and options.json")
    ap.add_argument("--doc", default=str(DOC_DEFAULT), help="the markdown written from the rows")
    ap.add_argument("--max-cases", type=int, default=None, help="run at most N new cases this time")
    ap.add_argument("--time-budget", type=float, default=None, metavar="S", help="start no new case after S seconds")
    ap.add_argument("--rescore", action="store_true", help="only score the stored rows and rewrite --doc")
    add_dask_arguments(ap, default_workers=1)
    args = ap.parse_args(argv)
    out, doc = Path(args.out), Path(args.doc)
    csv_path, opt_path, clean_path = out / "cases.csv", out / "options.json", out / "clean.csv"
    detect_kwargs = {}  # the detector's defaults: blind
    options = {"seed": args.seed, "T": args.T, "control": bool(args.control), "linear": args.linear,
               "detect_kwargs": detect_kwargs}
    command = "OMP_NUM_THREADS=1 python3 experiments/mismatch_multi.py " + " ".join(
        a for a in (argv if argv is not None else sys.argv[1:]) if a != "--rescore")
    if args.rescore:
        if opt_path.exists():
            options = json.loads(opt_path.read_text())
            command = options.get("command", command)
        rows = read_rows(csv_path)
        sm = summarize(rows)
        print_summary(sm)
        write_doc(rows, sm, doc, command, options, csv_path, read_rows(clean_path))
        print(f"wrote {doc}")
        return 0
    out.mkdir(parents=True, exist_ok=True)
    if opt_path.exists():
        old = json.loads(opt_path.read_text())
        if {k: old.get(k, 1.0 if k == "linear" else None) for k in OPTION_KEYS} != json.loads(json.dumps(options)):
            raise SystemExit(f"--out: {out} holds a run with other options {old}; use another --out")
    opt_path.write_text(json.dumps({**options, "command": command}, indent=1))
    rows = read_rows(csv_path)
    done = {r["case"] for r in rows}
    todo = [c for c in build_cases(args.cases, args.seed) if c["case_id"] not in done]
    if args.max_cases is not None:
        todo = todo[:max(0, args.max_cases)]

    params = [dict(**c, T=args.T, control=args.control, detect_kwargs=detect_kwargs, linear=args.linear)
              for c in todo]
    done_clean = {r["case"] for r in read_rows(clean_path)}
    clean_todo = [dict(case_id="clean-" + c["case_id"], seed=c["seed"], T=args.T, detect_kwargs=detect_kwargs)
                  for c in build_cases(args.clean, args.seed) if "clean-" + c["case_id"] not in done_clean]
    tasks = [(run_case, p) for p in params] + [(run_clean, p) for p in clean_todo]
    print(f"mismatch_multi: {args.cases} cases, {len(done)} done, running {len(todo)} (+ {len(clean_todo)} clean)",
          flush=True)
    t0 = time.perf_counter()
    within = lambda: args.time_budget is None or time.perf_counter() - t0 < args.time_budget  # noqa: E731

    def on_row(row):
        if row["case"].startswith("clean-"):
            _append_row(clean_path, row, CLEAN_COLUMNS)
            print(f"  {row['case']} ({row.get('seconds', 0) or 0:.0f} s): " + (row.get("error") or _cell(row.get("findings"))),
                  flush=True)
            return
        rows.append(row)
        _append_row(csv_path, row)
        s = score_run(row, "") if row.get("findings") else None
        print(f"  {row['case']} ({row.get('seconds', 0) or 0:.0f}+{row.get('twin_seconds', 0) or 0:.0f}+"
              f"{row.get('control_seconds', 0) or 0:.0f} s): " + (row.get("error") or
              f"first non-linear {s['first_nonlinear']} (truth {row['effect_true']}[{row['imu_true']}]) "
              f"twin {_cell(row.get('twin_findings'), 3)}"), flush=True)

    with dask_client(args) as client:
        if client is None:
            for fn, p in tasks:
                if not within():
                    break
                on_row(run_single_threaded(fn, p))
        else:
            from distributed import as_completed

            queue, ac = list(tasks), as_completed()
            for _ in range(min(max(1, int(args.workers)), len(queue))):
                ac.add(client.submit(run_single_threaded, *queue.pop(0), pure=False))
            for fut in ac:
                on_row(fut.result())
                if queue and within():
                    ac.add(client.submit(run_single_threaded, *queue.pop(0), pure=False))
    sm = summarize(rows)
    print_summary(sm)
    write_doc(rows, sm, doc, command, options, csv_path, read_rows(clean_path))
    print(f"ran {len(rows) - len(done)} case(s) in {time.perf_counter() - t0:.0f} s; wrote {doc}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
