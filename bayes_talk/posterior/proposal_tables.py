"""Compiled tables of the particle sweep's proposal (for speed).

:class:`~bayes_talk.posterior.particle_gibbs.MixtureProposal` evaluates, at every frame of
every sweep, two N × M tables (N particles, M ≈ 300 centres X_j): the smoothness weight of
each centre given each particle's ancestor at a block start,

    ln π_nj = ln π⁰_j + ln N(z_n; μ_j, diag v_j) − ln Σ_k (same for k),                  (W)

(z_n the ancestor's visual prediction plus the factor's pseudo-observation, μ_j and v_j the
visual predictive at centre j with the motion variance added), and the mixture's kernel
density at each particle,

    ln q_k(x_n) = ln Σ_j Σ_b π_nj N(x_n; X_j, h_b² I) − ln B.                            (K)

With NumPy each builds (N, M, D) temporaries and calls ``logsumexp`` (together 1.5 of every
5.8 s of a sweep on a held-out utterance); here each is one pass without temporaries, in a
fixed order (no threads, no BLAS: the bits do not depend on the machine's thread count).
Each row's log-sum-exp takes its maximum first, as ``scipy.special.logsumexp`` does.
"""
from __future__ import annotations

import math

import numba
import numpy as np

LOG_2PI = math.log(2.0 * math.pi)


@numba.njit(cache=True, fastmath={"reassoc"})
def smoothness_weights(lw0: np.ndarray, z: np.ndarray, mu: np.ndarray, ivar: np.ndarray,
                       half_logdet: np.ndarray) -> np.ndarray:
    """(W): ln π (N, M), each row normalised, from ln π⁰ (M,), z (N, D), μ (M, D), 1/v (M, D)
    and ½ Σ_m ln v_jm (M,) (the 2π constant cancels in the normalisation)."""
    N, D = z.shape
    M = mu.shape[0]
    out = np.empty((N, M))
    for n in range(N):
        top = -np.inf
        for j in range(M):
            q = 0.0
            for m in range(D):
                r = z[n, m] - mu[j, m]
                q += r * r * ivar[j, m]
            w = lw0[j] - half_logdet[j] - 0.5 * q
            out[n, j] = w
            top = max(top, w)
        acc = 0.0
        for j in range(M):
            acc += math.exp(out[n, j] - top)
        lse = top + math.log(acc)
        for j in range(M):
            out[n, j] -= lse
    return out


@numba.njit(cache=True, fastmath={"reassoc"})
def kernel_mixture_logpdf(X: np.ndarray, C: np.ndarray, lw: np.ndarray, hs: np.ndarray) -> np.ndarray:
    """(K): ln q_k at rows X (N, d) for centres C (M, d), log weights lw (N, M), or (1, M)
    for weights shared by every row, and bandwidths hs (B,) → (N,)."""
    N, d = X.shape
    M, B = C.shape[0], hs.shape[0]
    shared = lw.shape[0] == 1
    inv2h2 = np.empty(B)
    logn = np.empty(B)
    for b in range(B):
        inv2h2[b] = 0.5 / (hs[b] * hs[b])
        logn[b] = -d * math.log(hs[b]) - 0.5 * d * LOG_2PI - math.log(B)
    out = np.empty(N)
    r2 = np.empty(M)
    for n in range(N):
        row = 0 if shared else n
        top = -np.inf
        for j in range(M):
            s = 0.0
            for k in range(d):
                r = X[n, k] - C[j, k]
                s += r * r
            r2[j] = s
            for b in range(B):
                e = lw[row, j] + logn[b] - s * inv2h2[b]
                top = max(top, e)
        if top == -np.inf:
            out[n] = -np.inf
            continue
        acc = 0.0
        for j in range(M):
            for b in range(B):
                acc += math.exp(lw[row, j] + logn[b] - r2[j] * inv2h2[b] - top)
        out[n] = top + math.log(acc)
    return out


__all__ = ["kernel_mixture_logpdf", "smoothness_weights"]
