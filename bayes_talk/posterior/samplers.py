"""Samplers for an unnormalised log density on a flat vector (docs/uncertainty.md).

Every sampler here takes ``log_prob(x: torch.Tensor[n]) -> scalar tensor`` (float64,
differentiable), a starting point (the MAP point of the synthesis posterior) and a seed,
and returns a :class:`Draws`: ``samples`` of shape (chains, draws, n) plus sampler
statistics for :mod:`bayes_talk.posterior.diagnostics`. Same seed -> same draws.

* :func:`run_nuts` - Pyro NUTS with ``potential_fn = -log_prob``, diagonal mass matrix
  adapted during warm-up; one task per chain through the project's executor (this
  process by default, ``workers`` processes on request; chain c seeded by ``seed`` and c
  alone), so the draws are reproducible whatever the worker count. Every
  post-warm-up iteration's acceptance statistic, leapfrog steps, tree depth, divergence,
  energy and ln p are recorded (``Draws.sample_stats``). Given displacements between known
  modes, every iteration is followed by mode-jumping Metropolis moves (below).
* :func:`run_emcee` - emcee's affine-invariant ensemble with a differential-evolution move
  mix (80 % ``DEMove``, 20 % ``DESnookerMove``: the default stretch move mixes badly on
  correlated, higher-dimensional targets); walkers start in a small
  Gaussian ball around the MAP point; the log density is evaluated for all walkers at
  once (``torch.func.vmap`` over the torch function; a Python loop when vmap fails).
  The chains reported are the walkers, thinned. The integrated autocorrelation time
  (``get_autocorr_time``) is checked against emcee's rule (chain ≥ 50 τ) and the chain run
  on up to ``max_steps`` to meet it; ``Draws.stats["autocorr_ok"]`` says whether it did.
* variational inference (:func:`bayes_talk.posterior.variational.run_vi`) lives in its own
  module and returns the same :class:`Draws`.
* :func:`run_laplace` - Gaussian N(x_MAP, (-∇²log p)⁻¹), the one Laplace approximation of
  the package (the synthesis posterior's ``method="laplace"`` runs it with the closed-form
  Hessian of the joint MAP; otherwise ``torch.autograd.functional.hessian``); a
  non-positive-definite negative Hessian (MAP not exactly at a maximum) has its
  eigenvalues floored (negative ones by their modulus), and that is recorded.

Torch runs with one thread inside every sampler (:func:`bayes_talk.gp.threads.torch_threads`).
"""
from __future__ import annotations

import copy
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from bayes_talk.base import progress
from bayes_talk.gp.threads import torch_threads
from bayes_talk.posterior.methods import NUTS_DEFAULTS
from bayes_talk.posterior.nuts_chain import ChainState, draw_chain, warmup_chain

log = logging.getLogger(__name__)

LogProb = Callable[[torch.Tensor], torch.Tensor]


@dataclass
class Draws:
    """samples: (chains, draws, n). stats: sampler statistics (divergences per chain,
    acceptance fraction, Hessian eigenvalue floor, ...). seconds: wall time.
    sample_stats: per-draw statistics (chains, draws) under ArviZ's names (NUTS:
    ``acceptance_rate``, ``n_steps``, ``tree_depth``, ``diverging``, ``energy``, ``lp``,
    ``step_size``, and ``jumps``; with a particle Gibbs sweep also ``pg_sweep`` and
    ``pg_frame_moved`` (chains, draws, T); emcee: ``lp``), for ``InferenceData.sample_stats``."""

    method: str
    samples: np.ndarray
    stats: dict = field(default_factory=dict)
    seconds: float = 0.0
    sample_stats: dict = field(default_factory=dict)

    @property
    def flat(self) -> np.ndarray:
        """All draws pooled over chains, (chains * draws, n)."""
        return self.samples.reshape(-1, self.samples.shape[-1])


def _as_tensor(x) -> torch.Tensor:
    return torch.as_tensor(np.asarray(x, dtype=np.float64))


# ---------------------------------------------------------------------------- NUTS
#: spread of the overdispersed chain starts: z ~ N(0, INIT_SCALE² I) in whitened coordinates
INIT_SCALE = 2.0


def run_nuts(log_prob: LogProb, x0, n_draws: int = NUTS_DEFAULTS["draws_per_chain"],
             warmup: int = NUTS_DEFAULTS["warmup"], chains: int = 1, seed: int = 0,
             target_accept: float = NUTS_DEFAULTS["target_accept"],
             max_tree_depth: int = NUTS_DEFAULTS["max_tree_depth"], jumps: np.ndarray | None = None,
             jump_attempts: int = NUTS_DEFAULTS["jump_attempts"], workers: int = 1, executor=None,
             extra_move=None, extra_every: int = 1, enough: Callable[[np.ndarray], bool] | None = None,
             min_draws: int | None = None, check_every: int = 50) -> Draws:
    """Pyro NUTS on ``log_prob`` from ``x0``: (n,) for every chain, or (chains, n), one
    start per chain (overdispersed starts make R-hat meaningful). Diagonal mass matrix and
    step size adapted during ``warmup`` (Stan's windowed schedule, Pyro's adapter).
    ``jumps`` (K, n): displacements for mode-jumping Metropolis moves after every
    iteration, ``jump_attempts`` per displacement
    (:class:`~bayes_talk.posterior.nuts_chain.RecordingNUTS`; chain c's move draws seeded by
    (seed, c)).

    Chains run through the project's executor (:func:`bayes_talk.base.executor.executor_for`:
    ``executor`` an :class:`~bayes_talk.base.executor.Executor` or a kind, else "processes" when
    ``workers`` > 1, else this process), two tasks per chain — its warm-up, then its kept draws
    (:mod:`bayes_talk.posterior.nuts_chain`) — each seeded by (``seed``, its chain index) only
    and run with one thread, so the draws do not depend on the worker count or engine (tested). ``log_prob`` must then be picklable (a module-level function
    or an object of one: the synthesis densities are). ``warmup_seconds`` sums the chains'.

    ``extra_move(x, rng) -> x'`` (picklable): a further posterior-invariant kernel applied
    after the NUTS transition and the jumps of every ``extra_every``-th iteration (the
    particle Gibbs sweep of :mod:`bayes_talk.posterior.particle_gibbs`); a composition of
    invariant kernels is invariant. A move may return ``(x', record)``, ``record`` a dict of
    arrays of fixed shapes: each key becomes a per-draw statistic (chains, n_draws, ...) of
    ``Draws.sample_stats``, zero (False) at the iterations where the move did not run (the
    sweep's ``pg_sweep`` and ``pg_frame_moved``). A move with ``begin_adaptation()``,
    ``adaptation_state()`` and ``end_adaptation(states)`` (the sweep with ``pg_adapt_weights``)
    adapts during the warm-ups only: each chain deep-copies it and begins before its first
    iteration; after every chain's warm-up, a copy of the caller's move pools the chains'
    ``adaptation_state()`` (in chain order) and is frozen, and every chain takes its kept draws
    with that one move — fixed, so the kept draws leave the posterior invariant, and the same for
    all chains, so a mode only one chain's warm-up found is proposed in all. The caller's move is
    not changed; the frozen move's ``adaptation_summary()`` (if it has one, and not None) is
    ``stats["extra_move_adaptation"]``.

    ``enough(samples) -> bool``: a stopping rule on the kept draws so far, (chains, n, dim) in
    the coordinates of ``log_prob``, asked after ``min_draws`` draws per chain (default
    ``n_draws`` // 2) and after every ``check_every`` more; True ends the draws there, so
    ``n_draws`` is the most a chain draws. The chains draw in batches between the checks, each
    continuing from where its last stopped (:func:`~bayes_talk.posterior.nuts_chain.draw_chain`):
    batches draw exactly what one uninterrupted run draws (tested), and the rule sees only the
    draws, so where it stops depends on the seed alone. ``stats["checks"]`` lists the draws per
    chain at each check and ``stats["stopped_early"]`` whether one ended the draws.

    ``Draws.sample_stats`` holds (chains, n_draws) arrays ``acceptance_rate``, ``n_steps``,
    ``tree_depth``, ``diverging``, ``energy``, ``lp``, ``jumps`` (mode jumps accepted),
    ``step_size`` (and the extra move's records); ``Draws.stats`` the per-chain totals
    (``divergences``, ``step_size``, ``max_tree_depth_hits``, ``chain_seconds``, …)."""
    if chains < 1 or n_draws < 1 or warmup < 0:
        raise ValueError(f"NUTS needs chains >= 1, draws >= 1, warmup >= 0; got {chains}, {n_draws}, {warmup}")
    if not 0 < target_accept < 1:
        raise ValueError(f"target_accept must be in (0, 1), got {target_accept}")
    if max_tree_depth < 1:
        raise ValueError(f"max_tree_depth must be >= 1, got {max_tree_depth}")
    if jump_attempts < 0:
        raise ValueError(f"jump_attempts must be >= 0, got {jump_attempts}")
    first = n_draws if enough is None else min(n_draws, n_draws // 2 if min_draws is None else int(min_draws))
    if first < 1 or check_every < 1:
        raise ValueError(f"a stopping rule needs min_draws >= 1 and check_every >= 1; got {min_draws} and "
                         f"{check_every}")
    x0 = _as_tensor(x0)
    if jumps is not None:
        jumps = np.asarray(jumps, dtype=np.float64)
        jumps = jumps.reshape(len(jumps), -1) if jumps.size else jumps.reshape(0, x0.shape[-1])
        if jumps.ndim != 2 or jumps.shape[1] != x0.shape[-1] or not np.all(np.isfinite(jumps)):
            raise ValueError(f"jumps must be finite, (K, {x0.shape[-1]}); got {jumps.shape}")
        if len(jumps) == 0:
            jumps = None
    if x0.ndim == 2 and x0.shape[0] != chains:
        raise ValueError(f"x0 holds {x0.shape[0]} starts for {chains} chains")
    starts = [(x0[c] if x0.ndim == 2 else x0).reshape(-1).clone().numpy() for c in range(chains)]
    kernel_kw = {"target_accept": target_accept, "max_tree_depth": max_tree_depth, "jumps": jumps,
                 "jump_attempts": jump_attempts, "extra_move": extra_move, "extra_every": int(extra_every)}
    t0 = time.perf_counter()
    from bayes_talk.base.executor import executor_for

    with executor_for(executor, workers) as ex:
        if warmup:
            states = list(ex.map(warmup_chain, [(log_prob, starts[c], warmup, seed, c, kernel_kw)
                                                for c in range(chains)]))
        else:
            states = [ChainState(starts[c]) for c in range(chains)]
        if hasattr(extra_move, "begin_adaptation"):   # one move, frozen from every chain's warm-up
            kernel_kw["extra_move"] = copy.deepcopy(extra_move)
            kernel_kw["extra_move"].begin_adaptation()
            kernel_kw["extra_move"].end_adaptation([st.adaptation for st in states])
        states = [replace(st, adaptation=None) for st in states]   # not needed by the draws
        warm_s = float(sum(st.seconds for st in states))   # 0 without a warm-up
        batches, done, checks, stopped = [], 0, [], False
        while done < n_draws:   # one batch: every chain on to `first` draws (all of them without a rule)
            res = list(ex.map(draw_chain, [(log_prob, states[c], first - done, warmup + done, seed, c, kernel_kw)
                                           for c in range(chains)]))
            batches.append(res)
            states, done = [r["state"] for r in res], first
            if enough is not None and done < n_draws:
                checks.append(done)
                if enough(np.concatenate([np.stack([r["samples"] for r in b]) for b in batches], axis=1)):
                    stopped = True
                    break
            first = min(n_draws, done + int(check_every))
    max_draws, n_draws = n_draws, done
    out = [np.concatenate([b[c]["samples"] for b in batches]) for c in range(chains)]
    res = batches[-1]
    steps = [r["step_size"] for r in res]
    recs = [_joined_records([b[c] for b in batches]) for c in range(chains)]
    jump_counts = [r["jump_counts"] for r in res]
    n_grad = int(sum(r["n_gradients"] for r in res))
    ss = {k: np.array([r[k] for r in recs]) for k in recs[0]}
    ss["step_size"] = np.repeat(np.array(steps)[:, None], n_draws, axis=1)
    stats = {"divergences": [int(d.sum()) for d in ss["diverging"]], "step_size": steps,
             "accept_prob": [float(a.mean()) for a in ss["acceptance_rate"]],
             "max_tree_depth": int(max_tree_depth), "target_accept": float(target_accept),
             "max_tree_depth_hits": int(np.sum(ss["tree_depth"] >= max_tree_depth)),
             "warmup": int(warmup), "n_gradients": n_grad, "warmup_seconds": warm_s,
             "chain_seconds": [float(r["seconds"]) for r in res],
             "n_jumps": 0 if jumps is None else len(jumps), "jump_attempts": [int(a) for a, _ in jump_counts],
             "jumps_accepted": [int(b) for _, b in jump_counts]}
    if enough is not None:
        stats.update(checks=checks, stopped_early=stopped, max_draws_per_chain=int(max_draws))
    learnt = getattr(kernel_kw["extra_move"], "adaptation_summary", lambda: None)()
    if learnt is not None:   # what the chains' warm-ups taught the move
        stats["extra_move_adaptation"] = learnt
    return Draws("nuts", np.stack(out), stats, time.perf_counter() - t0, ss)


def _joined_records(batches: list[dict]) -> dict:
    """One chain's per-draw records over its batches of draws (``draw_chain`` results), each key
    concatenated along the draws; an extra move's key missing from a batch (the move did not run
    in it) is zero (False) there, as within a batch (:func:`~bayes_talk.posterior.nuts_chain.extra_records`)."""
    keys = list(dict.fromkeys(k for b in batches for k in b["records"]))
    like = {k: np.asarray(next(b["records"][k] for b in batches if k in b["records"])) for k in keys}
    return {k: np.concatenate([np.asarray(b["records"][k]) if k in b["records"]
                               else np.zeros((len(b["samples"]), *like[k].shape[1:]), like[k].dtype)
                               for b in batches]) for k in keys}


# ---------------------------------------------------------------------------- emcee
#: emcee's rule (Foreman-Mackey et al. 2013, ``emcee.autocorr.integrated_time``): the
#: chain after burn-in should be at least this many integrated autocorrelation times long
AUTOCORR_TOL = 50.0


def batch_log_prob(log_prob: LogProb) -> Callable[[np.ndarray], np.ndarray]:
    """Vectorised log density for emcee: (W, n) numpy -> (W,) numpy, -inf where not finite.

    A ``log_prob`` with a ``batch_numpy`` attribute ((W, n) numpy -> (W,) numpy: all walkers
    in one call, e.g. the synthesis density's batched twin) is evaluated through it; otherwise
    ``torch.func.vmap`` over the torch function, or a loop when vmap fails."""
    direct = getattr(log_prob, "batch_numpy", None)
    vm = torch.func.vmap(log_prob)
    state = {"vmap": True}

    def f(P: np.ndarray) -> np.ndarray:
        if direct is not None:
            v = np.asarray(direct(np.asarray(P, dtype=np.float64)), dtype=np.float64).copy()
            v[~np.isfinite(v)] = -np.inf
            return v
        P_t = _as_tensor(P)
        with torch.no_grad():
            if state["vmap"]:
                try:
                    lp = vm(P_t)
                except (RuntimeError, NotImplementedError) as exc:  # no batching rule, data-dependent flow: loop
                    log.info("vmap over the log density failed (%s); looping over walkers", exc)
                    state["vmap"] = False
            if not state["vmap"]:
                lp = torch.stack([log_prob(p) for p in P_t])
        v = lp.detach().numpy().astype(np.float64)
        v[~np.isfinite(v)] = -np.inf
        return v

    return f


def _autocorr_time(sampler, discard: int) -> np.ndarray:
    """emcee's integrated autocorrelation time per coordinate of the chain after ``discard``
    (``get_autocorr_time(quiet=True)``: an estimate even when the chain is too short)."""
    import emcee

    emlog = logging.getLogger(emcee.autocorr.__name__)
    level = emlog.level
    emlog.setLevel(logging.ERROR)   # "the chain is shorter than 50 times ...": reported by us
    try:
        return np.asarray(sampler.get_autocorr_time(discard=discard, quiet=True), dtype=float)
    finally:
        emlog.setLevel(level)


def run_emcee(log_prob: LogProb, x0, n_draws: int = 200, warmup: int = 500, n_walkers: int | None = None,
              seed: int = 0, ball: float = 1e-2, thin: int = 1, n_keep: int | None = None,
              de_fraction: float = 0.8, max_steps: int | None = None, autocorr_tol: float = AUTOCORR_TOL) -> Draws:
    """emcee ensemble from a ball of radius ``ball`` around ``x0``.

    Runs ``warmup + n_draws * thin`` steps, storing every ``thin``-th (``thin_by``); then, while the chain after the warm-up is
    shorter than ``autocorr_tol`` × the largest integrated autocorrelation time τ_max
    (``sampler.get_autocorr_time``) and ``max_steps`` (default: the first run's length, i.e.
    no extension) allows, runs on to that length (at most doubling each round). Keeps
    ``n_draws`` evenly thinned steps of the chain after the warm-up (at least ``thin``
    apart). ``n_keep`` (default: all) keeps that many walkers as the reported chains
    (evenly spaced) to bound memory. Walkers default to max(32, 4 n) rounded up to even.
    ``Draws.sample_stats``: ``lp`` (reported walkers, kept steps). ``Draws.stats``:
    acceptance, ``autocorr_time_max`` / ``_mean``, ``autocorr_steps`` (after
    warm-up), ``autocorr_ok`` (length ≥ ``autocorr_tol`` · τ_max), ``steps``.
    """
    import emcee

    x0 = np.asarray(x0, dtype=np.float64).reshape(-1)
    n = x0.size
    W = n_walkers if n_walkers is not None else max(32, 4 * n)
    W += W % 2
    # every count below is in stored steps (emcee keeps every `thin`-th step: thin_by)
    k = max(1, int(thin))
    w_st = -(-int(warmup) // k)
    first = w_st + n_draws
    max_st = first if max_steps is None else max(int(max_steps) // k, first)
    rng = np.random.default_rng(seed)
    p0 = x0[None, :] + ball * rng.standard_normal((W, n))
    moves = [(emcee.moves.DEMove(), de_fraction), (emcee.moves.DESnookerMove(), 1.0 - de_fraction)]
    t0 = time.perf_counter()
    with torch_threads(1):
        f = batch_log_prob(log_prob)
        sampler = emcee.EnsembleSampler(W, n, f, moves=moves, vectorize=True)
        sampler.random_state = np.random.RandomState(seed).get_state()
        log.info("emcee: %d walkers, %d steps", W, first * k)
        sampler.run_mcmc(p0, first, thin_by=k, progress=progress.enabled())
        tau = _autocorr_time(sampler, w_st)
        while sampler.iteration - w_st < autocorr_tol * np.nanmax(tau) and sampler.iteration < max_st:
            want = int(np.ceil(autocorr_tol * np.nanmax(tau))) + w_st
            more = max(1, min(want - sampler.iteration, sampler.iteration, max_st - sampler.iteration))
            log.info("emcee: autocorrelation time %.1f steps; %d more steps", np.nanmax(tau) * k, more * k)
            sampler.run_mcmc(None, more, thin_by=k, progress=progress.enabled())
            tau = _autocorr_time(sampler, w_st)
    after = sampler.iteration - w_st
    step = max(1, after // n_draws)
    chain = sampler.get_chain()[w_st:][::-1][::step][:n_draws][::-1]  # the last n_draws, `step` apart
    lp = sampler.get_log_prob()[w_st:][::-1][::step][:n_draws][::-1].T   # the same steps, (W, draws)
    chain = np.transpose(chain, (1, 0, 2))
    if n_keep is not None and n_keep < W:
        keep = np.linspace(0, W - 1, n_keep).round().astype(int)
        chain, lp = chain[keep], lp[keep]
    acc = sampler.acceptance_fraction
    tau_max = float(np.nanmax(tau))
    return Draws("emcee", np.ascontiguousarray(chain),
                 {"acceptance_fraction": float(np.mean(acc)), "acceptance_min": float(np.min(acc)),
                  "n_walkers": int(W), "steps": int(sampler.iteration * k), "thin": int(step * k),
                  "warmup": int(w_st * k),
                  "autocorr_time_max": tau_max * k, "autocorr_time_mean": float(np.nanmean(tau)) * k,
                  "autocorr_steps": int(after * k), "autocorr_tol": float(autocorr_tol),
                  "autocorr_ok": bool(after >= autocorr_tol * tau_max)},
                 time.perf_counter() - t0, {"lp": np.ascontiguousarray(lp)})


# ---------------------------------------------------------------------------- Laplace
def laplace_scale(hessian: np.ndarray) -> tuple[np.ndarray, dict]:
    """L with L Lᵀ = P⁻¹, P = −H the precision of the Laplace approximation at a mode whose
    log-density Hessian is the dense matrix ``H`` (a generic log density; the whole-utterance
    synthesis density's block-tridiagonal Hessian has its banded factor,
    :meth:`~bayes_talk.synthesis.joint_map.MapResult.laplace_factor`): L = U Λ^(−1/2) from P's
    eigen-decomposition, eigenvalues floored at 1e-8·max|λ| and negative ones replaced by their
    modulus (the mode may be approximate). Also ``{"n_floored": number of eigenvalues modified}``."""
    P = -0.5 * (hessian + hessian.T)
    lam, U = np.linalg.eigh(P)
    lo = 1e-8 * max(1.0, float(np.max(np.abs(lam))))
    n_mod = int(np.sum(lam < lo))
    lam = np.maximum(np.abs(lam), lo)
    return U / np.sqrt(lam), {"n_floored": n_mod}


def run_laplace(log_prob: LogProb | None, x_map, n_draws: int = 200, seed: int | np.random.Generator = 0, *,
                hessian=None, scale: np.ndarray | None = None, factor=None) -> Draws:
    """``n_draws`` iid draws x = x_MAP + L z, z ~ N(0, I), of the Laplace approximation
    N(x_MAP, P⁻¹), P = −∇² ln p(x_MAP) (one chain; the one Laplace of the package: the
    synthesis posterior's ``method="laplace"`` runs it too).

    L comes from, in this order: ``factor``, a banded Cholesky factor R of P
    (:class:`~bayes_talk.synthesis.banded.BandedFactor`; L = R⁻ᵀ applied by banded solves, time
    and memory linear in the length: the synthesis posterior's); ``scale``, L itself (dense);
    ``hessian``, ∇² ln p as a :class:`~bayes_talk.synthesis.banded.BlockTridiagonal` (factorised,
    :func:`~bayes_talk.synthesis.joint_map.laplace_factor`) or a dense matrix
    (:func:`laplace_scale`); else torch autograd of ``log_prob`` at ``x_map``. ``seed``: an int
    or a numpy Generator to draw z from. ``stats``: ``mean``, ``z`` (the standard-normal draws,
    for importance weights), and ``cov`` (L Lᵀ) and ``n_floored`` (eigenvalues of P floored or
    negated) for a dense L, ``shift`` (the modified Cholesky's τ) for a banded one."""
    from bayes_talk.synthesis.banded import BlockTridiagonal

    t0 = time.perf_counter()
    x = np.asarray(x_map, dtype=np.float64).reshape(-1)
    info: dict = {}
    if factor is None and scale is None and isinstance(hessian, BlockTridiagonal):
        from bayes_talk.synthesis.joint_map import laplace_factor

        factor = laplace_factor(hessian)
    if factor is None and scale is None:
        if hessian is None:
            if log_prob is None:
                raise ValueError("run_laplace: give log_prob, hessian, scale or factor")
            with torch_threads(1):
                hessian = torch.autograd.functional.hessian(log_prob, _as_tensor(x)).detach().numpy()
        scale, info = laplace_scale(np.asarray(hessian))
    n = factor.n if factor is not None else scale.shape
    if n != x.size and n != (x.size, x.size):
        raise ValueError(f"run_laplace: the Laplace scale is for {n} coordinates, x_map has {x.size}")
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    z = rng.standard_normal((int(n_draws), x.size))
    if factor is not None:
        s = x[None] + factor.scale_matvec(z.T).T
        info.update(mean=x.copy(), z=z, shift=factor.shift)
    else:
        s = x[None] + z @ scale.T
        info.update(mean=x.copy(), cov=scale @ scale.T, z=z)
    return Draws("laplace", s[None], info, time.perf_counter() - t0)


__all__ = [
    "Draws",
    "batch_log_prob",
    "laplace_scale",
    "run_emcee",
    "run_laplace",
    "run_nuts",
]
