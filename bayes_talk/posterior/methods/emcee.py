"""``emcee``: the affine-invariant ensemble (differential-evolution moves) on z, X = X_MAP + L z,
walkers in a ball around 0, run on until the chain after the burn-in is 50 autocorrelation
times long, within a step budget (:func:`~bayes_talk.posterior.samplers.run_emcee`). In a few
hundred dimensions it mixes slowly; its diagnostics say so (docs/uncertainty.md)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bayes_talk.posterior.diagnostics import sampler_diagnostics
from bayes_talk.posterior.methods import EMCEE_WARMUP, Context, Output
from bayes_talk.posterior.samplers import AUTOCORR_TOL, run_emcee
from bayes_talk.synthesis.whitening import Whitened

#: walkers reported as chains; the chain may run on to this many times its first length to
#: meet the autocorrelation rule, within this many stored floats
EMCEE_REPORTED_WALKERS = 16
EMCEE_MAX_STEPS_FACTOR = 10
EMCEE_MAX_STORED_FLOATS = 1.25e8


@dataclass(frozen=True)
class Options:
    """n_walkers: walkers (None: max(32, 2·T·d); made even); max_steps: the most steps the
    chain may run to meet the autocorrelation rule (None: a budget of
    :data:`EMCEE_MAX_STEPS_FACTOR` times its first length within
    :data:`EMCEE_MAX_STORED_FLOATS` stored floats); autocorr_tol: the chain after the burn-in
    must be this many autocorrelation times long."""

    n_walkers: int | None = None
    max_steps: int | None = None
    autocorr_tol: float = AUTOCORR_TOL

    def __post_init__(self):
        if self.n_walkers is not None and int(self.n_walkers) < 2:
            raise ValueError(f"emcee needs n_walkers >= 2, got {self.n_walkers}")
        if self.max_steps is not None and int(self.max_steps) < 0:
            raise ValueError(f"max_steps must be >= 0, got {self.max_steps}")


def run(context: Context, options: Options) -> Output:
    """The ensemble's draws: burn-in ``context.warmup`` steps (default :data:`EMCEE_WARMUP`),
    then draws of :data:`EMCEE_REPORTED_WALKERS` walkers thinned by ``context.thin``, at least
    20 per walker."""
    T, d = context.shape
    g = Whitened(context.density, context.x_map, context.scale)
    W = options.n_walkers or max(32, 2 * T * d)
    W += W % 2
    n_keep = min(W, EMCEE_REPORTED_WALKERS)
    per_walker = max(20, -(-context.n_draws // n_keep))
    warmup = EMCEE_WARMUP if context.warmup is None else context.warmup
    max_steps = options.max_steps
    if max_steps is None:   # bound the stored chain (steps/thin × walkers × dim floats)
        first = warmup + per_walker * context.thin
        fits = int(EMCEE_MAX_STORED_FLOATS / (W * T * d)) * context.thin
        max_steps = max(first, min(EMCEE_MAX_STEPS_FACTOR * first, fits))
    draws = run_emcee(g, np.zeros(T * d), n_draws=per_walker, seed=context.seed, n_walkers=W, ball=0.1,
                      n_keep=n_keep, warmup=warmup, thin=context.thin, max_steps=max_steps,
                      autocorr_tol=options.autocorr_tol)
    Xs = g.to_x(draws.samples).reshape(draws.samples.shape[0], draws.samples.shape[1], T, d)
    return Output(Xs, sampler_diagnostics(draws, Xs), draws.sample_stats)
