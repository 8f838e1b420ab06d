"""Per-phone left-to-right Gaussian HMMs trained on segments with known boundaries.

Each phone p of the package's phone set (ARPAbet 39 + ``sil``) gets an
``hmmlearn.hmm.GaussianHMM`` with ``N_STATES = 3`` emitting states, diagonal covariances,
start in state 0 and left-to-right transitions (``a_ii`` stay, ``a_i,i+1`` move). It is
fitted by Baum-Welch on every training segment of p (its feature frames between the known
boundaries), initialised by a flat start (each segment cut into three equal parts; the
means and variances of the parts). Zero transitions stay zero under EM, so the topology
is kept.

Exit probability. Segments are fitted in isolation, so hmmlearn never sees the last state
being left; the exit probability of the last state is set to ``1 / d`` where d is the mean
number of frames the training segments spend in it (Viterbi state paths of the fitted
model, ``GaussianHMM.predict``): the geometric duration with the observed mean.

Emission log-likelihood of state s of phone p (diagonal Gaussian)::

    log b_ps(x) = -1/2 sum_d [ log(2 pi var_psd) + (x_d - mu_psd)^2 / var_psd ]

computed for all ``P * N_STATES`` states at once by matrix products
(:meth:`PhoneHMMs.log_emissions`). A floor ``VAR_FLOOR`` on the variances keeps the
digital silence of synthetic speech (constant features) from giving infinite densities.
"""
from __future__ import annotations

import logging
import warnings

import numpy as np

from bayes_talk.data.phones import PHONES

__all__ = ["N_STATES", "PhoneHMMs"]

log = logging.getLogger(__name__)

N_STATES = 3
VAR_FLOOR = 1e-2
_MIN_LOG = -1e30


class PhoneHMMs:
    """One left-to-right Gaussian HMM per phone (see the module docstring).

    Attributes after :meth:`fit`: ``means_`` and ``vars_`` (P, N_STATES, D), ``log_stay_``
    and ``log_move_`` (P, N_STATES) (``log_move_[:, -1]`` is the exit), ``counts_`` (P,)
    training segments per phone. ``phones`` is the phone order (default: the package's).
    """

    def __init__(self, n_iter: int = 8, seed: int = 0, phones: tuple[str, ...] = PHONES) -> None:
        self.n_iter = int(n_iter)
        self.seed = int(seed)
        self.phones = tuple(phones)

    # ------------------------------------------------------------------ fitting
    def fit(self, segments: dict[str, list[np.ndarray]]) -> PhoneHMMs:
        """Fit every phone's HMM on its list of (n_i, D) feature segments.

        A phone without segments gets the pooled mean/variance of all frames (and a
        warning), so decoding can still run; one with fewer than 3 frames in total too.
        """
        from hmmlearn.hmm import GaussianHMM

        all_frames = np.concatenate([s for segs in segments.values() for s in segs if len(s)])
        D = all_frames.shape[1]
        P, S = len(self.phones), N_STATES
        self.means_ = np.tile(all_frames.mean(axis=0), (P, S, 1))
        self.vars_ = np.tile(np.maximum(all_frames.var(axis=0), VAR_FLOOR), (P, S, 1))
        self.log_stay_ = np.full((P, S), np.log(0.5))
        self.log_move_ = np.full((P, S), np.log(0.5))
        self.counts_ = np.zeros(P, dtype=np.int64)
        for i, p in enumerate(self.phones):
            segs = [np.asarray(s, dtype=np.float64) for s in segments.get(p, []) if len(s) > 0]
            self.counts_[i] = len(segs)
            if sum(len(s) for s in segs) < 3 * S:
                warnings.warn(f"phone {p!r}: {sum(len(s) for s in segs)} training frames; "
                              "using the pooled model", RuntimeWarning, stacklevel=2)
                continue
            X = np.concatenate(segs)
            lengths = [len(s) for s in segs]
            # flat start: each segment cut into S equal parts
            parts = [[] for _ in range(S)]
            for s in segs:
                cuts = np.linspace(0, len(s), S + 1).round().astype(int)
                for k in range(S):
                    if cuts[k + 1] > cuts[k]:
                        parts[k].append(s[cuts[k]:cuts[k + 1]])
            mu = np.stack([np.concatenate(pp).mean(axis=0) if pp else X.mean(axis=0) for pp in parts])
            var = np.stack([np.concatenate(pp).var(axis=0) if pp and sum(map(len, pp)) > 1 else X.var(axis=0)
                            for pp in parts])
            m = GaussianHMM(n_components=S, covariance_type="diag", n_iter=self.n_iter, tol=1e-3,
                            min_covar=VAR_FLOOR, random_state=self.seed, init_params="",
                            params="tmc")
            m.startprob_ = np.eye(S)[0]
            A = np.zeros((S, S))
            for k in range(S):
                A[k, k] = 0.5 if k < S - 1 else 1.0
                if k < S - 1:
                    A[k, k + 1] = 0.5
            m.transmat_ = A
            m.means_ = mu
            m.covars_ = np.maximum(var, VAR_FLOOR)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                m.fit(X, lengths)
            path = m.predict(X, lengths)
            last_frames = int(np.sum(path == S - 1))
            n_last = sum(1 for start, n in zip(np.cumsum([0] + lengths[:-1]), lengths)
                         if np.any(path[start:start + n] == S - 1))
            d_last = last_frames / max(n_last, 1) if last_frames else 1.0
            T = np.asarray(m.transmat_)
            stay = np.clip(np.diag(T).copy(), 1e-3, 1 - 1e-3)
            stay[-1] = np.clip(1.0 - 1.0 / max(d_last, 1.0), 1e-3, 1 - 1e-3)
            self.means_[i] = m.means_
            self.vars_[i] = np.maximum(np.asarray(m._covars_ if hasattr(m, "_covars_") else m.covars_)
                                       .reshape(S, D), VAR_FLOOR)
            self.log_stay_[i] = np.log(stay)
            self.log_move_[i] = np.log1p(-stay)
        self._prepare()
        return self

    # ------------------------------------------------------------------ scoring
    def _prepare(self) -> None:
        P, S, D = self.means_.shape
        iv = 1.0 / self.vars_.reshape(P * S, D)
        mu = self.means_.reshape(P * S, D)
        self._iv = iv
        self._mu_iv = mu * iv
        self._const = -0.5 * (np.log(2 * np.pi * self.vars_.reshape(P * S, D)).sum(axis=1)
                              + (mu * mu * iv).sum(axis=1))

    def log_emissions(self, X: np.ndarray) -> np.ndarray:
        """(T, P * N_STATES) log b of every state (phone-major: column ``p * N_STATES + s``)."""
        X = np.asarray(X, dtype=np.float64)
        return self._const + X @ self._mu_iv.T - 0.5 * (X * X) @ self._iv.T

    # ------------------------------------------------------------------ persistence
    def arrays(self) -> dict[str, np.ndarray]:
        """The fitted HMM parameters as named arrays (for an NPZ)."""
        return {"hmm_means": self.means_, "hmm_vars": self.vars_, "hmm_log_stay": self.log_stay_,
                "hmm_log_move": self.log_move_, "hmm_counts": self.counts_}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], phones: tuple[str, ...]) -> PhoneHMMs:
        """Phone HMMs from :meth:`arrays` and their phone list."""
        self = cls(phones=tuple(phones))
        self.means_ = np.asarray(arrays["hmm_means"], dtype=np.float64)
        self.vars_ = np.asarray(arrays["hmm_vars"], dtype=np.float64)
        self.log_stay_ = np.asarray(arrays["hmm_log_stay"], dtype=np.float64)
        self.log_move_ = np.asarray(arrays["hmm_log_move"], dtype=np.float64)
        self.counts_ = np.asarray(arrays["hmm_counts"], dtype=np.int64)
        if self.means_.shape[:2] != (len(self.phones), N_STATES) or self.vars_.shape != self.means_.shape:
            raise ValueError(f"phone HMM arrays have shape {self.means_.shape}, expected "
                             f"({len(self.phones)}, {N_STATES}, D)")
        self._prepare()
        return self
