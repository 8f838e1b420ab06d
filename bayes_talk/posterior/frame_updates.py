"""Multiple-try updates of single frames and short dynamics blocks given their neighbours
(pg-nuts, after each particle Gibbs sweep).

``ff`` below is a :class:`~bayes_talk.posterior.particle_gibbs.FrameFactors` and a proposal
anything with its ``sample_logq(t, Xprev, N, rng, X=None, ref=None) -> (X, ln q)``, e.g.
:class:`~bayes_talk.posterior.particle_gibbs.MixtureProposal` (not imported: that module's
particle Gibbs move imports this one).

The synthesis density is Markov over frames (:mod:`bayes_talk.posterior.particle_gibbs`,
(1)), so a block of frames [s, e) has the full conditional given its neighbours

    π(x_{s:e}) ∝ exp(Σ_{u=s}^{e} f_u(x_{u−1}, x_u)).

:func:`block_mtm` updates a block from it by independence multiple-try Metropolis (Liu,
Liang & Wong 2000): tries of its first frame from a proposal that does not depend on the
block, the rest of each try's path from the dynamics. The particle Gibbs move
(:class:`~bayes_talk.posterior.particle_gibbs.ParticleGibbsMove`, ``frame_tries``,
``block_len``) applies it after each sweep to the isolated frames and the dynamics runs of
at most ``block_len`` frames (:func:`dynamics_blocks`): with dynamics noise 10⁻⁶ the sweep
moves such a run only when a particle lands on its first frame's narrow bumps. The tries
come from the sweep's own proposal or from :class:`BlockModeProposal`: the Laplace
approximations at the local maxima of the block's own factor (:func:`block_factor`: audio
and entry along the path the dynamics means continue; :func:`factor_modes`) — at an
isolated frame the marginal is a mixture of narrow, separated bumps there
(docs/uncertainty.md, "Which sampler").
"""
from __future__ import annotations

import itertools

import numpy as np
from scipy.special import logsumexp

from bayes_talk.gp.predictive_fused import Runs
from bayes_talk.posterior.methods import PG_NUTS_DEFAULTS
from bayes_talk.posterior.mode_adaptation import LearntModes, component_logpdf


def block_mtm(ff, q, x: np.ndarray, blocks, K: int, rng: np.random.Generator,
              _broken: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Multiple-try Metropolis updates of blocks of frames given their neighbours (Liu, Liang &
    Wong 2000, with independent proposals). For each block [s, e) of ``blocks`` in turn (a
    frame s and the frames s + 1 … e − 1 that follow it through the dynamics; e = s + 1: one
    frame), the block's full conditional (the density is Markov, (1) of
    :mod:`~bayes_talk.posterior.particle_gibbs`)

        π(x_{s:e}) ∝ exp(Σ_{u=s}^{e} f_u(x_{u−1}, x_u))            (x_{s−1}, x_e held fixed)

    is the target. K tries Y^k: y_s ~ q_s(· | x_{s−1}) (independent of the block's current
    value: an independence MTM), then y_u ~ p_π(· | y_{u−1}) through the block's dynamics, so the
    proposal density is q(Y) = q_s(y_s) Π_u p_π(y_u | y_{u−1}) and the weight w = π/q has the
    dynamics terms cancelled (with noise 10⁻⁶ the rest of the path is nearly a function of y_s).
    Y = Y^J with probability ∝ w_J, accepted with probability min(1, Σ_k w_k / (Σ_k w_k − w_J
    + w(x_{s:e}))). A *group* [s, e) of consecutive blocks (frames after s without a dynamics
    factor into them: later starts) takes all its starts' tries at once from
    ``q.sample_starts`` (:class:`PairModeProposal`, given the group's neighbours x_{s−1} and
    x_e), the frames after each start from the dynamics as above. Each update leaves π, hence p(X | Ŷ), invariant. Returns the new path and,
    per block, whether it moved. (``_broken``: accept always — not invariant; the tests'
    control.)"""
    x = np.array(x, dtype=np.float64, copy=True)
    T = ff.T
    moved = np.zeros(len(blocks), dtype=bool)
    for i, (s, e) in enumerate(blocks):
        prev = None if s == 0 else np.repeat(x[s - 1][None], K + 1, 0)
        inner = [u for u in range(s + 1, e) if u not in ff.dyn_gp]      # later block starts (a group)
        P = np.empty((K + 1, e - s, ff.d))                                # the K tries and the current block
        P[K] = x[s:e]
        if inner:   # all the starts' tries at once from the group's joint proposal
            Y, lq = q.sample_starts(s, e, K + 1, rng, ref=x[[s, *inner]], x_prev=None if s == 0 else x[s - 1],
                                    x_next=x[e] if e < T else None)
            P[:K, [0, *(u - s for u in inner)]] = Y[:K]
        else:
            Y, lq = q.sample_logq(s, prev, K + 1, rng, ref=x[s],           # K tries and the current x_s
                                  x_next=x[e] if e < T else None)
            P[:K, 0] = Y[:K]
        lw = ff.log_f(s, prev, P[:, 0]) - lq
        for u in range(s + 1, e):
            if u in inner:
                lw += ff.log_f(u, P[:, u - s - 1], P[:, u - s])
                continue
            mu, sd = ff.dynamics_mean_sd(u, P[:K, u - s - 1])
            P[:K, u - s] = mu + sd * rng.standard_normal(mu.shape)
            lw += ff.log_f(u, P[:, u - s - 1], P[:, u - s]) - ff.dynamics_logpdf(u, P[:, u - s - 1], P[:, u - s])
        if e < T:
            lw = lw + ff.link_logf(e, P[:, -1], np.repeat(x[e][None], K + 1, 0))   # x_e's own terms cancel
        j = rng.choice(K, p=np.exp(lw[:K] - logsumexp(lw[:K])))
        s_y = logsumexp(lw[:K])
        s_x = logsumexp(np.concatenate([np.delete(lw[:K], j), lw[K:]]))
        if _broken or np.log(rng.random()) < s_y - s_x:
            x[s:e] = P[j]
            moved[i] = True
        if getattr(q, "adapting", False):   # a warm-up: the proposal learns its modes' weights
            if inner:
                q.record(s, e, Y[:K], lw[:K], x[[s, *inner]])
            else:
                q.record(s, P[:K, 0], lw[:K], x[s])
    return x, moved


def block_factor(ff, s: int, e: int, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """G_s(x) = g_s(x) + Σ_{u=s+1}^{e−1} g_u(m_u) and ∂G_s/∂x for rows X (N, d): block [s, e)'s
    own factors (audio, and entry at s) along the deterministic continuation m_s = x, m_u =
    μ_x(m_{u−1}) (:meth:`~bayes_talk.posterior.particle_gibbs.FrameFactors.own_factor`,
    :meth:`~bayes_talk.posterior.particle_gibbs.FrameFactors.continuation`): up to the
    dynamics noise, the block's marginal density of its first frame apart from the
    smoothness factors at its two ends."""
    g, gx = ff.own_factor(s, X)
    if e - s == 1:
        return g, gx
    c, gc = ff.continuation(s, X, e)
    return g + c, gx + gc


def factor_modes(own, starts: np.ndarray, n_iter: int = 40, max_step: float = 0.05,
                 max_modes: int = 32) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Local maxima of a function g (``own(X) -> (g (N,), ∂g/∂X (N, d))``, e.g. a block's own
    factor :func:`block_factor`) and their Laplace
    approximations: damped Newton ascent from every row of ``starts`` at once (Hessian by
    central differences of the analytic gradient; steps capped at ``max_step``, halved until
    g rises; a gradient step where the Hessian is not negative definite), then maxima closer
    than one standard deviation (Mahalanobis, in the heavier one's covariance) merged (the
    lighter dropped); a point whose Hessian is not clearly negative definite, or where the ascent
    has not converged within ``n_iter`` steps (Newton decrement ≥ 10⁻⁶), is no maximum. Returns
    the means (K, d), covariances Σ_k = (−∇²g)⁻¹ (K, d, d) and log weights ln w_k =
    g(m_k) + ½ ln det Σ_k normalised (each maximum's Laplace mass), the ``max_modes`` heaviest."""
    X = np.array(starts, dtype=np.float64, copy=True)
    d, h = X.shape[1], 1e-6
    eye = np.eye(d)

    def hessian(X):
        H = np.stack([(own(X + h * eye[j])[1] - own(X - h * eye[j])[1]) / (2 * h)
                      for j in range(d)], axis=1)
        return 0.5 * (H + np.swapaxes(H, 1, 2))

    g, gx = own(X)
    for _ in range(n_iter):
        a = np.flatnonzero(np.linalg.norm(gx, axis=1) >= 1e-6)      # the rows still moving
        if not len(a):
            break
        Xa, ga, gxa = X[a], g[a], gx[a]
        H = hessian(Xa)
        lam = np.linalg.eigvalsh(H)
        newton = lam[:, -1] < 0
        step = np.where(newton[:, None], -np.linalg.solve(np.where(newton[:, None, None], H, -eye), gxa[..., None])[..., 0],
                        gxa / np.maximum(np.abs(lam[:, :1]), 1.0))
        norm = np.linalg.norm(step, axis=1, keepdims=True)
        step *= np.minimum(1.0, max_step / np.maximum(norm, 1e-300))
        done = np.zeros(len(a), dtype=bool)
        for _ in range(8):                                   # halve until g rises (per row)
            g1, gx1 = own(Xa + step)
            up = ~done & (g1 >= ga)
            Xa[up], ga[up], gxa[up] = Xa[up] + step[up], g1[up], gx1[up]
            done |= up
            if done.all():
                break
            step[~done] *= 0.5
        X[a], g[a], gx[a] = Xa, ga, gxa
    H = hessian(X)
    lam, U = np.linalg.eigh(-H)                          # the precision's eigenvalues, ascending
    # a maximum only where every curvature is clearly negative (a flat direction, e.g. a latent
    # dimension the audio GP does not read in a frame without an entry, has no Laplace mass)
    ok = np.all(np.isfinite(lam), axis=1) & np.isfinite(g) & (lam[:, 0] > 1e-8 * np.abs(lam).max(1, initial=1.0))
    X, g, gx, lam, U, H = X[ok], g[ok], gx[ok], lam[ok], U[ok], H[ok]
    S = np.einsum("kij,kj,klj->kil", U, 1.0 / lam, U)
    S = 0.5 * (S + np.swapaxes(S, 1, 2))
    # and only where the ascent has converged: Newton decrement ∇gᵀ Σ ∇g < 10⁻⁶
    ok = np.einsum("ki,kij,kj->k", gx, S, gx) < 1e-6
    X, g, lam, H, S = X[ok], g[ok], lam[ok], H[ok], S[ok]
    if not len(X):
        return np.empty((0, d)), np.empty((0, d, d)), np.empty(0)
    logw = g - 0.5 * np.log(lam).sum(1)
    keep: list[int] = []
    Pk = -H
    for i in np.argsort(-logw):
        if all(float((X[i] - X[k]) @ Pk[k] @ (X[i] - X[k])) > 1.0 for k in keep):
            keep.append(int(i))
        if len(keep) == max_modes:
            break
    lw = logw[keep]
    return X[keep], S[keep], lw - logsumexp(lw)


def _own_modes_task(task) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """An executor task: (ff, [(s, e, starts), …]) → :func:`factor_modes` of each block's own
    factor :func:`block_factor` from its starts."""
    ff, jobs = task
    return [factor_modes(lambda X, s=s, e=e: block_factor(ff, s, e, X), starts) for s, e, starts in jobs]


def own_modes(ff, jobs, executor=None) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The own modes (:func:`factor_modes`) of blocks ``jobs`` = [(s, e, starts (N, d)), …], in
    order. With an ``executor`` of n workers the blocks are dealt round-robin into n tasks (one
    copy of ``ff`` sent per worker; one-frame and longer blocks alternate, so the tasks cost
    about the same); without one they run here through a local executor, with one BLAS thread
    as in a worker (:mod:`bayes_talk.base.executor`), so the modes do not depend on the executor."""
    from bayes_talk.base.executor import executor_for

    with executor_for(executor, 1) as ex:
        n = max(1, min(ex.n_workers, len(jobs)))
        out: list = [None] * len(jobs)
        for i, found in enumerate(ex.map(_own_modes_task, [(ff, jobs[i::n]) for i in range(n)])):
            out[i::n] = found
    return out


class BlockModeProposal(LearntModes):
    """An independence proposal for the first frame s of a block's multiple-try update
    (:func:`block_mtm`): q_s(x | x_{s−1}) = (1 − δ) Σ_k w_k C⁻¹ Σ_c N(x; m_k, c² Σ_k) + δ q⁰_s(x | x_{s−1})
    (c over the C ``scale`` factors: a wider copy of each mode for a full conditional broader than
    the own factor's bump) with (m_k, Σ_k, w_k) the Laplace approximations at the local maxima of the block's own
    factor G_s (:func:`block_factor`; :func:`factor_modes`, found once, from the frame's
    proposal centres: its state model's training latents and any extra centres; for a block of
    more than one frame only the ``n_starts`` of highest weight (None: all) — on held-out
    `utt0001` of the default model the 64 of ~300 find every maximum of weight ≥ 0.001 at a fifth
    of the cost) and q⁰ the sweep's proposal
    (:class:`~bayes_talk.posterior.particle_gibbs.MixtureProposal`) as the defensive
    component. An isolated frame's marginal is a mixture of narrow, separated bumps (on the toy
    utterance frame 63's chain draws sit in clusters near −0.13 and −0.03, each ~0.01 wide,
    and switch every ~30 draws), and a short dynamics block's first frame likewise (its path a
    function of that frame): tries from the bumps themselves land in them. q_s is fixed while the
    kept draws are taken (its weights w_k may be learnt in the warm-up: :meth:`begin_adaptation`;
    with ``moments`` also a component per mode at its mean and covariance under the full
    conditional, and with ``clusters`` a Gaussian mixture fitted to the warm-up's states,
    :mod:`~bayes_talk.posterior.mode_adaptation`, used without ``neighbours``)
    and evaluated exactly. Blocks without a maximum found fall back to q⁰ alone
    (listed in ``without_modes``, the diagnostics' ``pg_blocks_without_modes``). ``executor``
    (a :class:`~bayes_talk.base.executor.Executor`): the blocks' mode searches spread over its
    workers (:func:`own_modes`; the same modes whatever the executor)."""

    def __init__(self, base, blocks, delta: float = PG_NUTS_DEFAULTS["pg_mode_delta"],
                 scale: float | tuple = PG_NUTS_DEFAULTS["pg_mode_scale"],
                 n_starts: int | None = PG_NUTS_DEFAULTS["pg_mode_starts"], neighbours: bool = False,
                 moments: bool = PG_NUTS_DEFAULTS["pg_adapt_moments"],
                 clusters: bool = PG_NUTS_DEFAULTS["pg_adapt_clusters"], executor=None):
        scales = np.atleast_1d(np.asarray(scale, dtype=np.float64))
        if (not 0 < delta <= 1 or scales.ndim != 1 or not scales.size or np.any(~(scales > 0))
                or (n_starts is not None and n_starts < 1)):
            raise ValueError(f"BlockModeProposal needs 0 < delta <= 1, scales > 0 and n_starts >= 1, got {delta}, "
                             f"{scale}, {n_starts}")
        self.base, self.ff, self.delta, self.scales = base, base.ff, float(delta), scales
        self.neighbours, self.learn_moments, self.learn_clusters = bool(neighbours), bool(moments), bool(clusters)
        self.modes, self.laplace, self.end, self.without_modes = {}, {}, {}, []
        self.adapting, self.own_weights, self.tally, self.learnt, self.clustered = False, {}, {}, {}, {}
        # ascend from all centres (one frame) or the n_starts of highest weight
        jobs = [(s, e, base.centres[s][np.argsort(-base.logw[s], kind="stable")[:None if e - s == 1 else n_starts]])
                for s, e in blocks]
        for (s, e, _), (m, S, lw) in zip(jobs, own_modes(self.ff, jobs, executor), strict=True):
            if len(m):
                self.modes[s], self.end[s] = self._scaled(m, S, lw), e
                self.laplace[s] = (m, np.linalg.inv(S), lw)   # the modes' own Laplace: means, precisions, weights
                self.own_weights[s] = lw
            else:
                self.without_modes.append((s, e))

    def _scaled(self, m: np.ndarray, S: np.ndarray, lw: np.ndarray):
        """Components N(m_k, c² S_k) for every mode k and scale c of ``scales``, each scale an
        equal share of the mode's weight: means (C·K, d), Cholesky factors (C·K, d, d), log
        weights (C·K,), scale-major."""
        C, (K, d) = len(self.scales), m.shape
        L = np.linalg.cholesky(0.5 * (S + np.swapaxes(S, 1, 2)))
        return (np.tile(m, (C, 1)), (self.scales[:, None, None, None] * L[None]).reshape(C * K, d, d),
                np.tile(lw, C) - np.log(C))

    def components(self, s: int, x_prev: np.ndarray | None, x_next: np.ndarray | None):
        """The mixture's components (means (K, d), Cholesky factors of the covariances
        (K, d, d), log weights (K,)) for block s given its neighbours: the own factor's modes,
        or with ``neighbours`` (:func:`neighbour_adjusted`) those modes conditioned on the
        smoothness factors at the block's two ends."""
        if not self.neighbours:
            return self.modes[s]
        m, P, lw = self.laplace[s]
        m, Pn, lwn = neighbour_adjusted(self.ff, s, self.end[s], m, P, lw, x_prev, x_next)
        return self._scaled(m, np.linalg.inv(Pn), lwn)

    def sample_logq(self, t: int, Xprev: np.ndarray | None, N: int, rng: np.random.Generator,
                    X: np.ndarray | None = None, ref: np.ndarray | None = None,
                    x_next: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """N draws of q_t given the neighbour Xprev (N, d) (or the given X) and their ln q_t (N,);
        ``ref`` (d,): the last draw replaced by it before ln q_t is evaluated; ``x_next`` (d,):
        the frame after the block (None at the end or when unknown), read with ``neighbours``."""
        if t not in self.modes:
            return self.base.sample_logq(t, Xprev, N, rng, X, ref)
        m, L, lw = self.components(t, None if Xprev is None else Xprev[0], x_next)
        d = self.ff.d
        if X is None:
            X, _ = self.base.sample_logq(t, Xprev, N, rng)
            mine = rng.random(N) >= self.delta
            k = rng.choice(len(m), size=int(mine.sum()), p=np.exp(lw))
            X[mine] = m[k] + np.einsum("kij,kj->ki", L[k], rng.standard_normal((len(k), d)))
        if ref is not None:
            X[-1] = ref
        _, lq0 = self.base.sample_logq(t, Xprev, N, rng, X)
        lm = logsumexp(lw[None] + component_logpdf(X, m, L), axis=1)
        if self.delta == 1.0:
            return X, lq0
        return X, np.logaddexp(np.log1p(-self.delta) + lm, np.log(self.delta) + lq0)


class PairModeProposal:
    """A joint independence proposal for the two starts of a pair of consecutive blocks
    [s, m) and [m, e) (a group of :func:`block_mtm`; :func:`adjacent_pairs`): when the blocks'
    modes must be matched (a mode of one block compatible with only some of the other's through
    the smoothness factor between them), updating one block given the other cannot switch both.

        q(y_s, y_m) = Σ_{k,l} π'_kl N(y_s; a_k, c² Σ^a_k) N(y_m; b_l, c² Σ^b_l),
        π_kl ∝ w^a_k w^b_l exp(ℓ_m(ā_k, b_l)),   π' = (1 − δ) π + δ / (K_a K_b),

    with (a_k, Σ^a_k, w^a_k), (b_l, Σ^b_l, w^b_l) the blocks' own modes
    (:class:`BlockModeProposal`, its scale c and δ), ā_k the end of the path the dynamics
    means continue from a_k, ℓ_m the terms of f_m linking frame m to its predecessor (the
    smoothness factor; :meth:`~bayes_talk.posterior.particle_gibbs.FrameFactors.link_logf`).
    With the modes' ``neighbours`` the components are conditioned on the pair's outer
    smoothness factors (:func:`neighbour_adjusted`: block [s, m)'s modes on the factor from
    x_{s−1}, block [m, e)'s on the one into x_e) and π recomputed from them at every update; the
    proposal still depends on the neighbours only. Otherwise it is fixed before sampling. The
    uniform δ share keeps every pair of modes proposed. Pairs where either block has no mode are
    left out (``pairs``: the groups kept)."""

    def __init__(self, modes: BlockModeProposal, pairs):
        self.modes, self.ff, self.delta, self.groups = modes, modes.ff, modes.delta, {}
        for (s, m), (m2, e) in pairs:
            if m != m2:
                raise ValueError(f"a pair needs consecutive blocks, got [{s}, {m}) and [{m2}, {e})")
            if s not in modes.modes or m not in modes.modes:
                continue
            self.groups[(s, e)] = (m,)
        self.refresh()
        self.pairs = list(self.groups)

    @property
    def adapting(self) -> bool:
        """Whether the modes' weights are being learnt (:meth:`BlockModeProposal.begin_adaptation`)."""
        return self.modes.adapting

    def record(self, s: int, e: int, Y: np.ndarray, lw: np.ndarray, x_starts: np.ndarray) -> None:
        """While the modes adapt, tally one update of the group [s, e): each start's tries
        Y[:, 0], Y[:, 1] with the joint log weights and its value after the update, x_starts
        (2, d) (:meth:`BlockModeProposal.record`)."""
        m = self.groups[(s, e)][0]
        self.modes.record(s, Y[:, 0], lw, x_starts[0])
        self.modes.record(m, Y[:, 1], lw, x_starts[1])

    def refresh(self) -> None:
        """Each group's components and pair weights π from the modes' current weights (at
        construction, and after the modes' weights were learnt)."""
        for (s, e), (m, *_) in list(self.groups.items()):
            (a, La, lwa), (b, Lb, lwb) = self.modes.modes[s], self.modes.modes[m]
            self.groups[(s, e)] = (m, a, La, b, Lb, self._pair_weights(s, m, a, lwa, b, lwb))

    def _pair_weights(self, s: int, m: int, a: np.ndarray, lwa: np.ndarray, b: np.ndarray,
                      lwb: np.ndarray) -> np.ndarray:
        """ln π'_kl (K_a, K_b) of the pair [s, m), [m, e) with components a, b of log weights lwa, lwb."""
        end = a
        for u in range(s + 1, m):
            end, _ = self.ff.dynamics_mean_sd(u, end)
        link = self.ff.link_logf(m, np.repeat(end, len(b), 0), np.tile(b, (len(a), 1))).reshape(len(a), len(b))
        lp = lwa[:, None] + lwb[None] + link
        return np.logaddexp(np.log1p(-self.delta) + lp - logsumexp(lp), np.log(self.delta) - np.log(lp.size))

    def sample_starts(self, s: int, e: int, N: int, rng: np.random.Generator, ref: np.ndarray | None = None,
                      x_prev: np.ndarray | None = None, x_next: np.ndarray | None = None
                      ) -> tuple[np.ndarray, np.ndarray]:
        """N draws (N, 2, d) of the group [s, e)'s two starts and their ln q (N,); ``ref`` (2, d):
        the last draw replaced by it before ln q is evaluated; ``x_prev``, ``x_next`` (d,): the
        frames before and after the group (None at the ends or when unknown), read with the
        modes' ``neighbours``."""
        m, a, La, b, Lb, lp = self.groups[(s, e)]
        if self.modes.neighbours:
            a, La, lwa = self.modes.components(s, x_prev, None)
            b, Lb, lwb = self.modes.components(m, None, x_next)
            lp = self._pair_weights(s, m, a, lwa, b, lwb)
        d = self.ff.d
        kl = rng.choice(lp.size, size=N, p=np.exp(lp.ravel()))
        k, l = np.divmod(kl, lp.shape[1])
        Y = np.stack([a[k] + np.einsum("nij,nj->ni", La[k], rng.standard_normal((N, d))),
                      b[l] + np.einsum("nij,nj->ni", Lb[l], rng.standard_normal((N, d)))], 1)
        if ref is not None:
            Y[-1] = ref
        ga, gb = component_logpdf(Y[:, 0], a, La), component_logpdf(Y[:, 1], b, Lb)
        return Y, logsumexp(lp[None] + ga[:, :, None] + gb[:, None, :], axis=(1, 2))


def adjacent_pairs(blocks) -> list[tuple[tuple[int, int], tuple[int, int]]]:
    """The pairs of consecutive blocks [s, m), [m, e) of ``blocks`` (:func:`dynamics_blocks`)."""
    return [(b1, b2) for b1, b2 in itertools.pairwise(blocks) if b1[1] == b2[0]]


def neighbour_adjusted(ff, s: int, e: int, m: np.ndarray, P: np.ndarray, lw: np.ndarray,
                       x_prev: np.ndarray | None, x_next: np.ndarray | None):
    """Gaussian components N(m_k, P_k⁻¹) with weights w_k (a block's own modes, Laplace
    precisions P_k) conditioned on the block's smoothness factors, linearised at m_k. The
    block [s, e)'s full conditional is its own factor G_s × the smoothness factor at s,
    ln N(ȳ_s; μ_s(x), V_s) (ȳ_s = the previous state's visual prediction at x_{s−1} plus the
    factor's u_s, μ_s and V_s the visual predictive of x with the motion variance added) × the
    one at e, ln N(ȳ_e(x); μ_e, V_e) (ȳ_e from the end c(x) of the path the dynamics means
    continue from x, μ_e and V_e at the fixed x_e). With both means linear in x near m_k
    (Jacobians H by central differences) and V at m_k, each component is a linear-Gaussian
    model with observation z = H x + ε, ε ~ N(0, V), whose posterior and evidence are exact:

        P'_k = P_k + Hᵀ V⁻¹ H,   m'_k = m_k + P'_k⁻¹ Hᵀ V⁻¹ r_k,   r_k the residual at m_k,
        ln w'_k = ln w_k − ½ r_kᵀ V⁻¹ r_k + ½ bᵀ P'_k⁻¹ b − ½ ln det V + ½ ln det P_k − ½ ln det P'_k,
        b = Hᵀ V⁻¹ r_k (the evidence by the determinant lemma; its 2π constant cancels).

    Everything is a deterministic function of the neighbours (x_{s−1}, x_e), not of the block,
    so a proposal built from it stays an independence proposal for :func:`block_mtm`. A
    factor that is absent (no smoothness factor, or the neighbour unknown) is left out.
    Returns (m' (K, d), P' (K, d, d), ln w' normalised (K,))."""
    tm, d, K = ff.tm, ff.d, len(m)
    h = 1e-6
    rows = np.concatenate([m[:, None, :] + h * np.concatenate([np.eye(d), -np.eye(d)])[None], m[:, None, :]], 1)
    rows = rows.reshape(-1, d)                                    # per mode: +h e_j, −h e_j, m_k
    Hs, rs, vs = [], [], []

    def add(pred, y, var):                                        # pred (K·(2d+1), D): a mean linear in x
        pred = pred.reshape(K, 2 * d + 1, -1)
        Hs.append(np.swapaxes((pred[:, :d] - pred[:, d:2 * d]) / (2 * h), 1, 2))   # (K, D, d)
        rs.append(y - pred[:, -1])
        vs.append(var)

    if s in ff.smooth and x_prev is not None:
        gp, gv = ff.smooth[s]
        zp, _ = tm.vis_gps.mean_var(Runs.one(gp, 1), np.ascontiguousarray(x_prev[None], dtype=np.float64))
        mu, sv = tm.vis_gps.mean_var(Runs.one(gv, len(rows)), rows)
        var = sv.reshape(K, 2 * d + 1)[:, -1:] / tm.vis_gps.w2[gv][None] + tm.motion_var[None]
        add(mu, (zp + ff.smooth_shift[s])[0][None], var)
    if e < ff.T and e in ff.smooth and x_next is not None:
        gp, gv = ff.smooth[e]
        c = rows
        for u in range(s + 1, e):
            c, _ = tm.dyn_gps.mean_var(Runs.one(ff.dyn_gp[u], len(c)), np.ascontiguousarray(c))
        zp, _ = tm.vis_gps.mean_var(Runs.one(gp, len(c)), np.ascontiguousarray(c))
        mu, sv = tm.vis_gps.mean_var(Runs.one(gv, 1), np.ascontiguousarray(x_next[None], dtype=np.float64))
        var = sv[:, None] / tm.vis_gps.w2[gv][None] + tm.motion_var[None]
        # ȳ_e(x) = zp(c(x)) + u_e against μ_e: the prediction zp(c(x)), the observed value μ_e − u_e
        add(zp, (mu - ff.smooth_shift[e])[0][None], np.broadcast_to(var, (K, var.shape[1])))
    if not Hs:
        return m, P, lw
    H = np.concatenate(Hs, 1)                                      # (K, D_tot, d)
    r = np.concatenate(rs, 1)                                      # (K, D_tot)
    iv = 1.0 / np.concatenate(vs, 1)
    Pn = P + np.einsum("kai,ka,kaj->kij", H, iv, H)
    b = np.einsum("kai,ka->ki", H, iv * r)
    Lp = np.linalg.cholesky(Pn)
    step = np.linalg.solve(Pn, b[..., None])[..., 0]
    lwn = (lw - 0.5 * (r * r * iv).sum(1) + 0.5 * (b * step).sum(1) + 0.5 * np.log(iv).sum(1)
           + 0.5 * np.linalg.slogdet(P)[1] - np.log(np.diagonal(Lp, axis1=1, axis2=2)).sum(1))
    return m + step, Pn, lwn - logsumexp(lwn)


def dynamics_blocks(ff, max_len: int = 1) -> list[tuple[int, int]]:
    """The blocks [s, e) of at most ``max_len`` frames: a frame s with no dynamics factor into
    it and the frames s + 1 … e − 1 that follow it through the dynamics, e the next frame
    without one (or T). ``max_len`` = 1: the isolated frames (no dynamics on either side;
    one-frame blocks of a state model without dynamics, coupled to their neighbours by
    smoothness factors only); inside a longer run the noise 10⁻⁶ pins a frame to its
    neighbours, so a run moves only as a whole."""
    out, s = [], 0
    for t in range(1, ff.T + 1):
        if t == ff.T or t not in ff.dyn_gp:
            if t - s <= max_len:
                out.append((s, t))
            s = t
    return out


__all__ = ["BlockModeProposal", "PairModeProposal", "adjacent_pairs", "block_factor", "block_mtm",
           "dynamics_blocks", "factor_modes", "neighbour_adjusted", "own_modes"]
