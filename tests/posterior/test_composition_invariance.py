"""Particle Gibbs ∘ NUTS ∘ mode jumps leaves a density with known, separated modes invariant
(issue 24, item 3).

The test density is a 3-frame chain with a bimodal per-frame factor,

    ln p(x) = Σ_t ln g_t(x_t) − Σ_{t≥1} (x_t − x_{t−1})² / (2 c²),
    g_t = w_t N(·; +2, s²) + (1 − w_t) N(·; −2, s²),   s = 0.35,

whose modes are 16 nats apart at the barrier (NUTS alone never crosses it). The exact marginals
P(x_t > 0), E x_t and E x_t² come from a forward-backward pass on a fine grid. The sampler is
the project's :func:`~bayes_talk.posterior.samplers.run_nuts` with its mode-jumping Metropolis
moves and, as ``extra_move``, the library's particle Gibbs move
(:class:`~bayes_talk.posterior.particle_gibbs.ParticleGibbsMove`, the object ``pg-nuts`` runs):
one conditional-SMC sweep with ancestor sampling per iteration, then multiple-try Metropolis
updates of the blocks {0} and {1, 2} given their neighbours (the second frame of a block drawn
from the coupling, as the synthesis blocks' later frames are drawn from the dynamics). Every
estimate must lie within 5 Monte-Carlo standard errors (batch means) of the exact value. Two
deliberately broken extra moves must fail the same check: the move with its proposal density
missing from the sweep's and the tries' weights (f_t instead of f_t / q_t), and a sign flip
accepted without a Metropolis test.
"""
from __future__ import annotations

import functools
from typing import ClassVar

import numpy as np
import pytest
import torch
from scipy.special import logsumexp

from bayes_talk.posterior.particle_gibbs import ParticleGibbsMove
from bayes_talk.posterior.samplers import run_nuts

T, M, S, C = 3, 2.0, 0.35, 2.5          # frames, mode location ±M, mode sd, coupling sd
W = np.array([0.75, 0.35, 0.6])         # weight of the + mode per frame


def _log_g(x: np.ndarray, t: int) -> np.ndarray:
    lp = -0.5 * ((x - M) / S) ** 2 + np.log(W[t])
    lm = -0.5 * ((x + M) / S) ** 2 + np.log1p(-W[t])
    return np.logaddexp(lp, lm) - np.log(S * np.sqrt(2 * np.pi))


def log_prob(x: torch.Tensor) -> torch.Tensor:
    """ln p(x) of the module docstring (unnormalised), torch for NUTS."""
    w = torch.as_tensor(W, dtype=x.dtype)
    lg = torch.logaddexp(-0.5 * ((x - M) / S) ** 2 + torch.log(w), -0.5 * ((x + M) / S) ** 2 + torch.log1p(-w))
    return lg.sum() - 0.5 * ((x[1:] - x[:-1]) ** 2).sum() / C**2


@functools.cache
def exact_moments(n: int = 4001, lim: float = 6.0) -> dict:
    """P(x_t > 0), E x_t, E x_t² by forward-backward on an n-point grid of [−lim, lim].
    Computed once per grid (3 s on the fine one, which the three moves' tests share); the
    callers only read the result."""
    g = np.linspace(-lim, lim, n)
    lk = -0.5 * (g[:, None] - g[None]) ** 2 / C**2          # coupling, (from, to)
    fwd = [_log_g(g, 0)]
    for t in range(1, T):
        fwd.append(_log_g(g, t) + logsumexp(fwd[-1][:, None] + lk, axis=0))
    bwd = [np.zeros(n)]
    for t in range(T - 1, 0, -1):
        bwd.insert(0, logsumexp(lk + (_log_g(g, t) + bwd[0])[None], axis=1))
    out = {"p_pos": [], "mean": [], "m2": []}
    for t in range(T):
        lm = fwd[t] + bwd[t]
        p = np.exp(lm - logsumexp(lm))
        out["p_pos"].append(p[g > 0].sum())
        out["mean"].append(p @ g)
        out["m2"].append(p @ g**2)
    return {k: np.array(v) for k, v in out.items()}


class Chain:
    """The density as frame factors f_t for the particle Gibbs move, the coupling as its "dynamics"
    (mean x_{t−1}, sd c: what the block updates draw a block's later frames from), and a
    proposal q_t: ρ · a random
    walk from the ancestor (N(0, 3²) at t = 0) + (1 − ρ) · a mixture of N(+2, 0.5²) and N(−2, 0.5²)
    with weights 0.1 and 0.9 (deliberately unlike the target's, so that a sweep whose weights
    miss q_t is visibly biased)."""

    T, d, rho, h, q_pos = T, 1, 0.3, 0.5, 0.1
    dyn_gp: ClassVar[dict] = {2: 0}        # frame 2 follows frame 1 through the "dynamics"; frame 1 starts a block


    def log_f(self, t, Xprev, X):
        out = _log_g(X[:, 0], t)
        if t:
            out = out - 0.5 * (X[:, 0] - Xprev[:, 0]) ** 2 / C**2
        return out

    def link_logf(self, t, Xprev, X):      # the terms of f_t with x_{t−1}
        return np.zeros(len(X)) if t == 0 else -0.5 * (X[:, 0] - Xprev[:, 0]) ** 2 / C**2

    def dynamics_mean_sd(self, t, Xprev):
        return Xprev, np.full_like(Xprev, C)

    def dynamics_logpdf(self, t, Xprev, X):
        return -0.5 * ((X[:, 0] - Xprev[:, 0]) / C) ** 2 - np.log(C) - 0.5 * np.log(2 * np.pi)

    def sample_logq(self, t, Xprev, N, rng, X=None, ref=None, x_next=None):
        m, sd = (np.zeros(N), 3.0) if t == 0 else (Xprev[:, 0], C)
        if X is None:
            walk = rng.random(N) < self.rho
            x = np.where(rng.random(N) < self.q_pos, M, -M) + self.h * rng.standard_normal(N)
            X = np.where(walk, m + sd * rng.standard_normal(N), x)[:, None]
        if ref is not None:
            X[-1] = ref
        x = X[:, 0]
        lw = -0.5 * ((x - m) / sd) ** 2 - np.log(sd)
        lc = np.logaddexp(np.log(self.q_pos) - 0.5 * ((x - M) / self.h) ** 2,
                          np.log1p(-self.q_pos) - 0.5 * ((x + M) / self.h) ** 2) - np.log(self.h)
        return X, np.logaddexp(np.log(self.rho) + lw, np.log1p(-self.rho) + lc) - 0.5 * np.log(2 * np.pi)


class NoProposalCorrection(Chain):
    """Broken: ln q_t reported as 0, so the weights are f_t, not f_t / q_t (not invariant)."""

    def sample_logq(self, t, Xprev, N, rng, X=None, ref=None, x_next=None):
        X, _ = super().sample_logq(t, Xprev, N, rng, X, ref)
        return X, np.zeros(N)


def pg_move(model: Chain) -> ParticleGibbsMove:
    """``extra_move`` for run_nuts: a 16-particle sweep, then 4-try updates of the blocks [0, 1)
    and [1, 3); NUTS's state x (T,) is the move's (T, 1) path."""
    return ParticleGibbsMove(model, model, to_x=lambda u: np.reshape(u, (T, 1)), to_u=lambda x: np.reshape(x, -1),
                             n_particles=16, blocks=[(0, 1), (1, 3)], frame_tries=4)


def naive_flip(x, rng):
    """Broken: flips the sign of one random frame with probability ½, no Metropolis test."""
    x = np.array(x, dtype=np.float64)
    if rng.random() < 0.5:
        t = rng.integers(T)
        x[t] = -x[t]
    return x


def _batch_se(v: np.ndarray, n_batches: int = 20) -> np.ndarray:
    """Monte-Carlo standard error of the mean of v (chains, draws, k) by batch means per chain."""
    c, n, k = v.shape
    b = v[:, : n - n % n_batches].reshape(c, n_batches, -1, k).mean(2).reshape(-1, k)
    return b.std(0, ddof=1) / np.sqrt(len(b))


@pytest.mark.parametrize("move", ["pg", "pg-no-proposal-correction", "naive-flip"])
def test_pg_nuts_jumps_leaves_a_separated_bimodal_chain_invariant(move):
    extra = {"pg": pg_move(Chain()), "pg-no-proposal-correction": pg_move(NoProposalCorrection()),
             "naive-flip": naive_flip}[move]
    broken = move != "pg"
    # mode jump: all three frames to the other mode (the displacement between the two extreme modes)
    jumps = 2 * M * np.ones((1, T))
    x0 = np.array([[M, M, M], [-M, -M, -M]])
    dr = run_nuts(log_prob, x0, n_draws=400, warmup=100, chains=2, seed=3, jumps=jumps, jump_attempts=1,
                  extra_move=extra)
    X = dr.samples                                                 # (2, 400, 3)
    ex = exact_moments()
    ok = True
    for key, f in (("p_pos", lambda v: (v > 0).astype(float)), ("mean", lambda v: v), ("m2", lambda v: v * v)):
        v = f(X)
        est, se = v.reshape(-1, T).mean(0), _batch_se(v)
        z = np.abs(est - ex[key]) / np.maximum(se, 1e-3)
        ok &= bool(np.all(z < 5))
        if not broken:
            assert np.all(z < 5), (key, est, ex[key], se)
    if not broken:   # each chain (one started in each extreme mode) visits both modes of every frame
        frac = (X > 0).mean(1)
        assert np.all((frac > 0.05) & (frac < 0.95)), frac
    assert ok != broken, (move, "passed the invariance check" if ok else "failed")


def test_exact_moments_match_direct_quadrature():
    """The forward-backward marginals equal brute-force summation on a coarser 3-D grid."""
    g = np.linspace(-6, 6, 241)
    A, B, Cc = np.meshgrid(g, g, g, indexing="ij")
    lp = _log_g(A, 0) + _log_g(B, 1) + _log_g(Cc, 2) - 0.5 * ((B - A) ** 2 + (Cc - B) ** 2) / C**2
    p = np.exp(lp - logsumexp(lp))
    ex = exact_moments(n=241)
    for t, Xt in enumerate((A, B, Cc)):
        assert (p * (Xt > 0)).sum() == pytest.approx(ex["p_pos"][t], abs=1e-10)
        assert (p * Xt).sum() == pytest.approx(ex["mean"][t], abs=1e-10)
        assert (p * Xt**2).sum() == pytest.approx(ex["m2"][t], abs=1e-10)
