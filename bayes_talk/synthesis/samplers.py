"""Samplers for an unnormalised log density on a flat vector (DESIGN.md §6).

Every sampler here takes ``log_prob(x: torch.Tensor[n]) -> scalar tensor`` (float64,
differentiable), a starting point (the MAP point of the synthesis posterior) and a seed,
and returns a :class:`Draws`: ``samples`` of shape (chains, draws, n) plus sampler
statistics for :mod:`bayes_talk.evaluation.diagnostics`. Same seed -> same draws.

* :func:`run_nuts` - Pyro NUTS with ``potential_fn = -log_prob``, diagonal mass matrix
  adapted during warm-up; chains run one after another in this process (chain c seeded
  ``seed + c``), so there is no multiprocessing and the draws are reproducible.
* :func:`run_emcee` - emcee's affine-invariant ensemble with a differential-evolution move
  mix (80 % ``DEMove``, 20 % ``DESnookerMove``: the default stretch move mixes badly on
  correlated, higher-dimensional targets, FACTS.md "Samplers"); walkers start in a small
  Gaussian ball around the MAP point; the log density is evaluated for all walkers at
  once (``torch.func.vmap`` over the torch function; a Python loop when vmap fails).
  The chains reported are the walkers, thinned.
* :func:`run_laplace` - Gaussian N(x_MAP, (-∇²log p)⁻¹) with the Hessian from
  ``torch.autograd.functional.hessian``; a non-positive-definite negative Hessian (MAP not
  exactly at a maximum) has its eigenvalues floored, and that is recorded.

Torch runs with one thread inside every sampler (:func:`bayes_talk.gp.threads.torch_threads`).
"""
from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from bayes_talk import progress
from bayes_talk.gp.threads import torch_threads

log = logging.getLogger(__name__)

LogProb = Callable[[torch.Tensor], torch.Tensor]
METHODS = ("nuts", "emcee", "laplace")


@dataclass
class Draws:
    """samples: (chains, draws, n). stats: sampler statistics (divergences per chain,
    acceptance fraction, Hessian eigenvalue floor, ...). seconds: wall time."""

    method: str
    samples: np.ndarray
    stats: dict = field(default_factory=dict)
    seconds: float = 0.0

    @property
    def flat(self) -> np.ndarray:
        """All draws pooled over chains, (chains * draws, n)."""
        return self.samples.reshape(-1, self.samples.shape[-1])


def _as_tensor(x) -> torch.Tensor:
    return torch.as_tensor(np.asarray(x, dtype=np.float64))


# ---------------------------------------------------------------------------- NUTS
def run_nuts(log_prob: LogProb, x0, n_draws: int = 200, warmup: int = 200, chains: int = 1,
             seed: int = 0, target_accept: float = 0.8, max_tree_depth: int = 8) -> Draws:
    """Pyro NUTS on ``log_prob`` from ``x0``: (n,) for every chain, or (chains, n), one
    start per chain (overdispersed starts make R-hat meaningful)."""
    import pyro
    from pyro.infer.mcmc import MCMC, NUTS

    x0 = _as_tensor(x0)
    if x0.ndim == 2 and x0.shape[0] != chains:
        raise ValueError(f"x0 holds {x0.shape[0]} starts for {chains} chains")

    def potential(params):
        return -log_prob(params["x"])

    out, divs, accept, steps = [], [], [], []
    t0 = time.perf_counter()
    with torch_threads(1):
        for c in range(chains):
            pyro.set_rng_seed(seed + c)
            start = (x0[c] if x0.ndim == 2 else x0).reshape(-1).clone()
            kernel = NUTS(potential_fn=potential, adapt_step_size=True, adapt_mass_matrix=True,
                          full_mass=False, target_accept_prob=target_accept, max_tree_depth=max_tree_depth)
            mcmc = MCMC(kernel, num_samples=n_draws, warmup_steps=warmup, initial_params={"x": start},
                        num_chains=1, disable_progbar=not progress.enabled())
            log.info("NUTS chain %d/%d: %d warm-up + %d draws", c + 1, chains, warmup, n_draws)
            mcmc.run()
            out.append(mcmc.get_samples()["x"].detach().numpy().reshape(n_draws, -1))
            diag = mcmc.diagnostics()
            d = diag.get("divergences", {})
            divs.append(int(sum(len(v) for v in d.values())) if isinstance(d, dict) else len(d))
            a = diag.get("acceptance rate", {})
            accept.append(float(np.mean(list(a.values()))) if isinstance(a, dict) and a else float("nan"))
            steps.append(float(kernel.step_size))
    return Draws("nuts", np.stack(out), {"divergences": divs, "accept_prob": accept, "step_size": steps},
                 time.perf_counter() - t0)


# ---------------------------------------------------------------------------- emcee
def batch_log_prob(log_prob: LogProb) -> Callable[[np.ndarray], np.ndarray]:
    """Vectorised log density for emcee: (W, n) numpy -> (W,) numpy, -inf where not finite."""
    vm = torch.func.vmap(log_prob)
    state = {"vmap": True}

    def f(P: np.ndarray) -> np.ndarray:
        P_t = _as_tensor(P)
        with torch.no_grad():
            if state["vmap"]:
                try:
                    lp = vm(P_t)
                except Exception as exc:  # an op without a batching rule: loop instead
                    log.info("vmap over the log density failed (%s); looping over walkers", exc)
                    state["vmap"] = False
            if not state["vmap"]:
                lp = torch.stack([log_prob(p) for p in P_t])
        v = lp.detach().numpy().astype(np.float64)
        v[~np.isfinite(v)] = -np.inf
        return v

    return f


def run_emcee(log_prob: LogProb, x0, n_draws: int = 200, warmup: int = 500, n_walkers: int | None = None,
              seed: int = 0, ball: float = 1e-2, thin: int = 1, n_keep: int | None = None,
              de_fraction: float = 0.8) -> Draws:
    """emcee ensemble from a ball of radius ``ball`` around ``x0``.

    Runs ``warmup + n_draws * thin`` steps and keeps the last ``n_draws * thin`` thinned by
    ``thin``. ``n_keep`` (default: all) keeps that many walkers as the reported chains
    (evenly spaced) to bound memory. Walkers default to max(32, 4 n) rounded up to even.
    """
    import emcee

    x0 = np.asarray(x0, dtype=np.float64).reshape(-1)
    n = x0.size
    W = n_walkers if n_walkers is not None else max(32, 4 * n)
    W += W % 2
    rng = np.random.default_rng(seed)
    p0 = x0[None, :] + ball * rng.standard_normal((W, n))
    moves = [(emcee.moves.DEMove(), de_fraction), (emcee.moves.DESnookerMove(), 1.0 - de_fraction)]
    t0 = time.perf_counter()
    with torch_threads(1):
        f = batch_log_prob(log_prob)
        sampler = emcee.EnsembleSampler(W, n, f, moves=moves, vectorize=True)
        sampler.random_state = np.random.RandomState(seed).get_state()
        log.info("emcee: %d walkers, %d steps", W, warmup + n_draws * thin)
        sampler.run_mcmc(p0, warmup + n_draws * thin, progress=progress.enabled())
    chain = sampler.get_chain(discard=warmup, thin=thin)  # (steps, W, n)
    chain = np.transpose(chain, (1, 0, 2))
    if n_keep is not None and n_keep < W:
        chain = chain[np.linspace(0, W - 1, n_keep).round().astype(int)]
    acc = sampler.acceptance_fraction
    return Draws("emcee", np.ascontiguousarray(chain),
                 {"acceptance_fraction": float(np.mean(acc)), "acceptance_min": float(np.min(acc)),
                  "n_walkers": int(W), "steps": int(warmup + n_draws * thin)},
                 time.perf_counter() - t0)


# ---------------------------------------------------------------------------- Laplace
def laplace_gaussian(log_prob: LogProb, x_map, floor: float = 1e-8) -> tuple[np.ndarray, np.ndarray, dict]:
    """Mean and covariance of the Laplace approximation at ``x_map``."""
    x = _as_tensor(x_map).reshape(-1)
    with torch_threads(1):
        H = torch.autograd.functional.hessian(log_prob, x).detach().numpy()
    P = -0.5 * (H + H.T)
    lam, U = np.linalg.eigh(P)
    lo = floor * max(1.0, float(np.max(np.abs(lam))))
    n_floored = int(np.sum(lam < lo))
    lam_c = np.maximum(lam, lo)
    cov = (U / lam_c) @ U.T
    return x.numpy().copy(), 0.5 * (cov + cov.T), {"min_eig_precision": float(lam.min()), "n_floored": n_floored}


def run_laplace(log_prob: LogProb, x_map, n_draws: int = 200, seed: int = 0) -> Draws:
    """``n_draws`` iid draws of the Laplace approximation (one chain)."""
    t0 = time.perf_counter()
    mean, cov, info = laplace_gaussian(log_prob, x_map)
    L = np.linalg.cholesky(cov + 1e-14 * np.eye(len(mean)) * max(1.0, float(np.trace(cov))))
    z = np.random.default_rng(seed).standard_normal((n_draws, len(mean)))
    s = mean[None, :] + z @ L.T
    info.update(mean=mean, cov=cov)
    return Draws("laplace", s[None], info, time.perf_counter() - t0)


__all__ = [
    "METHODS",
    "Draws",
    "batch_log_prob",
    "laplace_gaussian",
    "run_emcee",
    "run_laplace",
    "run_nuts",
]
