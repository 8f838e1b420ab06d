"""Multiple-try updates of single frames given their neighbours (issue 24, after the sweep).

``ff`` below is a :class:`~bayes_talk.synthesis.particle_gibbs.FrameFactors` and a proposal
anything with its ``sample_logq(t, Xprev, N, rng, X=None) -> (X, ln q)``, e.g.
:class:`~bayes_talk.synthesis.particle_gibbs.MixtureProposal` (not imported: that module's
particle Gibbs move imports this one).

The synthesis density is Markov over frames (:mod:`bayes_talk.synthesis.particle_gibbs`,
(1)), so frame t's full conditional given its neighbours is

    π_t(x_t) ∝ exp(f_t(x_{t−1}, x_t) + f_{t+1}(x_t, x_{t+1})).

:func:`frame_mtm` updates a frame from π_t by independence multiple-try Metropolis (Liu,
Liang & Wong 2000), its tries from a proposal that does not depend on x_t; the particle Gibbs
move (:class:`~bayes_talk.synthesis.particle_gibbs.ParticleGibbsMove`, ``frame_tries``)
applies it to the isolated frames (:func:`isolated_frames`) after each sweep. The tries come
from the sweep's own proposal or from :class:`FrameModeProposal`: the Laplace approximations
at the local maxima of the frame's own factor g_t(x) = ln p_π(ŷ_t | x) + [entry] ln N(x; μ_π,
Σ_π) (:func:`frame_modes`) — at an isolated frame the marginal is a mixture of narrow,
separated bumps there (docs/uncertainty.md, "The isolated frames' own modes").
"""
from __future__ import annotations

import numpy as np
from scipy.special import logsumexp

from bayes_talk.synthesis.segment_objective import LOG_2PI


def frame_mtm(ff, q, x: np.ndarray, frames, K: int, rng: np.random.Generator,
              _broken: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Multiple-try Metropolis updates of single frames given their neighbours (Liu, Liang &
    Wong 2000, with independent proposals): for each t in ``frames`` in turn, the full
    conditional π_t(x_t) ∝ exp(f_t(x_{t−1}, x_t) + f_{t+1}(x_t, x_{t+1})) of (1) (the density is
    Markov), K tries y_k ~ q_t(· | x_{t−1}) — independent of x_t, so the move is an
    independence MTM — w_k = π_t(y_k)/q_t(y_k), y = y_J with probability ∝ w_J, accepted with
    probability min(1, Σ_k w_k / (Σ_k w_k − w_J + w(x_t))). Each update leaves π_t, hence
    p(X | Ŷ), invariant. Returns the new path and, per frame of ``frames``, whether it moved.
    (``_broken``: accept always — not invariant; the tests' control.)"""
    x = np.array(x, dtype=np.float64, copy=True)
    T = ff.T
    moved = np.zeros(len(frames), dtype=bool)
    for i, t in enumerate(frames):
        prev = None if t == 0 else np.repeat(x[t - 1][None], K + 1, 0)
        Y, lq = q.sample_logq(t, None if prev is None else prev[:K], K, rng)
        _, lq_x = q.sample_logq(t, None if prev is None else prev[:1], 1, rng, x[t][None])
        C = np.vstack([Y, x[t][None]])                                   # the K tries and the current value
        lw = ff.log_f(t, prev, C)
        if t + 1 < T:
            lw = lw + ff.log_f(t + 1, C, np.repeat(x[t + 1][None], K + 1, 0))
        lw = lw - np.concatenate([lq, lq_x])
        j = rng.choice(K, p=np.exp(lw[:K] - logsumexp(lw[:K])))
        s_y = logsumexp(lw[:K])
        s_x = logsumexp(np.concatenate([np.delete(lw[:K], j), lw[K:]]))
        if _broken or np.log(rng.random()) < s_y - s_x:
            x[t] = Y[j]
            moved[i] = True
    return x, moved


def frame_modes(ff, t: int, starts: np.ndarray, n_iter: int = 40, max_step: float = 0.05,
                max_modes: int = 32) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Local maxima of frame t's own factor g_t (:meth:`~bayes_talk.synthesis.particle_gibbs.FrameFactors.own_factor`) and their Laplace
    approximations: damped Newton ascent from every row of ``starts`` at once (Hessian by
    central differences of the analytic gradient; steps capped at ``max_step``, halved until
    g_t rises; a gradient step where the Hessian is not negative definite), then maxima closer
    than one standard deviation (Mahalanobis, in the heavier one's covariance) merged (the
    lighter dropped); a point whose Hessian is not clearly negative definite is no maximum. Returns
    the means (K, d), covariances Σ_k = (−∇²g_t)⁻¹ (K, d, d) and log weights ln w_k =
    g_t(m_k) + ½ ln det Σ_k normalised (each maximum's Laplace mass), the ``max_modes`` heaviest."""
    X = np.array(starts, dtype=np.float64, copy=True)
    d, h = ff.d, 1e-6
    eye = np.eye(d)

    def hessian(X):
        H = np.stack([(ff.own_factor(t, X + h * eye[j])[1] - ff.own_factor(t, X - h * eye[j])[1]) / (2 * h)
                      for j in range(d)], axis=1)
        return 0.5 * (H + np.swapaxes(H, 1, 2))

    g, gx = ff.own_factor(t, X)
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
            g1, gx1 = ff.own_factor(t, Xa + step)
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
    X, g, lam, U, H = X[ok], g[ok], lam[ok], U[ok], H[ok]
    if not len(X):
        return np.empty((0, d)), np.empty((0, d, d)), np.empty(0)
    S = np.einsum("kij,kj,klj->kil", U, 1.0 / lam, U)
    S = 0.5 * (S + np.swapaxes(S, 1, 2))
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


class FrameModeProposal:
    """An independence proposal for the multiple-try update of an isolated frame t
    (:func:`frame_mtm`): q_t(x | x_{t−1}) = (1 − δ) Σ_k w_k N(x; m_k, s² Σ_k) + δ q⁰_t(x | x_{t−1})
    with (m_k, Σ_k, w_k) the Laplace approximations at the local maxima of the frame's own
    factor (:func:`frame_modes`, found once, from the frame's proposal centres: its state
    model's training latents and any extra centres; with ``n_starts`` only that many, those of
    highest audio × entry weight) and q⁰ the sweep's proposal
    (:class:`MixtureProposal`) as the defensive component. The isolated frames' marginals are
    mixtures of narrow, separated bumps (on the toy utterance frame 63's chain draws sit in
    clusters near −0.13 and −0.03, each ~0.01 wide, and switch every ~30 draws): tries from
    the bumps themselves land in them. q_t is fixed before sampling and evaluated exactly.
    Frames without a maximum found fall back to q⁰ alone."""

    def __init__(self, base, frames, delta: float = 0.2, scale: float = 1.5,
                 n_starts: int | None = None):
        if not 0 < delta <= 1 or scale <= 0 or (n_starts is not None and n_starts < 1):
            raise ValueError(f"FrameModeProposal needs 0 < delta <= 1, scale > 0 and n_starts >= 1, got {delta}, "
                             f"{scale}, {n_starts}")
        self.base, self.ff, self.delta, self.scale = base, base.ff, float(delta), float(scale)
        self.modes = {}
        for t in frames:   # ascend from the n_starts centres of highest audio × entry weight (None: all)
            m, S, lw = frame_modes(self.ff, t, base.centres[t][np.argsort(-base.logw[t], kind="stable")[:n_starts]])
            if len(m):
                L = np.linalg.cholesky(S * self.scale ** 2)
                self.modes[t] = (m, L, lw)

    def sample_logq(self, t: int, Xprev: np.ndarray | None, N: int, rng: np.random.Generator,
                    X: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """N draws of q_t given the neighbour Xprev (N, d) (or the given X) and their ln q_t (N,)."""
        if t not in self.modes:
            return self.base.sample_logq(t, Xprev, N, rng, X)
        m, L, lw = self.modes[t]
        d = self.ff.d
        if X is None:
            X, _ = self.base.sample_logq(t, Xprev, N, rng)
            mine = rng.random(N) >= self.delta
            k = rng.choice(len(m), size=int(mine.sum()), p=np.exp(lw))
            X[mine] = m[k] + np.einsum("kij,kj->ki", L[k], rng.standard_normal((len(k), d)))
        _, lq0 = self.base.sample_logq(t, Xprev, N, rng, X)
        z = np.linalg.solve(L[None], (X[:, None, :] - m[None])[..., None])[..., 0]        # (N, K, d)
        lg = -0.5 * (z * z).sum(-1) - np.log(np.diagonal(L, axis1=1, axis2=2)).sum(1)[None] - 0.5 * d * LOG_2PI
        lm = logsumexp(lw[None] + lg, axis=1)
        if self.delta == 1.0:
            return X, lq0
        return X, np.logaddexp(np.log1p(-self.delta) + lm, np.log(self.delta) + lq0)


def isolated_frames(ff) -> list[int]:
    """Frames with no dynamics factor into them or out of them (one-frame blocks of a state
    model without dynamics, coupled to their neighbours by smoothness factors only): the
    frames whose full conditional :func:`frame_mtm` samples well (inside a dynamics run the
    noise 10⁻⁶ pins a frame to its neighbours)."""
    return [t for t in range(ff.T) if t not in ff.dyn_gp and t + 1 not in ff.dyn_gp]


__all__ = ["FrameModeProposal", "frame_modes", "frame_mtm", "isolated_frames"]
