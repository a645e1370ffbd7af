"""The one Jacobian module of the kinematics (accel_bayes.physics.jacobians).

Independent references: autograd through the one signal model (models.specific_force,
models.u_of_omega) and central finite differences of it; the factored axis-projected form
against the plain form rotated into the sensor frames.
"""
import torch

from accel_bayes.physics.geometry import quat_to_matrix, random_quaternion
from accel_bayes.physics.models import specific_force, u_of_omega
from accel_bayes.physics import jacobians as jac

DT = torch.float64


def _motion(gen, *batch):
    w = 3.0 * torch.randn(*batch, 3, generator=gen, dtype=DT)
    wd = 30.0 * torch.randn(*batch, 3, generator=gen, dtype=DT)
    s = 10.0 * torch.randn(*batch, 3, generator=gen, dtype=DT)
    return w, wd, s


def test_partials_match_autograd_of_specific_force():
    """Every partial of f, batched over samples (T) and points (A), equals autograd of f."""
    gen = torch.Generator().manual_seed(0)
    T, A = 4, 5
    r = 0.05 * torch.randn(A, 3, generator=gen, dtype=DT)
    w, wd, s = _motion(gen, T)
    Jw, Jwd, Js, Jr = jac.df_domega(r, w), jac.df_domega_dot(r), jac.df_ds(r), jac.df_dr(w, wd)
    Jx = jac.df_dmotion(r, w)
    assert Jw.shape == (T, A, 3, 3) and Jwd.shape == (A, 3, 3) and Jr.shape == (T, 3, 3) and Jx.shape == (T, A, 3, 9)
    for t in range(T):
        f = lambda *a: specific_force(*a)  # noqa: E731
        Aw, Awd, As = (torch.autograd.functional.jacobian(lambda v: f(r, v, wd[t], s[t]), w[t]),
                       torch.autograd.functional.jacobian(lambda v: f(r, w[t], v, s[t]), wd[t]),
                       torch.autograd.functional.jacobian(lambda v: f(r, w[t], wd[t], v), s[t]))
        torch.testing.assert_close(Jw[t], Aw, rtol=1e-13, atol=1e-13)
        torch.testing.assert_close(Jwd, Awd, rtol=1e-13, atol=1e-13)
        torch.testing.assert_close(Js, As, rtol=0, atol=0)
        torch.testing.assert_close(Jx[t], torch.cat((Aw, Awd, As), -1), rtol=1e-13, atol=1e-13)
        for k in range(A):  # ∂f_k/∂r_k, the same matrix for every point
            Ar = torch.autograd.functional.jacobian(lambda v: f(v.unsqueeze(0), w[t], wd[t], s[t])[0], r[k])
            torch.testing.assert_close(Jr[t], Ar, rtol=1e-13, atol=1e-13)


def test_partials_match_finite_differences():
    """Central differences (step h, error O(h²) ~ 1e-10 relative for these magnitudes)."""
    gen = torch.Generator().manual_seed(1)
    T, A, h = 3, 4, 1e-6
    r = 0.05 * torch.randn(A, 3, generator=gen, dtype=DT)
    w, wd, s = _motion(gen, T)
    e = torch.eye(3, dtype=DT)
    for i in range(3):
        fd = (specific_force(r, w + h * e[i], wd, s) - specific_force(r, w - h * e[i], wd, s)) / (2 * h)
        torch.testing.assert_close(jac.df_domega(r, w)[..., i], fd, rtol=1e-8, atol=1e-8)
        fd = (specific_force(r, w, wd + h * e[i], s) - specific_force(r, w, wd - h * e[i], s)) / (2 * h)
        torch.testing.assert_close(jac.df_domega_dot(r)[..., i].expand_as(fd), fd, rtol=1e-8, atol=1e-8)
        fd = (specific_force(r + h * e[i], w, wd, s) - specific_force(r - h * e[i], w, wd, s)) / (2 * h)
        torch.testing.assert_close(jac.df_dr(w, wd)[:, None, :, i].expand_as(fd), fd, rtol=1e-8, atol=1e-8)


def test_du_domega_and_its_derivative_match_autograd():
    w = torch.tensor([[0.3, -1.2, 2.0], [1.0, 0.5, -0.7]], dtype=DT)
    J = torch.stack([torch.autograd.functional.jacobian(u_of_omega, wi) for wi in w])
    assert torch.allclose(jac.du_domega(w), J)
    H = torch.autograd.functional.jacobian(lambda v: jac.du_domega(v), w[0])  # (6, 3, 3)
    torch.testing.assert_close(jac.d2u_domega2(), H, rtol=0, atol=0)


def test_axis_projected_form_matches_the_plain_form():
    """f_m and ∂f_m/∂x of the factored form equal R_k f(r_k) and R_k ∂f/∂x, for one geometry
    and for a batch of geometry draws."""
    gen = torch.Generator().manual_seed(2)
    K, N = 5, 6
    R = quat_to_matrix(random_quaternion(K, generator=gen))
    for r in (0.02 * torch.randn(K, 3, generator=gen, dtype=DT), 0.02 * torch.randn(3, K, 3, generator=gen, dtype=DT)):
        G = r.shape[:-2]
        w, wd, s = _motion(gen, *G, N)
        x = torch.cat((w, wd, s), -1)
        proj = jac.AxisProjection(R, r)
        f, _, _ = jac.axis_force(x, proj)
        J = jac.axis_force_jacobian(x, proj)
        rr = r.unsqueeze(-3)  # (*G, 1, K, 3): broadcast over samples
        f_plain = (R @ specific_force(rr, w, wd, s).unsqueeze(-1)).squeeze(-1).flatten(-2)
        J_plain = (R @ jac.df_dmotion(rr, w)).flatten(-3, -2)
        torch.testing.assert_close(f, f_plain, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(J, J_plain, rtol=1e-12, atol=1e-12)
