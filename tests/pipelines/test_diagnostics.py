"""ArviZ conversion, statistics, NetCDF round trip and plots (accel_bayes.diagnostics: arviz_calls, stats, plots)."""
import math

import matplotlib
import numpy as np
import pytest
import scipy.stats

from accel_bayes.diagnostics import arviz_calls as dg_az, plots as dg_plots, stats as dg_stats
from accel_bayes.physics.arrays import mimu4444_8
from accel_bayes.errors import UserError

C, D, AF = 3, 400, 7  # chains, draws, free triads (8-IMU board)


def _draws(shift_chain=0.0, seed=0):
    rng = np.random.default_rng(seed)
    arr = mimu4444_8()
    pos = arr.positions.numpy()
    theta = pos[1:] - pos[0]
    x = theta + 1e-4 * rng.standard_normal((C, D, AF, 3))
    x[0] += shift_chain
    return x, rng


def _idata(**kw):
    x, rng = _draws(**kw)
    return dg_az.to_inference_data(
        x, list(range(1, 8)), rng.standard_normal((C, D)), log_prior=np.full((C, D), -3.0),
        accepted=rng.random((C, D)) < 0.2, accept_prob=rng.random((C, D)), step_size=np.array([0.1, 0.2, 0.3]),
        reference_imu=0, attrs={"seed": 5, "method": "pmmh"},
    ), x


def test_inference_data_dims_coords_groups():
    idata, x = _idata()
    r = idata.posterior["r"]
    assert r.dims == ("chain", "draw", "imu", "axis")
    assert list(r.coords["imu"].values) == list(range(1, 8))
    assert list(r.coords["axis"].values) == ["x", "y", "z"]
    np.testing.assert_array_equal(r.values, x)
    ss = idata.sample_stats
    for name in ("lp", "log_phat", "log_prior", "accept", "acceptance_rate", "step_size"):
        assert name in ss, name
    np.testing.assert_allclose(ss["lp"].values, ss["log_phat"].values - 3.0)
    assert ss["accept"].dtype == bool
    np.testing.assert_array_equal(ss["step_size"].values[:, 0], [0.1, 0.2, 0.3])
    np.testing.assert_array_equal(idata.log_likelihood["y"].values, ss["log_phat"].values)
    assert idata.posterior.attrs["reference_imu"] == 0 and idata.posterior.attrs["seed"] == 5


def test_pointwise_log_likelihood_and_shape_errors():
    x, rng = _draws()
    pw = rng.standard_normal((C, D, 11))
    idata = dg_az.to_inference_data(x, range(1, 8), pw.sum(-1), pointwise_log_lik=pw)
    assert idata.log_likelihood["y"].dims == ("chain", "draw", "time")
    with pytest.raises(UserError, match="imu_labels"):
        dg_az.to_inference_data(x, range(1, 7))
    with pytest.raises(UserError, match="log_phat"):
        dg_az.to_inference_data(x, range(1, 8), np.zeros((C, D + 1)))
    with pytest.raises(UserError, match="draws"):
        dg_az.to_inference_data(x[0], range(1, 8))


def test_summary_statistics_and_rhat():
    idata, x = _idata()
    s = dg_az.summarize(idata)
    assert len(s) == AF * 3
    for col in ("mean", "sd", "mcse_mean", "mcse_sd", "ess_bulk", "ess_tail", "r_hat"):
        assert col in s.columns, col
    # unrounded values: the mean of r[3, y] is the plain average of its draws
    assert s.loc["r[3, y]", "mean"] == pytest.approx(x[:, :, 2, 1].mean(), rel=1e-12)
    # independent draws: R̂ ≈ 1 and ESS ≈ C·D; one chain shifted by 3 sd: R̂ clearly > 1.1
    assert dg_az.rhat_max(idata) < 1.01
    assert dg_az.ess_bulk_min(idata) > 0.7 * C * D
    bad, _ = _idata(shift_chain=3e-4)
    assert dg_az.rhat_max(bad) > 1.1


def test_posterior_moments_match_numpy():
    idata, x = _idata()
    mom = dg_stats.posterior_moments(idata)
    flat = x.reshape(-1, AF, 3)
    np.testing.assert_allclose(mom["mean"], flat.mean(0), rtol=1e-12)
    for k in range(AF):
        np.testing.assert_allclose(mom["cov"][k], np.cov(flat[:, k].T), rtol=1e-10)
    assert mom["imu"] == list(range(1, 8))


def test_netcdf_round_trip(tmp_path):
    idata, x = _idata()
    p = dg_az.save(idata, tmp_path / "post.nc")
    back = dg_az.load(p)
    np.testing.assert_array_equal(back.posterior["r"].values, x)
    np.testing.assert_array_equal(back.sample_stats["accept"].values, idata.sample_stats["accept"].values)
    assert list(back.posterior["r"].coords["axis"].values) == ["x", "y", "z"]
    assert back.posterior.attrs["reference_imu"] == 0
    with pytest.raises(FileNotFoundError):
        dg_az.load(tmp_path / "missing.nc")


def test_ellipse_geometry_matches_chi2():
    # the 2-D Gaussian ellipse with probability p has squared Mahalanobis radius χ²₂(p)
    for p in (0.5, 0.95):
        assert dg_plots._chi2_2_quantile(p) == pytest.approx(scipy.stats.chi2.ppf(p, 2), rel=1e-12)
    arr = mimu4444_8()
    mom = {"imu": [1], "mean": np.array([[0.0, 0.0, -2e-3]]),
           "cov": np.array([[[4e-8, 0, 0], [0, 1e-8, 0], [0, 0, 1e-8]]])}
    fig = dg_plots.plot_ellipses(mom, arr, level=(0.5, 0.95))
    ells = [p for ax in fig.axes for p in ax.patches if isinstance(p, matplotlib.patches.Ellipse)]
    assert len(ells) == 2
    widths = sorted(e.width for e in ells)
    # semi-axis along x = √χ²₂(p)·σ_x, σ_x = 0.2 mm; drawn in mm
    assert widths[0] == pytest.approx(2 * math.sqrt(scipy.stats.chi2.ppf(0.5, 2)) * 0.2, rel=1e-9)
    assert widths[1] == pytest.approx(2 * math.sqrt(scipy.stats.chi2.ppf(0.95, 2)) * 0.2, rel=1e-9)
    # IMU 1 is on the bottom side (z < 0): its ellipse goes in the second panel, at nominal x–y
    assert len(fig.axes) == 2 and len(fig.axes[1].patches) > len(fig.axes[0].patches) - 8
    assert ells[0].center == pytest.approx(tuple(arr.positions[1, :2].numpy() * 1e3))
    with pytest.raises(UserError, match="level"):
        dg_plots.plot_ellipses(mom, arr, level=1.5)


def test_plots_return_figures_and_files(tmp_path):
    idata, _ = _idata()
    arr = mimu4444_8()
    for fn in (dg_plots.plot_trace, dg_plots.plot_rank, dg_plots.plot_autocorr):
        fig = fn(idata, max_imus=1)
        assert isinstance(fig, matplotlib.figure.Figure)
    fig = dg_plots.plot_ellipses(idata, arr, prior_std=3e-3, exaggerate=5)
    assert "×5" in fig.axes[0].get_title()
    # 95 % semi-axis of a 0.1 mm posterior ≈ 0.245 mm; a quarter of a 4 mm package wants ×4.1 → 2
    assert dg_plots.auto_exaggeration(idata, arr) == 2.0
    tiny = {"imu": [1], "mean": np.zeros((1, 3)), "cov": np.eye(3)[None] * 1e-10}  # 10 µm: ×40.8 → 20
    assert dg_plots.auto_exaggeration(tiny, arr) == 20.0
    paths = dg_plots.save_plots(idata, arr, tmp_path, max_imus=1)
    assert [p.name for p in paths] == ["trace.png", "rank.png", "autocorr.png", "ellipses.png"]
    assert all(p.stat().st_size > 1000 for p in paths)


def test_convergence_rule_R_hat_below_1_01_and_100_ESS_per_chain():
    from accel_bayes.diagnostics.stats import convergence_warnings

    assert convergence_warnings(1.009, 400.0, 4) == []
    assert [w.split()[0] for w in convergence_warnings(1.01, 400.0, 4)] == ["max"]  # R̂ = 1.01 is not < 1.01
    (w,) = convergence_warnings(1.0, 399.0, 4)
    assert "399 < 100 per chain (400 for 4)" in w
    assert len(convergence_warnings(None, float("nan"), 1)) == 2  # not computable: not established


def _ar1(rho, C, D, P, seed):
    """C independent stationary AR(1) chains of D draws, P coordinates, unit marginal variance."""
    rng = np.random.default_rng(seed)
    e = rng.normal(size=(C, D, P)) * np.sqrt(1 - rho * rho)
    x = np.empty((C, D, P))
    x[:, 0] = rng.normal(size=(C, P))
    for t in range(1, D):
        x[:, t] = rho * x[:, t - 1] + e[:, t]
    return x


def test_convergence_check_on_chains_with_a_known_answer():
    """iid normal draws converge; chains with shifted means fail R-hat (at the shifted coordinate);
    strongly autocorrelated AR(1) chains fail ESS (ρ = 0.98: ESS ≈ N(1−ρ)/(1+ρ) ≈ 40 of 4000
    draws) though their R-hat may pass; too few draws cannot establish anything."""
    rng = np.random.default_rng(0)
    iid = rng.normal(size=(4, 500, 2, 3))
    ok = dg_stats.convergence_check(iid)
    assert ok.converged and ok.failed == [] and ok.rhat_max < 1.01 and ok.ess_bulk_min >= 400
    assert ok.ess_tail_min >= 400 and (ok.rhat_limit, ok.ess_min) == (1.01, 400.0)
    assert ok.chains == 4 and ok.draws == 500
    d = ok.as_dict()
    assert d["converged"] is True and d["draws"] == 500 and d["rhat_at"].startswith("coordinate ")

    shifted = iid.copy()
    shifted[0, :, 1, 2] += 2.0  # chain 0 sits elsewhere in coordinate r[2, z]
    names = [f"r[{i}, {a}]" for i in (1, 2) for a in "xyz"]
    bad = dg_stats.convergence_check(shifted, names=names)
    assert not bad.converged and bad.rhat_at == "r[2, z]" and bad.rhat_max > 1.1
    assert bad.failed[0].startswith("R-hat") and "r[2, z]" in bad.failed[0] and ">= 1.01" in bad.failed[0]
    assert "1 of 6 coordinates" in bad.failed[0]

    ar = dg_stats.convergence_check(_ar1(0.98, 4, 1000, 3, seed=1))
    assert not ar.converged and ar.ess_bulk_min < 400
    assert any(f.startswith("bulk ESS") and "< 400" in f for f in ar.failed)
    # the same chains with a lenient threshold pass, and a stricter one fails R-hat too
    assert dg_stats.convergence_check(_ar1(0.5, 4, 1000, 3, seed=1), ess_min=400).converged
    assert not dg_stats.convergence_check(iid, rhat_max=1.0001).converged

    few = dg_stats.convergence_check(iid[:, :2])
    assert not few.converged and any("could not be computed" in f for f in few.failed)
    with pytest.raises(UserError, match="rhat_max"):
        dg_stats.convergence_check(iid, rhat_max=1.0)
    with pytest.raises(UserError, match="ess_min"):
        dg_stats.convergence_check(iid, ess_min=float("nan"))
    with pytest.raises(UserError, match="names"):
        dg_stats.convergence_check(iid, names=["a"])


def test_truth_check_against_the_closed_form():
    """truth_check on draws from N(truth + e, C) with known e and C (4 free IMUs, 12 coordinates,
    200 000 draws): χ² = eᵀC⁻¹e and the scale-mode z = uᵀe/(uᵀCu)^½ within 2 % (Monte Carlo error
    of the draws' mean and covariance), the 99 % band equal to scipy's χ²₁₂ quantiles; a truth
    drawn from the posterior itself (the calibrated case, fixed seed) lies inside the band, and a
    posterior centred exactly on the truth lies below it (χ² ≈ 0 is as suspicious as a large one)."""
    from scipy import stats

    rng = np.random.default_rng(7)
    K, d = 5, 12
    truth = rng.normal(0, 0.02, (K, 3))
    truth[0] = 0.0  # the reference
    A = rng.normal(0, 1e-4, (d, d))
    C = A @ A.T + np.eye(d) * 1e-8
    L = np.linalg.cholesky(C)
    e = L @ rng.normal(0, 1, d) * 2.0
    u = truth[1:].reshape(-1)
    calibrated = L @ rng.normal(0, 1, d)
    for offset in (e, calibrated, np.zeros(d)):
        x = (u + offset) + rng.normal(0, 1, (200_000, d)) @ L.T
        idata = dg_az.to_inference_data(x.reshape(4, 50_000, 4, 3), range(1, 5))
        tc = dg_stats.truth_check(idata, truth)
        assert tc["dof"] == d
        assert np.allclose(tc["band99"], stats.chi2.ppf([0.005, 0.995], d))
        want = float(offset @ np.linalg.solve(C, offset))
        if offset is e or offset is calibrated:
            assert abs(tc["chi2"] / want - 1) < 0.02
            assert abs(tc["radial_z"] - float(u @ offset) / np.sqrt(u @ C @ u)) < 0.02 * max(1.0, abs(tc["radial_z"]))
        if offset is calibrated:
            assert tc["inside99"] and abs(tc["radial_z"]) < 3
        if offset is not e and offset is not calibrated:
            assert not tc["inside99"] and tc["chi2"] < 0.01 and abs(tc["radial_z"]) < 0.1


def test_importing_and_plotting_leave_the_matplotlib_backend_alone(tmp_path):
    """Issue #26: diagnostics switched every importer (a notebook) to Agg at import.  Under a
    backend of the caller's choosing (here pdf), importing the module, drawing and saving a PNG
    leave that backend in place."""
    import subprocess
    import sys

    code = ("import matplotlib, numpy as np; from accel_bayes.diagnostics import plots as dg_plots; "
            "from accel_bayes.data.outputs import save_figure; "
            "from accel_bayes.physics.arrays import mimu4444_8; "
            "b = matplotlib.get_backend(); "
            "mom = {'imu': [1], 'mean': np.zeros((1, 3)), 'cov': np.eye(3)[None] * 1e-8}; "
            f"save_figure(dg_plots.plot_ellipses(mom, mimu4444_8()), r'{tmp_path / 'e.png'}'); "
            "print(b, matplotlib.get_backend())")
    env = {**__import__("os").environ, "MPLBACKEND": "pdf"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    assert out.stdout.split() == ["pdf", "pdf"], out.stdout + out.stderr
    assert (tmp_path / "e.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def _ink_on_the_border(fig) -> bool:
    """Whether anything is drawn in the outermost 2 pixels of ``fig`` rendered: a title or a label
    cut by the figure's edge leaves ink there; a figure laid out with margins does not."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    img = np.asarray(canvas.buffer_rgba())[..., :3]
    border = np.concatenate([img[:2].reshape(-1, 3), img[-2:].reshape(-1, 3), img[:, :2].reshape(-1, 3),
                             img[:, -2:].reshape(-1, 3)])
    return bool((border < 250).any())


def test_offsets_plot_is_readable_at_a_glance():
    """Issue #26 item 6: the demo's ellipse figure had a clipped title, no legend and ellipses too
    small to see against the board.  Now: one panel per free IMU, the offset from the nominal
    position in mm (ellipses at their true size), the truth, a legend, no text outside the figure."""
    arr = mimu4444_8()
    nominal = arr.positions.numpy() - arr.positions.numpy()[0]
    off = np.array([[1e-4, -2e-4, 5e-5]] * 7)  # m, each triad 0.1 mm in x, -0.2 mm in y from nominal
    mom = {"imu": list(range(1, 8)), "mean": nominal[1:] + off,
           "cov": np.array([np.diag([4e-10, 1e-10, 1e-10])] * 7)}  # std 20 µm in x, 10 µm in y, z
    truth = nominal.copy()
    truth[1:] += off + 3e-5
    fig = dg_plots.plot_offsets(mom, arr, truth=truth, prior_std=3e-3)
    assert not _ink_on_the_border(fig)
    panels = [a for a in fig.axes if a.get_visible()]
    assert len(panels) == 7 and [a.get_title().split("\n")[0] for a in panels] == [f"IMU {k}" for k in range(1, 8)]
    assert "Δz +0.050 ± 0.010" in panels[0].get_title() and "(true +0.080)" in panels[0].get_title()
    ells = [p for p in panels[0].patches if isinstance(p, matplotlib.patches.Ellipse)]
    assert len(ells) == 2 and ells[0].center == pytest.approx((0.1, -0.2))  # offset from nominal, mm
    assert sorted(e.width for e in ells)[0] == pytest.approx(2 * math.sqrt(scipy.stats.chi2.ppf(0.5, 2)) * 0.02)
    assert panels[0].get_xlim()[1] < 0.5  # the axes fit the offsets, not the 40 mm board
    legend = [t.get_text() for lg in fig.legends for t in lg.get_texts()]
    assert legend == ["nominal (design) position", "posterior mean", "50 % ellipse", "95 % ellipse", "truth"]
    assert "3 mm" in fig.get_suptitle()


def test_the_board_view_with_a_title_is_clipped_no_more():
    """The board view ([C21] Fig. 5, kept for studies) under constrained layout: its two-line titles fit."""
    arr = mimu4444_8()
    mom = {"imu": [1], "mean": np.array([[0.0, 0.0, -2e-3]]), "cov": np.eye(3)[None] * 1e-8}
    assert not _ink_on_the_border(dg_plots.plot_ellipses(mom, arr, exaggerate=5))
