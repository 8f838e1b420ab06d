"""``laplace``: iid draws of the Gaussian at the joint MAP, N(X_MAP, P⁻¹), P = −∇² ln p at the
MAP (P + τ·diag(|P_ii|) where P is not positive definite), drawn as X_MAP + R⁻ᵀ z from P's banded
Cholesky factor R in time linear in the length (docs/uncertainty.md, "Inference"). Judged by the
PSIS Pareto k̂ of the importance weights p/q (k̂ ≤ 0.7 wanted), not by R-hat on independent
draws."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bayes_talk.posterior.diagnostics import psis_diagnostics
from bayes_talk.posterior.methods import KHAT_DRAWS, Context, Output
from bayes_talk.posterior.samplers import run_laplace


@dataclass(frozen=True)
class Options:
    """khat_draws: draws k̂ is estimated from (at least the draws kept; the first ``n_draws``
    are the result)."""

    khat_draws: int = KHAT_DRAWS

    def __post_init__(self):
        if int(self.khat_draws) < 1:
            raise ValueError(f"khat_draws must be >= 1, got {self.khat_draws}")


def run(context: Context, options: Options) -> Output:
    """``n_draws`` draws x = X_MAP + L z, z ~ N(0, I) from ``context.rng`` (L = R⁻ᵀ,
    ``context.factor``), and k̂ from ``max(n_draws, khat_draws)`` of them."""
    T, d = context.shape
    n_k = max(context.n_draws, int(options.khat_draws))
    draws = run_laplace(None, context.x_map, n_k, context.rng, factor=context.factor)
    Xall, Z = draws.samples[0], draws.stats["z"]
    sample_stats: dict = {}
    diag = psis_diagnostics(context.density, Xall, -0.5 * np.sum(Z * Z, axis=1), context.n_draws, sample_stats)
    return Output(Xall[None, :context.n_draws].reshape(1, -1, T, d), diag, sample_stats)
