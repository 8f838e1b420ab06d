"""Variational inference for an unnormalised log density on a flat vector (docs/uncertainty.md).

:func:`run_vi` fits a full-rank Gaussian by the ELBO (Pyro SVI, ``AutoMultivariateNormal``)
and returns iid draws of it as a :class:`~bayes_talk.posterior.samplers.Draws`, with their
ln q for the PSIS k̂ check (:func:`bayes_talk.posterior.diagnostics.psis`). The synthesis
posterior (:mod:`bayes_talk.posterior.sampling`, ``method="vi"``) runs it on coordinates
whitened by the Laplace approximation, so it starts *at* that approximation.
"""
from __future__ import annotations

import time

import numpy as np
import torch

from bayes_talk.base import progress
from bayes_talk.gp.threads import torch_threads
from bayes_talk.posterior.methods import VI_DEFAULTS
from bayes_talk.posterior.samplers import Draws, LogProb


def run_vi(log_prob: LogProb, n: int, n_draws: int = 64, seed: int = 0, steps: int = VI_DEFAULTS["steps"],
           particles: int = VI_DEFAULTS["particles"], lr: float = VI_DEFAULTS["lr"],
           init_scale: float = 1.0) -> Draws:
    """Variational inference (Pyro SVI): a full-rank Gaussian q(x) = N(m, S Sᵀ)
    (``AutoMultivariateNormal``) fitted by maximising the ELBO E_q[ln p(x)] + H[q] with
    ``particles`` reparameterised draws per step (``Trace_ELBO``) and Adam (learning rate
    ``lr`` decayed tenfold over ``steps``). ``log_prob`` is the target on R^n, started at
    m = 0, S = ``init_scale`` · I: for the synthesis posterior, coordinates whitened by the
    Laplace approximation, so the start *is* the Laplace approximation and VI moves off it
    where the density says so (KL(q‖p): mode-seeking, within one mode).

    Returns ``n_draws`` iid draws of the fitted q (one chain) and, in ``stats``, ``log_q`` of
    each draw (for PSIS k̂ against p), the ELBO at the start and the end (means over the
    first and last 10 % of steps) and the number of gradients."""
    import pyro
    import pyro.distributions as pdist
    from pyro.infer import SVI, Trace_ELBO
    from pyro.infer.autoguide import AutoMultivariateNormal
    from pyro.infer.autoguide.initialization import init_to_value

    if steps < 1 or particles < 1 or n_draws < 1 or lr <= 0:
        raise ValueError(f"VI needs steps, particles, n_draws >= 1 and lr > 0; got {steps}, {particles}, "
                         f"{n_draws}, {lr}")
    counter = [0]

    def model():
        x = pyro.sample("x", pdist.ImproperUniform(pdist.constraints.real, (), (n,)))
        counter[0] += 1
        pyro.factor("log_p", log_prob(x))

    t0 = time.perf_counter()
    with torch_threads(1):
        pyro.clear_param_store()
        pyro.set_rng_seed(seed)
        guide = AutoMultivariateNormal(model, init_loc_fn=init_to_value(values={"x": torch.zeros(n, dtype=torch.float64)}),
                                       init_scale=init_scale)
        optim = pyro.optim.ClippedAdam({"lr": lr, "lrd": 0.1 ** (1.0 / steps)})
        svi = SVI(model, guide, optim, Trace_ELBO(num_particles=particles))
        elbo = np.empty(steps)
        for i in progress.bar(range(steps), desc="VI", unit="step"):
            elbo[i] = -svi.step()
        with torch.no_grad():
            q = guide.get_posterior()
            x = q.sample((n_draws,))
            log_q = q.log_prob(x).numpy().astype(np.float64)
        samples = x.numpy().astype(np.float64)
        pyro.clear_param_store()
    k = max(1, steps // 10)
    stats = {"log_q": log_q, "steps": int(steps), "particles": int(particles), "lr": float(lr),
             "elbo_start": float(np.mean(elbo[:k])), "elbo_end": float(np.mean(elbo[-k:])),
             "n_gradients": int(counter[0])}
    return Draws("vi", samples[None], stats, time.perf_counter() - t0)


__all__ = ["run_vi"]
