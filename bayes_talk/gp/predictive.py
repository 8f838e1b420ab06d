"""GP predictive distributions at new latent points (deena2009 §4.1, deena2010 §4.2.2).

For a view with training latents X, centred outputs Y, kernel k and noise precision β,
after training (everything fixed):

    μ(x)  = k(x, X) K⁻¹ Y + ȳ
    σ²(x) = k(x, x) − k(x, X) K⁻¹ k(X, x) + β⁻¹
    ln p(ŷ | x) = Σ_m ln N(ŷ_m; μ_m(x), σ²(x) / w_m²)

The dynamics predictive is the same object with inputs X_in, outputs X_out and w = 1:
p(x_t | x_{t−1}) = N(x_t; μ_x(x_{t−1}), σ²_x(x_{t−1}) I).

A view's GP may read only the first k of the d latent dimensions (``in_dims`` = k; shared
and private latent spaces, Ek, Rihan, Torr, Rogez & Lawrence 2008): then X and x above are
their first k columns, and the other d − k dimensions are private to the views that read
them (:class:`~bayes_talk.models.sgpdm_program.SGPDMConfig` ``view_dims``).

The factors L and K⁻¹Y are computed on one thread (:func:`bayes_talk.gp.threads.one_thread`):
a predictor built from the same arrays has the same bits whatever the thread count of the
process that builds it (at training or at loading).
"""
from __future__ import annotations

import math

import torch

from bayes_talk.gp.kernels import rbf, rbf_diag, train_cov
from bayes_talk.gp.linalg import cho_solve, cholesky, solve_lower
from bayes_talk.gp.threads import one_thread


class GPPredictor:
    """Predictive mean/variance of one GP mapping, differentiable in the test inputs."""

    def __init__(
        self,
        X: torch.Tensor,
        Y: torch.Tensor,
        alpha: float,
        gamma: float,
        beta: float,
        w: torch.Tensor | None = None,
        mean: torch.Tensor | None = None,
        alpha_lin: float | None = None,
        what: str = "kernel matrix",
        in_dims: int | None = None,
    ):
        self.X = X.detach()
        #: the GP reads the first ``in_dims`` latent dimensions of a test input (the training
        #: inputs X have just those columns); None: all of them (SGPDMConfig.view_dims)
        self.in_dims = in_dims
        self.Y = Y.detach()
        self.alpha, self.gamma, self.beta, self.alpha_lin = alpha, gamma, beta, alpha_lin
        D = Y.shape[1]
        self.w = (w.detach() if w is not None else torch.ones(D, dtype=torch.float64))
        self.mean = mean.detach() if mean is not None else torch.zeros(D, dtype=torch.float64)
        with one_thread():  # the same bits whatever the caller's thread count (bayes_talk.gp.threads)
            self.L = cholesky(train_cov(self.X, alpha, gamma, beta, alpha_lin, fixed=True), what)
            self.A = cho_solve(self.L, self.Y)

    @classmethod
    def from_factors(
        cls,
        X: torch.Tensor,
        Y: torch.Tensor,
        L: torch.Tensor,
        A: torch.Tensor,
        alpha: float,
        gamma: float,
        beta: float,
        w: torch.Tensor | None = None,
        mean: torch.Tensor | None = None,
    ) -> GPPredictor:
        """A predictor from precomputed factors: μ(x) = k(x, X) A + ȳ and
        σ²(x) = α − ‖L⁻¹k(X, x)‖² + β⁻¹ (e.g. a sparse GP's, :mod:`bayes_talk.gp.sparse`,
        with X the inducing inputs); ``Y`` only gives the training frames and output size."""
        obj = cls.__new__(cls)
        D = Y.shape[1]
        obj.X, obj.Y, obj.L, obj.A = X.detach(), Y.detach(), L.detach(), A.detach()
        obj.alpha, obj.gamma, obj.beta, obj.alpha_lin = alpha, gamma, beta, None
        obj.in_dims = None
        obj.w = w.detach() if w is not None else torch.ones(D, dtype=torch.float64)
        obj.mean = mean.detach() if mean is not None else torch.zeros(D, dtype=torch.float64)
        return obj

    @property
    def out_dim(self) -> int:
        """Output dimension D."""
        return int(self.Y.shape[1])

    def mean_var(self, Xs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """μ (T×D, with the training mean added back) and σ² (T,) at the rows of Xs."""
        if self.in_dims is not None:
            Xs = Xs[..., :self.in_dims]
        Ks = rbf(self.X, Xs, self.alpha, self.gamma, self.alpha_lin)  # N×T
        mu = Ks.mT @ self.A + self.mean
        V = solve_lower(self.L, Ks)
        var = rbf_diag(Xs, self.alpha, self.alpha_lin) - (V * V).sum(0) + 1.0 / self.beta
        return mu, var.clamp_min(1.0 / self.beta)  # σ² ≥ β⁻¹ exactly; only round-off goes below

    def log_lik(self, Ys: torch.Tensor, Xs: torch.Tensor, extra_var: torch.Tensor | None = None) -> torch.Tensor:
        """ln p(ŷ_t | x_t) for each row pair (T,), per-dimension variance σ²/w_m²
        (plus ``extra_var`` per dimension when given)."""
        mu, var = self.mean_var(Xs)
        return self.log_density(Ys, mu, var, extra_var)

    def log_density(self, Ys: torch.Tensor, mu: torch.Tensor, var: torch.Tensor,
                    extra_var: torch.Tensor | None = None) -> torch.Tensor:
        """ln N(ŷ; μ, σ²/w²) given μ (..., D) and σ² (...) from :meth:`mean_var`; broadcasts,
        e.g. Ys (T, 1, D) against μ (1, M, D) and σ² (M,) gives a (T, M) table."""
        D = self.out_dim
        if extra_var is not None:
            v = var[..., None] / (self.w * self.w) + extra_var
            r = Ys - mu
            return -0.5 * (D * math.log(2.0 * math.pi) + torch.log(v).sum(-1) + (r * r / v).sum(-1))
        r = (Ys - mu) * self.w
        return (
            torch.log(self.w).sum()
            - 0.5 * D * (math.log(2.0 * math.pi) + torch.log(var))
            - 0.5 * (r * r).sum(-1) / var
        )

    def dim_var(self, var: torch.Tensor) -> torch.Tensor:
        """Per-dimension predictive variance σ²(x)/w_m², shape (T, D)."""
        return var[:, None] / (self.w * self.w)[None, :]
