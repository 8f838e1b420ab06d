"""``vi``: variational inference (Pyro SVI, :func:`~bayes_talk.posterior.variational.run_vi`), a
full-rank Gaussian in the coordinates whitened at the MAP, started at the Laplace approximation
(m = 0, S = I) and fitted by the ELBO; iid draws of q, judged like Laplace by the PSIS k̂ of
p/q (docs/uncertainty.md, "Inference")."""
from __future__ import annotations

from dataclasses import dataclass

from bayes_talk.posterior.diagnostics import psis_diagnostics
from bayes_talk.posterior.methods import KHAT_DRAWS, VI_DEFAULTS, Context, Output
from bayes_talk.posterior.variational import run_vi
from bayes_talk.synthesis.whitening import Whitened


@dataclass(frozen=True)
class Options:
    """steps: optimisation steps; particles: ELBO draws per step; lr: Adam's learning rate
    (decayed tenfold over the steps); init_scale: S at the start (I: the Laplace
    approximation); khat_draws: draws of q k̂ is estimated from (at least the draws kept)."""

    steps: int = VI_DEFAULTS["steps"]
    particles: int = VI_DEFAULTS["particles"]
    lr: float = VI_DEFAULTS["lr"]
    init_scale: float = 1.0
    khat_draws: int = KHAT_DRAWS

    def __post_init__(self):
        if int(self.steps) < 1 or int(self.particles) < 1 or not float(self.lr) > 0 or not float(self.init_scale) > 0:
            raise ValueError(f"vi needs steps >= 1, particles >= 1, lr > 0 and init_scale > 0, got {self.steps}, "
                             f"{self.particles}, {self.lr} and {self.init_scale}")
        if int(self.khat_draws) < 1:
            raise ValueError(f"khat_draws must be >= 1, got {self.khat_draws}")


def run(context: Context, options: Options) -> Output:
    """q fitted, then ``max(n_draws, khat_draws)`` draws of it (the first ``n_draws`` kept)."""
    T, d = context.shape
    g = Whitened(context.density, context.x_map, context.scale)
    n_k = max(context.n_draws, int(options.khat_draws))
    draws = run_vi(g, T * d, n_draws=n_k, seed=context.seed, steps=options.steps, particles=options.particles,
                   lr=options.lr, init_scale=options.init_scale)
    Xall = g.to_x(draws.samples[0])
    st = draws.stats
    sample_stats: dict = {}
    diag = psis_diagnostics(context.density, Xall, st["log_q"], context.n_draws, sample_stats)
    diag.update({"vi_steps": st["steps"], "vi_particles": st["particles"], "vi_elbo_start": st["elbo_start"],
                 "vi_elbo_end": st["elbo_end"], "n_gradients": st["n_gradients"],
                 "sampler_seconds": float(draws.seconds)})
    return Output(Xall[None, :context.n_draws].reshape(1, -1, T, d), diag, sample_stats)
