"""The RBF matrix-normal term in one fused pass, with a closed-form backward.

    ℓ(X, α, γ, β, V) = −(N·D/2) ln 2π − (D/2) ln|K| − ½ tr(K⁻¹ V Vᵀ),
    K = α E + β⁻¹ I,   E_ij = exp(−(γ/2) ‖x_i − x_j‖²)

is the core of both likelihood terms of the SGPDM (deena2010 eq. 5 with V = Y W, eq. 7
with X = X_in, V = X_out). Its gradient, with A = K⁻¹V and G = gK ∘ αE:

    gK = ∂ℓ/∂K = ½ (A Aᵀ − D K⁻¹)
    ∂ℓ/∂x_i = −2γ Σ_j G_ij (x_i − x_j)
    ∂ℓ/∂α = Σ_ij G_ij / α,   ∂ℓ/∂γ = −½ Σ_ij G_ij ‖x_i − x_j‖²,   ∂ℓ/∂β = −tr(gK) / β²,
    ∂ℓ/∂V = −A.

Everything N×N lives in ONE Fortran-ordered buffer per term (32 MB at N = 2000):

* forward: one compiled pass (numba) writes K into the lower triangle and E into the
  strict upper triangle (E_ij, i > j, at row i−j−1 of column N−1−j, so both triangles
  are written column by column); LAPACK ``dpotrf`` turns the lower triangle into L in
  place and ``dpotrs`` gives A = K⁻¹V (N×D).
* backward: ``dpotri`` turns L into K⁻¹ in place, and a second compiled pass reads K⁻¹
  and E once, forms G_ij = ½(a_i·a_j − D K⁻¹_ij) α E_ij pair by pair (the a_i·a_j of
  AAᵀ computed on the fly: no N×N AAᵀ, no BLAS call) and sums ∂ℓ/∂X (x_i − x_j formed
  directly, no s_i x_i − (GX)_i cancellation), Σ G, Σ G r² and tr gK. The upper
  triangle (E) is never touched by LAPACK ('L' only).

No N×N matrix is symmetrised, copied or allocated twice; the floor is LAPACK's
``dpotrf`` + ``dpotri`` (N³ flops), taken from the MKL inside torch where it is exported
(:mod:`bayes_talk.gp.lapack`). Below N = :data:`~bayes_talk.gp.threads.THREADED_MIN_N`
a term runs on the calling thread only (its LAPACK calls on one MKL thread, whatever torch
was given: threads cost more than they gain there). The compiled passes run on
``torch.get_num_threads()`` threads (from N = :data:`~bayes_talk.gp.threads.THREADED_MIN_N`;
the calling thread and a small pool of plain
threads running GIL-free numba code) over a fixed set of :data:`N_CHUNKS` column chunks
(balanced: columns j and N−1−j together) whose partial sums are added in chunk order,
so their results do not depend on the number of threads. (numba's own OpenMP threading
layer next to torch's OpenMP and MKL threads made a whole evaluation at N = 200 10-20x
slower on this loaded 2-core machine, even with one thread.) The backward is re-entrant
(``retain_graph``): the buffer records whether L has been inverted already, and the
gradient pass only reads it.

When ``dpotrf`` fails (K not numerically positive definite) :func:`rbf_matrix_normal`
returns None and the caller takes the torch path, whose Cholesky escalates the jitter
and logs it (:mod:`bayes_talk.gp.linalg`). float64 throughout.
"""
from __future__ import annotations

import itertools
import math
import os
from concurrent.futures import ThreadPoolExecutor

import numba
import numpy as np
import torch

from bayes_talk.base import settings
from bayes_talk.gp.lapack import potrf_lower, potri_lower, potrs_lower
from bayes_talk.gp.threads import THREADED_MIN_N

LOG_2PI = math.log(2.0 * math.pi)

#: column chunks of the compiled passes (fixed, so results do not depend on threads)
N_CHUNKS = 32


@numba.njit(cache=True)
def _build_column(X: np.ndarray, alpha: float, h: float, noise: float, buf: np.ndarray, j: int) -> None:
    N, d = X.shape
    buf[j, j] = alpha + noise
    u = N - 1 - j
    for i in range(j + 1, N):
        r2 = 0.0
        for q in range(d):
            t = X[i, q] - X[j, q]
            r2 += t * t
        e = math.exp(h * r2)
        buf[i, j] = alpha * e
        buf[i - j - 1, u] = e


@numba.njit(cache=True)
def _build_chunk(X: np.ndarray, alpha: float, gamma: float, noise: float, buf: np.ndarray,
                 n_chunks: int, c: int) -> None:
    """The columns of chunk c (j = p and N−1−p for p ≡ c mod n_chunks) of :func:`_build`."""
    N = X.shape[0]
    for p in range(c, (N + 1) // 2, n_chunks):
        _build_column(X, alpha, -0.5 * gamma, noise, buf, p)
        if N - 1 - p != p:
            _build_column(X, alpha, -0.5 * gamma, noise, buf, N - 1 - p)


@numba.njit(cache=True, nogil=True)
def _build_chunks(X, alpha, gamma, noise, buf, n_chunks, first, step):
    """Chunks first, first + step, … of :func:`_build` (without the GIL)."""
    for c in range(first, n_chunks, step):
        _build_chunk(X, alpha, gamma, noise, buf, n_chunks, c)


@numba.njit(cache=True, fastmath={"reassoc"})
def _dot_rows(A: np.ndarray, i: int, j: int) -> float:
    """a_i · a_j for rows of the C-ordered A (vectorised: reassociation allowed)."""
    s = 0.0
    for k in range(A.shape[1]):
        s += A[i, k] * A[j, k]
    return s


@numba.njit(cache=True)
def _gradient_column(X: np.ndarray, buf: np.ndarray, A: np.ndarray, alpha: float, j: int,
                     acc: np.ndarray, dl: np.ndarray):
    """Column j of G = ½(AAᵀ − D K⁻¹) ∘ αE: adds G_ij (x_i − x_j) to acc[i] and subtracts
    it from acc[j] (i > j); returns (Σ_i G_ij over the column and its mirror,
    Σ_{i>j} G_ij r²_ij, gK_jj)."""
    N, d = X.shape
    D = A.shape[1]
    gjj = 0.5 * (_dot_rows(A, j, j) - D * buf[j, j])
    sg = gjj * alpha
    sr = 0.0
    u = N - 1 - j
    for i in range(j + 1, N):
        r2 = 0.0
        for q in range(d):
            t = X[i, q] - X[j, q]
            dl[q] = t
            r2 += t * t
        g = 0.5 * (_dot_rows(A, i, j) - D * buf[i, j]) * alpha * buf[i - j - 1, u]
        sg += 2.0 * g
        sr += g * r2
        for q in range(d):
            acc[i, q] += g * dl[q]
            acc[j, q] -= g * dl[q]
    return sg, sr, gjj


@numba.njit(cache=True)
def _gradient_chunk(X, buf, A, alpha, n_chunks, c, acc, dl, sums) -> None:
    """The columns of chunk c of :func:`_gradient` (same columns as :func:`_build_chunk`)."""
    N = X.shape[0]
    for p in range(c, (N + 1) // 2, n_chunks):
        a, b, t = _gradient_column(X, buf, A, alpha, p, acc, dl)
        sums[0] += a
        sums[1] += b
        sums[2] += t
        if N - 1 - p != p:
            a, b, t = _gradient_column(X, buf, A, alpha, N - 1 - p, acc, dl)
            sums[0] += a
            sums[1] += b
            sums[2] += t


@numba.njit(cache=True, nogil=True)
def _gradient_chunks(X, buf, A, alpha, n_chunks, acc, dl, sums, first, step):
    """Chunks first, first + step, … of :func:`_gradient` (without the GIL)."""
    for c in range(first, n_chunks, step):
        _gradient_chunk(X, buf, A, alpha, n_chunks, c, acc[c], dl[c], sums[c])


_POOL: tuple[tuple[int, int], ThreadPoolExecutor] | None = None


def _threads() -> int:
    return max(1, min(torch.get_num_threads(), os.cpu_count() or 1))


def _term_threads(N: int) -> int:
    """The threads of a term of size N: below :data:`~bayes_talk.gp.threads.THREADED_MIN_N`
    its compiled passes and its LAPACK calls run on the calling thread only (one MKL
    thread), from it on :func:`_threads`."""
    return _threads() if N >= THREADED_MIN_N else 1


def _run_chunked(fn, N: int, n_chunks: int, *args) -> None:
    """``fn(*args, first, step)`` over the ``n_chunks`` chunks: all on the calling thread,
    or chunk by chunk from a shared counter on it and ``torch.get_num_threads() − 1`` pool
    threads (plain threads running GIL-free compiled code, so no OpenMP runtime meets
    torch's or MKL's; a thread that the OS holds back leaves its share to the others)."""
    global _POOL
    n = _term_threads(N)
    if n == 1:
        fn(*args, 0, 1)
        return
    key = (os.getpid(), n - 1)  # a forked child, or more threads, gets a pool of its own
    if _POOL is None or _POOL[0] != key:
        if _POOL is not None and _POOL[0][0] == key[0]:
            _POOL[1].shutdown(wait=False)
        _POOL = (key, ThreadPoolExecutor(max_workers=n - 1, thread_name_prefix="bayes_talk_gp"))
    counter = itertools.count()

    def work() -> None:
        while (c := next(counter)) < n_chunks:
            fn(*args, c, n_chunks)

    futures = [_POOL[1].submit(work) for _ in range(n - 1)]
    work()
    for f in futures:
        f.result()


def _build(X: np.ndarray, alpha: float, gamma: float, noise: float, buf: np.ndarray, n_chunks: int) -> None:
    """Lower triangle of ``buf`` ← K = αE + noise·I; E_ij (i > j) at buf[i−j−1, N−1−j]."""
    _run_chunked(_build_chunks, X.shape[0], n_chunks, X, alpha, gamma, noise, buf, n_chunks)


def _gradient(X: np.ndarray, buf: np.ndarray, A: np.ndarray, alpha: float, n_chunks: int):
    """From K⁻¹ in the lower triangle of ``buf``, E in its upper triangle and A = K⁻¹V
    (C-ordered): per chunk, Σ_j G_ij (x_i − x_j) for every i (n_chunks×N×d), and
    (Σ_ij G_ij, Σ_{i>j} G_ij r²_ij, tr gK) (n_chunks×3)."""
    N, d = X.shape
    acc = np.zeros((n_chunks, N, d))
    dl = np.empty((n_chunks, d))
    sums = np.zeros((n_chunks, 3))
    _run_chunked(_gradient_chunks, N, n_chunks, X, buf, A, alpha, n_chunks, acc, dl, sums)
    return acc, sums


class _Buffer:
    """The N×N buffer of one term and how far its lower triangle has been transformed."""

    def __init__(self, Xn: np.ndarray, a: float, gm: float, noise: float):
        N = Xn.shape[0]
        self.X = Xn
        self.a = a
        self.m = np.empty((N, N), order="F")
        _build(Xn, a, gm, noise, self.m, N_CHUNKS)
        self.stage = "K"

    def factor(self) -> bool:
        ok = potrf_lower(self.m, _term_threads(self.m.shape[0])) == 0
        self.stage = "L"
        return ok

    def inverse(self) -> np.ndarray:
        """The buffer with K⁻¹ in its lower triangle (``dpotri`` on L, once)."""
        if self.stage == "L":
            info = potri_lower(self.m, _term_threads(self.m.shape[0]))
            if info != 0:
                raise np.linalg.LinAlgError(f"dpotri failed (LAPACK info {info})")
            self.stage = "Kinv"
        return self.m


class _RBFMatrixNormal(torch.autograd.Function):
    @staticmethod
    def forward(ctx, X, alpha, gamma, beta, V, state):  # type: ignore[override]
        ctx.save_for_backward(alpha, gamma, beta)
        ctx.state = state
        return torch.as_tensor(state["ll"], dtype=torch.float64)

    @staticmethod
    def backward(ctx, g):  # type: ignore[override]
        alpha, gamma, beta = ctx.saved_tensors
        st = ctx.state
        buf, A = st["buf"], st["A"]
        a, gm, b = float(alpha.detach()), float(gamma.detach()), float(beta.detach())
        gs = float(g)
        out = [None] * 6
        if any(ctx.needs_input_grad[:4]):
            acc, sums = _gradient(buf.X, buf.inverse(), st["A_rows"], a, N_CHUNKS)
            s_g, s_r2, tr = sums.sum(0)
            if ctx.needs_input_grad[0]:
                out[0] = torch.from_numpy(acc.sum(0) * (-2.0 * gm * gs))
            if ctx.needs_input_grad[1]:
                out[1] = torch.tensor(gs * s_g / a, dtype=torch.float64)
            if ctx.needs_input_grad[2]:
                out[2] = torch.tensor(-gs * s_r2, dtype=torch.float64)
            if ctx.needs_input_grad[3]:
                out[3] = torch.tensor(-gs * tr / (b * b), dtype=torch.float64)
        if ctx.needs_input_grad[4]:
            out[4] = torch.from_numpy(-gs * A)
        return tuple(out)


def rbf_matrix_normal(X: torch.Tensor, alpha, gamma, beta, V: torch.Tensor) -> torch.Tensor | None:
    """ℓ above as a differentiable scalar, or None when K cannot be factorised without
    jitter (the caller then takes the torch path). X, V: float64 CPU tensors."""
    f64 = torch.float64
    alpha, gamma, beta = (torch.as_tensor(t, dtype=f64) for t in (alpha, gamma, beta))
    a, gm, b = float(alpha.detach()), float(gamma.detach()), float(beta.detach())
    solved = _factor_solve(X.detach().numpy(), a, gm, b, V.detach().numpy())
    if solved is None:
        return None
    buf, A, ll = solved
    state = {"buf": buf, "A": A, "A_rows": np.ascontiguousarray(A), "ll": ll}
    return _RBFMatrixNormal.apply(X, alpha, gamma, beta, V, state)


def _factor_solve(X: np.ndarray, a: float, gm: float, b: float, V: np.ndarray):
    """The shared forward pass of ℓ above: (the factorised kernel buffer, A = K⁻¹V, ℓ), or
    None when K cannot be factorised without jitter."""
    Xn = np.ascontiguousarray(X, dtype=np.float64)
    V = np.asarray(V, dtype=np.float64)
    A = np.array(V, order="F", copy=True)
    N, D = A.shape
    buf = _Buffer(Xn, a, gm, 1.0 / b)
    if not buf.factor():
        return None
    L = buf.m
    logdet = 2.0 * np.log(np.diagonal(L)).sum()
    if potrs_lower(L, A, _term_threads(N)) != 0:
        return None
    return buf, A, -0.5 * D * logdet - 0.5 * float((V * A).sum()) - 0.5 * N * D * LOG_2PI


def rbf_matrix_normal_grad(X: np.ndarray, a: float, gm: float, b: float, V: np.ndarray):
    """ℓ above and its whole gradient in NumPy, without autograd (for the direct
    objective of :mod:`bayes_talk.models.sgpdm_objective`): ``(ℓ, ∂ℓ/∂X, ∂ℓ/∂α, ∂ℓ/∂γ,
    ∂ℓ/∂β, ∂ℓ/∂V)`` by the same passes and formulas as :func:`rbf_matrix_normal` and its
    backward (so the same numbers), or None when K cannot be factorised without jitter.
    X (N×d) and V (N×D): float64 arrays; α, γ, β: floats."""
    solved = _factor_solve(X, a, gm, b, V)
    if solved is None:
        return None
    buf, A, ll = solved
    acc, sums = _gradient(buf.X, buf.inverse(), np.ascontiguousarray(A), a, N_CHUNKS)
    s_g, s_r2, tr = sums.sum(0)
    return ll, acc.sum(0) * (-2.0 * gm), s_g / a, -s_r2, -tr / (b * b), -A


def fused_ok(*tensors) -> bool:
    """Whether the fused path applies: switched on (:mod:`bayes_talk.base.settings` ``fused``),
    float64 CPU tensors (or plain numbers)."""
    return settings.get("fused") and all(not isinstance(t, torch.Tensor) or (t.dtype == torch.float64 and t.device.type == "cpu")
               for t in tensors)
