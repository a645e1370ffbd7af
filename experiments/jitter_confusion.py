"""sampling_jitter versus noise_level: does the detector tell a random sampling instant from noise
larger than stated?  (issue #11; DESIGN §7.2 vocabulary 1.1)

Cases (fixed seeds, default detector options but n_twins/loo_draws reduced, every effect of the
vocabulary tried, at most two findings):

* concealed ``sampling_jitter`` (experiments/_conceal.py, independent generator: exact
  kinematics at jittered instants), widths drawn in 0.1–1 ms, and two at 0.1 ms exactly;
* concealed ``noise_level`` (accelerometer noise × 1.2–2);
* ``noise_level`` on one *gyroscope* (× 1.5), from the package simulator — the sensor that the
  jitter shows on most, so the harder confusion;
* with ``--real``: MIMU4444 experiment 1 (whole, as ``detect`` prepares it), the round-1 evidences of
  the per-IMU jitter and noise candidates (no truth: what the data say).

Writes ``experiments/jitter_confusion.md``::

    PYTHONPATH=. python experiments/jitter_confusion.py [--real]
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import _conceal as C  # noqa: E402

DEG = math.pi / 180
OPTS = dict(n_twins=10, loo_draws=20, n_refit=3, max_findings=2, seed=0)


def _row(tag, truth_eff, truth_imu, truth_val, rep):
    f = [x for x in rep.findings if x.effect != "unexplained"]
    r1 = {x["candidate"]: x.get("evidence") for x in rep.rounds[0]["refits"]} if rep.rounds else {}
    best_j = max((v for k, v in r1.items() if k.startswith("sampling_jitter") and v is not None), default=None)
    best_n = max((v for k, v in r1.items() if k.startswith("noise_level") and v is not None), default=None)
    named = f[0] if f else None
    ok = bool(named) and named.effect == truth_eff and named.model.imu == truth_imu
    est = iv = ""
    if named is not None and named.effect == "sampling_jitter":
        est = f"{named.model.params['width'].item() * 1e3:.4g} ms"
        lo, hi = named.model.stats["width_interval_s"]
        iv = f"[{lo * 1e3:.4g}, {hi * 1e3:.4g}] ms"
        ok = ok and lo <= truth_val <= hi
    elif named is not None and named.effect == "noise_level":
        est = f"×{named.model.params['factor'].item():.3g} ({named.model.which})"
    return {"case": tag, "truth": f"{truth_eff} imu {truth_imu} {truth_val:.4g}",
            "named": "—" if named is None else named.model.label(), "estimate": est, "interval": iv,
            "evidence": "" if named is None else f"{named.evidence:.4g}",
            "jitter_r1": "" if best_j is None else f"{best_j:.4g}", "noise_r1": "" if best_n is None else f"{best_n:.4g}",
            "ok": ok}


def main(argv=None):
    from accel_bayes.mismatch import detect, make_effect
    from accel_bayes.physics.arrays import mimu4444_8
    from accel_bayes.simulate import simulate

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--real", action="store_true", help="also MIMU4444 experiment 1 (about 3 min)")
    ap.add_argument("--out", type=Path, default=HERE / "jitter_confusion.md")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    rows = []
    cases = [("sampling_jitter", s, None) for s in (11, 12, 13, 14)] + [("sampling_jitter", s, 1e-4) for s in (21, 22)]
    cases += [("noise_level", s, None) for s in (11, 12, 13, 14)]
    for eff, seed, mag in cases:
        case = C.make_case("mimu8", eff, seed=seed, T=500, magnitude=mag)
        rep = detect(case.recording, **OPTS)
        rows.append(_row(f"conceal {eff} seed {seed}", eff, case.truth["imu"], case.truth["magnitude"], rep))
        print(rows[-1], flush=True)
    for seed in (31, 32):
        e = make_effect("noise_level", imu=5, sensor="gyro", parameters={"factor": 1.5})
        sim = simulate(mimu4444_8(), "smooth", T=400, rate=200.0, seed=seed, effects=[e], acc_noise_std=0.02,
                       gyro_noise_std=0.1 * DEG)
        rows.append(_row(f"simulate gyro noise seed {seed}", "noise_level", 5, 1.5, detect(sim.recording, **OPTS)))
        print(rows[-1], flush=True)
    n_ok = sum(r["ok"] for r in rows)
    lines = ["# sampling_jitter versus noise_level (issue #11)", "",
             "Regenerate: `PYTHONPATH=. python experiments/jitter_confusion.py"
             + (" --real" if a.real else "") + "` (this file is its output).", "",
             "\n\n".join(__doc__.split("\n\n")[1:3]).strip(), "",
             f"**{n_ok}/{len(rows)} cases named correctly** (right effect, right IMU, and for jitter the true "
             "width inside the 95 % profile interval); confusion "
             f"{100 * (len(rows) - n_ok) / len(rows):.0f} %.", "",
             "| case | truth | named first | estimate | 95 % interval | evidence | round-1 best jitter LR | "
             "round-1 best noise_level LR | ok |", "|---|---|---|---|---|---|---|---|---|"]
    note = ["", "Round-1 columns: the likelihood ratios of the best refitted candidate of each kind in the first "
            "round; blank = none refitted (screen statistic below half the threshold)."]
    for r in rows:
        lines.append(f"| {r['case']} | {r['truth']} | {r['named']} | {r['estimate']} | {r['interval']} | {r['evidence']} | "
                     f"{r['jitter_r1']} | {r['noise_r1']} | {'yes' if r['ok'] else '**no**'} |")
    lines += note
    if a.real:
        sys.path.insert(0, str(HERE))
        from mimu_mismatch import load_recording
        from _data import data_dir

        rec, _ = load_recording(1, data_dir())  # whole: detect prepares it (intrinsics, selection)
        rep = detect(rec, **{**OPTS, "max_findings": 3})
        lines += ["", "## Real data: MIMU4444 experiment 1, whole (every sample the selection keeps)", "",
                  f"Baseline χ²/dof {rep.baseline_fit.chi2_per_dof:.4g}.  Findings: "
                  + ", ".join(f"{f.model.label()} ({f.evidence:.4g})" for f in rep.findings) + ".", "",
                  "Refitted variance candidates per round (evidence = likelihood ratio):", "",
                  "| round | candidate | evidence |", "|---|---|---|"]
        for r in rep.rounds:
            for x in r["refits"]:
                if x["candidate"].startswith(("sampling_jitter", "noise_level")):
                    lines.append(f"| {r['round']} | {x['candidate']} | {x.get('evidence', float('nan')):.4g} |")
        r1 = {x["candidate"]: x.get("evidence") for x in rep.rounds[0]["refits"]} if rep.rounds else {}
        jit = {k: v for k, v in r1.items() if k.startswith("sampling_jitter") and v is not None}
        if jit:
            kj, vj = max(jit.items(), key=lambda kv: kv[1])
            imu = kj[kj.index("imu=") + 4:].rstrip("]")
            same = [v for k, v in r1.items() if k.startswith(f"noise_level[imu={imu},") and v is not None]
            every = [v for k, v in r1.items() if k.startswith("noise_level[sensor=") and v is not None]
            lines += ["", f"Round 1: the strongest jitter candidate {kj} has likelihood ratio {vj:.4g}"
                      + (f"; noise_level on the same IMU {max(same):.4g}" if same else "")
                      + (f"; noise_level on every IMU of a sensor {max(every):.4g}" if every else "")
                      + ".  (An every-IMU jitter is not a vocabulary candidate: DESIGN §7.2 sets imu.)"]
    lines += ["", f"Run time {time.perf_counter() - t0:.0f} s."]
    a.out.write_text("\n".join(lines) + "\n")
    print(f"wrote {a.out}: {n_ok}/{len(rows)} correct")


if __name__ == "__main__":
    main()
