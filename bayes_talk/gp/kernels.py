"""Kernels in the papers' parametrisation (deena2010 eq. 6, DESIGN.md §3).

    k(x, x') = α · exp(−(γ/2) · ‖x − x'‖²)  [+ α_lin · xᵀx']

α is the signal variance, γ the inverse width (γ = 1/ℓ²), α_lin an optional linear term.
The noise enters only on the training diagonal as β⁻¹ I, β a precision (eq. 1).
"""
from __future__ import annotations

import torch


def sq_dist(X1: torch.Tensor, X2: torch.Tensor) -> torch.Tensor:
    """Pairwise squared Euclidean distances ``‖x1_i − x2_j‖²``, clamped at 0."""
    d = (X1 * X1).sum(-1)[:, None] + (X2 * X2).sum(-1)[None, :] - 2.0 * X1 @ X2.mT
    return d.clamp_min(0.0)


def rbf(
    X1: torch.Tensor,
    X2: torch.Tensor,
    alpha: torch.Tensor | float,
    gamma: torch.Tensor | float,
    alpha_lin: torch.Tensor | float | None = None,
) -> torch.Tensor:
    """Cross-covariance ``k(X1, X2)`` (eq. 6), optionally plus the linear term."""
    K = alpha * torch.exp(-0.5 * gamma * sq_dist(X1, X2))
    if alpha_lin is not None:
        K = K + alpha_lin * (X1 @ X2.mT)
    return K


def rbf_diag(
    X: torch.Tensor,
    alpha: torch.Tensor | float,
    alpha_lin: torch.Tensor | float | None = None,
) -> torch.Tensor:
    """``k(x, x)`` for each row of X (= α, plus α_lin ‖x‖² with the linear term)."""
    d = torch.as_tensor(alpha, dtype=X.dtype).expand(X.shape[0]).clone()
    if alpha_lin is not None:
        d = d + alpha_lin * (X * X).sum(-1)
    return d


def train_cov(
    X: torch.Tensor,
    alpha: torch.Tensor | float,
    gamma: torch.Tensor | float,
    beta: torch.Tensor | float,
    alpha_lin: torch.Tensor | float | None = None,
) -> torch.Tensor:
    """Training covariance ``K = k(X, X) + β⁻¹ I``."""
    K = rbf(X, X, alpha, gamma, alpha_lin)
    n = X.shape[0]
    return K + torch.eye(n, dtype=X.dtype) / beta
