"""Regression harness for the numerical core (issue #10): the deterministic outputs of every
solver, with fixed seeds, saved to an .npz so that two commits can be compared.

    python experiments/refactor_check.py --out after.npz
    cd /tmp && PYTHONPATH=/work/base7adf python3 /path/to/experiments/refactor_check.py --out base.npz
    python experiments/refactor_check.py --compare base.npz after.npz

Outputs (each a small problem, seconds each):

* ``map.*`` — [C21] MAP on a simulated mimu8 data set: positions and Laplace covariance;
* ``selfcal.*`` — [S16] self-calibration (process-model motion, noisy plate): poses, states,
  Laplace covariance;
* ``selfcal_modes.*`` — the same data through the other motion models and options of
  ``self_calibrate``: "estimate-snap" (intensity fixed point, Laplace scale correction, fit check),
  "estimate" with the "score" scale correction, and "s16" over left-out samples (bridged process
  factors) with known sensor parameters, another fixed triad and ``rerun_from_estimate="auto"``;
* ``conventional.*`` — [S16] eq. 19 conventional calibration: poses, sensor parameters, covariance;
* ``intrinsics.*`` — intrinsics from a simulated recording with 24 rests;
* ``crb`` — the Cramér–Rao bound of θ for the MAP data set;
* ``motion.*`` — motion estimation (ω, ω̇, s, their std; draws and linear geometry);
* ``mismatch.*`` — ``mismatch.detect`` on a simulated mimu8 case with one
  ``axis_displacement`` (the package's simulator): evidence and parameters of the findings,
  refined log-likelihood;
* ``conceal.*`` — the same on a recording of the independent generator
  (``experiments/_conceal.py``) hiding one ``time_offset``;
* ``noise.*`` — the modelling layer on the MAP data set (added with issue #26, which moved it
  into ``model/``): log p̂ of the [C21] likelihood and of the tempered one with fixed draws, the
  empirical φ prior, the MAP with the noise levels estimated, the sandwich κ and the tempered MAP.
* ``pipelines.*`` — the ``calibrate`` (four option sets: run until converged, estimated noise,
  no MAP with a box prior and flat φ prior, fixed N with a given correlation; and on a second
  recording with noisy gyroscopes, the N rule and the automatic correlated kernel), ``map`` and
  ``selfcal`` commands on one simulated recording, run through the command line as a user runs
  them, and ``calibrate(rec, ...)`` called as a library on a recording whose misfit (one
  accelerometer axis displaced by 3 mm) makes the sandwich temper the likelihood (κ ≈ 1.5): each
  ``positions.json`` document whole (provenance settings included) as JSON text, compared for
  equality, with only the wall-clock ``seconds`` left out (issue #26 item 3: the options records
  must not change a setting, their order or a draw); since issue #26 item 1 (one
  ``PreparedRecording`` for every fit) also ``selfcal --drop-clipped``, ``map --select rotation``,
  ``motion`` (its NetCDF estimates, ``pipelines.motion.*``) and ``mismatch`` (its ``report.json``,
  layout for equality and numbers to the tolerance) on the same recording;
* ``demo.*`` — ``accel-bayes demo`` (seed 1, the full run; minutes): its posterior
  ``positions.json`` and the mismatch ``report.json`` (layout compared for equality, numbers to
  the tolerance), ``summary.csv`` and the demo's ``report.md`` (text), wall-clock times left
  out.  Not in the default stages (``--only demo``).

Only public names that exist at 7adf109 and later are imported, by their 7adf109 paths, so the
same file runs against both: 0.1 kept those paths as aliases, and in a tree that has dropped them
(0.2.0) :func:`_bind_old_paths` binds each to its new home.  Keep it so: a rewrite to the new
paths would silently run today's modules in the baseline too.  For the
baseline, hide an editable install of today's checkout, whose import finder would otherwise
serve modules missing from the old tree::

    mkdir -p /tmp/noeditable && printf 'import sys\nsys.meta_path[:] = [f for f in sys.meta_path if "Editable" not in type(f).__name__ and "Editable" not in getattr(f, "__name__", "")]\n' > /tmp/noeditable/sitecustomize.py
    cd /tmp && PYTHONPATH=/work/base7adf:/tmp/noeditable python3 /path/to/experiments/refactor_check.py --out base.npz

The options records (issue #26 item 3) were checked against 9279a3c with the ``pipelines`` and
``demo`` stages (2026-11-27, the shared 2-core development machine; every output equal, the
demo's mismatch report, which these records do not touch, with max |a − b| 2.6e-11 over numbers up
to 1.1e5, e.g. its gyro-linear group statistic 66.15036471200 vs 66.15036471199, 1e-13 relative)::

    git -C /work/main archive 9279a3c | tar -x -C /tmp/opt_base
    cd /tmp && PYTHONPATH=/tmp/opt_base:/tmp/noeditable python3 /path/to/experiments/refactor_check.py \
        --only pipelines,demo --out base.npz
    cd /tmp && PYTHONPATH=/path/to/checkout python3 /path/to/experiments/refactor_check.py --only pipelines,demo --out after.npz
    python3 experiments/refactor_check.py --compare /tmp/base.npz /tmp/after.npz

The ``PreparedRecording`` work (issue #26 item 1) was checked against its parent c03e6a6 with every
stage, the demo included (``experiments/refactor_check.md`` holds the table and says when and
where)::

    git -C /work/main archive c03e6a6 | tar -x -C /tmp/prep_base
    cd /tmp/prep_run && cp /tmp/prep_base/experiments/_conceal.py . && cp /path/to/experiments/refactor_check.py .
    PYTHONPATH=/tmp/prep_base:/tmp/noeditable python3 refactor_check.py --out base.npz \
        --only map,selfcal,selfcal_modes,conventional,intrinsics,motion,mismatch,conceal,noise,pipelines,demo
    PYTHONPATH=/path/to/checkout python3 /path/to/experiments/refactor_check.py --out after.npz --only <the same>
    python3 experiments/refactor_check.py --compare base.npz after.npz --report experiments/refactor_check.md \
        --header "A: c03e6a6 (parent), B: this checkout"

``--compare`` prints max |a − b| and max |a − b| / max |a| per output and flags every output
whose relative difference exceeds ``--tol`` (default 1e-6: the LM solvers stop at relative cost
changes of 1e-10–1e-12, i.e. parameter changes of ~1e-6–1e-5 relative in the worst-conditioned
directions; the mismatch statistics are differences of log-likelihoods and get the same bound
relative to their scale).
"""
from __future__ import annotations

import argparse
import math
import sys
import time

import numpy as np
import torch

DEG = math.pi / 180

# the 7adf109 paths this file imports -> their homes since 0.1
OLD_PATHS = {"arrays": "physics.arrays", "models": "physics.models", "motion": "physics.motion_generators",
             "geometry": "physics.geometry", "recording": "data.recording", "intrinsics": "prep.intrinsics",
             "motion_estimation": "inference.motion_estimate"}


def _bind_old_paths() -> None:
    """In a tree without the 0.1 aliases, put each old path in ``sys.modules`` as its new module
    (the tree's own module or alias wins wherever one exists)."""
    import importlib
    import importlib.util

    for old, new in OLD_PATHS.items():
        if importlib.util.find_spec(f"accel_bayes.{old}") is None:
            sys.modules[f"accel_bayes.{old}"] = importlib.import_module(f"accel_bayes.{new}")


def _name(name: str, *modules: str):
    """``name`` from the first of ``modules`` (paths under accel_bayes, oldest first) that has it:
    the ``noise`` stage's names moved in issue #26 (likelihood → model.likelihood, prep.noise →
    model.noise / model.tempering / inference.noise_fit …) with no alias left behind, so the old
    path is tried first and a baseline tree always runs its own code."""
    import importlib

    for mod in modules:
        try:
            m = importlib.import_module(f"accel_bayes.{mod}")
        except ModuleNotFoundError:
            continue
        if hasattr(m, name):
            return getattr(m, name)
    raise ImportError(f"{name} not found in any of {modules}")


def _np(x):
    if torch.is_tensor(x):
        return x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


def _map_data():
    """The simulated mimu8 data set of the ``map`` and ``noise`` stages (array frame)."""
    from accel_bayes.arrays import mimu4444_8
    from accel_bayes.models import imu_outputs, to_array_frame
    from accel_bayes.motion import iid_motion

    dt = torch.float64
    sa, sg = 0.04, 0.06 * DEG
    arr = mimu4444_8()
    g = torch.Generator().manual_seed(7)
    m = iid_motion(300, generator=g)
    K = arr.K
    true = arr.positions + 1e-4 * torch.randn(K, 3, generator=g, dtype=dt)
    true[0] = arr.positions[0]
    acc, gyro = imu_outputs(true, arr.orientations, m.omega, m.omega_dot, m.s)
    acc = acc + sa * torch.randn(acc.shape, generator=g, dtype=dt)
    gyro = gyro + sg * torch.randn(gyro.shape, generator=g, dtype=dt)
    acc_a = to_array_frame(acc, arr.orientations)
    wbar = to_array_frame(gyro, arr.orientations).mean(1)
    P = torch.eye(3, dtype=dt) * sg**2 / K
    return arr, true, m, sa, sg, acc_a, wbar, P


def run_map(out: dict):
    from accel_bayes.inference.crb import crb_theta
    from accel_bayes.inference.map import fit_map

    arr, true, m, sa, sg, acc_a, wbar, P = _map_data()
    K = arr.K
    res = fit_map(acc_a, wbar, P, sa, prior_mean=arr.positions, prior_std=3e-3)
    out["map.positions"] = _np(res.positions)
    out["map.laplace_cov"] = _np(res.laplace_cov)
    out["map.omega"] = _np(res.omega)
    out["crb"] = _np(crb_theta(true, m.omega, m.omega_dot, m.s, sa, torch.full((K,), sg), prior_std=3e-3))


def run_selfcal(out: dict):
    from accel_bayes import models
    from accel_bayes.arrays import s16_plate
    from accel_bayes.geometry import boxplus
    from accel_bayes.inference.selfcal import self_calibrate

    simulate_process_motion = _process_motion()
    f64 = torch.float64
    gen = torch.Generator().manual_seed(22)
    T, A = 200, 5
    x = simulate_process_motion(T, 1 / 125.0, seed=6, segment_length=20, omega_dot_std=8.0, omega0_std=3.0)
    arr = s16_plate()
    q_true = boxplus(arr.orientations, 0.05 * torch.randn(A, 3, generator=gen, dtype=f64))
    p_true = arr.positions + 2e-3 * torch.randn(A, 3, generator=gen, dtype=f64)
    z = models.triad_output(x, q_true, p_true) + 0.01 * torch.randn(T, A, 3, generator=gen, dtype=f64)
    res = self_calibrate(z, 1 / 125.0, nominal_positions=arr.positions, nominal_orientations=arr.orientations,
                         acc_noise_std=0.01)
    out["selfcal.positions"] = _np(res.positions)
    out["selfcal.orientations"] = _np(res.orientations)
    out["selfcal.states"] = _np(res.states)
    out["selfcal.covariance"] = _np(res.covariance)


def _process_motion():
    """``simulate_process_motion`` from its 7adf109 home (``inference.selfcal``) or, in a tree where
    the self-calibration became a package, from the motion generators (``physics.motion_generators``)."""
    try:
        from accel_bayes.inference.selfcal import simulate_process_motion
    except ImportError:
        from accel_bayes.motion import simulate_process_motion
    return simulate_process_motion


def _selfcal_case(seed: int, T: int):
    from accel_bayes import models
    from accel_bayes.arrays import s16_plate
    from accel_bayes.geometry import boxplus

    f64 = torch.float64
    gen = torch.Generator().manual_seed(seed)
    x = _process_motion()(T, 1 / 125.0, seed=seed, segment_length=20, omega_dot_std=8.0, omega0_std=3.0)
    arr = s16_plate()
    A = arr.K
    q_true = boxplus(arr.orientations, 0.05 * torch.randn(A, 3, generator=gen, dtype=f64))
    p_true = arr.positions + 2e-3 * torch.randn(A, 3, generator=gen, dtype=f64)
    z = models.triad_output(x, q_true, p_true) + 0.01 * torch.randn(T, A, 3, generator=gen, dtype=f64)
    return arr, z


def _selfcal_outputs(out: dict, key: str, res) -> None:
    out[f"{key}.positions"] = _np(res.positions)
    out[f"{key}.orientations"] = _np(res.orientations)
    out[f"{key}.states"] = _np(res.states)
    if res.covariance is not None:
        out[f"{key}.covariance"] = _np(res.covariance)
    out[f"{key}.cost"] = np.array([res.cost, res.n_iter, len(res.full_cost_log), len(res.runs)], dtype=np.float64)
    pn = res.process_noise
    if pn.get("intensities"):
        out[f"{key}.intensities"] = np.array([pn["intensities"]["acc"], pn["intensities"]["omega"]])
        out[f"{key}.history"] = np.array([[h["intensities"]["acc"], h["intensities"]["omega"], h["change"]]
                                          for h in pn["history"]])
    sc = pn.get("scale_correction")
    if sc:
        out[f"{key}.scale"] = np.array([sc["factor"]] + [v for s in sc["steps"] for v in s.values()])


def run_selfcal_modes(out: dict):
    from accel_bayes.inference.selfcal import fit_check, self_calibrate

    arr, z = _selfcal_case(8, 160)
    res = self_calibrate(z, 1 / 125.0, nominal_positions=arr.positions, nominal_orientations=arr.orientations,
                         acc_noise_std=0.01, process_noise="estimate-snap", max_iter=60)
    _selfcal_outputs(out, "selfcal_modes.snap", res)
    chk = fit_check(res, arr.positions).to_dict()
    out["selfcal_modes.snap.fit_check"] = np.array([float(v) for v in chk.values()])
    res = self_calibrate(z, 1 / 125.0, nominal_positions=arr.positions, nominal_orientations=arr.orientations,
                         acc_noise_std=0.01, process_noise="estimate", marginal_scale="score", max_iter=60,
                         rerun_from_estimate=False)
    _selfcal_outputs(out, "selfcal_modes.score", res)
    keep = np.r_[0:40, 43:90, 92:160]  # two gaps: the process factors bridge 3 and 2 grid steps
    t = np.arange(160) / 125.0
    S = torch.eye(3, dtype=torch.float64).expand(arr.K, 3, 3) * 1.01
    o = torch.full((arr.K, 3), 0.02, dtype=torch.float64)
    res = self_calibrate(z[keep], t[keep], steps=np.diff(keep), nominal_positions=arr.positions,
                         nominal_orientations=arr.orientations, fixed=2, acc_noise_std=0.01, process_noise="s16",
                         sensor_params=(S, o), rerun_from_estimate="auto")
    _selfcal_outputs(out, "selfcal_modes.bridged", res)


def run_conventional(out: dict):
    from accel_bayes import models
    from accel_bayes.arrays import s16_plate
    from accel_bayes.geometry import boxplus
    from accel_bayes.inference.conventional import IDENTITY_SENSITIVITY, conventional_calibrate
    from accel_bayes.motion import smooth_motion

    f64 = torch.float64
    gen = torch.Generator().manual_seed(32)
    m = smooth_motion(400, 125.0, seed=1, omega_rms=3.0, freq_range=(0.1, 0.5), accel_rms=2.0)
    x = torch.cat((m.s, m.omega, m.omega_dot), -1)
    arr = s16_plate()
    A = arr.K
    p = arr.positions + 3e-3 * torch.randn(A, 3, generator=gen, dtype=f64)
    q = boxplus(arr.orientations, 0.05 * torch.randn(A, 3, generator=gen, dtype=f64))
    sp = torch.tensor(IDENTITY_SENSITIVITY, dtype=f64) + 0.02 * torch.randn(A, 6, generator=gen, dtype=f64)
    o = 0.1 * torch.randn(A, 3, generator=gen, dtype=f64)
    z = models.triad_output(x, q, p, models.sensitivity_matrix(sp), o)
    z = z + 0.02 * torch.randn(z.shape, generator=gen, dtype=f64)
    res = conventional_calibrate(z, x, nominal_positions=arr.positions, nominal_orientations=arr.orientations,
                                 acc_noise_std=0.02)
    out["conventional.positions"] = _np(res.positions)
    out["conventional.orientations"] = _np(res.orientations)
    out["conventional.sensitivity"] = _np(res.sensitivity)
    out["conventional.offset"] = _np(res.offset)
    out["conventional.covariance"] = _np(res.covariance)


def _rest_recording(K=4, n_orient=24, n=300, sigma=0.04, sigma_g=0.003, dyn=40):
    """Rests in random orientations (raw a = T⁻¹ g u + b + noise) between dynamic stretches."""
    from accel_bayes.recording import Recording

    g0 = 9.80665
    rng = np.random.default_rng(11)
    b = rng.normal(0, 0.3, (K, 3))
    Tm = np.zeros((K, 3, 3))
    for k in range(K):
        Tm[k] = np.diag(1 + rng.normal(0, 0.01, 3))
        Tm[k][np.tril_indices(3, -1)] = rng.normal(0, 0.005, 3)
    bg = rng.normal(0, 0.02, (K, 3))
    dirs = rng.normal(size=(n_orient, K, 3))
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    Tinv = np.linalg.inv(Tm)
    acc, gyro, seg = [], [], []
    for s in range(n_orient):
        raw = np.einsum("kij,kj->ki", Tinv, g0 * dirs[s]) + b
        acc += [rng.normal(0, 20, (dyn, K, 3)), raw + sigma * rng.normal(size=(n, K, 3))]
        gyro += [rng.normal(0, 3, (dyn, K, 3)), bg + sigma_g * rng.normal(size=(n, K, 3))]
        seg += ["dynamic"] * dyn + ["static"] * n
    acc = np.concatenate(acc)
    return Recording(time=np.arange(acc.shape[0]) / 100.0, acc=acc, gyro=np.concatenate(gyro),
                     nominal_position=rng.normal(0, 0.01, (K, 3)), acc_noise_std=np.full(K, sigma),
                     gyro_noise_std=np.full(K, sigma_g), segment=np.array(seg), description="rests",
                     source="refactor_check")


def run_intrinsics(out: dict):
    from accel_bayes.intrinsics import estimate_intrinsics

    est = estimate_intrinsics(_rest_recording())
    out["intrinsics.acc_bias"] = _np(est.acc_bias)
    out["intrinsics.acc_matrix"] = _np(est.acc_matrix)
    out["intrinsics.acc_cov"] = _np(est.acc_cov)
    out["intrinsics.gyro_bias"] = _np(est.gyro_bias)


def run_motion(out: dict):
    from accel_bayes.arrays import mimu4444_8
    from accel_bayes.motion_estimation import estimate_motion
    from accel_bayes.simulate import simulate

    res = simulate(mimu4444_8(), "iid", T=300, rate=100, seed=3, position_error_std=1e-4)
    rel = (res.true_positions - res.true_positions[0]).numpy()
    imus = [{"imu": k, "mean": p.tolist(), "std": [0.0 if k == 0 else 1e-4] * 3,
             "cov": (np.zeros((3, 3)) if k == 0 else 1e-8 * np.eye(3)).tolist()} for k, p in enumerate(rel)]
    doc = {"schema": "accel_bayes.positions/1", "method": "map", "reference_imu": 0, "imus": imus,
           "diagnostics": {"seconds": 0.0}}
    for mode, kw in (("draws", dict(geometry="draws", draws=20, seed=1)), ("linear", dict(geometry="linear"))):
        ds = estimate_motion(res.recording, doc, **kw)
        for v in ("omega", "omega_dot", "s", "omega_std", "omega_dot_std", "s_std", "chi2"):
            if v in ds:
                out[f"motion.{mode}.{v}"] = np.asarray(ds[v].values, dtype=np.float64)


def run_mismatch(out: dict):
    from accel_bayes.arrays import mimu4444_8
    from accel_bayes.mismatch import detect, make_effect
    from accel_bayes.simulate import simulate

    eff = make_effect("axis_displacement", imu=6, axis="z", parameters={"displacement": [0.0, 2e-4, 8e-4]})
    rec = simulate(mimu4444_8(), "smooth", seed=22, effects=[eff], T=400, rate=200.0, acc_noise_std=0.02,
                   gyro_noise_std=0.1 * DEG).recording
    rep = detect(rec, seed=0, n_twins=20, loo_draws=40, n_refit=3).to_dict()
    out["mismatch.baseline"] = np.array([rep["baseline"]["loglik"], rep["baseline"]["chi2_per_dof"]])
    out["mismatch.threshold"] = np.array([rep["threshold"]])
    out["mismatch.evidence"] = np.array([f["evidence"] for f in rep["findings"]])
    params = [np.ravel(np.asarray(v, dtype=np.float64)) for f in rep["findings"]
              for v in f["parameters"].values() if isinstance(v, (list, float, int))]
    out["mismatch.parameters"] = np.concatenate(params) if params else np.zeros(0)
    ref = rep.get("refined") or {}
    out["mismatch.refined"] = np.array([ref.get("loglik", np.nan), ref.get("chi2_per_dof", np.nan)])
    out["mismatch.names"] = np.array([f"{f['effect']}:{f['imu']}:{f['axis']}" for f in rep["findings"]])


def run_conceal(out: dict):
    """mismatch.detect on a recording from the independent generator (experiments/_conceal.py,
    numpy from first principles) hiding one ``time_offset`` (the effect whose exact and
    linearised forms differ)."""
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from _conceal import make_case

    from accel_bayes.mismatch import detect

    case = make_case("mimu8", "time_offset", seed=3, T=600, rate=200.0, imu=5, magnitude=5e-4)
    rep = detect(case.recording, seed=0, n_twins=20, loo_draws=40, n_refit=3).to_dict()
    out["conceal.baseline"] = np.array([rep["baseline"]["loglik"], rep["baseline"]["chi2_per_dof"]])
    out["conceal.evidence"] = np.array([f["evidence"] for f in rep["findings"]])
    params = [np.ravel(np.asarray(v, dtype=np.float64)) for f in rep["findings"]
              for v in f["parameters"].values() if isinstance(v, (list, float, int))]
    out["conceal.parameters"] = np.concatenate(params) if params else np.zeros(0)
    ref = rep.get("refined") or {}
    out["conceal.refined"] = np.array([ref.get("loglik", np.nan), ref.get("chi2_per_dof", np.nan)])
    out["conceal.names"] = np.array([f"{f['effect']}:{f['imu']}:{f['axis']}" for f in rep["findings"]])


def run_noise(out: dict):
    lik_mods = ("likelihood", "model.likelihood", "model.gyro_posterior")
    noise_mods = ("prep.noise", "model.noise", "model.tempering", "inference.noise_fit")
    GyroPosterior = _name("GyroPosterior", *lik_mods)
    RaoBlackwellLikelihood = _name("RaoBlackwellLikelihood", *lik_mods)
    TemperedLikelihood = _name("TemperedLikelihood", *noise_mods)
    empirical_phi_prior = _name("empirical_phi_prior", "prep.phi_prior", "model.phi_prior")
    fit_map_with_noise = _name("fit_map_with_noise", *noise_mods)
    sandwich_inflation = _name("sandwich_inflation", *noise_mods)
    fit_map_tempered = _name("fit_map_tempered", *noise_mods)

    arr, true, m, sa, sg, acc_a, wbar, P = _map_data()
    T = acc_a.shape[0]
    post = GyroPosterior(wbar, P.expand(T, 3, 3).clone(), "calibrated")
    batch = torch.stack((arr.positions, true))
    lik = RaoBlackwellLikelihood(acc_a, post, sa, num_draws=8)
    out["noise.log_phat"] = _np(lik.log_phat(batch, generator=torch.Generator().manual_seed(5)))
    phi = empirical_phi_prior(acc_a, wbar, sa, arr.positions)
    out["noise.phi_prior_cov"] = _np(phi.cov)
    tl = TemperedLikelihood(acc_a, post, sa * 2.0**0.5, 8, kappa=2.0, phi_prior=phi)
    out["noise.tempered_log_phat"] = _np(tl.log_phat(batch, generator=torch.Generator().manual_seed(5)))
    res, model = fit_map_with_noise(acc_a, wbar, P, sa, prior_mean=arr.positions, prior_std=3e-3, bins=2)
    out["noise.map_positions"] = _np(res.positions)
    out["noise.std"] = _np(model.std)
    out["noise.bin_scale"] = _np(model.bin_scale)
    sw = sandwich_inflation(acc_a, wbar, P, model.std, res, prior_mean=arr.positions, prior_std=3e-3)
    out["noise.kappa"] = np.array([sw["kappa"]])
    out["noise.std_ratio"] = _np(sw["std_ratio"])
    kappa = max(sw["kappa"], 1.0)
    tm = fit_map_tempered(acc_a, wbar, P, model.std * kappa**0.5, kappa, prior_mean=arr.positions, prior_std=3e-3,
                          phi_prior=phi)
    out["noise.tempered_positions"] = _np(tm.positions)
    out["noise.tempered_cov"] = _np(tm.laplace_cov)


# (name, calibrate options): small runs, a few seconds each, that between them pass through every step
# of the pipeline (run until converged, noise estimated and tempered, no MAP, a given N and ρ)
CALIBRATE_RUNS = (
    ("auto", ["--chains", "2", "--warmup", "30", "--check-every", "30", "--max-draws", "60"]),
    ("estimate", ["--chains", "2", "--warmup", "30", "--draws", "40", "--noise", "estimate"]),
    ("nomap", ["--chains", "2", "--warmup", "30", "--draws", "40", "--no-map", "--prior", "box", "--phi-prior",
               "flat", "--seed", "4"]),
    ("rho", ["--chains", "2", "--warmup", "20", "--draws", "30", "--num-draws", "4", "--correlation", "0.5",
             "--proposal", "rw", "--gyro-method", "sample_cov_mean"]),
)


def _without_seconds(x):
    """A JSON document without its wall-clock entries (every key named ``seconds``)."""
    if isinstance(x, dict):
        return {k: _without_seconds(v) for k, v in x.items() if k != "seconds"}
    if isinstance(x, list):
        return [_without_seconds(v) for v in x]
    return x


def _split(doc, name: str) -> dict:
    """A JSON document as ``{name}.layout`` (every path in order, with its value unless a number)
    and ``{name}.numbers`` (the numbers in that order), so that --compare checks the layout for
    equality and the numbers to the tolerance.  Wall-clock times (keys ``*_s``, ``*_seconds``) are left out."""
    paths, numbers = [], []

    def walk(x, where):
        if isinstance(x, dict):
            for k, v in x.items():
                if not k.endswith(("_s", "_seconds")):
                    walk(v, f"{where}.{k}")
        elif isinstance(x, list):
            for i, v in enumerate(x):
                walk(v, f"{where}[{i}]")
        elif isinstance(x, (int, float)) and not isinstance(x, bool):
            paths.append(f"{where}: number")
            numbers.append(float(x))
        else:
            paths.append(f"{where}: {x!r}")

    walk(doc, "")
    return {f"{name}.layout": np.array(paths), f"{name}.numbers": np.array(numbers, dtype=np.float64)}


def run_pipelines(out: dict):
    """The commands as a user runs them, in a scratch folder with fixed relative names (the
    provenance records the recording's path as given)."""
    import contextlib
    import io
    import json
    import os
    import tempfile

    from accel_bayes.cli import main

    def cli(*args):
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()) as err:
            rc = main(list(args))
        if rc not in (0, 4):  # 4: finished, chains not converged (short runs): the outputs are written
            raise RuntimeError(f"accel-bayes {' '.join(args)}: exit {rc}: {err.getvalue()[-400:]}")

    def keep(name, path):
        doc = json.loads(open(path, encoding="utf-8").read())
        out[f"pipelines.{name}.document"] = np.array(json.dumps(_without_seconds(doc), sort_keys=False))
        imus = [i for i in doc["imus"] if i.get("mean") is not None]
        out[f"pipelines.{name}.means"] = np.array([i["mean"] for i in imus], dtype=np.float64)

    here = os.getcwd()
    with tempfile.TemporaryDirectory() as tmp:
        os.chdir(tmp)
        try:
            cli("simulate", "--preset", "mimu8", "-T", "200", "--seed", "3", "-o", "rec.nc")
            for name, opts in CALIBRATE_RUNS:
                cli("calibrate", "rec.nc", "--out", f"cal_{name}", "--quiet", "--no-plots", *opts)
                keep(f"calibrate_{name}", f"cal_{name}/positions.json")
            cli("simulate", "--preset", "mimu8", "-T", "200", "--seed", "3", "--gyro-noise", "0.02", "--acc-noise",
                "0.005", "-o", "noisy_gyro.nc")
            cli("calibrate", "noisy_gyro.nc", "--out", "cal_cpm", "--quiet", "--no-plots", "--chains", "2", "--warmup",
                "20", "--draws", "20", "--noise", "estimate")
            keep("calibrate_cpm", "cal_cpm/positions.json")
            cli("map", "rec.nc", "--out", "map")
            keep("map", "map/positions.json")
            cli("selfcal", "rec.nc", "--out", "selfcal", "--max-iter", "50", "--no-progress")
            keep("selfcal", "selfcal/positions.json")
            cli("selfcal", "rec.nc", "--out", "selfcal_clip", "--max-iter", "50", "--no-progress", "--drop-clipped")
            keep("selfcal_clip", "selfcal_clip/positions.json")
            cli("map", "rec.nc", "--out", "map_rot", "--select", "rotation")
            keep("map_rot", "map_rot/positions.json")
            cli("motion", "rec.nc", "--calibration", "map/positions.json", "-o", "motion.nc", "--draws", "20",
                "--seed", "1")
            motion_outputs(out, "motion.nc")
            cli("mismatch", "rec.nc", "--out", "mismatch", "--twins", "20", "--no-figures", "--max-findings", "2")
            doc = _without_seconds(json.loads(open("mismatch/report.json", encoding="utf-8").read()))
            for key, value in _split(doc, "pipelines.mismatch").items():
                out[key] = value
        finally:
            os.chdir(here)
    out["pipelines.calibrate_tempered.document"] = np.array(json.dumps(_without_seconds(_tempered_run())))


def motion_outputs(out: dict, path: str) -> None:
    """The estimates of an ``accel_bayes.motion/1`` file (``accel-bayes motion``) as outputs."""
    import xarray as xr

    with xr.open_dataset(path, engine="h5netcdf") as ds:
        for v in ("omega", "omega_dot", "s", "omega_std", "omega_dot_std", "s_std", "chi2"):
            out[f"pipelines.motion.{v}"] = np.asarray(ds[v].values, dtype=np.float64)


def _tempered_run() -> dict:
    """``calibrate`` as a library call with keywords (the form every version accepts) on a
    recording the model cannot fit (IMU 6's z axis displaced by 3 mm): its sandwich factor
    κ ≈ 1.5 tempers the likelihood; returns the positions document."""
    from accel_bayes.arrays import mimu4444_8
    from accel_bayes.mismatch import make_effect
    from accel_bayes.pipelines.calibrate import calibrate
    from accel_bayes.simulate import simulate

    eff = make_effect("axis_displacement", imu=6, axis="z", parameters={"displacement": [0.0, 7.5e-4, 3e-3]})
    rec = simulate(mimu4444_8(), "smooth", seed=22, effects=[eff], T=300, rate=200.0, acc_noise_std=0.02,
                   gyro_noise_std=0.1 * DEG).recording
    res = calibrate(rec, chains=2, draws=20, warmup=20, noise="estimate", progress=False, seed=1)
    if not res.settings["noise_model"]["sandwich"]["applied"] > 1.0:
        raise RuntimeError("the tempered case no longer tempers: choose a larger displacement")
    return res.positions


def run_demo(out: dict):
    """``accel-bayes demo`` in a scratch folder; its text outputs without wall-clock times."""
    import contextlib
    import io
    import json
    import os
    import re
    import tempfile

    from accel_bayes.cli import main

    here = os.getcwd()
    with tempfile.TemporaryDirectory() as tmp:
        os.chdir(tmp)
        try:
            with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
                rc = main(["demo", "--out", "demo", "--no-progress"])
            if rc not in (0, 4):
                raise RuntimeError(f"accel-bayes demo: exit {rc}")
            for name, path in (("positions", "demo/posterior/positions.json"), ("mismatch", "demo/mismatch/report.json")):
                doc = _without_seconds(json.loads(open(path, encoding="utf-8").read()))
                for key, value in _split(doc, name).items():
                    out[f"demo.{key}"] = value
            out["demo.summary"] = np.array(open("demo/posterior/summary.csv", encoding="utf-8").read())
            text = open("demo/report.md", encoding="utf-8").read()
            out["demo.report"] = np.array(re.sub(r"\d+(\.\d+)? s\b", "<seconds> s", text))
        finally:
            os.chdir(here)


STAGES = {"map": run_map, "selfcal": run_selfcal, "selfcal_modes": run_selfcal_modes, "conventional": run_conventional,
          "intrinsics": run_intrinsics, "motion": run_motion, "mismatch": run_mismatch, "conceal": run_conceal,
          "noise": run_noise, "pipelines": run_pipelines, "demo": run_demo}
DEFAULT_STAGES = [s for s in STAGES if s != "demo"]


def compare(a_path: str, b_path: str, tol: float, report: str | None = None, header: str = "") -> int:
    """Print max |a − b|, max |a| and their ratio per output of two .npz files (text outputs: equal
    or not) and return 1 when any is beyond ``tol``; with ``report``, also write that table as a
    Markdown document (``header`` first: how it was made)."""
    a, b = np.load(a_path), np.load(b_path)
    bad = 0
    rows = [f"{'output':34s} {'max|a-b|':>11s} {'max|a|':>11s} {'rel':>10s}"]
    for k in sorted(set(a.files) | set(b.files)):
        if k not in a.files or k not in b.files:
            rows.append(f"{k:34s} missing in {'A' if k not in a.files else 'B'}")
            bad += 1
            continue
        x, y = a[k], b[k]
        if x.dtype.kind in "US":
            same = x.shape == y.shape and bool((x == y).all())
            rows.append(f"{k:34s} {'equal' if same else 'DIFFERENT: ' + str(x)[:300] + ' vs ' + str(y)[:300]}")
            bad += not same
            continue
        if x.shape != y.shape:
            rows.append(f"{k:34s} shape {x.shape} vs {y.shape}")
            bad += 1
            continue
        d = float(np.nanmax(np.abs(x - y))) if x.size else 0.0
        s = float(np.nanmax(np.abs(x))) if x.size else 0.0
        rel = d / s if s > 0 else d
        flag = "" if rel <= tol else "  <-- exceeds tol"
        bad += rel > tol
        rows.append(f"{k:34s} {d:11.3e} {s:11.3e} {rel:10.2e}{flag}")
    verdict = f"{bad} output(s) beyond the tolerance {tol:g}" if bad else f"all outputs within the tolerance {tol:g}"
    exact = sum(1 for r in rows[1:] if r.split()[1:2] in (["equal"], ["0.000e+00"]))
    print("\n".join(rows))
    print(verdict)
    if report:
        from accel_bayes.data.outputs import write_text

        import datetime
        import os
        import platform

        made = (f"# refactor_check: {a_path} against {b_path}\n\nRegenerate with (after making both .npz files, "
                f"module docstring):\n\n    python3 experiments/refactor_check.py --compare {a_path} {b_path} "
                f"--report {report}" + (" --header ..." if header else "") + "\n\n"
                f"Made {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC on {platform.node()} "
                f"({platform.machine()}, {os.cpu_count()} CPUs, Python {platform.python_version()}, "
                f"torch {torch.__version__}).")
        text = made + "\n\n" + (header + "\n\n" if header else "") + f"**{verdict}**; {exact} of {len(rows) - 1} outputs " \
            "identical (text equal or max|a-b| = 0).\n\n```\n" + "\n".join(rows) + "\n```\n"
        write_text(report, text)
    return 1 if bad else 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", help="write the outputs to this .npz")
    ap.add_argument("--compare", nargs=2, metavar=("A", "B"), help="compare two .npz files")
    ap.add_argument("--tol", type=float, default=1e-6, help="max relative difference per output (default 1e-6)")
    ap.add_argument("--report", help="with --compare: also write the table as this Markdown file")
    ap.add_argument("--header", default="", help="with --report: Markdown put before the table (how it was made)")
    ap.add_argument("--only", default=",".join(DEFAULT_STAGES),
                    help=f"comma-separated stages to run (default {','.join(DEFAULT_STAGES)}; also: demo)")
    args = ap.parse_args(argv)
    if args.compare:
        return compare(*args.compare, args.tol, args.report, args.header)
    if not args.out:
        ap.error("give --out or --compare")
    torch.set_num_threads(1)
    _bind_old_paths()
    out: dict = {}
    for name in args.only.split(","):
        t0 = time.perf_counter()
        STAGES[name](out)
        print(f"{name}: {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    np.savez(args.out, **out)
    print(f"wrote {len(out)} outputs to {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
