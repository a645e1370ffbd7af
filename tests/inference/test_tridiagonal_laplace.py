"""The block-tridiagonal operations behind the Laplace approximations of the motion
(``accel_bayes.inference.lm.linear``: selected inverse and log det), against a dense
``torch.linalg.inv`` / ``slogdet`` of the assembled matrix, including the edge cases T = 1, 2."""
import numpy as np
import pytest
import torch

from accel_bayes.inference.lm.linear import (
    block_tridiagonal_logdet,
    block_tridiagonal_selected_inverse,
    dense_from_blocks,
)

F64 = torch.float64


def _spd_blocks(T, d, seed):
    """A random SPD block-tridiagonal matrix as blocks (D, B): JᵀJ of a random chain Jacobian + I,
    scaled so that the blocks span a few orders of magnitude (as motion states do)."""
    g = torch.Generator().manual_seed(seed)
    scale = torch.logspace(-2, 2, d, dtype=F64)
    A = torch.randn(T, 2 * d, d, generator=g, dtype=F64) * scale
    Pm = torch.randn(max(T - 1, 0), d, d, generator=g, dtype=F64) * scale
    Nx = torch.randn(max(T - 1, 0), d, d, generator=g, dtype=F64) * scale
    D = A.transpose(-1, -2) @ A + torch.eye(d, dtype=F64)
    D[:-1] += Pm.transpose(-1, -2) @ Pm
    D[1:] += Nx.transpose(-1, -2) @ Nx
    return D, Pm.transpose(-1, -2) @ Nx


def _dense(D, B):
    T, d = D.shape[0], D.shape[-1]
    return dense_from_blocks(D.new_zeros(0, 0), D.new_zeros(T, 0, d), D, B if T > 1 else None)


@pytest.mark.parametrize("T,d", [(1, 3), (2, 4), (7, 9), (30, 15)])
def test_selected_inverse_is_the_dense_inverses_band(T, d):
    D, B = _spd_blocks(T, d, seed=10 * T + d)
    Hi = torch.linalg.inv(_dense(D, B))
    Sig, C = block_tridiagonal_selected_inverse(D, B)
    assert Sig.shape == (T, d, d) and C.shape == (T - 1, d, d) and Sig.dtype == F64
    tol = 1e-9 * float(Hi.abs().max())
    for i in range(T):
        assert float((Sig[i] - Hi[i * d:(i + 1) * d, i * d:(i + 1) * d]).abs().max()) < tol
        assert torch.equal(Sig[i], Sig[i].T)  # symmetrised
    for i in range(T - 1):
        assert float((C[i] - Hi[i * d:(i + 1) * d, (i + 1) * d:(i + 2) * d]).abs().max()) < tol


@pytest.mark.parametrize("T,d", [(1, 3), (2, 4), (7, 9), (30, 15)])
def test_logdet_is_the_dense_one(T, d):
    D, B = _spd_blocks(T, d, seed=10 * T + d + 1)
    ref = torch.linalg.slogdet(_dense(D, B))
    assert float(ref.sign) == 1.0
    assert abs(block_tridiagonal_logdet(D, B) - float(ref.logabsdet)) < 1e-10 * abs(float(ref.logabsdet)) + 1e-9


def test_logdet_refuses_a_matrix_that_is_not_positive_definite():
    """The Laplace scale correction treats this error as an infinite negative log-likelihood."""
    D, B = _spd_blocks(5, 3, seed=2)
    D[3] = -D[3]
    with pytest.raises(np.linalg.LinAlgError):
        block_tridiagonal_logdet(D, B)
