"""The structured linear solvers of the LM graph solver (accel_bayes.inference.lm.linear).

Independent reference: a dense ``torch.linalg.solve`` / ``torch.linalg.cholesky`` of the
assembled matrix (small sizes only).  Tolerances: 1e-10 relative in float64 (the matrices are
well conditioned by construction), 1e-4 in float32.
"""
import pytest
import torch

from accel_bayes.inference.lm.linear import (
    BlockDiagonalCholesky,
    BlockTridiagonalCholesky,
    NotPositiveDefinite,
    SchurComplementSolver,
    band_storage,
    block_tridiagonal_solve,
    dense_from_blocks,
)

F64 = torch.float64


def _spd_block_tridiagonal(T, d, seed, dtype=F64):
    """A random SPD block-tridiagonal matrix as blocks (D, E): JᵀJ of a random chain Jacobian + I."""
    g = torch.Generator().manual_seed(seed)
    A = torch.randn(T, 2 * d, d, generator=g, dtype=F64)
    Pm = torch.randn(T - 1, d, d, generator=g, dtype=F64)
    Nx = torch.randn(T - 1, d, d, generator=g, dtype=F64)
    D = A.transpose(-1, -2) @ A + torch.eye(d, dtype=F64)
    D[:-1] += Pm.transpose(-1, -2) @ Pm
    D[1:] += Nx.transpose(-1, -2) @ Nx
    E = Pm.transpose(-1, -2) @ Nx
    return D.to(dtype), E.to(dtype)


def _dense(D, E):
    T, d = D.shape[0], D.shape[-1]
    return dense_from_blocks(D.new_zeros(0, 0), D.new_zeros(T, 0, d), D, E)


@pytest.mark.parametrize("T,d,k", [(1, 3, 2), (2, 4, 1), (7, 3, 5), (40, 9, 25)])
def test_block_tridiagonal_solve_matches_dense_solve(T, d, k):
    D, E = _spd_block_tridiagonal(T, d, seed=T + d)
    A = _dense(D, E)
    assert torch.allclose(A, A.T) and float(torch.linalg.eigvalsh(A).min()) > 0
    B = torch.randn(T, d, k, generator=torch.Generator().manual_seed(1), dtype=F64)
    ref = torch.linalg.solve(A, B.reshape(T * d, k))
    X = block_tridiagonal_solve(D, E, B)
    assert X.shape == B.shape and X.dtype == F64
    assert float((X.reshape(T * d, k) - ref).abs().max()) < 1e-10 * float(ref.abs().max())
    # a single right-hand side given as (T, d)
    x1 = block_tridiagonal_solve(D, E, B[..., 0])
    assert torch.allclose(x1, X[..., 0], rtol=1e-12, atol=1e-14)


def test_band_storage_and_triangular_factors_match_dense_cholesky():
    T, d = 6, 3
    D, E = _spd_block_tridiagonal(T, d, seed=3)
    A = _dense(D, E)
    ab = band_storage(D, E)
    assert ab.shape == (2 * d, T * d)
    for k in range(2 * d):  # ab[k, i] = A[i + k, i]
        diag = torch.diagonal(A, offset=-k)
        assert torch.equal(ab[k, :T * d - k], diag)
    L = torch.linalg.cholesky(A)
    F = BlockTridiagonalCholesky(D, E)
    B = torch.randn(T, d, 4, generator=torch.Generator().manual_seed(2), dtype=F64)
    Bf = B.reshape(T * d, 4)
    lo = torch.linalg.solve_triangular(L, Bf, upper=False)
    up = torch.linalg.solve_triangular(L.T, Bf, upper=True)
    assert torch.allclose(F.solve_lower(B).reshape(T * d, 4), lo, rtol=1e-11, atol=1e-13)
    assert torch.allclose(F.solve_upper(B).reshape(T * d, 4), up, rtol=1e-11, atol=1e-13)


def test_block_tridiagonal_float32_batched_and_not_positive_definite():
    T, d = 9, 4
    D, E = _spd_block_tridiagonal(T, d, seed=5)
    Db, Eb = torch.stack((D, 3 * D)), torch.stack((E, 3 * E))
    B = torch.randn(2, T, d, 2, generator=torch.Generator().manual_seed(4), dtype=F64)
    X = block_tridiagonal_solve(Db, Eb, B)
    X32 = block_tridiagonal_solve(Db.float(), Eb.float(), B.float())
    assert X32.dtype == torch.float32
    for i in range(2):
        ref = torch.linalg.solve(_dense(Db[i], Eb[i]), B[i].reshape(T * d, 2))
        assert float((X[i].reshape(T * d, 2) - ref).abs().max()) < 1e-10 * float(ref.abs().max())
        assert float((X32[i].reshape(T * d, 2).double() - ref).abs().max()) < 1e-4 * float(ref.abs().max())
    bad = D.clone()
    bad[4] = -bad[4]
    with pytest.raises(NotPositiveDefinite):
        BlockTridiagonalCholesky(bad, E)
    with pytest.raises(ValueError):
        BlockTridiagonalCholesky(D, E[:-1])


@pytest.mark.parametrize("tri", [False, True])
def test_schur_forward_only_elimination_matches_dense(tri):
    n, T, d = 4, 11, 3
    g = torch.Generator().manual_seed(7 + tri)
    D, E = _spd_block_tridiagonal(T, d, seed=9)
    if not tri:
        E = None
    W = 0.3 * torch.randn(T, n, d, generator=g, dtype=F64)
    U = torch.randn(n, 3 * n, generator=g, dtype=F64)
    U = U @ U.T + 5 * n * torch.eye(n, dtype=F64)
    b_g = torch.randn(n, generator=g, dtype=F64)
    b_x = torch.randn(T, d, generator=g, dtype=F64)
    A = dense_from_blocks(U, W, D, E)
    ref = torch.linalg.solve(A, torch.cat((b_g, b_x.reshape(-1))))
    solver = SchurComplementSolver("tridiagonal" if tri else "diagonal")
    dg, dx, S = solver.solve(U, W, D, b_g, b_x, E, return_reduced=True)
    assert float((torch.cat((dg, dx.reshape(-1))) - ref).abs().max()) < 1e-10 * float(ref.abs().max())
    assert torch.allclose(torch.linalg.inv(S), torch.linalg.inv(A)[:n, :n], rtol=1e-10, atol=1e-12)
    assert torch.allclose(solver.reduce(U, W, D, E), S, rtol=1e-10, atol=1e-10)
    if not tri:
        F = BlockDiagonalCholesky(D)
        assert torch.allclose(F.solve(b_x), torch.linalg.solve(D, b_x.unsqueeze(-1)).squeeze(-1), rtol=1e-10)


def test_chunked_band_packing_and_triangular_solves_match_dense(monkeypatch):
    """The chunked paths (band packed in sample chunks, triangular solves in row chunks with the
    coupling to the neighbouring chunk subtracted) give the unchunked answer."""
    import accel_bayes.inference.lm.linear as lin

    T, d, k = 23, 3, 4
    D, E = _spd_block_tridiagonal(T, d, seed=21)
    B = torch.randn(T, d, k, generator=torch.Generator().manual_seed(3), dtype=F64)
    A = _dense(D, E)
    L = torch.linalg.cholesky(A)
    Bf = B.reshape(T * d, k)
    ref = torch.linalg.solve(A, Bf)
    lo = torch.linalg.solve_triangular(L, Bf, upper=False)
    up = torch.linalg.solve_triangular(L.T, Bf, upper=True)
    ab_ref = band_storage(D, E).clone()
    for cs, cr in ((4, 20), (5, 23), (1, 21)):  # chunk sizes that do and do not divide T, T·d = 69
        monkeypatch.setattr(lin, "_CHUNK_SAMPLES", cs)
        monkeypatch.setattr(lin, "_CHUNK_ROWS", cr)
        assert torch.equal(band_storage(D, E), ab_ref)
        F = BlockTridiagonalCholesky(D, E)
        assert float((F.solve_lower(B).reshape(T * d, k) - lo).abs().max()) < 1e-11 * float(lo.abs().max())
        assert float((F.solve_upper(B).reshape(T * d, k) - up).abs().max()) < 1e-11 * float(up.abs().max())
        assert float((F.solve(B).reshape(T * d, k) - ref).abs().max()) < 1e-10 * float(ref.abs().max())
