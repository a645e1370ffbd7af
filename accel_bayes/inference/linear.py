"""Structured linear solvers for the normal equations of the LM graph solver (DESIGN §6).

The Gauss–Newton system of a problem with a few *global* variables g (n numbers: positions,
orientations, sensor parameters) and per-sample *local* blocks x_t (d numbers each: motion
states) has the arrow shape

    [ U    W  ] [δg]   [b_g]        U   (n, n)       dense, small
    [ Wᵀ   V  ] [δx] = [b_x]        W   (n, T·d)     stored as W_t (T, n, d)
                                    V   (T·d, T·d)   block-diagonal  V_t (T, d, d)   (i.i.d. motion)
                                                     or block-tridiagonal: V_t plus
                                                     E_t = V_{t,t+1} (T−1, d, d)    (process model)

Eliminating the locals (Schur complement, as in bundle adjustment) leaves the n×n system

    S δg = b_g − W V⁻¹ b_x,    S = U − W V⁻¹ Wᵀ,    then  δx = V⁻¹ (b_x − Wᵀ δg).

V⁻¹ is never formed and no (T·d)×(T·d) matrix is built:

* block-diagonal V: one batched Cholesky of the T blocks, one batched solve with the n + 1
  right-hand sides [Wᵀ | b_x] — fully vectorised, O(T (d³ + d² n)).
* block-tridiagonal V, default: block cyclic reduction (:func:`block_tridiagonal_cr_solve`):
  odd blocks eliminated level by level, ⌈log₂ T⌉ sequential levels, each one batched over all
  blocks of the level — O(T) work, no per-sample Python loop.
* block-tridiagonal V, alternative: the block Cholesky factorisation V = L Lᵀ with L block lower bidiagonal
  (diagonal blocks L_t, sub-diagonal blocks C_t), computed by the O(T) recursion

      L_0 = chol(V_0);  C_t = E_tᵀ L_t⁻ᵀ;  L_{t+1} = chol(V_{t+1} − C_t C_tᵀ),

  followed by forward (L z = b) and backward (Lᵀ y = z) block substitution.  This is the
  block-Thomas algorithm in its symmetric (Cholesky) form; it is stable for SPD V without
  pivoting.  The sequential loop over t is unavoidable here; every step is batched over any
  leading batch dimensions and over all n + 1 right-hand sides at once.

Batch dimensions: every function takes optional leading batch dimensions ``...`` (independent
problems solved together).  Failures of positive definiteness raise :class:`NotPositiveDefinite`
(the LM loop answers by raising the damping).
"""
from __future__ import annotations

import torch

__all__ = [
    "NotPositiveDefinite",
    "cholesky",
    "block_diagonal_factor",
    "block_diagonal_solve",
    "block_tridiagonal_factor",
    "block_tridiagonal_solve",
    "block_tridiagonal_cr_solve",
    "SchurComplementSolver",
    "dense_from_blocks",
]


class NotPositiveDefinite(RuntimeError):
    """A matrix that must be symmetric positive definite is not (numerically)."""


def cholesky(A: torch.Tensor, what: str = "matrix") -> torch.Tensor:
    """Lower Cholesky factor of SPD A (..., k, k); raises :class:`NotPositiveDefinite`."""
    L, info = torch.linalg.cholesky_ex(A)
    if bool((info != 0).any()) or not bool(torch.isfinite(L).all()):
        raise NotPositiveDefinite(f"{what} is not positive definite")
    return L


# ---------------------------------------------------------------- block-diagonal

def block_diagonal_factor(V: torch.Tensor) -> torch.Tensor:
    """Batched Cholesky factors of the diagonal blocks V (..., T, d, d)."""
    return cholesky(V, "local block")


def block_diagonal_solve(L: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
    """V⁻¹ B for block-diagonal V = blkdiag(L_t L_tᵀ); B (..., T, d, k) → (..., T, d, k)."""
    return torch.cholesky_solve(B, L)


# ---------------------------------------------------------------- block-tridiagonal

def block_tridiagonal_factor(D: torch.Tensor, E: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Block Cholesky factor of the SPD block-tridiagonal matrix with diagonal blocks D (..., T, d, d)
    and upper off-diagonal blocks E (..., T−1, d, d) (E_t = V_{t,t+1}, so V_{t+1,t} = E_tᵀ).

    Returns (Ld (..., T, d, d), C (..., T−1, d, d)): V = L Lᵀ with L's diagonal blocks Ld_t (lower
    triangular) and sub-diagonal blocks C_t = L_{t+1,t}.  O(T) recursion (module docstring).
    """
    T = D.shape[-3]
    Ld = torch.empty_like(D)
    C = torch.empty_like(E)
    Lt = cholesky(D[..., 0, :, :], "local block-tridiagonal matrix (block 0)")
    Ld[..., 0, :, :] = Lt
    for t in range(T - 1):
        # C_t = E_tᵀ L_t⁻ᵀ  ⇔  C_tᵀ = L_t⁻¹ E_t
        Ct = torch.linalg.solve_triangular(Lt, E[..., t, :, :], upper=False).transpose(-1, -2)
        C[..., t, :, :] = Ct
        L_next, info = torch.linalg.cholesky_ex(D[..., t + 1, :, :] - Ct @ Ct.transpose(-1, -2))
        if bool((info != 0).any()):
            raise NotPositiveDefinite(f"local block-tridiagonal matrix is not positive definite (block {t + 1})")
        Ld[..., t + 1, :, :] = L_next
        Lt = L_next
    return Ld, C


def block_tridiagonal_solve(factor: tuple[torch.Tensor, torch.Tensor], B: torch.Tensor) -> torch.Tensor:
    """V⁻¹ B for V factored by :func:`block_tridiagonal_factor`; B (..., T, d, k) → (..., T, d, k)."""
    Ld, C = factor
    T = Ld.shape[-3]
    Z = torch.empty_like(B)
    z = torch.linalg.solve_triangular(Ld[..., 0, :, :], B[..., 0, :, :], upper=False)
    Z[..., 0, :, :] = z
    for t in range(1, T):
        z = torch.linalg.solve_triangular(Ld[..., t, :, :], B[..., t, :, :] - C[..., t - 1, :, :] @ z, upper=False)
        Z[..., t, :, :] = z
    Y = torch.empty_like(B)
    y = torch.linalg.solve_triangular(Ld[..., T - 1, :, :].transpose(-1, -2), Z[..., T - 1, :, :], upper=True)
    Y[..., T - 1, :, :] = y
    for t in range(T - 2, -1, -1):
        rhs = Z[..., t, :, :] - C[..., t, :, :].transpose(-1, -2) @ y
        y = torch.linalg.solve_triangular(Ld[..., t, :, :].transpose(-1, -2), rhs, upper=True)
        Y[..., t, :, :] = y
    return Y


def _pad0(x: torch.Tensor, n: int, front: bool = False) -> torch.Tensor:
    """Pad the block axis (−3) with n zero blocks (at the end, or at the front)."""
    if n <= 0:
        return x
    z = x.new_zeros(*x.shape[:-3], n, *x.shape[-2:])
    return torch.cat((z, x) if front else (x, z), -3)


def block_tridiagonal_cr_solve(D: torch.Tensor, E: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
    """V⁻¹ B for the SPD block-tridiagonal V (diagonal D (..., T, d, d), upper off-diagonal
    E (..., T−1, d, d)) by block **cyclic reduction**; B (..., T, d, k) → (..., T, d, k).

    One level eliminates the odd-indexed blocks (batched Cholesky of all of them at once),
    which leaves a block-tridiagonal system of the even blocks with

        D'_j = D_j − E_{j−1}ᵀ D_{j−1}⁻¹ E_{j−1} − E_j D_{j+1}⁻¹ E_jᵀ,
        E'_j = −E_j D_{j+1}⁻¹ E_{j+1},   b'_j = b_j − E_{j−1}ᵀ D_{j−1}⁻¹ b_{j−1} − E_j D_{j+1}⁻¹ b_{j+1};

    the half-size system is solved recursively and the odd blocks are recovered by
    x_i = D_i⁻¹ (b_i − E_{i−1}ᵀ x_{i−1} − E_i x_{i+1}).  Total work O(T (d³ + d² k)) as for the
    sequential recursion, but only ⌈log₂ T⌉ sequential levels, each fully batched — the fast
    choice on CPU and GPU alike.  For SPD V this is Cholesky on the odd–even permuted matrix, so
    it is stable without pivoting; every eliminated block is an SPD Schur complement.
    """
    T = D.shape[-3]
    if T == 1:
        L = cholesky(D, "local block-tridiagonal matrix")
        return torch.cholesky_solve(B, L)
    Do, De = D[..., 1::2, :, :], D[..., 0::2, :, :]
    Bo, Be = B[..., 1::2, :, :], B[..., 0::2, :, :]
    no, ne = Do.shape[-3], De.shape[-3]
    El = E[..., 0::2, :, :]  # E_{i−1} of odd block i (coupling to its left even neighbour), no of them
    Er = _pad0(E[..., 1::2, :, :], no - E[..., 1::2, :, :].shape[-3])  # E_i (right), zero past the end
    Lo = cholesky(Do, "local block-tridiagonal matrix")
    X = torch.cholesky_solve(torch.cat((El.transpose(-1, -2), Er, Bo), -1), Lo)
    d = D.shape[-1]
    Xl, Xr, Xb = X[..., :d], X[..., d:2 * d], X[..., 2 * d:]
    # contributions to even block m from its right odd neighbour m and its left odd neighbour m−1
    Dn = De.clone()
    Bn = Be.clone()
    Dn[..., :no, :, :] -= El @ Xl
    Bn[..., :no, :, :] -= El @ Xb
    Dn[..., 1:no + 1, :, :] -= Er[..., :ne - 1, :, :].transpose(-1, -2) @ Xr[..., :ne - 1, :, :]
    Bn[..., 1:no + 1, :, :] -= Er[..., :ne - 1, :, :].transpose(-1, -2) @ Xb[..., :ne - 1, :, :]
    En = -(El[..., :ne - 1, :, :] @ Xr[..., :ne - 1, :, :])
    xe = block_tridiagonal_cr_solve(Dn, En, Bn)
    xe_next = _pad0(xe[..., 1:, :, :], no - (ne - 1))[..., :no, :, :]
    xo = Xb - Xl @ xe[..., :no, :, :] - Xr @ xe_next
    out = torch.empty_like(B)
    out[..., 0::2, :, :] = xe
    out[..., 1::2, :, :] = xo
    return out


# ---------------------------------------------------------------- Schur complement

class SchurComplementSolver:
    """Solve the arrow system of the module docstring by eliminating the local blocks.

    Parameters
    ----------
    structure : "diagonal" | "tridiagonal" | "auto" (default) — the structure of V; "auto" uses the
        tridiagonal solver exactly when off-diagonal blocks are passed.
    tridiagonal_method : "cyclic_reduction" (default; :func:`block_tridiagonal_cr_solve`, log₂ T
        batched levels) or "recursion" (:func:`block_tridiagonal_factor` /
        :func:`block_tridiagonal_solve`, the sequential block-Cholesky recursion, T steps).

    ``solve(U, W, V, b_g, b_x, V_off=None)`` returns (δg (..., n), δx (..., T, d)); ``reduce(U, W, V,
    V_off=None)`` returns S = U − W V⁻¹ Wᵀ (..., n, n).  W may be None (no locals) and n may be 0
    (no free globals).
    """

    def __init__(self, structure: str = "auto", tridiagonal_method: str = "cyclic_reduction"):
        if structure not in ("auto", "diagonal", "tridiagonal"):
            raise ValueError(f"structure: expected 'auto', 'diagonal' or 'tridiagonal', got {structure!r}")
        if tridiagonal_method not in ("cyclic_reduction", "recursion"):
            raise ValueError("tridiagonal_method: expected 'cyclic_reduction' or 'recursion', "
                             f"got {tridiagonal_method!r}")
        self.structure = structure
        self.tridiagonal_method = tridiagonal_method

    def _local(self, V, V_off):
        tri = (self.structure == "tridiagonal") or (self.structure == "auto" and V_off is not None)
        if tri:
            if V_off is None:
                V_off = V.new_zeros(*V.shape[:-3], max(V.shape[-3] - 1, 0), V.shape[-2], V.shape[-1])
            if self.tridiagonal_method == "cyclic_reduction":
                return lambda B: block_tridiagonal_cr_solve(V, V_off, B)
            f = block_tridiagonal_factor(V, V_off)
            return lambda B: block_tridiagonal_solve(f, B)
        if V_off is not None:
            raise ValueError("SchurComplementSolver(structure='diagonal') got off-diagonal local blocks")
        L = block_diagonal_factor(V)
        return lambda B: block_diagonal_solve(L, B)

    def reduce(self, U, W, V, V_off=None):
        """Reduced (Schur) matrix S = U − W V⁻¹ Wᵀ of the globals."""
        if W is None or V is None or V.shape[-3] == 0:
            return U
        solve = self._local(V, V_off)
        X = solve(W.transpose(-1, -2))  # (..., T, d, n)
        return U - torch.einsum("...tnd,...tdm->...nm", W, X)

    def solve(self, U, W, V, b_g, b_x, V_off=None, return_reduced: bool = False):
        """(δg, δx) [, S] solving the full arrow system (module docstring)."""
        n = U.shape[-1]
        if W is None or V is None:
            S = U
            dg = torch.cholesky_solve(b_g.unsqueeze(-1), cholesky(S, "reduced system")).squeeze(-1) if n else b_g
            return (dg, None, S) if return_reduced else (dg, None)
        solve = self._local(V, V_off)
        rhs = torch.cat((W.transpose(-1, -2), b_x.unsqueeze(-1)), -1)  # (..., T, d, n+1)
        X = solve(rhs)
        Xw, xb = X[..., :n], X[..., n]
        S = U - torch.einsum("...tnd,...tdm->...nm", W, Xw)
        if n:
            r = b_g - torch.einsum("...tnd,...td->...n", W, xb)
            S = 0.5 * (S + S.transpose(-1, -2))
            dg = torch.cholesky_solve(r.unsqueeze(-1), cholesky(S, "reduced (Schur) system")).squeeze(-1)
            dx = xb - torch.einsum("...tdn,...n->...td", Xw, dg)
        else:
            dg = b_g
            dx = xb
        return (dg, dx, S) if return_reduced else (dg, dx)


def dense_from_blocks(U, W, V, V_off=None) -> torch.Tensor:
    """The dense (n + T·d)² arrow matrix — for tests on small problems only."""
    n = U.shape[-1]
    T, d = V.shape[-3], V.shape[-1]
    N = n + T * d
    A = U.new_zeros(N, N)
    A[:n, :n] = U
    Wf = W.permute(1, 0, 2).reshape(n, T * d)
    A[:n, n:] = Wf
    A[n:, :n] = Wf.T
    for t in range(T):
        s = n + t * d
        A[s:s + d, s:s + d] = V[t]
        if V_off is not None and t < T - 1:
            A[s:s + d, s + d:s + 2 * d] = V_off[t]
            A[s + d:s + 2 * d, s:s + d] = V_off[t].T
    return A
