"""The mismatch report: DESIGN §7.2 format v1 (``report.json``) and a human report with figures.

:class:`MismatchReport` is what :func:`accel_bayes.mismatch.detect` returns.  The contract keys
of §7.2 are exactly those of :meth:`MismatchReport.to_dict`'s top level (``schema``,
``mismatch_detected``, ``threshold``, ``baseline``, ``findings``, ``refined`` and, vocabulary 1.1,
``budget``: the residual budget per sensor and motion regime, :mod:`accel_bayes.mismatch.budget`;
``refined.chi2_per_dof_stated`` is the refined mean model's χ²/dof under the stated noise, also
kept under its earlier name ``chi2_per_dof_stated_noise``); everything else
(located-excess tables, per-regime statistics, PPC, screening and refit logs, geometry before
and after, ELPD, timings) lives under the added key ``details`` or as added keys inside the
contract blocks, which §7.2 allows.  :func:`accel_bayes.data.mismatch_report.validate_report` checks a dict against the contract
(the schema, reading and writing of ``report.json`` live in :mod:`accel_bayes.data.mismatch_report`).

Attribute access mirrors the JSON: ``report.baseline`` and ``report.refined`` are the contract
blocks (dicts; ``refined`` is None on clean data or with ``refine=False``), ``report.findings``
the ranked :class:`Finding` list (``finding.effect`` the name, ``finding.model`` the fitted
:class:`~accel_bayes.physics.effects.Effect`; ``finding["evidence"]`` works too), and
``report.baseline_fit`` / ``report.refined_fit`` the :class:`~accel_bayes.mismatch.model.ModelFit`
objects behind them.
"""
from __future__ import annotations

import json
import warnings
from dataclasses import dataclass, field
from pathlib import Path

from ..data.mismatch_report import SCHEMA, report_json, write_report_json
from ..data.outputs import to_jsonable, write_text
from ..errors import UserError

__all__ = ["Finding", "MismatchReport"]




# ------------------------------------------------------------------------------ finding

@dataclass
class Finding:
    """One reported finding (§7.2 ``findings`` entry).

    model : the fitted :class:`~accel_bayes.physics.effects.Effect` (or ``Unexplained``).
    evidence : 2·(log L with − log L without) at the fitted optima (restricted likelihood ratio
        for ``noise_level``; the profiled exact marginal likelihood ratio for ``sampling_jitter``;
        the located-excess statistic for ``unexplained``).
    df : its degrees of freedom; log10_p : log10 of its χ²_df tail probability (for
        ``sampling_jitter``, a boundary hypothesis, of the ½χ²₀ + ½χ²₁ mixture).
    where : {"regime": …, "time_s": [t0, t1] or None, …}.
    """

    effect: object
    evidence: float
    df: int
    log10_p: float
    where: dict
    explanation: str
    screen_statistic: float | None = None
    orientations: object = field(default=None, repr=False)
    extra: dict = field(default_factory=dict)
    #: values the detector reports in place of the model's own (a parameter the data do not
    #: identify is null here while the model keeps its neutral value)
    parameters_reported: dict = field(default_factory=dict)

    def __post_init__(self):
        self.model = self.effect
        self.effect = self.model.vocabulary_name or self.model.name  # DESIGN §7.2 vocabulary

    @property
    def imu(self):
        return self.model.imu

    @property
    def axis(self):
        return self.model.axis

    @property
    def parameters(self) -> dict:
        m = self.model
        if m.name == "triad_orientation":
            return m.report_parameters(orientations=self.orientations)
        p = m.vocabulary_parameters() if hasattr(m, "vocabulary_parameters") else m.report_parameters()
        return {**p, **self.parameters_reported}

    def to_dict(self) -> dict:
        d = {"effect": self.effect, "imu": self.imu, "axis": self.axis, "evidence": float(self.evidence),
             "parameters": self.parameters,
             "where": {"regime": self.where.get("regime"), "time_s": self.where.get("time_s"),
                       **{k: v for k, v in self.where.items() if k not in ("regime", "time_s")}},
             "explanation": self.explanation, "df": int(self.df), "log10_p": float(self.log10_p)}
        sensor = getattr(self.model, "which", None)
        if sensor is not None:
            d["sensor"] = sensor
        if self.model.std:
            d["std"] = {k: (float(v) if v.dim() == 0 else v.detach().cpu().double().tolist())
                        for k, v in self.model.std.items()}
        if self.screen_statistic is not None:
            d["screen_statistic"] = float(self.screen_statistic)
        d.update({k: v for k, v in self.extra.items() if k not in d})
        return to_jsonable(d, nonfinite="null", unknown="keep")

    def __getitem__(self, key):
        return self.to_dict()[key]


# ------------------------------------------------------------------------------ report

@dataclass
class MismatchReport:
    """Result of :func:`accel_bayes.mismatch.detect` (module docstring)."""

    findings: list
    baseline_fit: object
    refined_fit: object
    threshold: float
    alpha: float
    n_candidates: int
    df_max: int
    location: object
    location_after: object = None
    comparison: dict | None = None
    posterior: dict | None = None
    settings: dict = field(default_factory=dict)
    timings: dict = field(default_factory=dict)
    rounds: list = field(default_factory=list)
    withdrawn: list = field(default_factory=list)
    screens: list = field(default_factory=list)
    baseline_info: dict = field(default_factory=dict)
    source: str | None = None
    recording_info: dict = field(default_factory=dict)
    prep: object = field(default=None, repr=False)
    characterisation: dict | None = None  # what the final model leaves: accel_bayes.mismatch.characterise
    budget: list = field(default_factory=list)
    gyro_linear: dict | None = None  # the detector's gyro linear stage (step 3a): tests, blocks kept
    acc_linear: dict | None = None  # its accelerometer linear stage (step 3a', opt-in): tests, blocks kept
    fixed_effects: list = field(default_factory=list)  # its blocks: in the refined model, not in refined_fit.effects
    clock: dict | None = None  # the detector's clock stage (step 3b): every IMU's beat search, the clocks kept
    unresolved: dict | None = None  # the detector's unresolved-motion stage (step 7a): tests, scales, the sensors kept

    # ---------------------------------------------------------------- contract blocks
    @property
    def mismatch_detected(self) -> bool:
        return len(self.findings) > 0

    @property
    def baseline(self) -> dict:
        b = self.baseline_fit
        return {"loglik": float(b.loglik), "chi2_per_dof": float(b.chi2_per_dof), "dof": int(b.dof),
                "n_obs": int(b.n_obs), "chi2_noise": "stated"}

    @property
    def refined(self) -> dict | None:
        if not self.findings or self.refined_fit is None:
            return None
        r = self.refined_fit
        noise = r.has_noise_effect
        allfx = list(self.fixed_effects) + list(r.effects)
        # unresolved_motion is marginalised beside the mean fit: its log-likelihood gain joins the refit's
        gain = float((self.unresolved or {}).get("loglik_gain", 0.0))
        d = {"effects": [e.vocabulary_name or e.name for e in allfx], "loglik": float(r.loglik) + gain,
             "chi2_per_dof": float(r.chi2_per_dof_model if noise else r.chi2_per_dof),
             "chi2_noise": ("refined (the model's own per-sample variance: "
                            + ", ".join(sorted({e.name for e in r.effects if e.kind in ("noise", "random")})) + ")")
             if noise else "stated",
             "chi2_per_dof_stated": float(r.chi2_per_dof), "chi2_per_dof_stated_noise": float(r.chi2_per_dof),
             "dof": int(r.dof),
             "labels": [e.label() for e in allfx]}
        if gain:
            d["loglik_unresolved_motion_gain"] = gain
        if self.comparison and "elpd_loo" in self.comparison and "difference" in self.comparison["elpd_loo"]:
            e = self.comparison["elpd_loo"]
            d["elpd_loo"] = e["after"]["elpd_loo"]
            d["elpd_loo_baseline"] = e["before"]["elpd_loo"]
            d["elpd_loo_difference"] = e["difference"]
        return d

    def to_dict(self) -> dict:
        """The §7.2 document (plus ``details``)."""
        doc = {
            "schema": SCHEMA,
            "mismatch_detected": self.mismatch_detected,
            "threshold": float(self.threshold),
            "baseline": self.baseline,
            "findings": [f.to_dict() for f in self.findings],
            "refined": self.refined,
            "budget": self.budget,
            "details": self.details(),
        }
        return to_jsonable(doc, nonfinite="null", unknown="keep")

    def details(self) -> dict:
        d = {
            "threshold_rule": (f"Bonferroni over the m = {self.n_candidates} tests made (round candidates and "
                               f"the gyro linear stage's tests): chi2_{self.df_max} quantile at 1 - alpha/m, "
                               f"alpha = {self.alpha}; a gyro_linear block (df 12) against its own chi2_12 quantile "
                               f"at 1 - alpha/m"),
            "alpha": self.alpha, "n_candidates": self.n_candidates, "df_max": self.df_max,
            "recording": {**self.recording_info, "source": self.source},
            "baseline_start": self.baseline_info,
            "located_excess": self.location.to_dict() if self.location is not None else None,
            "located_excess_after": self.location_after.to_dict() if self.location_after is not None else None,
            "positions_baseline": self.baseline_fit.positions.tolist(),
            "positions_refined": None if self.refined_fit is None or not self.findings else self.refined_fit.positions.tolist(),
            "comparison": self.comparison,
            "posterior": self.posterior,
            "gyro_linear_stage": self.gyro_linear,
            # only when the opt-in stage ran, so that the default report keeps its keys
            **({"acc_linear_stage": self.acc_linear} if self.acc_linear is not None else {}),
            "clock_stage": self.clock,
            "unresolved_stage": self.unresolved,
            "rounds": self.rounds,
            "withdrawn": self.withdrawn,
            "screen_top_last_round": self.screens,
            "settings": self.settings,
            "timings_s": self.timings,
            "characterisation": self.characterisation,
        }
        return d

    # ---------------------------------------------------------------- output
    def to_json(self, indent: int = 1) -> str:
        return report_json(self.to_dict(), indent)

    def write(self, out_dir, *, figures: bool = True) -> dict:
        """Write ``report.json`` (v1 contract), ``report.md`` and the figures into ``out_dir``.
        Returns {name: path}."""
        out = Path(out_dir)
        if out.exists() and not out.is_dir():
            raise UserError(f"--out: {out} exists and is not a directory")
        out.mkdir(parents=True, exist_ok=True)
        paths = {}
        paths["json"] = write_report_json(out / "report.json", self.to_dict())
        figs = {}
        if figures:
            try:
                figs = self.save_figures(out)
            except OSError:  # a full disk or an unwritable directory is the run's failure
                raise
            except Exception as exc:  # a plotting failure must not lose the report
                warnings.warn(f"figures not written: {exc}", RuntimeWarning, stacklevel=2)
        paths.update(figs)
        paths["markdown"] = write_text(out / "report.md", self.markdown({k: v.name for k, v in figs.items()}))
        return paths

    def save_figures(self, out: Path) -> dict:
        """The report's figures (drawn by :func:`accel_bayes.diagnostics.mismatch_figures.save_mismatch_figures`,
        where every plot of the package lives); returns {name: path}."""
        from ..diagnostics.mismatch_figures import save_mismatch_figures  # lazy: matplotlib only when writing figures
        from .locate import CHANNELS

        refined = self.location_after is not None and self.refined_fit is not None
        return save_mismatch_figures(
            out, self.location, self.location_after, channels=CHANNELS,
            K=self.recording_info.get("K", self.location.heat.shape[0]),
            positions_baseline=self.baseline_fit.positions.numpy() if refined else None,
            positions_refined=self.refined_fit.positions.numpy() if refined else None)

    def markdown(self, figures: dict | None = None) -> str:
        """The human report (Markdown)."""
        figures = figures or {}
        d = self.to_dict()
        L = ["# Model-mismatch report", ""]
        ri = self.recording_info
        L.append(f"Recording: {self.source or ri.get('description') or '(in memory)'} — T = {ri.get('T')} samples, "
                 f"K = {ri.get('K')} IMUs, reference IMU {ri.get('reference_imu')}.")
        prep_line = _preparation_line(ri.get("preparation"))
        if prep_line:
            L.append(prep_line)
        if ((ri.get("preparation") or {}).get("intrinsics") or {}).get("applied") and self.acc_linear is None:
            # the rests fix each triad's axes by convention, not its rotation on the board (mimu_blind_acc.md)
            L.append("Accelerometer linear stage not run (`--acc-linear`, opt-in): the rests' intrinsics cannot hold "
                     "each triad's rotation on the board, which the motion sees through the lever arms; with it, "
                     "`calibrate --model` integrates what the rests leave.")
        L.append("")
        verdict = "**Mismatch detected.**" if d["mismatch_detected"] else "**No mismatch detected**: the nominal model explains the recording within its stated noise."
        L += [verdict, "",
              f"Threshold on the evidence 2·Δlog L: **{self.threshold:.4g}** ({d['details']['threshold_rule']}).", ""]
        b = d["baseline"]
        L += ["## Baseline (nominal model)", "",
              f"log L = {b['loglik']:.6g}, χ²/dof = {b['chi2_per_dof']:.4g} (stated noise, dof = {b['dof']}).", "",
              self.location.summary, ""]
        if d["findings"]:
            L += ["## Findings (most supported first)", "",
                  "| # | effect | IMU | axis | evidence | df | parameters | where |", "|---|---|---|---|---|---|---|---|"]
            for i, f in enumerate(d["findings"], 1):
                par = ", ".join(f"{k}={_short(v)}" for k, v in f["parameters"].items())
                wh = f["where"].get("regime") or ""
                if f["where"].get("time_s"):
                    wh += f" t∈[{f['where']['time_s'][0]:.3g}, {f['where']['time_s'][1]:.3g}] s"
                L.append(f"| {i} | {f['effect']} | {_na(f['imu'])} | {_na(f['axis'])} | {f['evidence']:.4g} | {f['df']} "
                         f"| {_cell(par)} | {_cell(wh)} |")
            L.append("")
            for i, f in enumerate(d["findings"], 1):
                L.append(f"{i}. {f['explanation']}")
                alts = f.get("alternatives") or []
                if alts:
                    L.append("   Not ruled out by this recording (Akaike relative likelihood ≥ 5 %): " + "; ".join(
                        f"{a['effect']} (IMU {_na(a['imu'])}, axis {_na(a['axis'])}, evidence {a['evidence']:.4g}, "
                        f"relative likelihood {a['relative_likelihood']:.2f})" for a in alts) + ".")
            L.append("")
        r = d["refined"]
        if r:
            L += ["## Refined model", "",
                  f"Effects added: {', '.join(r['labels'])}.", "",
                  "| | baseline | refined |", "|---|---|---|",
                  f"| log L | {b['loglik']:.6g} | {r['loglik']:.6g} |",
                  f"| χ²/dof | {b['chi2_per_dof']:.4g} | {r['chi2_per_dof']:.4g} ({r['chi2_noise']} noise) |"]
            if "elpd_loo" in r:
                L.append(f"| ELPD (PSIS-LOO over time samples) | {r['elpd_loo_baseline']:.6g} | {r['elpd_loo']:.6g} |")
            L.append("")
            if self.location_after is not None:
                L += [self.location_after.summary, ""]
            L += ["Positions relative to the reference IMU (mm, array frame):", "",
                  "| IMU | baseline | refined | change (µm) |", "|---|---|---|---|"]
            pb = self.baseline_fit.positions.numpy()
            pr = self.refined_fit.positions.numpy()
            for k in range(len(pb)):
                L.append(f"| {k} | {_vec(pb[k] * 1e3)} | {_vec(pr[k] * 1e3)} | {_vec((pr[k] - pb[k]) * 1e6, 1)} |")
            L.append("")
        L += _budget_markdown(d.get("budget") or [])
        if self.posterior:
            L += ["## Posterior (PmMH) before/after correction", "", "```", json.dumps(to_jsonable(self.posterior, nonfinite="null", unknown="keep"), indent=1)[:4000],
                  "```", ""]
        pp = self.location.ppc
        L += ["## Posterior predictive check (baseline)", "",
              f"{pp['n_twins']} twin recordings from the fitted model at the stated noise, refitted.", "",
              "| statistic | real | twins (mean) | twins (95 %) | p |", "|---|---|---|---|---|"]
        for k, v in pp.items():
            if isinstance(v, dict):
                f4 = lambda x, fmt=".4g": "–" if x is None else format(x, fmt)  # noqa: E731
                L.append(f"| {k} | {f4(v['real'])} | {f4(v['twin_mean'])} | {f4(v['twin_q95'])} | "
                         f"{f4(v['p_value'], '.3g')} |")
        L.append("")
        if self.characterisation:
            L += ["## What the final model leaves unexplained", "",
                  "Per sensor: the excess of the standardized residuals (mean z² − 1), what it grows with (covariates "
                  "ranked by η², the share of the per-sample excess power explained by the covariate's quintiles), "
                  "its lag-1 autocorrelation and its anisotropy about the output's rate of change "
                  "(`accel_bayes.mismatch.characterise`).", ""]
            for sensor, c in self.characterisation.items():
                L += [f"- {c['summary']}"]
            L += ["", "| sensor | covariate | η² | power | mean z² per quintile |", "|---|---|---|---|---|"]
            for sensor, c in self.characterisation.items():
                for row in c["covariates"]:
                    pw = "–" if row["power"] is None else f"{row['power']:.2f}"
                    L.append(f"| {sensor} | {_cell(row['name'])} | {row['eta2']:.3g} | {pw} | "
                             f"{', '.join(f'{v:.3g}' for v in row['quintile_mean_z2'])} |")
            L.append("")
        L += ["## Located excess (baseline, worst cells)", "", "| IMU | sensor | axis | χ²/n | excess z | bias z | lag-1 z |",
              "|---|---|---|---|---|---|---|"]
        for c in sorted(self.location.cells, key=lambda c: -c["excess_z"])[:8]:
            L.append(f"| {c['imu']} | {c['sensor']} | {c['axis']} | {c['chi2_ratio']:.4g} | {c['excess_z']:.3g} | "
                     f"{c['bias_z']:.3g} | {c['lag1_z']:.3g} |")
        L.append("")
        for k, title in (("heatmap", "Residual excess per IMU and channel"), ("regimes", "Residual power per motion regime"),
                         ("before_after", "Before / after")):
            if k in figures:
                L += [f"### {title}", "", f"![{title}]({figures[k]})", ""]
        t = self.timings
        L += ["## Run", "", f"Total {t.get('total_s', float('nan')):.1f} s; settings: `{json.dumps(to_jsonable(self.settings, nonfinite='null', unknown='keep'))}`.", ""]
        return "\n".join(L)


def _budget_markdown(rows: list) -> list:
    """The ``budget`` rows as a Markdown section (a table per sensor), b/a where a > 0."""
    if not rows:
        return []
    L = ["## Residual budget", "",
         "Excess variance per channel-sample (sensor units²): a = mean leverage-corrected squared baseline "
         "residual − stated variance; b = the part the model with the findings accounts for (removed by its "
         "mean effects, on residuals with the motion states projected off in the stated noise's whitening, + "
         "predicted by its variance effects). A model that explains the misfit has b ≈ a in "
         "every regime. Bands are quantiles of the baseline's fitted |ω| and |ω̇|.", ""]
    for sensor, unit in (("acc", "(m/s²)²"), ("gyro", "(rad/s)²")):
        rs = [r for r in rows if r["sensor"] == sensor]
        if not rs:
            continue
        L += [f"**{sensor}** ({unit})", "", "| regime | samples | a | a / σ² | b | b / a |", "|---|---|---|---|---|---|"]
        for r in rs:
            a, b, s2 = r["excess_var_observed"], r["excess_var_explained"], r.get("stated_var")
            f = lambda x: "–" if x is None or x != x else f"{x:.3g}"  # noqa: E731
            rel = f(a / s2) if s2 else "–"
            ratio = f(b / a) if a is not None and a == a and a > 0 else "–"
            L.append(f"| {_cell(r['regime'])} | {r['samples']} | {f(a)} | {rel} | {f(b)} | {ratio} |")
        L.append("")
    return L


def _preparation_line(prep: dict | None) -> str:
    """One line saying how the recording was prepared (intrinsics, selection), or "" if unknown."""
    if not prep:
        return ""
    it = prep.get("intrinsics", {})
    s = prep.get("selection", {})
    intr = f"intrinsics applied ({it.get('how')})" if it.get("applied") else f"intrinsics not applied ({it.get('why')})"
    dropped = ", ".join(f"{v} {k}" for k, v in (s.get("dropped") or {}).items() if v) or "none"
    return (f"Preparation (as `calibrate`): {intr}; samples kept {s.get('kept')} of {s.get('recording')} in "
            f"{s.get('kept_runs')} run(s), dropped {dropped} (min_rotation {s.get('min_rotation')} rad/s).")


def _cell(text: str) -> str:
    """Text safe inside a Markdown table cell (regime names contain '|')."""
    return str(text).replace("|", "\\|")


def _na(x):
    return "–" if x is None else str(x)


def _short(v):
    if isinstance(v, list):  # nested lists too (a gyro linear block's 3 × 3 scale)
        return "[" + ", ".join(f"{x:.3g}" if isinstance(x, (int, float)) else _short(x) for x in v) + "]"
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def _vec(v, nd: int = 3):
    return "(" + ", ".join(f"{x:.{nd}f}" for x in v) + ")"
