"""The detector's opt-in unresolved angular jerk on the accelerometers (``fit_grid``'s ``lever``,
``DetectOptions.unresolved_angular_jerk``): its density against a dense Gaussian built here with
explicit cross products, its ML scales against a planted truth, its budget part, and the option."""
import math

import numpy as np
import pytest
import torch

from accel_bayes.mismatch.options import DetectOptions
from accel_bayes.mismatch.unresolved import UnresolvedMotion, _RotTerm, fit_grid
from tests.mismatch._true_clocks import true_clock_case


def _cross(c):
    """[c]× (3, 3) written out: [c]× w = c × w."""
    return np.array([[0.0, -c[2], c[1]], [c[2], 0.0, -c[0]], [-c[1], c[0], 0.0]])


def _board(K=5, seed=0):
    rng = np.random.default_rng(seed)
    r = rng.normal(0, 0.02, (K, 3))
    return r, r - r.mean(0)


def test_rot_term_density_is_the_dense_gaussian():
    """Per sample: v + e²s² + e²a²|row of [c_k]×|² on the diagonal, s² d dᵀ ⊗ I₃ and a² (d_k [c_k]×)(d_j [c_j]×)ᵀ
    off it; one triad masked out of one sample.  Against scipy's dense density to 1e-9 nats."""
    from scipy.stats import multivariate_normal

    K, T = 4, 6
    r, c = _board(K, 1)
    rng = np.random.default_rng(2)
    d = rng.normal(0, 3e-4, (T, K))
    w = np.ones((T, K))
    w[2, 1] = 0.0
    y = rng.normal(0, 0.05, (T, K, 3)) * w[..., None]
    v = rng.uniform(1e-3, 3e-3, (T, K))
    s2, a2, e2 = rng.uniform(1e4, 4e4, T), rng.uniform(1e8, 4e8, T), (2e-4) ** 2
    dt, wt = torch.as_tensor(d * w), torch.as_tensor(w)
    term = _RotTerm(dt, wt, torch.as_tensor(r))
    got = term.loglik(torch.as_tensor(y), torch.as_tensor(v) + e2 * torch.as_tensor(s2)[:, None],
                      torch.as_tensor(s2), torch.as_tensor(a2), e2).numpy()
    for t in range(T):
        keep = [k for k in range(K) if w[t, k] > 0]
        L = np.concatenate([np.concatenate([d[t, k] * np.eye(3), d[t, k] * _cross(c[k])], 1) for k in keep], 0)
        diag = np.concatenate([v[t, k] + e2 * s2[t] + e2 * a2[t] * ((c[k] ** 2).sum() - c[k] ** 2) for k in keep])
        S = np.diag(diag) + L @ np.diag([s2[t]] * 3 + [a2[t]] * 3) @ L.T
        want = multivariate_normal(np.zeros(len(diag)), S).logpdf(y[t, keep].reshape(-1))
        assert abs(got[t] - want) < 1e-9


def test_fit_grid_recovers_a_planted_angular_jerk():
    """Residuals drawn from the model (jerk 200 m/s³, angular jerk 2·10⁴ rad/s³ in cell 0 and 10⁴ in cell 1,
    white 0.02 m/s², centred sawtooth-like ages of 0.3 ms rms, 6 triads on a 30 mm board, 4000 samples,
    seed 3): the fitted scales within 10 % (the scales' relative standard errors here are ≈ 3 %); without
    the lever the white variance takes the angular part instead (excess ≥ 3× the fit's)."""
    K, T = 6, 4000
    r, c = _board(K, 3)
    r = r * 1.5
    c = r - r.mean(0)
    rng = np.random.default_rng(3)
    age = rng.uniform(0, 1e-3, (T, K))
    d = age - age.mean(1, keepdims=True)
    cell = (np.arange(T) % 2).astype(np.int64)
    s = np.where(cell == 0, 200.0, 200.0)
    a = np.where(cell == 0, 2e4, 1e4)
    m = rng.normal(0, 1, (T, 3)) * s[:, None]
    om = rng.normal(0, 1, (T, 3)) * a[:, None]
    y = np.empty((T, K, 3))
    for k in range(K):
        y[:, k] = d[:, k, None] * (m + np.cross(om, c[k])) + rng.normal(0, 0.02, (T, 3))
    yt, dt = torch.as_tensor(y), torch.as_tensor(d)
    wt = torch.ones(T, K, dtype=torch.float64)
    ct = torch.as_tensor(cell)
    floor = torch.full((K,), 0.02 ** 2 * 0.5, dtype=torch.float64)
    g = fit_grid(yt, dt, wt, ct, 2, v_floor=floor, std=False, lever=torch.as_tensor(r))
    assert g.a2 is not None and g.a2_no_age_error is not None
    ang = torch.sqrt(g.a2).numpy()
    assert abs(ang[0] / 2e4 - 1) < 0.1 and abs(ang[1] / 1e4 - 1) < 0.1
    assert abs(math.sqrt(float(g.s2[0])) / 200 - 1) < 0.1
    g0 = fit_grid(yt, dt, wt, ct, 2, v_floor=floor, std=False)
    assert g0.a2 is None
    excess = float((g.v - floor).mean())
    excess0 = float((g0.v - floor).mean())
    assert excess0 > 3 * max(excess, 1e-6)
    assert g.loglik > g0.loglik + 100


def test_term_predicts_the_angular_part_and_scores_it():
    """``UnresolvedMotion`` with ``angular_jerk_rms``: the accelerometers' predicted variance per channel is the
    jerk's s²d² plus a² d² |c_k|²·⅔ (the mean of the triad's three squared rows of [c_k]×); the gyros' unchanged;
    its log-likelihood is the rank-6 density, higher than the jerk-only term's on data that carry the rotation."""
    K, T = 4, 3
    r, c = _board(K, 4)
    d = torch.tensor(np.random.default_rng(5).normal(0, 3e-4, (T, K)))
    lab = torch.zeros(T, dtype=torch.long)
    term = UnresolvedMotion(d=d, lab=lab, edges=[], jerk_rms=torch.tensor([100.0], dtype=torch.float64),
                            angular_acc_rms=torch.tensor([5.0], dtype=torch.float64),
                            angular_jerk_rms=torch.tensor([3e4], dtype=torch.float64),
                            lever=torch.as_tensor(c))
    va, vg = term.predicted_variance()
    c2 = (c ** 2).sum(1)
    want = (100.0 ** 2 + 3e4 ** 2 * c2[None, :] * 2 / 3) * d.numpy() ** 2
    assert np.allclose(va[..., 0].numpy(), want, rtol=1e-12) and np.allclose(va[..., 2].numpy(), want, rtol=1e-12)
    assert np.allclose(vg[..., 1].numpy(), 25.0 * d.numpy() ** 2, rtol=1e-12)
    plain = UnresolvedMotion(d=d, lab=lab, edges=[], jerk_rms=term.jerk_rms, angular_acc_rms=term.angular_acc_rms)
    rng = np.random.default_rng(6)
    om = rng.normal(0, 3e4, (T, 3))
    y = torch.as_tensor(np.stack([d.numpy()[:, k, None] * np.cross(om, c[k]) for k in range(K)], 1))
    w = torch.ones(T, K, dtype=torch.float64)
    v = torch.full((T, K), 1e-4, dtype=torch.float64)
    zero = torch.zeros(T, K, 3, dtype=torch.float64)
    assert float(term.loglik(y, zero, w, v, v).sum()) > float(plain.loglik(y, zero, w, v, v).sum())


def test_option_is_opt_in_and_leaves_default_settings_alone():
    import argparse

    from accel_bayes.cli import mismatch as cli

    base = DetectOptions()
    assert base.unresolved_angular_jerk is False and "unresolved_angular_jerk" not in base.to_settings()
    on = DetectOptions(unresolved_angular_jerk=True)
    assert on.to_settings()["unresolved_angular_jerk"] is True
    assert on.fingerprint("x")["options"] != base.fingerprint("x")["options"]
    ap = argparse.ArgumentParser()
    sub = ap.add_subparsers()
    cli.register(sub)
    args = ap.parse_args(["mismatch", "rec.nc", "--out", "o", "--unresolved-angular-jerk"])
    assert DetectOptions.from_args(args).unresolved_angular_jerk is True
    assert DetectOptions.from_args(ap.parse_args(["mismatch", "rec.nc", "--out", "o"])).unresolved_angular_jerk is False


def _stage_on_clockgen(drop=()):
    """The stage with and without the angular jerk on the shared true-clock case (:mod:`tests.mismatch._true_clocks`:
    clockgen's clock case 3, mimu4444 at 62.5 Hz, 8 s, no linear errors); ``drop``: motion pieces removed."""
    from accel_bayes.mismatch.budget import residual_budget
    from accel_bayes.mismatch.unresolved_stage import unresolved_stage

    prep, fit, _, clocks = true_clock_case(drop=drop)
    kw = dict(threshold=24.0, alpha=0.01, m=400, n_permutations=5, seed=0)
    plain = unresolved_stage(prep, fit, clocks, **kw)
    rot = unresolved_stage(prep, fit, clocks, angular_jerk=True, **kw)
    b = [next(r for r in residual_budget(prep, fit, fit, extra=[st.effect]) if r["sensor"] == "acc"
              and r["regime"] == "all") for st in (plain, rot)]
    return plain, rot, b


def test_stage_names_the_rotational_vibration_through_the_lever_arms():
    """clockgen's board vibrates in rotation and translation (an independent first-principles generator): the
    stage's angular jerk is large with the rotational vibration and impacts and ≥ 5× smaller with them dropped
    from the motion; the accelerometers' b rises with the term and stays under 1.3 a; the finding carries the
    scales; the gyro half is the jerk-only stage's."""
    plain, rot, (b0, b1) = _stage_on_clockgen()
    acc = rot.info["sensors"]["acc"]
    assert rot.info["angular_jerk"] is True and "angular_jerk_rms" not in plain.info["sensors"]["acc"]
    assert all(math.isfinite(x) and x > 0 for x in acc["angular_jerk_rms"])
    assert rot.effect.vocabulary_parameters()["angular_jerk_rms"] == pytest.approx(acc["angular_jerk_rms"])
    assert b1["excess_var_explained"] > b0["excess_var_explained"] and b1["excess_var_explained"] < 1.3 * b1["excess_var_observed"]
    assert rot.info["sensors"]["gyro"]["angular_acc_rms"] == plain.info["sensors"]["gyro"]["angular_acc_rms"]
    _, rot_q, _ = _stage_on_clockgen(drop=("rot_vib", "rot_imp"))
    quiet = rot_q.info["sensors"]["acc"].get("angular_jerk_rms")
    assert quiet is not None and np.median(quiet) < 0.2 * np.median(acc["angular_jerk_rms"]), (quiet, acc["angular_jerk_rms"])
