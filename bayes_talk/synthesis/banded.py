"""Block-tridiagonal precisions of a latent path, factorised in time and memory linear in its length.

The whole-utterance synthesis density (:mod:`bayes_talk.synthesis.joint`) is a sum of terms
that each read one frame (audio, entry) or two neighbouring frames (dynamics, smoothness), so
its Hessian in the path X (T×d, flattened frame-major) is **block-tridiagonal**: d×d blocks on
the diagonal and on the first off-diagonals, zero elsewhere. As a scalar matrix of order
n = T·d it is banded with half-bandwidth 2d − 1, and its Cholesky factor stays inside that
band (the factor's envelope is the matrix's: no fill outside the first sub-diagonal block).
So every operation the joint MAP and the Laplace posterior need costs O(T·d³) time and
O(T·d²) memory instead of the dense O(T³d³) and O(T²d²):

* :class:`BlockTridiagonal`: the blocks, the matrix-vector product, the dense matrix (tests
  and short paths only), the inertia (how many eigenvalues are ≤ 0) by the block LDLᵀ
  recursion D₀ = P₀₀, D_{t+1} = P_{t+1,t+1} − B_tᵀ D_t⁻¹ B_t (Sylvester's law of inertia);
* :meth:`BlockTridiagonal.cholesky`: P = R Rᵀ by LAPACK's banded Cholesky (``dpbtrf``,
  through :func:`scipy.linalg.cholesky_banded`), R lower;
* :func:`modified_cholesky`: the factor of P + τ·diag(|P_ii|) with τ escalated tenfold from 0
  until P + τ·diag is positive definite (the "added multiple of the diagonal" modified
  Cholesky of Nocedal & Wright 2006, Algorithm 3.3, scaled per coordinate because the
  posterior's scales span orders of magnitude); τ is logged and returned;
* :class:`BandedFactor`: solves P⁻¹b (``dpbtrs``), the scale L = R⁻ᵀ with L Lᵀ = P⁻¹ applied
  to vectors (L z: the Laplace draws X_MAP + L z; Lᵀ g: gradients in whitened coordinates)
  by banded triangular solves (``dtbtrs``), log |P|, and the **selected inverse**: the d×d
  diagonal blocks of Σ = P⁻¹ (each frame's marginal covariance) without forming Σ, by
  Takahashi's recursion on the block factor (A_t the diagonal blocks of R, C_t the blocks
  R_{t+1,t}; from Rᵀ Σ = R⁻¹, R⁻¹ block lower triangular with diagonal blocks A_t⁻¹):

      Σ_{T−1,T−1} = A_{T−1}⁻ᵀ A_{T−1}⁻¹
      Σ_{t,t+1}   = −A_t⁻ᵀ C_tᵀ Σ_{t+1,t+1}
      Σ_{t,t}     = A_t⁻ᵀ (A_t⁻¹ − C_tᵀ Σ_{t+1,t}),        t = T−2, …, 0.

Everything is float64.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numba
import numpy as np
from scipy.linalg import cho_solve_banded, cholesky_banded
from scipy.linalg.lapack import dtbtrs

log = logging.getLogger(__name__)

#: the modified Cholesky's first relative shift τ (then ×10 until positive definite)
SHIFT_START = 1e-10
#: ... and its last: a matrix that needs more is rejected (it is not a curvature any more)
SHIFT_MAX = 1e12


@dataclass
class BlockTridiagonal:
    """A symmetric block-tridiagonal matrix: ``diag`` (T, d, d) the blocks (t, t) and
    ``upper`` (T−1, d, d) the blocks (t, t+1) (the blocks (t+1, t) are their transposes)."""

    diag: np.ndarray
    upper: np.ndarray

    def __post_init__(self) -> None:
        self.diag = np.ascontiguousarray(self.diag, dtype=np.float64)
        self.upper = np.ascontiguousarray(self.upper, dtype=np.float64)
        T, d, d2 = self.diag.shape
        if d != d2 or self.upper.shape != (max(T - 1, 0), d, d):
            raise ValueError(f"block-tridiagonal: diagonal blocks {self.diag.shape} and upper blocks "
                             f"{self.upper.shape} do not fit (want (T, d, d) and (T-1, d, d))")

    @classmethod
    def zeros(cls, T: int, d: int) -> BlockTridiagonal:
        """The zero matrix of T blocks of size d."""
        return cls(np.zeros((T, d, d)), np.zeros((max(T - 1, 0), d, d)))

    @classmethod
    def from_dense(cls, A: np.ndarray, d: int) -> BlockTridiagonal:
        """The block-tridiagonal part of a dense (T·d)×(T·d) matrix (the rest is ignored)."""
        A = np.asarray(A, dtype=np.float64)
        T = A.shape[0] // d
        A4 = A.reshape(T, d, T, d)
        t = np.arange(T)
        return cls(A4[t, :, t, :], A4[t[:-1], :, t[1:], :])

    @property
    def n_blocks(self) -> int:
        """T, the number of diagonal blocks (frames)."""
        return self.diag.shape[0]

    @property
    def block(self) -> int:
        """d, the block size (latent dimensions)."""
        return self.diag.shape[1]

    @property
    def shape(self) -> tuple[int, int]:
        """(T·d, T·d)."""
        n = self.n_blocks * self.block
        return n, n

    def __neg__(self) -> BlockTridiagonal:
        return BlockTridiagonal(-self.diag, -self.upper)

    def __add__(self, other: BlockTridiagonal) -> BlockTridiagonal:
        return BlockTridiagonal(self.diag + other.diag, self.upper + other.upper)

    def scaled(self, c: float) -> BlockTridiagonal:
        """c times the matrix."""
        return BlockTridiagonal(c * self.diag, c * self.upper)

    def symmetrised(self) -> BlockTridiagonal:
        """½(A + Aᵀ): the diagonal blocks symmetrised (the off-diagonal ones are shared)."""
        return BlockTridiagonal(0.5 * (self.diag + np.transpose(self.diag, (0, 2, 1))), self.upper)

    def diagonal(self) -> np.ndarray:
        """The scalar diagonal (T·d,)."""
        return np.einsum("tii->ti", self.diag).reshape(-1)

    def matvec(self, v: np.ndarray) -> np.ndarray:
        """A v for v (T·d,) or (T·d, k)."""
        v = np.asarray(v, dtype=np.float64)
        T, d = self.n_blocks, self.block
        V = v.reshape(T, d, -1)
        out = np.einsum("tij,tjk->tik", self.diag, V)
        if T > 1:
            out[:-1] += np.einsum("tij,tjk->tik", self.upper, V[1:])
            out[1:] += np.einsum("tji,tjk->tik", self.upper, V[:-1])
        return out.reshape(v.shape)

    def dense(self) -> np.ndarray:
        """The dense (T·d)×(T·d) matrix (short paths and tests only: quadratic memory)."""
        T, d = self.n_blocks, self.block
        A4 = np.zeros((T, d, T, d))
        t = np.arange(T)
        A4[t, :, t, :] = self.diag
        A4[t[:-1], :, t[1:], :] = self.upper
        A4[t[1:], :, t[:-1], :] = np.transpose(self.upper, (0, 2, 1))
        return A4.reshape(T * d, T * d)

    def lower_band(self) -> np.ndarray:
        """LAPACK's lower band storage (2d, T·d): ``ab[i − j, j] = A[i, j]`` for 0 ≤ i − j ≤ 2d − 1."""
        T, d = self.n_blocks, self.block
        ab = np.zeros((2 * d, T * d))
        for a in range(d):
            for b in range(a + 1):
                ab[a - b, b::d] = self.diag[:, a, b]
            for b in range(d):
                ab[d + a - b, b:(T - 1) * d:d] = self.upper[:, b, a]    # block (t+1, t) = upper[t]ᵀ
        return ab

    def cholesky(self) -> BandedFactor:
        """P = R Rᵀ (R lower, banded); ``numpy.linalg.LinAlgError`` when P is not positive definite."""
        return BandedFactor(cholesky_banded(self.lower_band(), lower=True, check_finite=False),
                            self.n_blocks, self.block, matrix=self)

    def inertia(self) -> int:
        """The number of eigenvalues ≤ 0 (block LDLᵀ and Sylvester's law of inertia; a pivot
        block that is singular to working precision counts its zero eigenvalues)."""
        return int(_nonpositive_pivots(self.diag, self.upper))


@numba.njit(cache=True)
def _nonpositive_pivots(D: np.ndarray, B: np.ndarray) -> int:
    """Σ_t #{eigenvalues of the pivot D_t ≤ 0}, D₀ = A₀₀, D_{t+1} = A_{t+1,t+1} − B_tᵀ D_t⁻¹ B_t."""
    T, d = D.shape[0], D.shape[1]
    piv = D[0].copy()
    count = 0
    for t in range(T):
        sym = 0.5 * (piv + piv.T)
        lam, U = np.linalg.eigh(sym)
        big = np.max(np.abs(lam))
        tol = 1e-14 * big if big > 0 else 1e-300
        inv = np.zeros((d, d))
        for k in range(d):
            if lam[k] <= tol:
                count += 1
            if abs(lam[k]) > tol:
                inv += np.outer(U[:, k], U[:, k]) / lam[k]
        if t + 1 < T:
            piv = D[t + 1] - B[t].T @ inv @ B[t]
    return count


@dataclass
class BandedFactor:
    """The banded Cholesky factor R (lower, LAPACK band storage ``ab`` of shape (2d, T·d)) of
    a block-tridiagonal positive definite P = R Rᵀ, and what it gives (module docstring).
    ``shift``: the τ of :func:`modified_cholesky` (0: the factor of P itself); ``matrix``: the
    matrix R Rᵀ (P, or P + τ·diag(|P_ii|))."""

    ab: np.ndarray
    n_blocks: int
    block: int
    shift: float = 0.0
    #: the positive definite matrix factorised (P, or P + τ·diag(|P_ii|))
    matrix: BlockTridiagonal | None = None

    @property
    def n(self) -> int:
        """T·d."""
        return self.n_blocks * self.block

    def solve(self, b: np.ndarray) -> np.ndarray:
        """P⁻¹ b for b (n,) or (n, k)."""
        return cho_solve_banded((self.ab, True), b, check_finite=False)

    def _tri(self, b: np.ndarray, trans: str) -> np.ndarray:
        b = np.asarray(b, dtype=np.float64)
        x, info = dtbtrs(self.ab, b.reshape(self.n, -1), uplo="L", trans=trans)
        if info != 0:
            raise np.linalg.LinAlgError(f"banded triangular solve failed (LAPACK info {info})")
        return x.reshape(b.shape)

    def scale_matvec(self, z: np.ndarray) -> np.ndarray:
        """L z = R⁻ᵀ z (L Lᵀ = P⁻¹) for z (n,) or (n, k): x_MAP + L z, z ~ N(0, I), is a draw of N(x_MAP, P⁻¹)."""
        return self._tri(z, "T")

    def scale_rmatvec(self, g: np.ndarray) -> np.ndarray:
        """Lᵀ g = R⁻¹ g for g (n,) or (n, k): a gradient in the coordinates z of x = x₀ + L z."""
        return self._tri(g, "N")

    def unscale_matvec(self, x: np.ndarray) -> np.ndarray:
        """L⁻¹ x = Rᵀ x for x (n,) or (n, k): a displacement in x as whitened coordinates."""
        x = np.asarray(x, dtype=np.float64)
        X = x.reshape(self.n, -1)
        out = self.ab[0][:, None] * X
        for k in range(1, self.ab.shape[0]):           # (Rᵀx)_j += R[j+k, j] x_{j+k}
            out[:-k] += self.ab[k, :-k, None] * X[k:]
        return out.reshape(x.shape)

    def dense_scale(self) -> tuple[np.ndarray, np.ndarray]:
        """(L, L⁻¹) as dense n×n matrices (the samplers that move in whitened coordinates on
        short paths: quadratic memory)."""
        eye = np.eye(self.n)
        return self.scale_matvec(eye), self.unscale_matvec(eye)

    def logdet(self) -> float:
        """ln |P| = 2 Σ ln R_ii."""
        return 2.0 * float(np.sum(np.log(self.ab[0])))

    def blocks(self) -> tuple[np.ndarray, np.ndarray]:
        """R's diagonal blocks A (T, d, d) (lower triangular) and sub-diagonal blocks C (T−1, d, d), C_t = R_{t+1,t}."""
        T, d = self.n_blocks, self.block
        A = np.zeros((T, d, d))
        C = np.zeros((max(T - 1, 0), d, d))
        for a in range(d):
            for b in range(a + 1):
                A[:, a, b] = self.ab[a - b, b::d]
            for b in range(d):
                C[:, a, b] = self.ab[d + a - b, b:(T - 1) * d:d]
        return A, C

    def marginal_covariances(self) -> np.ndarray:
        """The diagonal blocks Σ_tt (T, d, d) of Σ = P⁻¹ by the selected inverse (module docstring)."""
        A, C = self.blocks()
        return _selected_inverse(A, C)


@numba.njit(cache=True)
def _selected_inverse(A: np.ndarray, C: np.ndarray) -> np.ndarray:
    """Takahashi's recursion (module docstring) for the diagonal blocks of (R Rᵀ)⁻¹."""
    T, d = A.shape[0], A.shape[1]
    S = np.empty((T, d, d))
    Ai = np.linalg.inv(A[T - 1])
    S[T - 1] = Ai.T @ Ai
    for t in range(T - 2, -1, -1):
        Ai = np.linalg.inv(A[t])
        X = -(Ai.T @ C[t].T) @ S[t + 1]               # Σ_{t,t+1}
        St = Ai.T @ (Ai - C[t].T @ X.T)
        S[t] = 0.5 * (St + St.T)
    return S


def modified_cholesky(P: BlockTridiagonal, what: str = "precision") -> BandedFactor:
    """The banded Cholesky factor of P when P is positive definite, else of P + τ·diag(|P_ii|)
    with the smallest τ in ``SHIFT_START``·10^k that makes it so (module docstring); τ is in
    the result's ``shift`` and logged (``what`` names the matrix in the log line). A
    ``numpy.linalg.LinAlgError`` when not even ``SHIFT_MAX`` does, or P is not finite."""
    if not (np.all(np.isfinite(P.diag)) and np.all(np.isfinite(P.upper))):
        raise np.linalg.LinAlgError(f"{what}: not finite")
    try:
        return P.cholesky()
    except np.linalg.LinAlgError:
        pass
    scale = np.abs(P.diagonal())
    scale = np.maximum(scale, 1e-12 * max(float(scale.max(initial=0.0)), 1e-300)).reshape(P.n_blocks, P.block)
    tau = SHIFT_START
    while tau <= SHIFT_MAX:
        Q = BlockTridiagonal(P.diag + tau * np.einsum("ti,ij->tij", scale, np.eye(P.block)), P.upper)
        try:
            f = Q.cholesky()
        except np.linalg.LinAlgError:
            tau *= 10.0
            continue
        f.shift = tau
        log.debug("%s not positive definite: factorised with %.1e x its diagonal's modulus added", what, tau)
        return f
    raise np.linalg.LinAlgError(f"{what}: not positive definite even with {SHIFT_MAX:g} x its diagonal added")


__all__ = ["SHIFT_MAX", "SHIFT_START", "BandedFactor", "BlockTridiagonal", "modified_cholesky"]
