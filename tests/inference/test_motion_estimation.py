"""Per-sample motion from a calibrated array (accel_bayes.inference.motion_estimate).

Independent checks: the factored normal equations against autograd on the one signal model
(models.specific_force), exact recovery of simulated ω, ω̇, s without noise, the reported noise
std against the empirical error spread, draws against first-order geometry propagation, and
the calibration file checks.
"""
import json

import numpy as np
import pytest
import torch

from accel_bayes import mimu4444_8
from accel_bayes.errors import UserError
from accel_bayes.physics.geometry import quat_to_matrix
from accel_bayes.physics.models import specific_force
from accel_bayes.inference.motion_estimate import (
    _cost_grad_hess,
    _Data,
    estimate_motion,
    load_calibration,
    write_motion,
)
from accel_bayes.physics.jacobians import AxisProjection
from accel_bayes.simulate import simulate

DEG = np.pi / 180


def _sim(T=500, seed=1, noise=True, clip=False, **kw):
    arr = mimu4444_8()
    opts = {} if noise else {"acc_noise_std": 0.0, "gyro_noise_std": 0.0, "validate": False}
    res = simulate(arr, "iid", T=T, rate=100, seed=seed, clip=clip, position_error_std=1e-4, **opts, **kw)
    rel = (res.true_positions - res.true_positions[0]).numpy()
    tr = res.motion
    s_ref = specific_force(res.true_positions[0:1], tr.omega, tr.omega_dot, tr.s)[:, 0]
    truth = {"omega": tr.omega.numpy(), "omega_dot": tr.omega_dot.numpy(), "s": s_ref.numpy()}
    return res.recording, rel, truth


def _positions_doc(rel, std=1e-4, orientation=None):
    imus = []
    for k, p in enumerate(rel):
        e = {"imu": k, "mean": p.tolist(), "std": [0.0] * 3 if k == 0 else [std] * 3,
             "cov": (np.zeros((3, 3)) if k == 0 else std**2 * np.eye(3)).tolist()}
        if orientation is not None:
            e["orientation"] = orientation[k].tolist()
        imus.append(e)
    return {"schema": "accel_bayes.positions/1", "method": "map", "reference_imu": 0, "imus": imus,
            "diagnostics": {"seconds": 0.0}}


# ------------------------------------------------------------------ the kernel
def test_factored_normal_equations_match_autograd():
    """JᵀWe and JᵀWJ of the factored kernel equal those of autograd through specific_force with
    per-axis weights (some zero) and the gyro term, for one geometry and for a batch of draws."""
    gen = torch.Generator().manual_seed(0)
    K, N = 5, 7
    q = torch.nn.functional.normalize(torch.randn(K, 4, generator=gen, dtype=torch.float64), dim=-1)
    R = quat_to_matrix(q)
    for r in (0.01 * torch.randn(K, 3, generator=gen, dtype=torch.float64),
              0.01 * torch.randn(3, K, 3, generator=gen, dtype=torch.float64)):
        G = r.shape[:-2]
        x = torch.randn(*G, N, 9, generator=gen, dtype=torch.float64) * torch.tensor([20.0] * 3 + [500.0] * 3 + [20.0] * 3)
        y = 30 * torch.randn(N, K, 3, generator=gen, dtype=torch.float64)
        w = torch.rand(N, K, 3, generator=gen, dtype=torch.float64) * (torch.rand(N, K, 3, generator=gen) > 0.2)
        yg = torch.randn(N, K, 3, generator=gen, dtype=torch.float64)
        wg = torch.rand(N, K, 3, generator=gen, dtype=torch.float64)
        Gam = torch.einsum("kai,nka,kaj->nij", R, wg, R)
        GY = torch.einsum("kai,nka->ni", R, wg * yg)
        d = _Data(y.reshape(N, -1), w.reshape(N, -1), Gam, GY, (wg * yg * yg).sum((1, 2)))
        cost, g, H = _cost_grad_hess(x, AxisProjection(R, r), d)

        def weighted_residuals(v, rr, n):
            """√w·(model) for sample n (the data enter only as a constant offset)."""
            f = specific_force(rr, v[0:3], v[3:6], v[6:9])  # (K, 3) array frame
            fs = torch.einsum("kab,kb->ka", R, f)  # sensor frame
            gs = torch.einsum("kab,b->ka", R, v[0:3])
            return torch.cat(((w[n].sqrt() * (y[n] - fs)).reshape(-1), (wg[n].sqrt() * (yg[n] - gs)).reshape(-1)))

        for idx in ([()] if not G else [(i,) for i in range(G[0])]):
            rr = r[idx]
            for n in (0, 3):
                xn = x[idx][n]
                e = weighted_residuals(xn, rr, n)
                Jr = torch.autograd.functional.jacobian(lambda v: weighted_residuals(v, rr, n), xn)
                torch.testing.assert_close(cost[idx][n], (e * e).sum(), rtol=1e-12, atol=1e-9)
                torch.testing.assert_close(g[idx][n], -Jr.T @ e, rtol=1e-10, atol=1e-8)  # JᵀWe, J = ∂f/∂x
                torch.testing.assert_close(H[idx][n], Jr.T @ Jr, rtol=1e-10, atol=1e-8)


# ------------------------------------------------------------------ estimates
def test_noise_free_recovers_motion():
    rec, rel, truth = _sim(T=400, noise=False)
    ds = estimate_motion(rec, rel, acc_noise_std=0.04, gyro_noise_std=1e-3)
    for name in ("omega", "omega_dot", "s"):
        np.testing.assert_allclose(ds[name].values, truth[name], rtol=0, atol=1e-8)
    assert ds["converged"].values.all() and not ds["ill_posed"].values.any()
    assert ds.attrs["geometry_method"] == "none"
    assert float(np.abs(ds["omega_std_geometry"]).max()) == 0.0


def test_noise_free_accelerometers_alone():
    """Without gyros (all weights zero) ω comes from the accelerometers; started from a wrong
    magnitude with the right sign, the solve still lands on the truth."""
    rec, rel, truth = _sim(T=200, seed=4, noise=False)
    rec.gyro_clipped = np.ones((rec.T, rec.K), bool)
    rec.gyro = 0.5 * rec.gyro  # "clipped" readings: right sign, wrong magnitude
    rec.gyro_range = 1e-6  # every axis counts as at the range
    ds = estimate_motion(rec, rel, acc_noise_std=0.04, gyro_noise_std=1e-3)
    assert ds["omega_needs_acc"].values.all() and ds["gyro_clipped"].values.all()
    for name in ("omega", "omega_dot", "s"):
        np.testing.assert_allclose(ds[name].values, truth[name], rtol=0, atol=1e-7)


def test_reported_noise_std_matches_empirical_error():
    """Noise only (exact positions): the error std over samples, in units of the reported std,
    is 1 within 15 % for every component (T = 3000 → ±2.6 % sampling error at 2σ)."""
    rec, rel, truth = _sim(T=3000, seed=3, gyro_noise_std=0.003)
    ds = estimate_motion(rec, rel)
    for name in ("omega", "omega_dot", "s"):
        z = (ds[name].values - truth[name]) / ds[f"{name}_std"].values
        ratio = z.std(0)
        assert np.all(np.abs(ratio - 1) < 0.15), (name, ratio)
    np.testing.assert_array_equal(ds["omega_std"].values, ds["omega_std_noise"].values)
    chi2 = ds["chi2"].values.sum() / ds["dof"].values.sum()
    assert abs(chi2 - 1) < 0.03


def test_clipped_gyro_samples_flagged_and_estimated():
    rec, rel, truth = _sim(T=1500, seed=5, clip=True, motion_kwargs={"omega_std": 1500 * DEG})
    ds = estimate_motion(rec, rel)
    gc = ds["gyro_clipped"].values
    assert 0.2 < gc.mean() < 0.8 and ds["omega_needs_acc"].values[gc].mean() > 0.5
    assert not ds["ill_posed"].values.any()
    for name in ("omega", "omega_dot", "s"):
        z = (ds[name].values - truth[name]) / ds[f"{name}_std"].values
        assert np.all(np.abs(z[gc].std(0) - 1) < 0.2), (name, z[gc].std(0))


def test_geometry_uncertainty_adds_and_scales():
    rec, rel, _ = _sim(T=300, seed=6)
    base = estimate_motion(rec, _positions_doc(rel, std=1e-4), geometry="linear")
    big = estimate_motion(rec, _positions_doc(rel, std=4e-4), geometry="linear")
    for name in ("omega_dot", "s"):
        assert np.all(big[f"{name}_std"].values > base[f"{name}_std"].values)
        # first-order propagation is linear in the position std
        np.testing.assert_allclose(big[f"{name}_std_geometry"].values, 4 * base[f"{name}_std_geometry"].values, rtol=1e-9)
        np.testing.assert_allclose(big[f"{name}_std_noise"].values, base[f"{name}_std_noise"].values)
        tot = np.sqrt(base[f"{name}_std_noise"].values ** 2 + base[f"{name}_std_geometry"].values ** 2)
        np.testing.assert_allclose(base[f"{name}_std"].values, tot, rtol=1e-10)
    # draws: the same growth, up to Monte Carlo error
    d1 = estimate_motion(rec, _positions_doc(rel, std=1e-4), draws=100, seed=1)
    d4 = estimate_motion(rec, _positions_doc(rel, std=4e-4), draws=100, seed=1)
    ratio = np.median(d4["s_std_geometry"].values / d1["s_std_geometry"].values)
    assert 3.6 < ratio < 4.4
    assert np.all(d4["s_std"].values >= d1["s_std"].values)


def test_draws_agree_with_linear_propagation():
    """Re-solving under 200 geometry draws and first-order propagation give the same geometry
    std (median ratio over moving samples within 10 %; each draw std carries ~5 % MC error)."""
    rec, rel, _ = _sim(T=300, seed=7)
    doc = _positions_doc(rel, std=2e-4)
    lin = estimate_motion(rec, doc, geometry="linear")
    dr = estimate_motion(rec, doc, draws=200, seed=3)
    assert dr.attrs["geometry_method"] == "draws" and dr.attrs["draws"] == 200
    assert dr.attrs["draws_last_step_max_in_noise_std"] < 1e-3
    for name in ("omega", "omega_dot", "s"):
        r = dr[f"{name}_std_geometry"].values / lin[f"{name}_std_geometry"].values
        assert np.all(np.abs(np.median(r, 0) - 1) < 0.1), (name, np.median(r, 0))
    # same seed → identical; another seed → different draws
    again = estimate_motion(rec, doc, draws=200, seed=3)
    np.testing.assert_array_equal(again["s_std"].values, dr["s_std"].values)
    other = estimate_motion(rec, doc, draws=200, seed=4)
    assert not np.array_equal(other["s_std"].values, dr["s_std"].values)
    none = estimate_motion(rec, doc, draws=0)
    assert none.attrs["geometry_method"] == "none" and float(none["s_std_geometry"].max()) == 0.0
    np.testing.assert_array_equal(none["s_std"].values, dr["s_std_noise"].values)


def test_calibration_orientation_is_used():
    """Outputs simulated with rotated IMUs: the nominal orientations misfit, the calibration's
    orientations fit exactly."""
    arr = mimu4444_8()
    from accel_bayes.physics.geometry import boxplus

    q_true = boxplus(arr.orientations, 0.05 * torch.randn(8, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64))
    res = simulate(arr, "iid", T=100, seed=2, clip=False, true_orientations=q_true, acc_noise_std=0.0,
                   gyro_noise_std=0.0, validate=False, position_error_std=0.0)
    rel = (res.true_positions - res.true_positions[0]).numpy()
    nominal = estimate_motion(res.recording, _positions_doc(rel, 0.0), acc_noise_std=0.04, gyro_noise_std=1e-3)
    given = estimate_motion(res.recording, _positions_doc(rel, 0.0, orientation=q_true.numpy()),
                            acc_noise_std=0.04, gyro_noise_std=1e-3)
    np.testing.assert_allclose(given["omega"].values, res.motion.omega.numpy(), atol=1e-8)
    assert np.abs(nominal["omega"].values - res.motion.omega.numpy()).max() > 0.1
    assert given.attrs["orientations"] == "calibration"


def test_intrinsics_are_applied():
    from accel_bayes.pipelines.motion import prepare_motion
    from accel_bayes.prep.intrinsics import Intrinsics

    rec, rel, truth = _sim(T=200, seed=8, noise=False)
    K = rec.K
    rng = np.random.default_rng(0)
    b = rng.normal(0, 0.3, (K, 3))
    T = np.tile(np.eye(3), (K, 1, 1)) + np.tril(rng.normal(0, 0.01, (K, 3, 3)))
    bg = rng.normal(0, 0.02, (K, 3))
    raw = rec.copy()
    raw.acc = np.einsum("kij,tkj->tki", np.linalg.inv(T), rec.acc) + b
    raw.gyro = rec.gyro + bg
    nan = np.full((K,), np.nan)
    intr = Intrinsics(acc_bias=b, acc_matrix=T, acc_cov=np.zeros((K, 9, 9)), gyro_bias=bg,
                      gyro_bias_cov=np.zeros((K, 3, 3)), residual_rms=nan, chi2_per_dof=nan, acc_noise_std=nan,
                      n_rests=np.zeros(K, int), n_orientations=0, g=9.80665, source="test")
    ds = estimate_motion(prepare_motion(raw, intr), rel, acc_noise_std=0.04, gyro_noise_std=1e-3)
    for name in ("omega", "omega_dot", "s"):
        np.testing.assert_allclose(ds[name].values, truth[name], atol=1e-8)
    assert ds.attrs["intrinsics"] == "test"


# ------------------------------------------------------------------ calibration checks
def test_bad_calibration_names_the_field(tmp_path):
    rel = np.zeros((8, 3))
    rel[1:] = np.random.default_rng(0).normal(0, 0.01, (7, 3))
    good = _positions_doc(rel)
    cal = load_calibration(good, 8)
    assert cal.reference_imu == 0 and cal.cov[1, 0, 0] == pytest.approx(1e-8)

    def bad(mutate, match, K=8):
        d = json.loads(json.dumps(good))
        mutate(d)
        with pytest.raises(UserError, match=match):
            load_calibration(d, K)

    bad(lambda d: d.update(schema="accel_bayes.positions/0"), r"calibration\.schema")
    bad(lambda d: d.update(imus=[]), r"calibration\.imus")
    bad(lambda d: d["imus"][3].update(mean=[0.0, 1.0]), r"calibration\.imus\[3\]\.mean")
    bad(lambda d: d["imus"][2].update(cov=[[1e-8, 0, 0], [0, -1e-8, 0], [0, 0, 1e-8]]), r"calibration\.imus\[2\]\.cov")
    bad(lambda d: d["imus"][2].update(cov=[[1e-8, 5e-9, 0], [0, 1e-8, 0], [0, 0, 1e-8]]), r"calibration\.imus\[2\]\.cov")
    bad(lambda d: d["imus"][4].update(imu=7), r"calibration\.imus\[4\]\.imu")
    bad(lambda d: (d["imus"][5].pop("cov"), d["imus"][5].update(std=[-1, 0, 0])), r"calibration\.imus\[5\]\.std")
    bad(lambda d: d["imus"][1].update(orientation=[0, 0, 0, 0]), r"calibration\.imus\[1\]\.orientation")
    bad(lambda d: d.update(reference_imu=9), r"calibration\.reference_imu")
    bad(lambda d: None, r"calibration\.imus: lists 8 IMUs, the recording has 4", K=4)
    with pytest.raises(UserError, match="shape"):
        load_calibration(np.zeros((8, 2)))
    p = tmp_path / "positions.json"
    p.write_text("{not json")
    with pytest.raises(UserError, match="not valid JSON"):
        load_calibration(p)
    d = json.loads(json.dumps(good))
    d["imus"][6]["cov"] = "x"
    p.write_text(json.dumps(d))
    with pytest.raises(UserError, match=r"positions\.json: calibration\.imus\[6\]\.cov"):
        load_calibration(p)
    with pytest.raises(FileNotFoundError):
        load_calibration(tmp_path / "missing.json")


def test_cli_and_netcdf(tmp_path, capsys):
    import xarray as xr

    from accel_bayes.cli import main
    from accel_bayes.data.io import write_recording

    rec, rel, truth = _sim(T=150, seed=9)
    src = tmp_path / "rec.nc"
    write_recording(rec, src)
    cal = tmp_path / "positions.json"
    cal.write_text(json.dumps(_positions_doc(rel)))
    out = tmp_path / "motion.nc"
    assert main(["motion", str(src), "--calibration", str(cal), "-o", str(out), "--draws", "20", "--seed", "2"]) == 0
    text = capsys.readouterr().out
    assert "omega_dot" in text and "wrote" in text
    with xr.open_dataset(out, engine="h5netcdf") as ds:
        assert ds["omega"].attrs["units"] == "rad s-1" and ds.attrs["schema"] == "accel_bayes.motion/1"
        assert ds.attrs["draws"] == 20 and ds["s_std_geometry"].dims == ("time", "axis")
        np.testing.assert_allclose(ds["omega"].values, truth["omega"], atol=0.05)
    # refuses to overwrite; bad calibration → exit 2 with one line naming the field
    assert main(["motion", str(src), "--calibration", str(cal), "-o", str(out)]) == 2
    capsys.readouterr()
    d = _positions_doc(rel)
    d["imus"][2]["mean"] = [0.0, "a", 0.0]
    cal.write_text(json.dumps(d))
    assert main(["motion", str(src), "--calibration", str(cal), "-o", str(tmp_path / "m2.nc")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "imus[2].mean" in err
    assert not (tmp_path / "m2.nc").exists()
    ds = estimate_motion(rec, rel)
    with pytest.raises(UserError, match="exists"):
        write_motion(ds, out)
