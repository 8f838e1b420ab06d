"""Initial latent trajectories for new audio (deena2010 §4.2; docs/switching.md), behind one interface.

An initialiser is a callable ``(model, view, Y) -> X0`` with ``model`` a fitted
:class:`~bayes_talk.models.sgpdm.SGPDM`, ``Y`` the (T, D) new observations of ``view``
and ``X0`` a (T, d) array:

* :class:`NearestNeighbour` (deena2010 §4.2.2): x*_t is the training latent point whose
  frame of ``view`` is closest to ŷ_t, distances measured in the model's own scaling
  (each dimension multiplied by its learned w_m).
* :class:`BackConstraint` ("SGPLVM A", deena2009): X* = g(Ŷ; φ).
* :class:`HMMViterbi` ("SGPLVM B", deena2009 §4.2): hidden states are M training
  latent points (a seeded random subset when N > M); transition log-probabilities are
  the dynamics log-density ln N(x_j; μ_x(x_i), σ²_x(x_i) I), normalised over j for each
  i; emission log-probabilities are ln p(ŷ_t | x_j); the Viterbi path in log space gives
  X0. Without dynamics the transitions are uniform.
"""
from __future__ import annotations

import weakref
from typing import TYPE_CHECKING, Protocol

import numpy as np
import torch
from scipy.special import logsumexp

if TYPE_CHECKING:
    from bayes_talk.models.sgpdm import SGPDM


class Initialiser(Protocol):
    """``(model, view, Y) -> X0``: a (T, d) start for the latents of new observations."""

    def __call__(self, model: SGPDM, view: str, Y: np.ndarray) -> np.ndarray: ...


class NearestNeighbour:
    """Nearest training frame in the model's scaling (deena2010 §4.2.2)."""

    def __call__(self, model: SGPDM, view: str, Y: np.ndarray) -> np.ndarray:
        p = model.predictors_[view]
        w = p.w.numpy()
        train = (p.Y.numpy() + p.mean.numpy()) * w
        new = np.asarray(Y, dtype=np.float64) * w
        d2 = (new * new).sum(1)[:, None] + (train * train).sum(1)[None, :] - 2.0 * new @ train.T
        return model.X_[np.argmin(d2, axis=1)].copy()


class BackConstraint:
    """The back-constraint mapping X* = g(Ŷ; φ) ("SGPLVM A", deena2009)."""

    def __call__(self, model: SGPDM, view: str, Y: np.ndarray) -> np.ndarray:
        bc = model.backconstraint
        if bc is None or model.config.back_constraint != view:
            raise ValueError(
                f"the back-constraint initialiser needs a model back-constrained on view {view!r} "
                f"(this one: {model.config.back_constraint!r})"
            )
        Yc = torch.as_tensor(np.asarray(Y, dtype=np.float64) - model.means_[view])
        with torch.no_grad():
            return bc(Yc).numpy()


def viterbi(log_start: np.ndarray, log_trans: np.ndarray, log_emit: np.ndarray) -> np.ndarray:
    """Most likely state path (T,) of an HMM given log start (M,), transition (M, M) and
    emission (T, M) probabilities."""
    T, M = log_emit.shape
    delta = log_start + log_emit[0]
    back = np.empty((T, M), dtype=np.int64)
    for t in range(1, T):
        scores = delta[:, None] + log_trans
        back[t] = np.argmax(scores, axis=0)
        delta = scores[back[t], np.arange(M)] + log_emit[t]
    path = np.empty(T, dtype=np.int64)
    path[-1] = int(np.argmax(delta))
    for t in range(T - 1, 0, -1):
        path[t - 1] = back[t, path[t]]
    return path


#: per-model caches of :class:`HMMViterbi` (states, transitions, emission parameters); they
#: depend only on the fitted model and go when it does
_HMM_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


class HMMViterbi:
    """Viterbi path over a subset of training latent points ("SGPLVM B", deena2009 §4.2)."""

    def __init__(self, n_states: int = 300, seed: int = 0):
        self.n_states = n_states
        self.seed = seed

    def _states(self, model: SGPDM) -> tuple[np.ndarray, np.ndarray]:
        """Hidden states (indices of training latents) and the log transition matrix. They
        do not depend on the new audio: computed once per model and cached on it."""
        cache = _HMM_CACHE.setdefault(model, {})
        key = (self.n_states, self.seed)
        if key not in cache:
            N = model.X_.shape[0]
            rng = np.random.default_rng(self.seed)
            idx = np.sort(rng.choice(N, self.n_states, replace=False)) if N > self.n_states else np.arange(N)
            S = torch.as_tensor(model.X_[idx])
            M = len(idx)
            dyn = model.dynamics_predictor_
            if dyn is not None:
                # trans[i, j] = ln p(x_j | x_i): the dynamics predictive at the M states once,
                # broadcast against every target (M x M x d; the M² (input, output) pairs
                # would take M² x N kernel rows, ~4 GB at M = 300, N = 1500)
                with torch.no_grad():
                    mu, var = dyn.mean_var(S)
                    trans = dyn.log_density(S[None, :, :], mu[:, None, :], var[:, None]).numpy()
                trans = trans - logsumexp(trans, axis=1, keepdims=True)
            else:
                trans = np.full((M, M), -np.log(M))
            cache[key] = (idx, trans)
        return cache[key]

    def _emission_params(self, model: SGPDM, view: str) -> tuple[torch.Tensor, torch.Tensor]:
        """Predictive mean (M, D) and variance (M,) of ``view`` at the hidden states (cached)."""
        cache = _HMM_CACHE.setdefault(model, {})
        key = (self.n_states, self.seed, view)
        if key not in cache:
            idx, _ = self._states(model)
            with torch.no_grad():
                cache[key] = model.predictors_[view].mean_var(torch.as_tensor(model.X_[idx]))
        return cache[key]

    def __call__(self, model: SGPDM, view: str, Y: np.ndarray) -> np.ndarray:
        idx, trans = self._states(model)
        mu, var = self._emission_params(model, view)
        Yt = torch.as_tensor(np.asarray(Y, dtype=np.float64))
        with torch.no_grad():  # emission ln p(ŷ_t | x_j) for every (t, j): a (T, M) table
            emit = model.predictors_[view].log_density(Yt[:, None, :], mu[None], var).numpy()
        start = np.full(len(idx), -np.log(len(idx)))
        return model.X_[idx[viterbi(start, trans, emit)]].copy()


INITIALISERS: dict[str, type] = {
    "nn": NearestNeighbour,
    "back-constraint": BackConstraint,
    "hmm": HMMViterbi,
}


def initialise(name: str, model: SGPDM, view: str, Y: np.ndarray) -> np.ndarray:
    """Run the initialiser registered under ``name`` (see :data:`INITIALISERS`)."""
    if name not in INITIALISERS:
        raise ValueError(f"unknown initialiser {name!r}; choose one of {sorted(INITIALISERS)}")
    return INITIALISERS[name]()(model, view, Y)
