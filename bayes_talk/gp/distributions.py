"""The SGPDM's two likelihoods as Pyro distributions, so the model is a Pyro program.

* :class:`GPObservation` — the matrix Y (N×D) of one view given latent points X
  (deena2010 eq. 5): independent GP columns with covariance K = k(X,X) + β⁻¹I, column m
  scaled by 1/w_m.
* :class:`GPDynamics` — the latent trajectory X (N×d) of one or several sequences under
  first-order GP dynamics (deena2010 eq. 7).

Both are event-only distributions (batch shape ``()``); ``log_prob`` is exactly the
corresponding function of :mod:`bayes_talk.gp.terms`. ``sample`` draws from the
generative process (used to simulate data in tests).
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

import torch
from pyro.distributions import TorchDistribution
from torch.distributions import constraints

from bayes_talk.gp.kernels import rbf, train_cov
from bayes_talk.gp.linalg import cho_solve, cholesky
from bayes_talk.gp.terms import dynamics_loglik, observation_loglik

#: the empty sample shape, the default of every ``sample``
NO_SHAPE = torch.Size()


class GPObservation(TorchDistribution):
    """p(Y | X) of deena2010 eq. 5 (Y centred, shape N×D)."""

    arg_constraints: ClassVar[dict] = {}
    support = constraints.real

    def __init__(self, X, alpha, gamma, beta, w, alpha_lin=None, what="observation kernel"):
        self.X, self.alpha, self.gamma, self.beta, self.w = X, alpha, gamma, beta, w
        self.alpha_lin, self.what = alpha_lin, what
        super().__init__(torch.Size(), torch.Size((X.shape[0], w.shape[0])), validate_args=False)

    def log_prob(self, value: torch.Tensor) -> torch.Tensor:
        """Log density of ``value`` (the equation in the class docstring)."""
        return observation_loglik(
            value, self.X, self.alpha, self.gamma, self.beta, self.w, self.alpha_lin, self.what
        )

    def sample(self, sample_shape: torch.Size = NO_SHAPE) -> torch.Tensor:
        """Draws of Y: each column L ε / w with K = L Lᵀ the kernel matrix and ε ~ N(0, I)."""
        K = train_cov(self.X, self.alpha, self.gamma, self.beta, self.alpha_lin)
        L = cholesky(K.detach(), self.what)
        shape = torch.Size(sample_shape) + self.event_shape
        eps = torch.randn(shape, dtype=K.dtype)
        return (L @ eps) / self.w.detach()


class GPDynamics(TorchDistribution):
    """p(X) of deena2010 eq. 7 for sequences of the given lengths (rows of X stacked)."""

    arg_constraints: ClassVar[dict] = {}
    support = constraints.real

    def __init__(
        self,
        seq_lengths: Sequence[int],
        latent_dim: int,
        alpha,
        gamma,
        beta,
        alpha_lin=None,
    ):
        self.seq_lengths = [int(t) for t in seq_lengths]
        self.alpha, self.gamma, self.beta, self.alpha_lin = alpha, gamma, beta, alpha_lin
        n = sum(self.seq_lengths)
        super().__init__(torch.Size(), torch.Size((n, latent_dim)), validate_args=False)

    def log_prob(self, value: torch.Tensor) -> torch.Tensor:
        """Log density of ``value`` (the equation in the class docstring)."""
        return dynamics_loglik(
            value, self.seq_lengths, self.alpha, self.gamma, self.beta, self.alpha_lin
        )

    def sample(self, sample_shape: torch.Size = NO_SHAPE) -> torch.Tensor:
        """Ancestral sampling: x^s_1 ~ N(0, I); x_t | all earlier pairs from the GP posterior.

        One dynamics GP is shared by all sequences, so each new step conditions on every
        (x_in, x_out) pair drawn before it (O(N⁴) overall: for simulation on small N).
        """
        if len(sample_shape) > 0:
            return torch.stack([self.sample() for _ in range(int(torch.Size(sample_shape).numel()))]).reshape(
                torch.Size(sample_shape) + self.event_shape
            )
        d = self.event_shape[1]
        rows: list[torch.Tensor] = []
        ins: list[torch.Tensor] = []
        outs: list[torch.Tensor] = []
        beta = torch.as_tensor(self.beta, dtype=torch.float64).detach()
        for T in self.seq_lengths:
            x = torch.randn(d, dtype=torch.float64)
            rows.append(x)
            for _ in range(T - 1):
                xs = x[None, :]
                kss = rbf(xs, xs, self.alpha, self.gamma, self.alpha_lin)[0, 0] + 1.0 / beta
                if ins:
                    Xin, Xout = torch.stack(ins), torch.stack(outs)
                    L = cholesky(train_cov(Xin, self.alpha, self.gamma, beta, self.alpha_lin))
                    ks = rbf(Xin, xs, self.alpha, self.gamma, self.alpha_lin)
                    mean = (ks.mT @ cho_solve(L, Xout))[0]
                    var = kss - (ks.mT @ cho_solve(L, ks))[0, 0]
                else:
                    mean, var = torch.zeros(d, dtype=torch.float64), kss
                nxt = mean + var.clamp_min(1e-300).sqrt() * torch.randn(d, dtype=torch.float64)
                ins.append(x)
                outs.append(nxt)
                rows.append(nxt)
                x = nxt
        return torch.stack(rows).detach()
