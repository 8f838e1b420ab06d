"""Context-window regression: ridge on phone-label and MFCC windows.

The baseline a practitioner tries first: a linear map from a window of context to the
face. The context vector of frame t is

    x_t = [ e(π_{t−L}), …, e(π_{t+L}),  ỹ_{t−M}, …, ỹ_{t+M} ]                     (CTX)

with e(π) the one-hot vector of phone π over the P phones seen in training (label
half-width L; ``label_window=None`` drops the label part) and ỹ_t the MFCCs standardised
with the training mean and standard deviation (half-width M; ``mfcc_window=None`` drops
the audio part). Beyond the ends of an utterance the label window is padded with the
silence label ``sil`` (an all-zero block if ``sil`` never occurred in training) and the
MFCC window repeats the first / last frame. Unseen phones at test time are mapped like
the other label baselines (:class:`~bayes_talk.estimators.baselines.base.LabelEncoder`: the most
frequent training phone of the same viseme, with a warning).

Ridge (one penalty per visual dimension d, unpenalised intercept):

    (w_d, b_d) = argmin Σ_t (z_td − b_d − w_d·x_t)² + α_d ‖w_d‖²,
    w_d = (X̃ᵀX̃ + α_d I)⁻¹ X̃ᵀ z̃_d   (X̃, z̃: training columns centred),            (RIDGE)

fitted with scikit-learn's ``Ridge`` (per-target ``alpha`` array).

Model selection by K-fold cross-validation grouped by utterance (scikit-learn
``GroupKFold``; every frame of an utterance is in the same fold), on the training
utterances only: for each window pair (L, M) of the grid and each α of ``alphas``, the
out-of-fold squared error of every dimension is computed exactly from one eigendecom-
position of each fold's centred Gram matrix, X̃ᵀX̃ = V Λ Vᵀ:

    ẑ_k(α) = (X_k − x̄) V diag(1/(λ + α)) Vᵀ X̃ᵀ z̃ + z̄.

The window pair minimises the out-of-fold MSE summed over dimensions (each at its own
best α); then α_d = the best α of dimension d for that pair.

Predictive variance: the out-of-fold mean squared residual of each dimension at the
chosen (L, M, α_d),

    σ²_d = (1/N) Σ_k Σ_{t ∈ fold k} (z_td − ẑ^{(−k)}_td)²,

constant over frames (a homoscedastic Gaussian predictive N(ẑ_t, diag σ²)).

Saved as every estimator (:meth:`bayes_talk.estimators.base.Estimator.save`, no pickle): the
context settings, the label encoder, the MFCC standardisation, ``coef_``/``intercept_`` and
the variances.
"""
from __future__ import annotations

from collections.abc import Sequence as Seq
from typing import Any, ClassVar, Self

import numpy as np
import scipy.linalg
import scipy.sparse as sp
from sklearn.linear_model import Ridge
from sklearn.model_selection import GroupKFold

from bayes_talk.data.utterance import Utterance, check_test
from bayes_talk.estimators.baselines.base import Baseline, check_train
from bayes_talk.features.context_window import (
    LABEL_WINDOWS,
    MFCC_WINDOWS,
    ContextFeatures,
    Window,
    stack_context,
    window_grid,
)

__all__ = ["ContextBaseline", "ContextRidge", "grouped_ridge_cv", "select_context"]

#: default ridge penalties searched per visual dimension
ALPHAS: tuple[float, ...] = tuple(float(a) for a in np.logspace(-2, 6, 17))


# --------------------------------------------------------------------------- cross-validation
def grouped_ridge_cv(X: sp.csr_matrix | np.ndarray, Z: np.ndarray, groups: np.ndarray,
                     column_sets: list[np.ndarray], alphas: Seq[float], n_splits: int = 5) -> np.ndarray:
    """Out-of-fold squared errors of (RIDGE), grouped K-fold (see the module docstring).

    Returns SSE of shape (len(column_sets), len(alphas), D_z): the sum over all N frames of
    the squared out-of-fold residual of each dimension, for ridge on the columns
    ``column_sets[c]`` of X with penalty ``alphas[a]`` (intercept unpenalised, as
    scikit-learn's ``Ridge(fit_intercept=True)``). Folds: ``GroupKFold(n_splits)`` on
    ``groups`` -- the only rows the function sees are the ones passed in.
    """
    X = sp.csr_matrix(X)
    Z = np.asarray(Z, dtype=np.float64)
    alphas = np.asarray(alphas, dtype=np.float64)
    D = Z.shape[1]
    A = len(alphas)
    folds = [te for _, te in GroupKFold(n_splits=n_splits).split(X, Z, groups)]
    # per-fold sufficient statistics of all columns: n, Σx, XᵀX, XᵀZ, Σz, Σz²
    stats = []
    for te in folds:
        Xk, Zk = X[te].toarray(), Z[te]
        stats.append((len(te), Xk.sum(axis=0), Xk.T @ Xk, Xk.T @ Zk, Zk.sum(axis=0), (Zk * Zk).sum(axis=0)))
    tot = [sum(s[i] for s in stats) for i in range(6)]
    sse = np.zeros((len(column_sets), A, D))
    for n_k, s_k, G_k, XZ_k, sz_k, zz_k in stats:
        # training part (all other folds), centred at its own means
        n = tot[0] - n_k
        xbar, zbar = (tot[1] - s_k) / n, (tot[4] - sz_k) / n
        G = (tot[2] - G_k) - n * np.outer(xbar, xbar)
        C = (tot[3] - XZ_k) - n * np.outer(xbar, zbar)
        # fold part, centred at the training means: X̃_kᵀX̃_k, X̃_kᵀZ̃_k, ‖Z̃_k‖² per dimension
        Ak = G_k - np.outer(s_k, xbar) - np.outer(xbar, s_k) + n_k * np.outer(xbar, xbar)
        Mk = XZ_k - np.outer(s_k, zbar) - np.outer(xbar, sz_k) + n_k * np.outer(xbar, zbar)
        rr = zz_k - 2 * zbar * sz_k + n_k * zbar**2
        for c, cols in enumerate(column_sets):
            ix = np.ix_(cols, cols)
            lam, V = scipy.linalg.eigh(G[ix], driver="evd")
            lam = np.maximum(lam, 0.0)
            U = V.T @ C[cols]                                          # (p, D)
            W = V.T @ Mk[cols]                                         # (p, D)
            H = V.T @ Ak[ix] @ V                                       # (p, p)
            Ut = (1.0 / (lam[:, None] + alphas[None, :]))[:, :, None] * U[:, None, :]   # (p, A, D)
            HU = (H @ Ut.reshape(len(cols), A * D)).reshape(len(cols), A, D)
            # Σ_t∈k (z̃ − x̃ B)² = ‖z̃‖² − 2 diag(Bᵀ X̃ᵀZ̃) + diag(Bᵀ X̃ᵀX̃ B), B = V Ũ
            sse[c] += rr[None, :] - 2 * np.einsum("pad,pd->ad", Ut, W) + np.einsum("pad,pad->ad", Ut, HU)
    return sse


# --------------------------------------------------------------------------- the model
def select_context(train: list[Utterance], label_window: Window | Seq[Window], mfcc_window: Window | Seq[Window],
                   alphas: Seq[float], n_splits: int) -> dict[str, Any]:
    """Grouped-CV choice of the windows and the per-dimension penalties (module docstring).

    Returns {"features": ContextFeatures of the chosen windows, "alpha": (D_z,),
    "residual_var": (D_z,) out-of-fold MSE per dimension, "table": [{"label_window",
    "mfcc_window", "cv_mse"}...] one row per window pair (mean over dimensions of the
    out-of-fold MSE at each dimension's best α), "n_splits": folds used, "X": sparse (N, F)
    context of the chosen windows, "Z": (N, D_z) targets}.
    """
    lw = window_grid(label_window, "label_window")
    mw = window_grid(mfcc_window, "mfcc_window")
    configs = [(a, b) for a in lw for b in mw if not (a is None and b is None)]
    if not configs:
        raise ValueError("label_window and mfcc_window cannot both be None (no inputs)")
    alphas = np.asarray(alphas, dtype=np.float64)
    if alphas.ndim != 1 or alphas.size < 1 or not np.all(alphas > 0) or not np.all(np.isfinite(alphas)):
        raise ValueError(f"alphas must be a non-empty 1-D sequence of positive finite numbers, got {alphas!r}")
    n_groups = len({s.name for s in train})
    if n_groups != len(train):
        raise ValueError("training utterances must have distinct names (they are the CV groups)")
    if n_groups < 2:
        raise ValueError(f"grouped cross-validation needs at least 2 training utterances, got {n_groups}")
    k = min(int(n_splits), n_groups)
    Lmax = max((a for a in lw if a is not None), default=None)
    Mmax = max((b for b in mw if b is not None), default=None)
    wide = ContextFeatures.fit(train, Lmax, Mmax)
    X, Z, groups = stack_context(wide, train)
    sets = [wide.columns(a, b) for a, b in configs]
    sse = grouped_ridge_cv(X, Z, groups, sets, alphas, n_splits=k)
    best = sse.min(axis=1)                                      # (C, D)
    c = int(np.argmin(best.sum(axis=1)))
    N = Z.shape[0]
    feats = ContextFeatures(wide.encoder, configs[c][0], configs[c][1], wide.mfcc_mean, wide.mfcc_scale)
    return {"features": feats, "alpha": alphas[np.argmin(sse[c], axis=0)], "residual_var": best[c] / N,
            "X": X[:, sets[c]], "Z": Z,
            "table": [{"label_window": a, "mfcc_window": b, "cv_mse": float(best[i].mean() / N)}
                      for i, (a, b) in enumerate(configs)],
            "n_splits": k}


class ContextBaseline(Baseline):
    """What the context regressions share: fitted ``features_`` (:class:`ContextFeatures`)
    and a per-dimension residual variance ``residual_var_`` used as a homoscedastic
    Gaussian predictive N(ẑ_t, diag σ²)."""

    has_log_likelihood: ClassVar[bool] = True
    features_: ContextFeatures
    residual_var_: np.ndarray

    @property
    def windows_(self) -> tuple[int | None, int | None]:
        """(L, M) used by the fitted model."""
        self._check_fitted()
        return self.features_.label_window, self.features_.mfcc_window

    def predict_var(self, seq: Utterance) -> np.ndarray:
        """(T, D_z) predictive variance: the residual variance σ²_d on every frame."""
        self._check_fitted()
        self.features_.check(seq)
        return np.broadcast_to(self.residual_var_, (seq.n_frames, self.n_visual_)).copy()

    def _get_state(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        """The fitted context features, dimensions and residual variance (the shared part);
        each regression adds its own coefficients."""
        return ({"features": self.features_.to_meta(), "n_audio": self.n_audio_, "n_visual": self.n_visual_},
                {**self.features_.arrays(), "residual_var": self.residual_var_})

    def _set_state(self, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> None:
        self.features_ = ContextFeatures.from_saved(meta["features"], arrays)
        self.n_audio_, self.n_visual_ = int(meta["n_audio"]), int(meta["n_visual"])
        self.residual_var_ = arrays["residual_var"]
        if self.residual_var_.shape != (self.n_visual_,):
            raise ValueError(f"residual_var has shape {self.residual_var_.shape}, expected ({self.n_visual_},)")
        if self.features_.mfcc_mean.shape != (self.n_audio_,):
            raise ValueError(f"mfcc_mean has shape {self.features_.mfcc_mean.shape}, expected ({self.n_audio_},)")

    def log_likelihood(self, seq: Utterance) -> float:
        """Σ_t Σ_d log N(z_td; ẑ_td, σ²_d) of the ground truth (labels and audio given)."""
        self._check_fitted()
        check_test(seq, n_visual=self.n_visual_, need_aam=True)
        r = seq.aam - self.predict(seq)
        v = self.residual_var_
        return float(-0.5 * np.sum(np.log(2 * np.pi * v) + r * r / v))


class ContextRidge(ContextBaseline):
    """Ridge regression from phone-label (and MFCC) context windows to the face (module docstring).

    Parameters
    ----------
    label_window : half-width L of the one-hot label window, None (no labels), or a grid of
        candidates chosen by grouped CV (default (2, 4, 8)).
    mfcc_window : half-width M of the standardised-MFCC window, None (no audio), or a grid
        (default (None, 4): "no MFCCs" is a candidate).
    alphas : ridge penalties searched for each visual dimension.
    n_splits : folds of the utterance-grouped cross-validation (fewer if fewer utterances).
    blas_threads : BLAS threads while fitting (1: fastest on a shared 2-core machine).
    """

    name: ClassVar[str] = "context-ridge"

    def __init__(self, label_window: Window | Seq[Window] = LABEL_WINDOWS,
                 mfcc_window: Window | Seq[Window] = MFCC_WINDOWS, alphas: Seq[float] = ALPHAS,
                 n_splits: int = 5, blas_threads: int | None = 1) -> None:
        window_grid(label_window, "label_window")
        window_grid(mfcc_window, "mfcc_window")
        if isinstance(n_splits, bool) or not isinstance(n_splits, (int, np.integer)) or n_splits < 2:
            raise ValueError(f"n_splits must be an integer >= 2, got {n_splits!r}")
        self.label_window = label_window
        self.mfcc_window = mfcc_window
        self.alphas = alphas
        self.n_splits = n_splits
        self.blas_threads = blas_threads

    def fit(self, train: list[Utterance]) -> Self:
        """Grouped CV on ``train`` (windows, α_d, σ²_d), then (RIDGE) on all of ``train``."""
        from threadpoolctl import threadpool_limits

        d_y, d_z = check_train(train, min_sequences=2)
        train = list(train)
        with threadpool_limits(limits=self.blas_threads):
            sel = select_context(train, self.label_window, self.mfcc_window, self.alphas, self.n_splits)
            feats: ContextFeatures = sel["features"]
            ridge = Ridge(alpha=sel["alpha"], fit_intercept=True, solver="cholesky").fit(
                sel["X"].toarray(), sel["Z"])
        self.features_ = feats
        # C order, as load() gives it back: sklearn's multi-output coef_ is a Fortran-ordered
        # view, and `X @ coef_.T` then takes another BLAS path whose sums differ in the last
        # bit, so a reloaded model would not predict bit-identically
        self.coef_ = np.ascontiguousarray(ridge.coef_, dtype=np.float64)   # (D_z, F)
        self.intercept_ = np.asarray(ridge.intercept_, dtype=np.float64)  # (D_z,)
        self.alpha_ = np.asarray(sel["alpha"], dtype=np.float64)
        self.residual_var_ = np.maximum(sel["residual_var"], np.finfo(np.float64).tiny)
        self.cv_table_ = sel["table"]
        self.cv_splits_ = sel["n_splits"]
        self.n_audio_, self.n_visual_ = d_y, d_z
        return self

    def predict(self, seq: Utterance) -> np.ndarray:
        """ẑ_t = W x_t + b for every frame of ``seq`` (labels and mfcc; never ``seq.aam``)."""
        self._check_fitted()
        self.features_.check(seq)
        return self.features_.transform(seq) @ self.coef_.T + self.intercept_

    def _get_state(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        meta, arrays = super()._get_state()
        return ({**meta, "cv_table": self.cv_table_, "cv_splits": self.cv_splits_},
                {**arrays, "coef": self.coef_, "intercept": self.intercept_, "alpha": self.alpha_})

    def _set_state(self, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> None:
        super()._set_state(meta, arrays)
        self.coef_, self.intercept_, self.alpha_ = arrays["coef"], arrays["intercept"], arrays["alpha"]
        self.cv_table_, self.cv_splits_ = meta["cv_table"], meta["cv_splits"]
        want = (self.n_visual_, self.features_.n_features)
        if self.coef_.shape != want or self.intercept_.shape != (want[0],):
            raise ValueError(f"coef {self.coef_.shape} / intercept {self.intercept_.shape} do not match "
                             f"(D_z, F) = {want}")
