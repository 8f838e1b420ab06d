"""The log-density terms of the shared GPDM (deena2010 eq. 5 and 7; docs/model.md).

Every term is a differentiable torch function of float64 tensors. The common core is the
matrix-normal log-density of an N×D matrix V with column covariance K,

    ℓ(K, V) = −(N·D/2)·ln 2π − (D/2)·ln|K| − ½·tr(K⁻¹ V Vᵀ),

evaluated through a Cholesky factor, with a closed-form backward pass

    ∂ℓ/∂K = ½ (A Aᵀ − D·K⁻¹),   ∂ℓ/∂V = −A,   A = K⁻¹ V,

which is about twice as fast as differentiating through the Cholesky (float64, 2 CPU threads).
"""
from __future__ import annotations

import functools
import math
from collections.abc import Sequence

import torch

from bayes_talk.gp.fused import fused_ok, rbf_matrix_normal
from bayes_talk.gp.kernels import train_cov
from bayes_talk.gp.linalg import cho_solve, cholesky, logdet

LOG_2PI = math.log(2.0 * math.pi)

#: variance κ² of the half-normal prior on each output scale w_m (the GPDM's prior, Wang,
#: Fleet & Hertzmann 2008, which the papers build on; docs/model.md)
W_PRIOR_VARIANCE = 1e6


class _MatrixNormalLogLik(torch.autograd.Function):
    @staticmethod
    def forward(ctx, K: torch.Tensor, V: torch.Tensor, what: str) -> torch.Tensor:  # type: ignore[override]
        L = cholesky(K, what)
        A = cho_solve(L, V)
        N, D = V.shape
        ll = -0.5 * D * logdet(L) - 0.5 * (V * A).sum() - 0.5 * N * D * LOG_2PI
        ctx.save_for_backward(L, A)
        return ll

    @staticmethod
    def backward(ctx, g: torch.Tensor):  # type: ignore[override]
        L, A = ctx.saved_tensors
        gK = gV = None
        if ctx.needs_input_grad[0]:
            D = A.shape[1]
            gK = (0.5 * g) * (A @ A.mT - D * torch.cholesky_inverse(L))
        if ctx.needs_input_grad[1]:
            gV = -g * A
        return gK, gV, None


def matrix_normal_loglik(K: torch.Tensor, V: torch.Tensor, what: str = "kernel matrix") -> torch.Tensor:
    """ℓ(K, V) above: Σ over the D columns of ln N(V[:, m]; 0, K)."""
    if V.shape[0] != K.shape[0]:
        raise ValueError(f"{what}: {K.shape[0]} rows in K but {V.shape[0]} in the data")
    return _MatrixNormalLogLik.apply(K, V, what)


def observation_loglik(
    Y: torch.Tensor,
    X: torch.Tensor,
    alpha: torch.Tensor,
    gamma: torch.Tensor,
    beta: torch.Tensor,
    w: torch.Tensor,
    alpha_lin: torch.Tensor | None = None,
    what: str = "observation kernel",
) -> torch.Tensor:
    """deena2010 eq. 5, for centred Y (N×D) and W = diag(w):

        ln p(Y | X) = N·Σ_m ln w_m − (N·D/2)·ln 2π − (D/2)·ln|K| − ½·tr(K⁻¹ Y W² Yᵀ),
        K = k(X, X) + β⁻¹ I.

    The factor N on ln|W| is the paper's |W|^N (some toolboxes drop it). Evaluated by the fused
    RBF pass of :mod:`bayes_talk.gp.fused` (closed-form backward), or through
    :func:`matrix_normal_loglik` with a linear kernel term or when K needs jitter.
    """
    N = Y.shape[0]
    V = Y * w
    if alpha_lin is None and fused_ok(X, V, alpha, gamma, beta):
        ll = rbf_matrix_normal(X, alpha, gamma, beta, V)
        if ll is not None:
            return N * torch.log(w).sum() + ll
    K = train_cov(X, alpha, gamma, beta, alpha_lin)
    return N * torch.log(w).sum() + matrix_normal_loglik(K, V, what)


def dynamics_split(seq_lengths: Sequence[int]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Row indices of X_in (x^s_1..x^s_{T_s−1}), X_out (x^s_2..x^s_{T_s}) and first frames.

    Remembered for the last few length lists (the objective asks for them at every L-BFGS
    evaluation); the index tensors are shared, so callers must not modify them."""
    return _dynamics_split(tuple(int(t) for t in seq_lengths))


@functools.lru_cache(maxsize=16)
def _dynamics_split(seq_lengths: tuple[int, ...]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    ins, outs, firsts = [], [], []
    start = 0
    for T in seq_lengths:
        firsts.append(start)
        ins.extend(range(start, start + T - 1))
        outs.extend(range(start + 1, start + T))
        start += T
    as_t = lambda v: torch.tensor(v, dtype=torch.long)
    return as_t(ins), as_t(outs), as_t(firsts)


def dynamics_loglik(
    X: torch.Tensor,
    seq_lengths: Sequence[int],
    alpha: torch.Tensor | float,
    gamma: torch.Tensor | float,
    beta: torch.Tensor | float,
    alpha_lin: torch.Tensor | float | None = None,
) -> torch.Tensor:
    """deena2010 eq. 7 over several sequences with one shared dynamics GP:

        ln p(X) = Σ_s ln N(x^s_1; 0, I) − (d·N'/2)·ln 2π − (d/2)·ln|K_X| − ½·tr(K_X⁻¹ X_out X_outᵀ),

    K_X = k_x(X_in, X_in) + β_x⁻¹ I, N' = Σ_s (T_s − 1).
    """
    if sum(seq_lengths) != X.shape[0]:
        raise ValueError(
            f"sequence lengths add up to {sum(seq_lengths)} but X has {X.shape[0]} rows"
        )
    i_in, i_out, i_first = dynamics_split(seq_lengths)
    d = X.shape[1]
    X1 = X[i_first]
    ll = -0.5 * (X1 * X1).sum() - 0.5 * X1.shape[0] * d * LOG_2PI
    if len(i_in) == 0:
        return ll
    beta_t = torch.as_tensor(beta, dtype=X.dtype)
    if alpha_lin is None and fused_ok(X, alpha, gamma, beta_t):
        lx = rbf_matrix_normal(X[i_in], alpha, gamma, beta_t, X[i_out])
        if lx is not None:
            return ll + lx
    K = train_cov(X[i_in], alpha, gamma, beta_t, alpha_lin)
    return ll + matrix_normal_loglik(K, X[i_out], "dynamics kernel")


def log_hyperprior(thetas: Sequence[torch.Tensor]) -> torch.Tensor:
    """Σ_θ ln p(θ) with the improper p(θ) ∝ 1/θ, in θ-space (no Jacobian; docs/model.md)."""
    if not thetas:
        return torch.zeros((), dtype=torch.float64)
    return -sum(torch.log(t).sum() for t in thetas)


def log_w_prior(w: torch.Tensor, variance: float = W_PRIOR_VARIANCE) -> torch.Tensor:
    """Σ_m ln HalfNormal(w_m; κ²): ln 2 − ½ ln(2π κ²) − w_m²/(2κ²) per scale."""
    return (math.log(2.0) - 0.5 * math.log(2.0 * math.pi * variance) - w * w / (2.0 * variance)).sum()
