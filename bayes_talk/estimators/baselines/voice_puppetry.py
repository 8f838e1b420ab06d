"""Brand's Voice Puppetry (Brand 1999; englebienne2008 §3; deena2009 §4.3).

Training
--------
1. A Gaussian HMM (hmmlearn ``GaussianHMM``, K states, Baum-Welch) is fitted to the
   visual features with deltas, o_t = [z_t, Δz_t] (2 D_z), standardised per column.
   Initial state means: seeded k-means (scikit-learn) on the *static* part z only, each
   state starting at its cluster's mean of [z, Δz]; hmmlearn initialises start
   probabilities, transitions and covariances. (k-means on [z, Δz] tends to spend states
   on the few large-Δz frames at transitions.)
2. *Remapping*: with the facial-state posteriors γ_tk = p(s_t = k | O) of the training
   data (``predict_proba``), each state gets an audio emission

       m_k = Σ_t γ_tk a_t / Σ_t γ_tk,
       C_k = Σ_t γ_tk (a_t − m_k)(a_t − m_k)ᵀ / Σ_t γ_tk + ε I,

   where a_t = [y_t, Δy_t] (``audio_deltas=True``) or a_t = y_t. The audio HMM keeps the
   start probabilities and transition matrix of the visual HMM.

Synthesis
---------
3. The new audio is Viterbi-decoded with the audio HMM: s*_{1:T}.
4. The most likely visual trajectory given the path maximises
   Σ_t log N(W_t z; μ_{s*_t}, Σ_{s*_t}), where W = [I; Δ] stacks the identity and the
   delta operator. Setting the gradient to zero gives the normal equations

       (Wᵀ Σ⁻¹ W) z = Wᵀ Σ⁻¹ μ,                                            (VP)

   μ, Σ being the path's state means/covariances over [z, Δz]. The delta operator is a
   central difference with replicated end frames,
   Δz_t = (z_{t+1} − z_{t−1}) / 2, z_0 := z_1, z_{T+1} := z_T,
   so Wᵀ Σ⁻¹ W is banded (bandwidth 2 frames). With diagonal visual covariances (the
   default) the system decouples into D_z pentadiagonal T×T systems; with full
   covariances it is one block-banded TD×TD system (frame-major ordering, bandwidth
   3 D_z − 1). Both are solved with ``scipy.linalg.solveh_banded``: O(T D_z) time for
   diagonal and O(T D_z³) for full covariances, O(T) memory in T either way.

Brand's model defines no density over z alone (the [z, Δz] "distribution" double-counts,
englebienne2008 §3 and §4), so no test log-likelihood is offered.
"""
from __future__ import annotations

from typing import ClassVar, Literal, Self

import numpy as np
import scipy.linalg
import scipy.sparse as sp
from hmmlearn.hmm import GaussianHMM
from sklearn.cluster import KMeans

from bayes_talk.data.utterance import Utterance, check_test
from bayes_talk.estimators.baselines.base import Baseline, check_train

__all__ = [
    "VoicePuppetry",
    "delta_features",
    "delta_matrix",
    "sparse_to_upper_banded",
    "trajectory_solve",
]

CovType = Literal["diag", "full"]


def delta_matrix(T: int) -> sp.csr_matrix:
    """Central-difference delta operator Δ (T×T, sparse) with replicated end frames.

    Row t computes (z_{t+1} − z_{t−1}) / 2 with z_0 := z_1 and z_{T+1} := z_T (1-based);
    for T = 1 the single row is zero.
    """
    if T < 1:
        raise ValueError(f"T must be >= 1, got {T}")
    rows, cols, vals = [], [], []
    for t in range(T):
        lo, hi = max(t - 1, 0), min(t + 1, T - 1)
        if lo != hi:
            rows += [t, t]
            cols += [lo, hi]
            vals += [-0.5, 0.5]
    return sp.csr_matrix((vals, (rows, cols)), shape=(T, T))


def delta_features(z: np.ndarray) -> np.ndarray:
    """[z, Δz] (T, 2D) with Δ from :func:`delta_matrix`."""
    z = np.asarray(z, dtype=np.float64)
    return np.hstack([z, delta_matrix(z.shape[0]) @ z])


def sparse_to_upper_banded(P: sp.spmatrix) -> np.ndarray:
    """Upper banded storage ``ab[u + i − j, j] = P[i, j]`` (i ≤ j) for ``solveh_banded``."""
    P = sp.coo_matrix(P)
    keep = P.col >= P.row
    r, c, v = P.row[keep], P.col[keep], P.data[keep]
    u = int((c - r).max()) if c.size else 0
    ab = np.zeros((u + 1, P.shape[0]))
    np.add.at(ab, (u + r - c, c), v)
    return ab


def trajectory_solve(mean: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Solve (VP): the z maximising Σ_t log N([z_t, Δz_t]; mean_t, cov_t).

    Parameters
    ----------
    mean : (T, 2D) per-frame means of [z, Δz] along the state path.
    cov : (T, 2D) diagonal variances, or (T, 2D, 2D) full covariances.

    Returns
    -------
    (T, D) trajectory z. Diagonal: D independent banded T×T solves; full: one banded
    TD×TD solve in frame-major order (index t·D + d).
    """
    mean = np.asarray(mean, dtype=np.float64)
    cov = np.asarray(cov, dtype=np.float64)
    if mean.ndim != 2 or mean.shape[1] % 2:
        raise ValueError(f"mean must have shape (T, 2D), got {mean.shape}")
    T, D2 = mean.shape
    D = D2 // 2
    Dm = delta_matrix(T)
    if cov.shape == (T, D2):
        if np.any(cov <= 0):
            raise ValueError("diagonal covariances must be positive")
        lam = 1.0 / cov
        out = np.empty((T, D))
        for d in range(D):
            lz, ld = lam[:, d], lam[:, D + d]
            P = sp.diags(lz) + Dm.T @ sp.diags(ld) @ Dm
            b = lz * mean[:, d] + Dm.T @ (ld * mean[:, D + d])
            out[:, d] = scipy.linalg.solveh_banded(sparse_to_upper_banded(P), b)
        return out
    if cov.shape == (T, D2, D2):
        # precision of each frame's [z_t, Δz_t] block (Cholesky solves, no explicit inverse)
        eye = np.eye(D2)
        prec = np.stack([scipy.linalg.cho_solve(scipy.linalg.cho_factor(c), eye) for c in cov])
        prec = 0.5 * (prec + prec.transpose(0, 2, 1))
        I_D = sp.identity(D, format="csr")
        # observation map M: z (TD, frame-major) -> o (T·2D, frame-major [z_t, Δz_t])
        Mz = sp.kron(sp.identity(T), I_D, format="csr")
        Md = sp.kron(Dm, I_D, format="csr")
        order = np.empty(2 * T * D, dtype=np.int64)
        base = np.arange(T)[:, None] * D2
        order[(base + np.arange(D)).ravel()] = np.arange(T * D)
        order[(base + D + np.arange(D)).ravel()] = T * D + np.arange(T * D)
        M = sp.vstack([Mz, Md], format="csr")[order]
        Lam = sp.block_diag(list(prec), format="csr")
        P = M.T @ Lam @ M
        b = M.T @ (Lam @ mean.ravel())
        z = scipy.linalg.solveh_banded(sparse_to_upper_banded(P), b)
        return z.reshape(T, D)
    raise ValueError(f"cov must have shape {(T, D2)} or {(T, D2, D2)}, got {cov.shape}")


class VoicePuppetry(Baseline):
    """Brand's Voice Puppetry: visual HMM on [z, Δz], audio remapping, Viterbi, (VP) solve.

    Parameters
    ----------
    n_states : number of HMM states K (26 by default).
    visual_covariance : "diag" (default; the (VP) system decouples per dimension) or "full".
    audio_covariance : "diag" or "full" (default) remapped audio covariances.
    audio_deltas : remap [y, Δy] (default) instead of y.
    n_iter, tol : Baum-Welch iterations / tolerance of the visual HMM (hmmlearn).
    min_covar : hmmlearn's floor on the visual covariance diagonal, in units of the
        per-dimension variance of the standardised data (the HMM is fitted on
        [z, Δz] standardised per column; the fitted means/covariances are mapped back).
    audio_reg : ridge ε added to the remapped audio covariances, as a fraction of each
        audio column's global variance.
    random_state : seed of hmmlearn's k-means initialisation (same seed -> same model).
    """

    name: ClassVar[str] = "voice-puppetry"
    _derived: ClassVar[tuple[str, ...]] = ("audio_hmm_",)
    has_log_likelihood: ClassVar[bool] = False

    def __init__(self, n_states: int = 26, visual_covariance: CovType = "diag",
                 audio_covariance: CovType = "full", audio_deltas: bool = True,
                 n_iter: int = 50, tol: float = 1e-3, min_covar: float = 1e-3,
                 audio_reg: float = 1e-3, random_state: int = 0) -> None:
        if n_states < 1:
            raise ValueError(f"n_states must be >= 1, got {n_states}")
        for nm, v in (("visual_covariance", visual_covariance), ("audio_covariance", audio_covariance)):
            if v not in ("diag", "full"):
                raise ValueError(f"{nm} must be 'diag' or 'full', got {v!r}")
        self.n_states = n_states
        self.visual_covariance: CovType = visual_covariance
        self.audio_covariance: CovType = audio_covariance
        self.audio_deltas = audio_deltas
        self.n_iter = n_iter
        self.tol = tol
        self.min_covar = min_covar
        self.audio_reg = audio_reg
        self.random_state = random_state

    def _audio(self, y: np.ndarray) -> np.ndarray:
        return delta_features(y) if self.audio_deltas else np.asarray(y, dtype=np.float64)

    def fit(self, train: list[Utterance]) -> Self:
        """Train the facial HMM on visual features, then remap its states to audio (Brand 1999); returns ``self``."""
        d_y, d_z = check_train(train)
        lengths = np.array([s.n_frames for s in train])
        if lengths.sum() < self.n_states:
            raise ValueError(f"{lengths.sum()} training frames for {self.n_states} states")
        V = np.concatenate([delta_features(s.aam) for s in train])
        A = np.concatenate([self._audio(s.mfcc) for s in train])
        # standardise the visual observations (hmmlearn's min_covar is absolute)
        loc, scale = V.mean(axis=0), V.std(axis=0)
        scale[scale <= 0] = 1.0
        Vs = (V - loc) / scale
        # initial state means: k-means on the static part z only, so that states start as
        # facial configurations rather than as the large-Δz transition frames
        km = KMeans(n_clusters=self.n_states, n_init=10, random_state=self.random_state).fit(Vs[:, :d_z])
        init_means = np.stack([Vs[km.labels_ == k].mean(axis=0) if np.any(km.labels_ == k)
                               else Vs.mean(axis=0) for k in range(self.n_states)])
        vis = GaussianHMM(n_components=self.n_states, covariance_type=self.visual_covariance,
                          min_covar=self.min_covar, n_iter=self.n_iter, tol=self.tol,
                          random_state=self.random_state, init_params="stc")
        vis.means_ = init_means
        vis.fit(Vs, lengths)
        gamma = vis.predict_proba(Vs, lengths)  # (N, K) facial-state posteriors
        self.startprob_ = vis.startprob_.copy()
        self.transmat_ = vis.transmat_.copy()
        self.visual_means_ = vis.means_ * scale + loc                       # (K, 2D)
        full = vis.covars_ * np.outer(scale, scale)                         # (K, 2D, 2D)
        self.visual_covars_ = (np.diagonal(full, axis1=1, axis2=2).copy()
                               if self.visual_covariance == "diag" else full)
        # remap to audio: occupancy-weighted moments
        occ = gamma.sum(axis=0)                                             # (K,)
        gvar = A.var(axis=0)
        gvar[gvar <= 0] = 1.0
        ridge = self.audio_reg * gvar
        means = np.empty((self.n_states, A.shape[1]))
        covs = np.empty((self.n_states, A.shape[1], A.shape[1]))
        for k in range(self.n_states):
            if occ[k] <= 1e-8:  # state never visited: global audio moments
                means[k] = A.mean(axis=0)
                covs[k] = np.cov(A.T, bias=True).reshape(A.shape[1], A.shape[1])
            else:
                w = gamma[:, k] / occ[k]
                means[k] = w @ A
                R = A - means[k]
                covs[k] = (R * w[:, None]).T @ R
            covs[k] += np.diag(ridge)
        self.occupancy_ = occ
        self.audio_means_ = means
        self.audio_covars_ = (np.diagonal(covs, axis1=1, axis2=2).copy()
                              if self.audio_covariance == "diag" else covs)
        self.n_audio_, self.n_visual_ = d_y, d_z
        self._rebuild()
        return self

    def _rebuild(self) -> None:
        """The audio HMM (hmmlearn) from the saved start, transition and audio parameters."""
        aud = GaussianHMM(n_components=self.n_states, covariance_type=self.audio_covariance,
                          init_params="", params="")
        aud.startprob_ = self.startprob_
        aud.transmat_ = self.transmat_
        aud.means_ = self.audio_means_
        aud.covars_ = self.audio_covars_
        self.audio_hmm_ = aud

    def decode_states(self, seq: Utterance) -> np.ndarray:
        """Viterbi state path s*_{1:T} (int array) of the audio HMM for ``seq.mfcc``."""
        self._check_fitted()
        check_test(seq, n_audio=self.n_audio_)
        _, path = self.audio_hmm_.decode(self._audio(seq.mfcc), algorithm="viterbi")
        return np.asarray(path, dtype=np.int64)

    def predict(self, seq: Utterance) -> np.ndarray:
        """Most likely visual trajectory given the Viterbi path of the audio, eq. (VP)."""
        path = self.decode_states(seq)
        return trajectory_solve(self.visual_means_[path], self.visual_covars_[path])
