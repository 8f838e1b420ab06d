"""Context-window MLP: one hidden layer on phone-label and MFCC windows.

Same inputs x_t as :mod:`bayes_talk.estimators.baselines.context` (CTX): one-hot labels in a window of
half-width L (padded with ``sil``) and standardised MFCCs in a window of half-width M
(edge frames repeated). With window *grids* (the default) the windows are the ones the
ridge's utterance-grouped cross-validation picks on the training utterances
(:func:`~bayes_talk.estimators.baselines.context.select_context`); a single value fixes them.

Network (scikit-learn ``MLPRegressor``, Adam, squared error, L2 penalty ``l2``):

    ẑ_t = s ⊙ (W₂ relu(W₁ x_t + b₁) + b₂) + m,

m, s: mean and standard deviation of the visual features of the fitting utterances (the
network learns standardised targets).

Early stopping by utterance: a seeded ``validation_fraction`` of the *training*
utterances (whole utterances, never single frames) is held out; the network is trained
one epoch at a time (``partial_fit``) on the rest, the held-out MSE is measured after
every epoch, and the weights of the best epoch are kept (stop after ``patience`` epochs
without improvement, at most ``max_epochs``). The held-out utterances are not refitted.

Predictive variance: the held-out residual variance of each dimension at the kept epoch,

    σ²_d = (1/N_val) Σ_{t ∈ held-out} (z_td − ẑ_td)²

(slightly optimistic: the same frames chose the epoch), constant over frames.

Predictions use the stored weights through :func:`mlp_forward` (float32 products, as
trained), so a saved and re-loaded model predicts bit-identically.
"""
from __future__ import annotations

import math
from collections.abc import Sequence as Seq
from typing import ClassVar, Self

import numpy as np
from sklearn.neural_network import MLPRegressor

from bayes_talk.data.utterance import Utterance
from bayes_talk.estimators.baselines.base import check_train
from bayes_talk.estimators.baselines.context import ContextBaseline, select_context
from bayes_talk.features.context_window import (
    LABEL_WINDOWS,
    MFCC_WINDOWS,
    ContextFeatures,
    Window,
    stack_context,
    window_grid,
)

__all__ = ["ContextMLP", "mlp_forward"]


def mlp_forward(X: np.ndarray, weights: list[np.ndarray], biases: list[np.ndarray]) -> np.ndarray:
    """relu hidden layers, identity output (scikit-learn's MLPRegressor forward pass)."""
    h = np.asarray(X, dtype=weights[0].dtype)
    for i, (W, b) in enumerate(zip(weights, biases, strict=True)):
        h = h @ W + b
        if i < len(weights) - 1:
            np.maximum(h, 0, out=h)
    return h


class ContextMLP(ContextBaseline):
    """One-hidden-layer MLP from label/MFCC context windows to the face (module docstring).

    Parameters
    ----------
    label_window, mfcc_window : fixed half-widths, or grids chosen by the ridge's grouped
        CV (see :class:`~bayes_talk.estimators.baselines.context.ContextRidge`).
    hidden : hidden units (one layer).
    l2 : scikit-learn's ``alpha`` (L2 penalty on the weights).
    learning_rate, batch_size : Adam step size and minibatch size.
    max_epochs, patience : epoch budget and early-stopping patience.
    validation_fraction : fraction of the training utterances held out for early stopping
        (at least one utterance).
    n_splits : folds of the window-selection CV.
    seed : seeds the held-out choice, the initial weights and the minibatch order.
    blas_threads : BLAS threads while fitting (1: fastest on a shared 2-core machine).
    """

    name: ClassVar[str] = "context-mlp"

    def __init__(self, label_window: Window | Seq[Window] = LABEL_WINDOWS,
                 mfcc_window: Window | Seq[Window] = MFCC_WINDOWS, hidden: int = 256, l2: float = 3.0,
                 learning_rate: float = 1e-3, batch_size: int = 256, max_epochs: int = 60, patience: int = 5,
                 validation_fraction: float = 0.15, n_splits: int = 5, seed: int = 0,
                 blas_threads: int | None = 1) -> None:
        window_grid(label_window, "label_window")
        window_grid(mfcc_window, "mfcc_window")
        for nm, v in (("hidden", hidden), ("batch_size", batch_size), ("max_epochs", max_epochs),
                      ("patience", patience), ("n_splits", n_splits)):
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"{nm} must be a positive integer, got {v!r}")
        if not (isinstance(seed, (int, np.integer)) and seed >= 0):
            raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
        if not (0 < validation_fraction < 1):
            raise ValueError(f"validation_fraction must be in (0, 1), got {validation_fraction!r}")
        for nm, v in (("l2", l2), ("learning_rate", learning_rate)):
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{nm} must be a positive number, got {v!r}")
        self.label_window = label_window
        self.mfcc_window = mfcc_window
        self.hidden = hidden
        self.l2 = l2
        self.learning_rate = learning_rate
        self.batch_size = batch_size
        self.max_epochs = max_epochs
        self.patience = patience
        self.validation_fraction = validation_fraction
        self.n_splits = n_splits
        self.seed = seed
        self.blas_threads = blas_threads

    def _features(self, train: list[Utterance]) -> ContextFeatures:
        lw = window_grid(self.label_window, "label_window")
        mw = window_grid(self.mfcc_window, "mfcc_window")
        if len(lw) == 1 and len(mw) == 1:
            return ContextFeatures.fit(train, lw[0], mw[0])
        return select_context(train, lw, mw, (1e-2, 1e-1, 1.0, 1e1, 1e2, 1e3, 1e4, 1e5),
                              self.n_splits)["features"]

    def fit(self, train: list[Utterance]) -> Self:
        """Windows (fixed or by grouped CV), then the MLP with utterance-held-out early stopping."""
        from threadpoolctl import threadpool_limits

        d_y, d_z = check_train(train, min_sequences=2)
        train = list(train)
        rng = np.random.default_rng(self.seed)
        perm = rng.permutation(len(train))
        n_val = min(max(1, round(self.validation_fraction * len(train))), len(train) - 1)
        val = [train[i] for i in sorted(perm[:n_val])]
        fit = [train[i] for i in sorted(perm[n_val:])]
        with threadpool_limits(limits=self.blas_threads):
            feats = self._features(train)
            Xf, Zf, _ = stack_context(feats, fit)
            Xv, Zv, _ = stack_context(feats, val)
            Xf, Xv = Xf.toarray().astype(np.float32), Xv.toarray().astype(np.float32)
            z_mean, z_scale = Zf.mean(axis=0), Zf.std(axis=0)
            z_scale[z_scale <= 0] = 1.0
            target = ((Zf - z_mean) / z_scale).astype(np.float32)
            net = MLPRegressor(hidden_layer_sizes=(self.hidden,), alpha=self.l2,
                               batch_size=min(self.batch_size, Xf.shape[0]),
                               learning_rate_init=self.learning_rate, random_state=self.seed, shuffle=True)
            best = (np.inf, None, None, None, 0)
            history = []
            for epoch in range(1, self.max_epochs + 1):
                net.partial_fit(Xf, target)
                W = [w.copy() for w in net.coefs_]
                b = [v.copy() for v in net.intercepts_]
                err = ((Zv - (mlp_forward(Xv, W, b) * z_scale + z_mean)) ** 2).mean(axis=0)
                history.append(float(err.mean()))
                if err.mean() < best[0]:
                    best = (float(err.mean()), W, b, err, epoch)
                elif epoch - best[4] >= self.patience:
                    break
        self.features_ = feats
        self.weights_, self.biases_ = best[1], best[2]
        self.z_mean_, self.z_scale_ = z_mean, z_scale
        self.residual_var_ = np.maximum(best[3], np.finfo(np.float64).tiny)
        self.best_epoch_ = best[4]
        self.val_history_ = history
        self.validation_utterances_ = [s.name for s in val]
        self.n_audio_, self.n_visual_ = d_y, d_z
        return self

    def predict(self, seq: Utterance) -> np.ndarray:
        """ẑ_t of every frame of ``seq`` (labels and mfcc; never ``seq.aam``)."""
        self._check_fitted()
        self.features_.check(seq)
        out = mlp_forward(self.features_.transform(seq), self.weights_, self.biases_)
        return out.astype(np.float64) * self.z_scale_ + self.z_mean_

    def _get_state(self) -> tuple[dict, dict[str, np.ndarray]]:
        meta, arrays = super()._get_state()
        meta = {**meta, "n_layers": len(self.weights_), "best_epoch": self.best_epoch_,
                "val_history": self.val_history_, "validation_utterances": self.validation_utterances_}
        arrays = {**arrays, "z_mean": self.z_mean_, "z_scale": self.z_scale_}
        for i, (W, b) in enumerate(zip(self.weights_, self.biases_, strict=True)):
            arrays[f"W{i}"], arrays[f"b{i}"] = W, b
        return meta, arrays

    def _set_state(self, meta: dict, arrays: dict[str, np.ndarray]) -> None:
        super()._set_state(meta, arrays)
        n = int(meta["n_layers"])
        self.weights_ = [arrays[f"W{i}"] for i in range(n)]
        self.biases_ = [arrays[f"b{i}"] for i in range(n)]
        self.z_mean_, self.z_scale_ = arrays["z_mean"], arrays["z_scale"]
        self.best_epoch_, self.val_history_ = meta["best_epoch"], meta["val_history"]
        self.validation_utterances_ = meta["validation_utterances"]
        fan_in = self.features_.n_features
        for i, (W, b) in enumerate(zip(self.weights_, self.biases_, strict=True)):
            if W.ndim != 2 or W.shape[0] != fan_in or b.shape != (W.shape[1],):
                raise ValueError(f"layer {i} has W {W.shape}, b {b.shape}; expected ({fan_in}, k) and (k,)")
            fan_in = W.shape[1]
        if fan_in != self.n_visual_:
            raise ValueError(f"output size {fan_in} does not match D_z = {self.n_visual_}")
