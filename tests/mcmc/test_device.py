"""The PmMH hot path creates no tensor on torch's default device (issue #15 item 4).

No GPU is needed to find the usual GPU bug, a tensor made without ``device=`` inside code that
works on the caller's device (``torch.rand((), generator=g)`` with a CUDA generator, a float std
broadcast beside CUDA positions …): such a tensor lands on torch's *default* device.  Here the
likelihood, priors and kernel are built on the explicit device ``cpu`` and the hot path — one
log p̂, kernel set-up, warm-up and kept iterations of the fresh-draw and the correlated kernel, the
multi-chain runner — then runs with the default device switched to ``meta``: a stray tensor is a
meta tensor, and meta and CPU tensors cannot be mixed (``Tensor on device meta is not on the
expected device cpu``), nor can a meta value be read (``Tensor.item() cannot be called on meta
tensors``), so every leak raises.

One quirk of the default-device mode is stricter than a real GPU run: ``torch.as_tensor(t)`` of a
CPU tensor ``t`` without ``device=`` is moved to the default device.  The hot path therefore passes
``device=`` explicitly there too, which is harmless.

With a GPU at hand, ``python experiments/bench_iteration.py --device cuda`` runs the per-iteration
benchmark on it beside the CPU (its docstring).
"""
import pytest
import torch

from types import SimpleNamespace

from accel_bayes.inference.mcmc import PMMHKernel, run_pmmh, run_pmmh_until
from accel_bayes.inference.mcmc.priors import BoxPrior, GaussianPrior
from accel_bayes.model.likelihood import RaoBlackwellLikelihood, theta_from_positions
from accel_bayes.physics import arrays
from accel_bayes.model.tempering import TemperedLikelihood
from accel_bayes.simulate import simulate

CPU = torch.device("cpu")


@pytest.fixture(scope="module")
def setup():
    sim = simulate(arrays.mimu4444_8(), "smooth", T=150, seed=4)
    lik = RaoBlackwellLikelihood.from_recording(sim.recording, num_draws=2, device=CPU)
    pos = sim.true_positions[list(lik.imu_labels)].clone().to(CPU)
    th = theta_from_positions(pos, lik.reference)
    cov = torch.eye(th.numel(), dtype=torch.float64, device=CPU) * (20e-6) ** 2
    empirical = lik.with_phi_prior((300.0, 30.0))  # a proper N(0, F) prior on φ (the default's form)
    tempered = TemperedLikelihood(lik.acc, lik.omega, lik.acc_noise_std * 2.0 ** 0.5, 2, 2.0,
                                  reference=lik.reference, device=CPU, phi_prior=(300.0, 30.0))
    return {"lik": lik, "pos": pos, "th": th, "cov": cov, "empirical": empirical, "tempered": tempered}


@pytest.fixture
def meta_default():
    """Torch's default device is ``meta`` inside the test, ``cpu`` again afterwards."""
    torch.set_default_device("meta")
    try:
        yield
    finally:
        torch.set_default_device(None)


def _kernel(lik, prior, th, cov, rho):
    k = PMMHKernel(lik, prior, seed=3, proposal_cov=cov, independence_prob=0.3, independence_mean=th,
                   independence_cov=cov, step_size=0.5, correlation=rho)
    return k


@pytest.mark.parametrize("which", ["lik", "empirical", "tempered"])
def test_log_phat_stays_on_its_device(setup, which, meta_default):
    lik = setup[which]
    gen = torch.Generator(device=CPU).manual_seed(1)
    v = lik.log_phat(setup["pos"], generator=gen)
    assert v.device == CPU and bool(torch.isfinite(v))
    z = lik.sample_z((), None, gen)
    assert z.device == CPU
    v2 = lik.log_phat(torch.stack([setup["pos"], setup["pos"]]), z=z)
    assert v2.shape == (2,) and v2.device == CPU


@pytest.mark.parametrize("rho", [0.0, 0.9])
@pytest.mark.parametrize("prior_kind", ["gaussian", "box"])
def test_kernel_iterations_stay_on_their_device(setup, rho, prior_kind, meta_default):
    pos, th, cov = setup["pos"], setup["th"], setup["cov"]
    prior = (GaussianPrior(pos, std=3e-3, reference=setup["lik"].reference) if prior_kind == "gaussian"
             else BoxPrior.with_std(pos, 3e-3, reference=setup["lik"].reference))
    k = _kernel(setup["lik"], prior, th, cov, rho)
    k.initial_params = {"r": th}
    k.setup(5)
    for _ in range(12):  # warm-up (adaptation) and kept iterations
        out = k.sample({})
    assert out["r"].device == CPU
    assert 0.0 <= k.diagnostics()["acceptance rate"] <= 1.0


def test_runner_stays_on_its_device(setup, meta_default):
    pos, th, cov = setup["pos"], setup["th"], setup["cov"]
    prior = GaussianPrior(pos, std=3e-3, reference=setup["lik"].reference)
    k = _kernel(setup["lik"], prior, th, cov, 0.5)
    res = run_pmmh(k, num_samples=6, warmup_steps=4, num_chains=2, initial_params=torch.stack([th, th + 1e-5]),
                   progress=False)
    assert res.theta.device == CPU and res.theta.shape[:2] == (2, 6)
    assert bool(torch.isfinite(res.log_phat).all())
    seen = []

    def check(theta):  # converged at the second check
        seen.append(theta.shape[1])
        return SimpleNamespace(converged=len(seen) == 2)

    k2 = _kernel(setup["lik"], prior, th, cov, 0.5)
    res2 = run_pmmh_until(k2, check, 4, 2, torch.stack([th, th + 1e-5]), check_every=3, max_samples=12,
                          progress=False)
    assert seen == [3, 6] and res2.stopped == "converged" and res2.theta.device == CPU


def test_priors_follow_their_positions(setup, meta_default):
    """A float std/half-width goes to the positions' device, not to the default device."""
    pos = setup["pos"]
    for prior in (GaussianPrior(pos, std=3e-3), BoxPrior.with_std(pos, 3e-3), BoxPrior.around(pos, 5e-3)):
        assert prior.std.device == CPU
        assert bool(torch.isfinite(prior.log_prob(prior.mean)))


def test_calibrate_device_path_matches_default():
    """``calibrate(device="cpu")`` takes the device path of step 6 (the likelihood, prior and starts
    copied with ``.to``, the draws brought back) and must give the default path's draws bit for bit."""
    from accel_bayes.pipelines.calibrate import calibrate

    sim = simulate(arrays.mimu4444_8(), "smooth", T=200, seed=5)
    kw = dict(chains=2, draws=30, warmup=30, seed=2, progress=False)
    a = calibrate(sim.recording, **kw)
    b = calibrate(sim.recording, device="cpu", **kw)
    assert torch.equal(a.run.theta, b.run.theta) and torch.equal(a.run.log_phat, b.run.log_phat)
    assert a.settings["device"] == b.settings["device"] == "cpu"
    assert b.run.theta.device == CPU


@pytest.mark.parametrize("device, field", [("nonsense", "device"), ("cuda", "device")])
def test_calibrate_refuses_unusable_device(device, field):
    from accel_bayes.errors import UserError
    from accel_bayes.pipelines.calibrate import calibrate

    if device == "cuda" and torch.cuda.is_available():
        pytest.skip("a GPU is present: 'cuda' is usable")
    with pytest.raises(UserError, match=f"^{field}: "):
        calibrate("/nonexistent.nc", device=device)
