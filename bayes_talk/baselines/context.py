"""Context-window regression: ridge on phone-label and MFCC windows (issue #15).

The baseline a practitioner tries first: a linear map from a window of context to the
face. The context vector of frame t is

    x_t = [ e(π_{t−L}), …, e(π_{t+L}),  ỹ_{t−M}, …, ỹ_{t+M} ]                     (CTX)

with e(π) the one-hot vector of phone π over the P phones seen in training (label
half-width L; ``label_window=None`` drops the label part) and ỹ_t the MFCCs standardised
with the training mean and standard deviation (half-width M; ``mfcc_window=None`` drops
the audio part). Beyond the ends of an utterance the label window is padded with the
silence label ``sil`` (an all-zero block if ``sil`` never occurred in training) and the
MFCC window repeats the first / last frame. Unseen phones at test time are mapped like
the other label baselines (:class:`~bayes_talk.baselines.base.LabelEncoder`: the most
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

Saved models are ``<base>.json`` + ``<base>.npz`` (no pickle): the context settings,
the label encoder, the MFCC standardisation, ``coef_``/``intercept_`` and the variances.
"""
from __future__ import annotations

import os
from collections.abc import Sequence as Seq
from pathlib import Path
from typing import Any, ClassVar, Self

import numpy as np
import scipy.linalg
import scipy.sparse as sp
from sklearn.linear_model import Ridge
from sklearn.model_selection import GroupKFold

from bayes_talk.baselines.base import Baseline, check_train
from bayes_talk.data.utterance import Utterance, check_test
from bayes_talk.features.context_window import (
    LABEL_WINDOWS,
    MFCC_WINDOWS,
    ContextFeatures,
    Window,
    listed,
    stack_context,
    tupled,
    window_grid,
)
from bayes_talk.files import check_format, read_model_files, write_model_files

__all__ = [
    "FORMAT_VERSION",
    "ContextBaseline",
    "ContextRidge",
    "grouped_ridge_cv",
    "read_saved",
    "select_context",
    "write_saved",
]

FORMAT_VERSION = 1
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


# --------------------------------------------------------------------------- files
def _paths(path: str | os.PathLike) -> tuple[Path, Path]:
    p = Path(path)
    base = p.with_suffix("") if p.suffix in (".json", ".npz") else p
    return base.with_name(base.name + ".json"), base.with_name(base.name + ".npz")


def write_saved(path: str | os.PathLike, fmt: str, meta: dict[str, Any], arrays: dict[str, np.ndarray],
                overwrite: bool = False) -> Path:
    """Write ``<base>.npz`` then ``<base>.json`` (atomically); returns the JSON path.

    The JSON records ``format``, ``version``, the NPZ's SHA-256 and every array's shape.
    An existing file is refused (FileExistsError) unless ``overwrite``.
    """
    jpath, npath = _paths(path)
    if not overwrite:
        for p in (jpath, npath):
            if p.exists():
                raise FileExistsError(f"{p} exists; pass overwrite=True to replace it")
    full = {"format": fmt, "version": FORMAT_VERSION, **meta,
            "arrays": {k: list(np.shape(a)) for k, a in arrays.items()}}
    return write_model_files(jpath, npath, full, arrays)


def read_saved(path: str | os.PathLike, fmt: str) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Read a pair written by :func:`write_saved`. A missing file is FileNotFoundError; a
    truncated, modified, foreign, wrong-format or wrong-version file a ValueError naming
    the file and the problem."""

    jpath, npath = _paths(path)
    meta, arrays = read_model_files(jpath, npath)
    check_format(meta, fmt, FORMAT_VERSION, f"model file {jpath}")
    for k, shape in (meta.get("arrays") or {}).items():
        if k not in arrays:
            raise ValueError(f"model file {npath}: array {k!r} missing")
        if list(arrays[k].shape) != list(shape):
            raise ValueError(f"model file {npath}: array {k!r} shape expected {shape}, "
                             f"found {list(arrays[k].shape)}")
    return meta, arrays


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
    _format: ClassVar[str] = "bayes_talk.context-ridge"

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

    # -- persistence
    def save(self, path: str | os.PathLike, overwrite: bool = False) -> Path:
        """Write ``<base>.json`` + ``<base>.npz`` (``path`` with or without suffix)."""
        self._check_fitted()
        meta = {"params": {"label_window": listed(self.label_window), "mfcc_window": listed(self.mfcc_window),
                           "alphas": [float(a) for a in self.alphas], "n_splits": self.n_splits},
                "features": self.features_.to_meta(), "n_audio": self.n_audio_, "n_visual": self.n_visual_,
                "cv_table": self.cv_table_, "cv_splits": self.cv_splits_}
        arrays = {**self.features_.arrays(), "coef": self.coef_, "intercept": self.intercept_,
                  "alpha": self.alpha_, "residual_var": self.residual_var_}
        return write_saved(path, self._format, meta, arrays, overwrite=overwrite)

    @classmethod
    def load(cls, path: str | os.PathLike) -> ContextRidge:
        """Read a model written by :meth:`save` (ValueError on any problem)."""
        meta, arrays = read_saved(path, cls._format)
        try:
            p = meta["params"]
            obj = cls(label_window=tupled(p["label_window"]), mfcc_window=tupled(p["mfcc_window"]),
                      alphas=tuple(p["alphas"]), n_splits=p["n_splits"])
            obj.features_ = ContextFeatures.from_saved(meta["features"], arrays)
            obj.n_audio_, obj.n_visual_ = int(meta["n_audio"]), int(meta["n_visual"])
            obj.coef_, obj.intercept_ = arrays["coef"], arrays["intercept"]
            obj.alpha_, obj.residual_var_ = arrays["alpha"], arrays["residual_var"]
            obj.cv_table_, obj.cv_splits_ = meta["cv_table"], meta["cv_splits"]
        except (KeyError, TypeError) as exc:
            raise ValueError(f"model file {path}: incomplete or corrupt (missing {exc})") from None
        want = (obj.n_visual_, obj.features_.n_features)
        if obj.coef_.shape != want or obj.intercept_.shape != (want[0],) or obj.residual_var_.shape != (want[0],):
            raise ValueError(f"model file {path}: coef {obj.coef_.shape} / intercept {obj.intercept_.shape} / "
                             f"residual_var {obj.residual_var_.shape} do not match (D_z, F) = {want}")
        if obj.features_.mfcc_mean.shape != (obj.n_audio_,):
            raise ValueError(f"model file {path}: mfcc_mean has shape {obj.features_.mfcc_mean.shape}, "
                             f"expected ({obj.n_audio_},)")
        return obj
