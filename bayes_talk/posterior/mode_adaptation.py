"""What a block's multiple-try updates learn about its full conditional during a sampler's
warm-up: each own mode's mass and, optionally, its mean and covariance.

A block's own-mode proposal (:class:`~bayes_talk.posterior.frame_updates.BlockModeProposal`)
places its components at the Laplace approximations of the block's *own* factor, which leaves
out the smoothness factors at the block's two ends. Where those decide, the full conditional
weighs the modes differently (held-out ``utt0002``: the utterance-start block sits at a mode of
own weight ≈ 0) and sits elsewhere within a mode (its frame 51: 3.7–5.7 own-factor sd away in
two coordinates and up to 4× wider; docs/uncertainty.md "Which sampler").

:class:`ModeTally` sums, over the warm-up's updates of one block, two estimates of the full
conditional π restricted to each mode k, with r_k(y) the responsibility of mode k for y under
the own modes' Laplace approximations with equal weights:

    the tries' self-normalised importance estimate   Σ_i w̄_i r_k(y_i) φ(y_i),
    the chain's own state after the update            r_k(x_s) φ(x_s),

each with weight ½, for φ(y) = 1 (the mass), y (the first moment) and y yᵀ (the second). The
first sees modes the chain has not reached yet; the second, modes the tries rarely land in.
Their means over the updates give the learnt weights M̄_k (:meth:`ModeTally.masses`) and, where
a mode has gathered enough mass, its mean and covariance under π (:meth:`ModeTally.moments`).
Because the neighbours move during the warm-up, these describe the conditional averaged over the
neighbours' states — wider than any one conditional, which an independence proposal tolerates.
Everything here is frozen before the kept draws, so the updates stay posterior-invariant.
"""
from __future__ import annotations

import numpy as np
from scipy.special import logsumexp

from bayes_talk.synthesis.segment_objective import LOG_2PI

#: the mass (in updates' worth, summed over the warm-up) a mode needs before its mean and
#: covariance under the full conditional are trusted (:meth:`ModeTally.moments`)
MIN_MOMENT_MASS = 20.0
#: the learnt covariance is floored by this fraction of the own Laplace covariance, so that a
#: moment estimate resting on a few heavy importance weights is never narrower than a tenth of
#: the own mode's sd in any direction
OWN_COVARIANCE_FLOOR = 0.01
#: the most Gaussian components fitted to a block's warm-up states (:meth:`ModeTally.clusters`;
#: the number chosen by BIC from 1 to this)
MAX_CLUSTERS = 3
#: the fewest warm-up states (pooled over the chains, second halves) a block needs for clusters
MIN_CLUSTER_STATES = 50
#: the share of a block's own-mode mixture given to its state clusters (:meth:`LearntModes._set_weights`)
CLUSTER_SHARE = 0.25


class ModeTally:
    """Sums over the warm-up's updates of one block of the full conditional's mass, first and
    second moments at each of its K own modes (module docstring): ``mass`` (K,), ``first``
    (K, d), ``second`` (K, d, d), ``n`` the updates recorded."""

    def __init__(self, K: int, d: int):
        self.mass = np.zeros(K)
        self.first = np.zeros((K, d))
        self.second = np.zeros((K, d, d))
        self.n = 0
        self.states: list[np.ndarray] = []   # the chain's state after each update, in order
        self.trimmed = False                 # True: ``states`` are already the late halves (pooled)

    def add(self, Y: np.ndarray, w: np.ndarray, r: np.ndarray, x: np.ndarray, rx: np.ndarray) -> None:
        """One update: its tries Y (N, d) with normalised importance weights w (N,) and
        responsibilities r (N, K), the state x (d,) after the update with responsibilities rx (K,)."""
        a = 0.5 * w[:, None] * r
        b = 0.5 * rx
        self.mass += a.sum(0) + b
        self.first += a.T @ Y + b[:, None] * x[None]
        self.second += np.einsum("nk,ni,nj->kij", a, Y, Y) + b[:, None, None] * np.outer(x, x)[None]
        self.n += 1
        self.states.append(np.array(x, dtype=np.float64))

    def late_states(self) -> np.ndarray:
        """The states recorded in the second half of the warm-up (M, d) — of each chain when
        pooled — away from the chains' overdispersed starts."""
        if self.trimmed:
            return np.array(self.states).reshape(len(self.states), -1)
        late = self.states[len(self.states) // 2:]
        return np.array(late).reshape(len(late), self.first.shape[1])

    @classmethod
    def pooled(cls, tallies: list[ModeTally]) -> ModeTally:
        """One tally of all the updates of ``tallies`` (the chains' warm-ups of one block, in
        chain order): their sums and counts added."""
        out = cls(*tallies[0].first.shape)
        for t in tallies:
            if t.first.shape != out.first.shape:
                raise ValueError(f"cannot pool tallies of {t.first.shape} and {out.first.shape} (modes, d)")
            out.mass += t.mass
            out.first += t.first
            out.second += t.second
            out.n += t.n
            out.states.extend(t.late_states())
        out.trimmed = True
        return out

    def masses(self) -> np.ndarray:
        """M̄ (K,): each mode's mass under the full conditional, the mean over the updates of the
        two estimates (sums to 1 when every try and state is assigned to a mode)."""
        return self.mass / max(self.n, 1)

    def moments(self, own_cov: np.ndarray, min_mass: float = MIN_MOMENT_MASS,
                floor: float = OWN_COVARIANCE_FLOOR) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The modes k whose summed mass is ≥ ``min_mass`` (indices (J,)), their means
        μ_k = Σ φ=y / Σ φ=1 (J, d) and covariances C_k = Σ yyᵀ / Σ 1 − μ_k μ_kᵀ + ``floor`` × the
        own Laplace covariance ``own_cov`` (K, d, d) (J, d, d), symmetrised; modes whose C_k is not
        positive definite are left out."""
        idx = np.flatnonzero(self.mass >= min_mass)
        mu = self.first[idx] / self.mass[idx, None]
        C = self.second[idx] / self.mass[idx, None, None] - np.einsum("ki,kj->kij", mu, mu)
        C = 0.5 * (C + np.swapaxes(C, 1, 2)) + floor * own_cov[idx]
        ok = np.array([np.all(np.isfinite(c)) and np.linalg.eigvalsh(c)[0] > 0 for c in C], dtype=bool)
        return idx[ok], mu[ok], C[ok]

    def clusters(self, own_cov: np.ndarray, max_k: int = MAX_CLUSTERS, min_states: int = MIN_CLUSTER_STATES,
                 floor: float = OWN_COVARIANCE_FLOOR, seed: int = 0):
        """A Gaussian mixture fitted to :meth:`late_states` (scikit-learn's ``GaussianMixture``,
        full covariances, 1 to ``max_k`` components chosen by BIC, seeded): its means (J, d),
        covariances (J, d, d) (+ ``floor`` × ``own_cov`` (d, d)) and weights (J,); None with
        fewer than ``min_states`` states. The modes the chains' warm-ups visited, including
        those of the full conditional that are no mode of the block's own factor (held-out
        `utt0002`'s utterance-start block: a second region, made by the smoothness factor into
        the next block, that earlier kernels' chains over-stayed in and that holds 0–1.4 % of
        each chain's draws once the clusters are proposed; docs/uncertainty.md "Clusters of the
        warm-up states")."""
        from sklearn.mixture import GaussianMixture

        X = self.late_states()
        if len(X) < min_states or not np.all(np.isfinite(X)):
            return None
        fits = [GaussianMixture(k, covariance_type="full", random_state=seed, reg_covar=1e-9).fit(X)
                for k in range(1, min(max_k, len(np.unique(X, axis=0))) + 1)]
        best = min(fits, key=lambda g: g.bic(X))
        C = 0.5 * (best.covariances_ + np.swapaxes(best.covariances_, 1, 2)) + floor * own_cov[None]
        return best.means_, C, best.weights_


def component_logpdf(X: np.ndarray, m: np.ndarray, L: np.ndarray) -> np.ndarray:
    """ln N(x_i; m_k, L_k L_kᵀ) for rows X (N, d), means m (K, d), Cholesky factors L (K, d, d) → (N, K)."""
    z = np.linalg.solve(L[None], (X[:, None, :] - m[None])[..., None])[..., 0]        # (N, K, d)
    return -0.5 * (z * z).sum(-1) - np.log(np.diagonal(L, axis1=1, axis2=2)).sum(1)[None] - 0.5 * X.shape[1] * LOG_2PI


class LearntModes:
    """The warm-up adaptation of an own-mode proposal
    (:class:`~bayes_talk.posterior.frame_updates.BlockModeProposal` inherits it). It reads and
    sets the proposal's ``laplace`` (per block start: the own modes' means, precisions, log
    weights), ``modes`` (the components proposed: :meth:`_scaled` of them), ``own_weights``,
    ``ff``, ``learn_moments`` and ``learn_clusters``, and keeps ``tally`` (a :class:`ModeTally`
    per block while adapting), ``learnt`` (per block: the modes with learnt moments, their means
    and covariances), ``clustered`` (per block: the clusters of its warm-up states) and
    ``adapting``."""

    def _set_weights(self, s: int, lw: np.ndarray, share: float = 0.5) -> None:
        """Mode weights ``lw`` for block s; with moments learnt for some of its modes
        (``self.learnt[s]``: indices, means, covariances) each of those modes' weight is split,
        1 − ``share`` to its own Laplace component and ``share`` to a component at its learnt
        mean and covariance; with clusters of its warm-up states (``self.clustered[s]``: means,
        covariances, weights) those get :data:`CLUSTER_SHARE` of the whole and the modes the rest."""
        m, P, _ = self.laplace[s]
        self.laplace[s] = (m, P, lw)
        means, covs, lws = [m], [np.linalg.inv(P)], [lw.copy()]
        if s in self.learnt:
            idx, mu, C = self.learnt[s]
            lws[0][idx] += np.log1p(-share)
            means, covs, lws = means + [mu], covs + [C], lws + [lw[idx] + np.log(share)]
        if s in self.clustered:
            mu, C, w = self.clustered[s]
            lws = [v + np.log1p(-CLUSTER_SHARE) for v in lws]
            means, covs, lws = means + [mu], covs + [C], lws + [np.log(w) + np.log(CLUSTER_SHARE)]
        self.modes[s] = self._scaled(np.concatenate(means), np.concatenate(covs), np.concatenate(lws))

    def begin_adaptation(self) -> None:
        """Start learning the modes' weights (and with ``moments`` their means and covariances;
        a sampler's warm-up): the own factor's modes and weights restored, the tallies of
        :meth:`record` cleared. Until :meth:`end_adaptation` the proposal changes with the
        chain's history, so draws taken meanwhile are warm-up only."""
        self.learnt, self.clustered = {}, {}
        for s, lw in self.own_weights.items():
            self._set_weights(s, lw)
        self.tally = {s: ModeTally(len(lw), self.ff.d) for s, lw in self.own_weights.items()}
        self._laplace_chol = {s: np.linalg.cholesky(np.linalg.inv(P)) for s, (_, P, _) in self.laplace.items()}
        self.adapting = True

    def record(self, s: int, Y: np.ndarray, lw: np.ndarray, x_s: np.ndarray) -> None:
        """Tally one multiple-try update of block s while adapting: its tries Y (K, d) of the
        block's first frame, their log weights ln π − ln q (:func:`block_mtm`: the full
        conditional's) and the first frame x_s (d,) after the update. Two estimates of each
        mode's mass under the full conditional are summed over the updates: the
        self-normalised importance one, Σ_i w̄_i r_k(y_i) (w̄ the normalised weights), and the
        chain's own, r_k(x_s) — r_k(y) the responsibility of mode k for y under the modes' own
        Laplace approximations with equal weights. The first sees modes the chain has not
        reached yet; the second, modes the tries rarely land in (where the importance estimate
        rests on a handful of tries)."""
        if not self.adapting or s not in self.tally:
            return
        Yx = np.vstack([Y, np.reshape(x_s, (1, -1))]).astype(np.float64)
        lr = component_logpdf(Yx, self.laplace[s][0], self._laplace_chol[s])
        r = np.exp(lr - logsumexp(lr, axis=1, keepdims=True))
        w = np.exp(lw - logsumexp(lw))
        if np.all(np.isfinite(w)) and np.all(np.isfinite(r)) and np.all(np.isfinite(Yx)):
            self.tally[s].add(Yx[:-1], w, r[:-1], Yx[-1], r[-1])

    def end_adaptation(self, tallies: list[dict] | None = None, share: float = 0.5) -> None:
        """Freeze the weights learnt while adapting: w_k = (1 − share) M̄_k + share · w⁰_k, M̄
        the mean over the recorded updates of the two estimates of the full conditional's mode
        masses (:meth:`record`; :meth:`~bayes_talk.posterior.mode_adaptation.ModeTally.masses`),
        w⁰ the own factor's Laplace masses (kept so that every mode stays proposed). The own
        factor misses the smoothness factors at the block's two ends: on held-out `utt0002` the
        first block's chains sit at a mode of own weight ≈ 0. With ``moments``, every mode that
        gathered enough mass also gets a component at its mean and covariance under the full
        conditional (:meth:`~bayes_talk.posterior.mode_adaptation.ModeTally.moments`), with a
        ``share`` of its weight (:meth:`_set_weights`); with ``clusters``, a Gaussian mixture
        fitted to the warm-up's late states (:meth:`ModeTally.clusters`) joins them. ``tallies``: the ``tally`` dicts of
        several chains' warm-ups (:meth:`adaptation_state`), pooled block by block
        (:meth:`ModeTally.pooled`) in place of this proposal's own. From here the proposal is
        fixed again, so the updates leave the posterior invariant."""
        if tallies is not None:   # [] (no warm-up): nothing learnt, the own weights stay
            self.tally = {s: ModeTally.pooled([t[s] for t in tallies]) for s in self.own_weights} if tallies else {}
        for s, tally in self.tally.items():
            if tally.n:
                if self.learn_moments:
                    idx, mu, C = tally.moments(np.linalg.inv(self.laplace[s][1]))
                    if len(idx):
                        self.learnt[s] = (idx, mu, C)
                if self.learn_clusters:
                    own = np.linalg.inv(self.laplace[s][1])
                    found = tally.clusters(own[int(np.argmax(self.own_weights[s]))])
                    if found is not None:
                        self.clustered[s] = found
                w = (1 - share) * tally.masses() + share * np.exp(self.own_weights[s])
                self._set_weights(s, np.log(w / w.sum()), share)
        self.adapting = False

    def adaptation_state(self) -> dict[int, ModeTally]:
        """What this proposal's warm-up recorded so far: its :class:`ModeTally` per block start
        (picklable; :meth:`end_adaptation` pools several chains')."""
        return self.tally

    def weight_shift(self) -> dict[int, float]:
        """Per block s with modes, the total-variation distance ½ Σ_k |w_k − w⁰_k| between the
        current weights and the own factor's (0 before any adaptation)."""
        return {s: float(0.5 * np.abs(np.exp(self.laplace[s][2]) - np.exp(lw)).sum())
                for s, lw in self.own_weights.items()}


__all__ = ["CLUSTER_SHARE", "MAX_CLUSTERS", "MIN_CLUSTER_STATES", "MIN_MOMENT_MASS", "OWN_COVARIANCE_FLOOR", "LearntModes", "ModeTally", "component_logpdf"]
