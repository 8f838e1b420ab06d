"""Particle Gibbs over the frames of an utterance (pg-nuts).

The synthesis density (docs/uncertainty.md) is a Markov state-space model: it factorises exactly
over frames,

    ln p(X | Ŷ) = Σ_t f_t(x_{t−1}, x_t),
    f_t = ln p_π(ŷ_t | x_t) + [t entry] ln N(x_t; μ_π, Σ_π) + [t dynamics] ln p_π(x_t | x_{t−1})
          + [t smooth] ln s(x_{t−1}, x_t)                                                    (1)

(:class:`FrameFactors`; a test holds Σ_t f_t equal to
:class:`~bayes_talk.synthesis.joint.UtteranceDensity` to round-off). Conditional SMC
with ancestor sampling (Andrieu, Doucet & Holenstein 2010; Lindsten, Jordan & Schön 2014,
"Particle Gibbs with ancestor sampling", Alg. 2) is then a Markov kernel that leaves
p(X | Ŷ) invariant: N − 1 particles are proposed frame by frame, the reference path is
kept as the N-th, and its ancestor at each frame is redrawn with probability ∝
W_{t−1}^i exp f_t(x_{t−1}^i, x_t^*) — so the new path can leave the reference anywhere.

Proposal (:class:`MixtureProposal`) at frame t given the ancestor x_{t−1}: with probability
ρ the frame's prior (the dynamics GP predictive from x_{t−1}, or the entry Gaussian), else
a Gaussian kernel (bandwidth h) around one of the frame's state model's training latents X_j,
chosen with probability ∝ its audio likelihood p_π(ŷ_t | X_j) × entry density × (at a block
start with a smoothness factor) s(x_{t−1}, X_j) given the particle's ancestor (the
visual predictive at every X_j precomputed, so this is an N × M table per frame); the posterior's modes sit at those training latents (docs/uncertainty.md). The
importance weight is exp f_t / q_t with q_t the mixture's exact density, so the smoothness
factor at a block start weighs every proposal.
"""
from __future__ import annotations

import time

import numpy as np
from scipy.special import logsumexp

from bayes_talk.gp.predictive_fused import Runs
from bayes_talk.posterior.diagnostics import frame_update_rate
from bayes_talk.posterior.frame_updates import (
    BlockModeProposal,
    PairModeProposal,
    adjacent_pairs,
    block_mtm,
    dynamics_blocks,
)
from bayes_talk.posterior.proposal_tables import kernel_mixture_logpdf, smoothness_weights
from bayes_talk.synthesis.joint import UtteranceDensity
from bayes_talk.synthesis.segment_objective import LOG_2PI


class FrameFactors:
    """The per-frame factors f_t of (1), evaluated for many (x_{t−1}, x_t) pairs of one frame."""

    def __init__(self, dens: UtteranceDensity):
        self.dens, self.T, self.d = dens, dens.T, dens.d
        tm = dens.terms
        self.tm = tm
        self.audio_gp = dict(zip(tm.a_idx.tolist(), tm.a_runs.row_gp(1).tolist(), strict=True))
        self.dyn_gp = dict(zip(tm.d_dst.tolist(), tm.d_runs.row_gp(1).tolist(), strict=True))
        self.entry = {int(t): i for i, t in enumerate(tm.e_idx)}
        s_prev = tm.s_prev_runs.row_gp(1)
        s_vis = np.empty(len(tm.s_idx), dtype=np.int64)
        s_vis[tm.s_order] = tm.s_vis_runs.row_gp(1)
        self.smooth = {int(t): (int(p), int(v)) for t, p, v in zip(tm.s_idx, s_prev, s_vis, strict=True)}
        # the factor's pseudo-observation u_t (joint.py, (S)): the factor observes μ_Z^{π'}(x_{t−1}) + u_t
        self.smooth_shift = {int(t): tm.s_shift[j] for j, t in enumerate(tm.s_idx)}

    def log_f(self, t: int, Xprev: np.ndarray | None, X: np.ndarray) -> np.ndarray:
        """f_t(x_{t−1}^i, x_t^i) for N pairs (Xprev (N, d) or None at t = 0, X (N, d)) → (N,)."""
        X = np.ascontiguousarray(X, dtype=np.float64)
        out = self.audio_loglik(t, X)
        if t in self.entry:
            out += self.entry_logpdf(t, X)
        return out + self.link_logf(t, Xprev, X)

    def link_logf(self, t: int, Xprev: np.ndarray | None, X: np.ndarray) -> np.ndarray:
        """The terms of f_t that involve x_{t−1}: [t dynamics] ln p_π(x_t | x_{t−1}) + [t smooth]
        ln s(x_{t−1}, x_t), for N pairs → (N,) (zeros where frame t has neither). The rest of
        f_t depends on x_t alone, so it cancels where x_t is fixed and only the ancestor varies
        (the sweep's ancestor and backward weights)."""
        tm, N = self.tm, len(X)
        out = np.zeros(N)
        if t in self.dyn_gp:
            out += self.dynamics_logpdf(t, Xprev, X)
        if t in self.smooth:
            gp, gv = self.smooth[t]
            zp, _ = tm.vis_gps.mean_var(Runs.one(gp, N), np.ascontiguousarray(Xprev, dtype=np.float64))
            out += tm.vis_gps.loglik_value(Runs.one(gv, N), zp + self.smooth_shift[t],
                                           np.ascontiguousarray(X, dtype=np.float64), tm.motion_var)
        return out

    def audio_loglik(self, t: int, X: np.ndarray) -> np.ndarray:
        """ln p_π(ŷ_t | x) of frame t's audio at rows X (N, d) → (N,)."""
        tm, N = self.tm, len(X)
        return tm.audio_gps.loglik_value(Runs.one(self.audio_gp[t], N), np.repeat(tm.a_Y[[self._a_row(t)]], N, 0),
                                         np.ascontiguousarray(X, dtype=np.float64))

    def own_factor(self, t: int, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """g_t(x) = ln p_π(ŷ_t | x) + [t entry] ln N(x; μ_π, Σ_π) and ∂g_t/∂x for rows X (N, d):
        the factors of frame t that involve x_t alone (the frame updates' modes,
        :func:`~bayes_talk.posterior.frame_updates.block_factor`)."""
        tm, N = self.tm, len(X)
        X = np.ascontiguousarray(X, dtype=np.float64)
        g, gx, _ = tm.audio_gps.loglik(Runs.one(self.audio_gp[t], N), np.repeat(tm.a_Y[[self._a_row(t)]], N, 0), X)
        g, gx = g.copy(), gx.copy()
        if t in self.entry:
            Ci = tm.e_chol_inv[self.entry[t]]
            u = (X - tm.e_mean[self.entry[t]]) @ Ci.T
            g += self.entry_logpdf(t, X)
            gx -= u @ Ci
        return g, gx

    def dynamics_mean_sd(self, t: int, Xprev: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mean (N, d) and sd (N, d) of frame t's dynamics p_π(x_t | x_{t−1}) at the rows Xprev (N, d)."""
        g = self.dyn_gp[t]
        mu, s = self.tm.dyn_gps.mean_var(Runs.one(g, len(Xprev)), np.ascontiguousarray(Xprev, dtype=np.float64))
        return mu, np.sqrt(s[:, None] / self.tm.dyn_gps.w2[g][None])

    def dynamics_logpdf(self, t: int, Xprev: np.ndarray, X: np.ndarray) -> np.ndarray:
        """ln p_π(x_t | x_{t−1}) of frame t's dynamics for N pairs (the term of f_t) → (N,)."""
        return self.tm.dyn_gps.loglik_value(Runs.one(self.dyn_gp[t], len(X)), np.ascontiguousarray(X, dtype=np.float64),
                                            np.ascontiguousarray(Xprev, dtype=np.float64))

    def run_end(self, t: int) -> int:
        """The first frame after t without a dynamics factor into it (T at the end): frames
        t + 1 … run_end − 1 follow x_t through the dynamics."""
        u = t + 1
        while u < self.T and u in self.dyn_gp:
            u += 1
        return u

    def continuation(self, t: int, X: np.ndarray, stop: int, grad: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """c(x) = Σ_{u=t+1}^{stop−1} g_u(m_u) along the deterministic continuation m_t = x,
        m_u = μ_x(m_{u−1}) (the dynamics means; frames t + 1 … stop − 1 must have dynamics
        factors), g_u the frame's own factor (:meth:`own_factor`), and ∂c/∂x by reverse
        accumulation through the means (``mean_vjp``), for rows X (N, d). With dynamics noise
        10⁻⁶ a run's path is nearly this function of its first frame. ``grad=False``: c alone
        (the reverse pass skipped; None for the gradient)."""
        X = np.ascontiguousarray(X, dtype=np.float64)
        c, ms, grads = np.zeros(len(X)), [X], []
        for u in range(t + 1, stop):
            m, _ = self.tm.dyn_gps.mean_var(Runs.one(self.dyn_gp[u], len(X)), ms[-1])
            ms.append(np.ascontiguousarray(m))
            g, gx = self.own_factor(u, ms[-1])
            c += g
            grads.append(gx)
        if not grad:
            return c, None
        G = np.zeros_like(X)
        for k in range(len(grads) - 1, -1, -1):      # ∂c/∂m_{u−1} = g'_{u−1} + J_uᵀ ∂c/∂m_u
            G = self.tm.dyn_gps.mean_vjp(Runs.one(self.dyn_gp[t + 1 + k], len(X)), ms[k], grads[k] + G)
        return c, G

    def _a_row(self, t: int) -> int:
        return int(np.flatnonzero(self.tm.a_idx == t)[0])

    def entry_logpdf(self, t: int, X: np.ndarray) -> np.ndarray:
        """ln N(x; μ_π, Σ_π) of frame t's entry distribution for rows X (N, d)."""
        tm, e = self.tm, self.entry[t]
        u = (X - tm.e_mean[e]) @ tm.e_chol_inv[e].T
        const = -np.log(np.abs(np.diag(tm.e_chol_inv[e]))).sum() + 0.5 * self.d * LOG_2PI
        return -0.5 * (u * u).sum(1) - const

    def total(self, X: np.ndarray) -> float:
        """Σ_t f_t along the path X (T, d): ln p(X | Ŷ) up to round-off."""
        X = np.asarray(X, dtype=np.float64).reshape(self.T, self.d)
        return float(sum(self.log_f(t, X[t - 1:t] if t else None, X[t:t + 1])[0] for t in range(self.T)))


class MixtureProposal:
    """q_t(x | x_{t−1}) of the module docstring: ρ · the frame's prior + (1 − ρ) · Σ_j π_j N(x; X_j, h² I).

    ``h``: one bandwidth, or several (h_1..h_B), each kernel then the equal mixture
    (1/B) Σ_b N(x; X_j, h_b² I): the posterior's modes sit 0.01–0.05 from the training latents
    and are 0.01–0.02 wide on the toy model (a step of 0.05 from the mode costs 8–36 nats of
    the frame's factor), so one bandwidth of 0.05 rarely lands in them.

    ``lookahead``: at a frame that starts a run of frames linked by dynamics (t without, t + 1
    with a dynamics factor), weigh each centre also by the audio likelihood of its
    deterministic continuation, Σ_{u=t+1}^{t+k} ln p(ŷ_u | m_u), m_{t} = X_j,
    m_u = μ_x(m_{u−1}) through the run (with dynamics noise 10⁻⁶ the run's path is nearly a
    function of its first frame, so a centre judged on frame t alone dies in the frames after).
    ``extra_centres`` (K, T, d): further fixed centres per frame (e.g. the joint MAP and the
    modes of its restarts), weighed the same way. Both change only the weights π_j and the
    centres, which are fixed before any sweep: the proposal stays a valid, exactly evaluated q_t."""

    def __init__(self, ff: FrameFactors, plan, rho: float = 0.5, h: float | tuple = 0.05, lookahead: bool = False,
                 extra_centres: np.ndarray | None = None):
        hs = np.atleast_1d(np.asarray(h, dtype=np.float64))
        if not 0 <= rho < 1 or hs.ndim != 1 or hs.size == 0 or np.any(hs <= 0):
            raise ValueError(f"proposal needs 0 <= rho < 1 and bandwidths h > 0, got rho={rho}, h={h}")
        if extra_centres is not None:
            extra_centres = np.asarray(extra_centres, dtype=np.float64)
            if extra_centres.ndim != 3 or extra_centres.shape[1:] != (ff.T, ff.d):
                raise ValueError(f"extra_centres: expected (K, {ff.T}, {ff.d}), got {extra_centres.shape}")
        self.ff, self.rho, self.hs = ff, float(rho), hs
        self.centres, self.logw, self.smooth_pred = {}, {}, {}
        for b in plan.blocks:
            Xtr0 = np.asarray(b.model.X_, dtype=np.float64)   # the training latents (all d dimensions)
            for t in range(b.start, b.stop):
                Xtr = Xtr0 if extra_centres is None else np.vstack([Xtr0, extra_centres[:, t]])
                ll = ff.audio_loglik(t, Xtr)
                if t in ff.entry:
                    ll = ll + ff.entry_logpdf(t, Xtr)
                if lookahead and t not in ff.dyn_gp:
                    ll = ll + ff.continuation(t, Xtr, ff.run_end(t), grad=False)[0]
                self.centres[t], self.logw[t] = Xtr, ll - logsumexp(ll)
                if t in ff.smooth:   # the smoothness factor's visual predictive at each centre
                    _, gv = ff.smooth[t]
                    mu, s = ff.tm.vis_gps.mean_var(Runs.one(gv, len(Xtr)), np.ascontiguousarray(Xtr))
                    var = s[:, None] / ff.tm.vis_gps.w2[gv][None] + ff.tm.motion_var[None]
                    self.smooth_pred[t] = (np.ascontiguousarray(mu), 1.0 / var, 0.5 * np.log(var).sum(1))

    def _weights(self, t: int, Xprev: np.ndarray | None, N: int) -> np.ndarray:
        """ln π_j per particle (N, M), or (1, M) when every particle shares them: audio × entry,
        × the smoothness factor s(x_{t−1}, X_j) given each particle's ancestor at a block
        start (:func:`~bayes_talk.posterior.proposal_tables.smoothness_weights`); normalised per row."""
        if t not in self.smooth_pred or Xprev is None:
            return self.logw[t][None]
        gp, _ = self.ff.smooth[t]
        zp, _ = self.ff.tm.vis_gps.mean_var(Runs.one(gp, N), np.ascontiguousarray(Xprev, dtype=np.float64))
        return smoothness_weights(self.logw[t], zp + self.ff.smooth_shift[t], *self.smooth_pred[t])

    def _prior(self, t: int, Xprev: np.ndarray | None, N: int):
        """Mean (N, d) and sd (N, d) of the frame's prior, or None (no prior: kernel only)."""
        ff = self.ff
        if t in ff.dyn_gp:
            return "dyn", *ff.dynamics_mean_sd(t, Xprev)
        if t in ff.entry:
            return "entry", None, None
        return None, None, None

    def sample_logq(self, t: int, Xprev: np.ndarray | None, N: int, rng: np.random.Generator,
                    X: np.ndarray | None = None, ref: np.ndarray | None = None,
                    x_next: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """N draws of q_t given ancestors Xprev (N, d) (or the given X) and their ln q_t (N,);
        ``ref`` (d,): the last draw replaced by it before ln q_t is evaluated (the reference
        particle of a sweep, the current value of a block). ``x_next``: ignored (a sweep's
        proposal does not look at the frame after; the block updates pass it to any proposal)."""
        d = self.ff.d
        kind, mu, sd = self._prior(t, Xprev, N)
        rho = self.rho if kind else 0.0
        C = self.centres[t]
        lw = self._weights(t, Xprev, N)
        if X is None:
            use_prior = rng.random(N) < rho
            cdf = np.cumsum(np.exp(lw), axis=1)
            j = np.minimum((cdf < rng.random(N)[:, None] * cdf[:, -1:]).sum(1), len(C) - 1)
            X = C[j] + self.hs[rng.integers(len(self.hs), size=N)][:, None] * rng.standard_normal((N, d))
            if use_prior.any():
                if kind == "dyn":
                    X[use_prior] = mu[use_prior] + sd[use_prior] * rng.standard_normal((int(use_prior.sum()), d))
                else:
                    e = self.ff.entry[t]
                    L = np.linalg.inv(self.ff.tm.e_chol_inv[e])
                    X[use_prior] = self.ff.tm.e_mean[e] + rng.standard_normal((int(use_prior.sum()), d)) @ L.T
        if ref is not None:
            X[-1] = ref
        lk = kernel_mixture_logpdf(np.ascontiguousarray(X, dtype=np.float64), C, lw, self.hs)
        if not rho:
            return X, lk
        if kind == "dyn":
            z = (X - mu) / sd
            lp = -0.5 * (z * z).sum(1) - np.log(sd).sum(1) - 0.5 * d * LOG_2PI
        else:
            lp = self.ff.entry_logpdf(t, X)
        return X, np.logaddexp(np.log(rho) + lp, np.log1p(-rho) + lk)


def csmc_as(ff: FrameFactors, q: MixtureProposal, x_ref: np.ndarray, N: int, rng: np.random.Generator,
            backward: bool = False):
    """One conditional SMC sweep (module docstring): a new path (T, d) given the reference path
    ``x_ref``, and the fraction of frames whose value changed. ``backward=False``: ancestor
    sampling (Lindsten, Jordan & Schön 2014, Alg. 2); ``True``: the reference keeps its own
    ancestry in the forward pass and the path is drawn by backward simulation instead
    (Whiteley 2010; Lindsten & Schön 2013, "Backward simulation methods for Monte Carlo
    statistical inference", §5.4): x_{T−1} ∝ W_{T−1}, then x_t = P_t^j with
    probability ∝ W_t^j exp f_{t+1}(P_t^j, x_{t+1}) — both leave p(X | Ŷ) invariant."""
    T, d = ff.T, ff.d
    P = np.empty((T, N, d))
    A = np.zeros((T, N), dtype=np.int64)
    LW = np.empty((T, N))
    X, lq = q.sample_logq(0, None, N, rng, ref=x_ref[0])
    P[0] = X
    logw = ff.log_f(0, None, X) - lq
    LW[0] = logw
    for t in range(1, T):
        W = np.exp(logw - logsumexp(logw))
        a = rng.choice(N, size=N, p=W)
        if backward:
            a[-1] = N - 1
        else:   # ancestor of the reference particle ∝ W_{t−1}^i exp f_t(x_{t−1}^i, x_t^*)
            la = np.log(W + 1e-300) + ff.link_logf(t, P[t - 1], np.repeat(x_ref[t][None], N, 0))
            a[-1] = rng.choice(N, p=np.exp(la - logsumexp(la)))
        Xprev = P[t - 1][a]
        X, lq = q.sample_logq(t, Xprev, N, rng, ref=x_ref[t])
        P[t], A[t] = X, a
        logw = ff.log_f(t, Xprev, X) - lq
        LW[t] = logw
    k = rng.choice(N, p=np.exp(logw - logsumexp(logw)))
    out = np.empty((T, d))
    out[T - 1] = P[T - 1, k]
    for t in range(T - 2, -1, -1):
        if backward:
            lb = LW[t] + ff.link_logf(t + 1, P[t], np.repeat(out[t + 1][None], N, 0))
            k = rng.choice(N, p=np.exp(lb - logsumexp(lb)))
        else:
            k = A[t + 1, k]
        out[t] = P[t, k]
    return out, float(np.mean(np.any(out != x_ref, axis=1)))


class ParticleGibbsMove:
    """One CSMC-AS sweep as a move in a sampler's coordinates u: x = to_x(u), the sweep, u' = to_u(x')
    (``to_x``/``to_u`` a bijection, e.g. the whitening or the non-centred map). The sweep leaves
    p(x | Ŷ) invariant, so the move leaves the sampler's target (p pushed through the bijection)
    invariant: for :func:`~bayes_talk.posterior.samplers.run_nuts`'s ``extra_move``
    (particle Gibbs ∘ NUTS). ``frame_tries`` = K > 0: after the sweep, a multiple-try
    Metropolis update (:func:`~bayes_talk.posterior.frame_updates.block_mtm`, K tries) of
    every isolated frame and every dynamics run of at most ``block_len`` frames
    (:func:`~bayes_talk.posterior.frame_updates.dynamics_blocks`) — also invariant, so the
    composition is; ``tries_from_modes``: the tries of a block's first frame from
    :class:`~bayes_talk.posterior.frame_updates.BlockModeProposal` (the block's own modes)
    instead of the sweep's proposal, with ``neighbours`` conditioned on the smoothness factors
    at the block's two ends given its current neighbours
    (:func:`~bayes_talk.posterior.frame_updates.neighbour_adjusted`); ``pairs`` (with
    ``tries_from_modes``): then an update of every pair of consecutive blocks together, the
    two starts' tries from their modes matched through the smoothness factor between them
    (:class:`~bayes_talk.posterior.frame_updates.PairModeProposal`).

    A call returns (u', record): ``record["pg_sweep"]`` True (a sweep ran) and
    ``record["pg_frame_moved"]`` (T,) whether the move (sweep and frame updates) changed
    frame t's latent x_t, compared in x, exactly, ``record["pg_seconds"]`` the move's own time;
    ``run_nuts`` keeps them per draw
    (:func:`~bayes_talk.posterior.diagnostics.frame_update_rate` turns them into the
    per-frame update rate)."""

    def __init__(self, ff, q, to_x, to_u, n_particles: int = 64, backward: bool = False, blocks=(),
                 frame_tries: int = 0, q_blocks=None, q_pairs=None, adapt_weights: bool = False,
                 block_sweeps: int = 1):
        """From its parts: the frame factors ``ff`` (:class:`FrameFactors` or any object with
        its methods), the sweep's proposal ``q``, the blocks [s, e) of the multiple-try
        updates and their proposal ``q_blocks`` (default ``q``), and the joint proposal of the
        pairs of blocks updated together ``q_pairs`` (its ``pairs``; None: no pair updates).
        :meth:`for_density` builds the parts of the synthesis density; the tests pass densities
        with known moments. ``block_sweeps``: passes of the multiple-try updates (blocks, then
        pairs) after each sweep."""
        if int(block_sweeps) < 1:
            raise ValueError(f"block_sweeps must be >= 1, got {block_sweeps}")
        self.block_sweeps = int(block_sweeps)
        self.ff, self.q = ff, q
        self.to_x, self.to_u, self.n, self.backward = to_x, to_u, int(n_particles), bool(backward)
        self.frame_tries = int(frame_tries)
        self.blocks = list(blocks) if self.frame_tries > 0 else []
        self.q_blocks = q if q_blocks is None else q_blocks
        self.q_pairs = q_pairs if self.frame_tries > 0 and q_pairs is not None and q_pairs.pairs else None
        self.adapt_weights = bool(adapt_weights) and hasattr(self.q_blocks, "begin_adaptation")

    def begin_adaptation(self) -> None:
        """A sampler's warm-up begins: with ``adapt_weights`` the blocks' own-mode proposal
        starts learning its modes' weights from the multiple-try updates
        (:meth:`~bayes_talk.posterior.frame_updates.BlockModeProposal.begin_adaptation`);
        otherwise nothing changes."""
        if self.adapt_weights:
            self.q_blocks.begin_adaptation()
            if self.q_pairs is not None:
                self.q_pairs.refresh()

    def adaptation_state(self):
        """What this move's warm-up learnt (the blocks' proposal's tallies,
        :meth:`~bayes_talk.posterior.mode_adaptation.LearntModes.adaptation_state`; None without
        ``adapt_weights``)."""
        return self.q_blocks.adaptation_state() if self.adapt_weights else None

    def end_adaptation(self, states: list | None = None) -> None:
        """The warm-up ends: the learnt weights are frozen — from this move's own warm-up, or with
        ``states`` from several chains' (their :meth:`adaptation_state`, pooled) — the pairs'
        weights recomputed from them, and the move is a fixed posterior-invariant kernel again."""
        if self.adapt_weights and self.q_blocks.adapting:
            self.q_blocks.end_adaptation(None if states is None else [st for st in states if st is not None])
            if self.q_pairs is not None:
                self.q_pairs.refresh()

    def adaptation_summary(self) -> dict | None:
        """What the warm-up adaptation learnt (None without ``adapt_weights``): per block start
        (a string key) the total-variation distance between the learnt and the own modes' weights
        (:meth:`~bayes_talk.posterior.frame_updates.BlockModeProposal.weight_shift`), its
        maximum over the blocks, and per block start the number of its modes proposed from their
        learnt means and covariances too (``pg_adapt_moments``; {} without) and the number of
        clusters fitted to its warm-up states (``pg_adapt_clusters``; {} without)."""
        if not self.adapt_weights:
            return None
        shift = self.q_blocks.weight_shift()
        return {"weight_shift": {str(s): v for s, v in shift.items()},
                "weight_shift_max": max(shift.values(), default=0.0),
                "modes_with_learnt_moments": {str(s): len(idx) for s, (idx, _, _) in self.q_blocks.learnt.items()},
                "state_clusters": {str(s): len(w) for s, (_, _, w) in self.q_blocks.clustered.items()}}

    @classmethod
    def for_density(cls, dens: UtteranceDensity, plan, to_x, to_u, n_particles: int = 64, rho: float = 0.5,
                    h: float | tuple = 0.05, lookahead: bool = False, extra_centres: np.ndarray | None = None,
                    backward: bool = False, frame_tries: int = 0, tries_from_modes: bool = False,
                    block_len: int = 1, neighbours: bool = False, mode_kw: dict | None = None,
                    pairs: bool = False, adapt_weights: bool = False, block_sweeps: int = 1,
                    executor=None) -> ParticleGibbsMove:
        """The move on the synthesis density ``dens``: :class:`FrameFactors`, the
        :class:`MixtureProposal` (``rho``, ``h``, ``lookahead``, ``extra_centres``), the
        dynamics runs of at most ``block_len`` frames and, with ``tries_from_modes``, their
        :class:`~bayes_talk.posterior.frame_updates.BlockModeProposal` (``neighbours`` and
        ``mode_kw``: its ``delta``, ``scale``, ``n_starts``), with ``pairs`` the consecutive
        blocks' :class:`~bayes_talk.posterior.frame_updates.PairModeProposal`; ``adapt_weights``:
        the modes' weights learnt during a sampler's warm-up (:meth:`begin_adaptation`);
        ``block_sweeps``: passes of the block and pair updates after each sweep; ``executor``: where
        the blocks' own-mode searches run (:func:`~bayes_talk.posterior.frame_updates.own_modes`)."""
        if int(block_len) < 1:
            raise ValueError(f"block_len must be >= 1 (1: isolated frames only), got {block_len}")
        ff = FrameFactors(dens)
        q = MixtureProposal(ff, plan, rho, h, lookahead, extra_centres)
        blocks = dynamics_blocks(ff, int(block_len)) if int(frame_tries) > 0 else []
        # the block updates' tries: from the block's own modes (BlockModeProposal) or the sweep's proposal
        q_blocks = (BlockModeProposal(q, blocks, neighbours=neighbours, executor=executor, **(mode_kw or {}))
                    if tries_from_modes and blocks else q)
        q_pairs = PairModeProposal(q_blocks, adjacent_pairs(blocks)) if pairs and q_blocks is not q else None
        return cls(ff, q, to_x, to_u, n_particles, backward, blocks, frame_tries, q_blocks, q_pairs, adapt_weights,
                   block_sweeps)

    @property
    def blocks_without_modes(self) -> list[tuple[int, int]]:
        """The blocks [s, e) whose tries come from the sweep's proposal alone because their
        own-mode proposal found no maximum ([] when the tries are not from modes)."""
        return list(getattr(self.q_blocks, "without_modes", []))

    def __call__(self, u: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, dict]:
        t0 = time.perf_counter()
        x = np.asarray(self.to_x(u), dtype=np.float64).reshape(self.ff.T, self.ff.d)
        x_new, _ = csmc_as(self.ff, self.q, x, self.n, rng, self.backward)
        for _ in range(self.block_sweeps if self.blocks else 0):
            x_new, _ = block_mtm(self.ff, self.q_blocks, x_new, self.blocks, self.frame_tries, rng)
            if self.q_pairs is not None:
                x_new, _ = block_mtm(self.ff, self.q_pairs, x_new, self.q_pairs.pairs, self.frame_tries, rng)
        moved = np.any(x_new != x, axis=1)
        u_new = np.asarray(self.to_u(x_new.reshape(np.shape(u))), dtype=np.float64) if moved.any() else u
        return u_new, {"pg_sweep": True, "pg_frame_moved": moved, "pg_seconds": time.perf_counter() - t0}


def run_particle_gibbs(dens: UtteranceDensity, plan, starts: np.ndarray, n_draws: int, warmup: int, seed: int,
                       n_particles: int = 64, rho: float = 0.5, h: float | tuple = 0.05, lookahead: bool = False,
                       extra_centres: np.ndarray | None = None) -> dict:
    """Chains of CSMC-AS sweeps from ``starts`` (chains, T, d): draws (chains, n_draws, T, d)
    after ``warmup`` sweeps, the per-frame update rate (chains, T) over all the sweeps, warm-up
    included (:func:`~bayes_talk.posterior.diagnostics.frame_update_rate`), ln p of each draw,
    seconds."""
    ff = FrameFactors(dens)
    q = MixtureProposal(ff, plan, rho, h, lookahead, extra_centres)
    C = len(starts)
    draws = np.empty((C, n_draws, ff.T, ff.d))
    lp = np.empty((C, n_draws))
    moved = np.zeros((C, warmup + n_draws, ff.T), dtype=bool)
    t0 = time.perf_counter()
    for c in range(C):
        rng = np.random.default_rng([seed, c, 0x7067])
        x = np.asarray(starts[c], dtype=np.float64).reshape(ff.T, ff.d)
        for it in range(warmup + n_draws):
            x_new, _ = csmc_as(ff, q, x, n_particles, rng)
            moved[c, it] = np.any(x_new != x, axis=1)
            x = x_new
            if it >= warmup:
                draws[c, it - warmup] = x
                lp[c, it - warmup] = dens(x)[0]
    return {"samples": draws, "lp": lp, "frame_update_rate": frame_update_rate(moved),
            "seconds": time.perf_counter() - t0}


__all__ = ["FrameFactors", "MixtureProposal", "ParticleGibbsMove", "csmc_as", "run_particle_gibbs"]
