"""The phonetic-context view: what the phone labels around a frame say about its face.

The switching SGPDM's audio view (deena2010 §3.3) is the sound of one frame, or of a few
(:mod:`bayes_talk.features.audio_context`). On held-out sentences most of what can be
predicted of the face is in the *timing of the phones around the frame* — a ridge on a
window of one-hot labels beats every audio-driven model here (docs/results.md). This
module makes that context part of the observed view the shared latent space must explain
(docs/model.md), so at synthesis the latent point
of frame t is pulled towards training latents whose phonetic context agrees.

The window is high-dimensional ((2L+1)·P one-hot columns plus (2M+1)·D_y MFCCs), and an
isotropic GP kernel over it would be dominated by columns that do not matter for the
face. So it is reduced *with supervision*, to the D_z directions that predict the face —
the reduced-rank reading of the context window:

    c_t = Bᵀ x_t + b,    (B, b) = argmin Σ_t ‖z_t − b − Bᵀ x_t‖² + α ‖B‖²             (1)

with x_t the context vector (CTX) of :mod:`bayes_talk.features.context_window` (labels
t−L..t+L, standardised MFCCs t−M..t+M) and α chosen by K-fold cross-validation grouped by
utterance. c_t lives in AAM units: it is a linear guess of the face, which the SGPDM
then explains jointly with the audio through its GP mapping and dynamics.

**Training frames see out-of-fold values.** Were the training view computed with the
(B, b) fitted on the same frames, it would fit them better than it fits new sentences,
and the state models would learn to trust it too much. So the training frames of
utterance i get c_t from the fit on the folds without i (``cross_val_predict``, the
stacking practice of Wolpert 1992), and only new utterances get (1) fitted on all.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from bayes_talk.data.utterance import Utterance
from bayes_talk.features.context_window import ContextFeatures

__all__ = ["ALPHAS", "ContextView", "ridge_out_of_fold"]

#: the ridge penalties compared by cross-validation
ALPHAS: tuple[float, ...] = (1.0, 10.0, 100.0, 1000.0)


def ridge_out_of_fold(X: np.ndarray, Z: np.ndarray, tests: Sequence[np.ndarray],
                      alphas: Sequence[float]) -> list[np.ndarray]:
    """Out-of-fold predictions of ridge regression with an intercept, one (n, D) array per
    penalty: row t of the k-th array is the prediction for x_t of sklearn's
    ``Ridge(alpha=alphas[k]).fit`` on the rows outside the test fold holding t (what
    ``cross_val_predict`` returns for those folds), to rounding.

    sklearn's Ridge (``cholesky`` solver) centres the training rows and solves
    (X_cᵀX_c + αI) B = X_cᵀZ_c for every fit, so ``cross_val_predict`` forms a training
    Gram matrix (n·F² flops) once per fold *and* penalty. The Gram matrix of the rows
    outside fold k follows from the whole one and the fold's own:

        X_cᵀX_c = Σ_{t∉k} x_t x_tᵀ − n_k m_k m_kᵀ = XᵀX − X_kᵀX_k − n_k m_k m_kᵀ,
        X_cᵀZ_c = XᵀZ − X_kᵀZ_k − n_k m_k μ_kᵀ,

    (m_k, μ_k the means of x and z outside the fold, n_k their count; X is centred on its
    overall mean first, which changes nothing but the rounding), so two Gram matrices'
    worth of products serve every fold and penalty; the prediction is
    (x_t − m_k)ᵀB + μ_k. On the default family's 250 utterances: 4 penalties × 5 folds
    would be 20 Gram matrices."""
    from scipy.linalg import solve

    X = np.asarray(X, dtype=np.float64)
    Z = np.asarray(Z, dtype=np.float64)
    Xc = X - X.mean(0)
    S, T = Xc.T @ Xc, Xc.T @ Z
    sx, sz = Xc.sum(0), Z.sum(0)
    eye = np.eye(X.shape[1])
    out = [np.empty_like(Z) for _ in alphas]
    for test in tests:
        Xt, Zt = Xc[test], Z[test]
        n = X.shape[0] - len(test)
        mx, mz = (sx - Xt.sum(0)) / n, (sz - Zt.sum(0)) / n
        G = S - Xt.T @ Xt - n * np.outer(mx, mx)
        C = T - Xt.T @ Zt - n * np.outer(mx, mz)
        for k, a in enumerate(alphas):
            B = solve(G + a * eye, C, assume_a="pos")
            out[k][test] = (Xt - mx) @ B + mz
    return out


class ContextView:
    """The view (1) of the module docstring. ``label_window`` L = 0 switches it off
    (``transform`` then returns a (T, 0) array); ``mfcc_window`` M (None: labels only)."""

    def __init__(self, label_window: int = 0, mfcc_window: int | None = 4, folds: int = 5) -> None:
        if int(label_window) != label_window or label_window < 0:
            raise ValueError(f"context view: label window must be a whole number of frames >= 0, "
                             f"got {label_window!r}")
        self.label_window = int(label_window)
        self.mfcc_window = mfcc_window
        self.folds = int(folds)
        self.features_: ContextFeatures | None = None
        self.coef_: np.ndarray | None = None        # (F, D_z)
        self.intercept_: np.ndarray | None = None   # (D_z,)
        self.alpha_: float | None = None

    @property
    def enabled(self) -> bool:
        """Whether the view is used (L > 0)."""
        return self.label_window > 0

    @property
    def n_dims(self) -> int:
        """Columns of the view (D_z when fitted and enabled, else 0)."""
        return 0 if not self.enabled or self.coef_ is None else int(self.coef_.shape[1])

    def fit(self, train: Sequence[Utterance]) -> list[np.ndarray]:
        """Fit (1) on ``train`` (labels, MFCCs and AAM parameters) and return each training
        utterance's out-of-fold view (module docstring), (T_i, D_z) each; with L = 0, (T_i, 0)."""
        if not self.enabled:
            return [np.zeros((s.n_frames, 0)) for s in train]
        from sklearn.linear_model import Ridge
        from sklearn.model_selection import GroupKFold

        train = list(train)
        if len(train) < 2:
            raise ValueError(f"context view: needs at least 2 training utterances, found {len(train)}")
        self.features_ = ContextFeatures.fit(train, self.label_window, self.mfcc_window)
        X = np.vstack([self.features_.transform(s) for s in train])
        Z = np.vstack([s.aam for s in train])
        groups = np.concatenate([np.full(s.n_frames, i) for i, s in enumerate(train)])
        cv = GroupKFold(n_splits=min(self.folds, len(train)))
        tests = [test for _, test in cv.split(X, Z, groups)]
        best = None
        for a, oof in zip(ALPHAS, ridge_out_of_fold(X, Z, tests, ALPHAS)):
            err = float(np.mean((oof - Z) ** 2))
            if best is None or err < best[0]:
                best = (err, a, oof)
        _, self.alpha_, oof = best
        r = Ridge(alpha=self.alpha_).fit(X, Z)
        self.coef_, self.intercept_ = np.asarray(r.coef_.T, np.float64), np.asarray(r.intercept_, np.float64)
        cuts = np.cumsum([s.n_frames for s in train])[:-1]
        return [np.asarray(o, np.float64) for o in np.split(oof, cuts)]

    def transform(self, mfcc: np.ndarray, labels: Sequence[str]) -> np.ndarray:
        """The view c_t (1) of every frame of a new utterance, (T, D_z); (T, 0) when off."""
        mfcc = np.asarray(mfcc, dtype=np.float64)
        if not self.enabled:
            return np.zeros((mfcc.shape[0], 0))
        if self.coef_ is None or self.features_ is None:
            raise ValueError("context view: transform before fit")
        if labels is None or len(labels) != mfcc.shape[0]:
            raise ValueError(f"context view: needs one phone label per frame; found "
                             f"{None if labels is None else len(labels)} labels for {mfcc.shape[0]} frames")
        seq = Utterance("context-view", mfcc, None, list(labels))
        return self.features_.transform(seq) @ self.coef_ + self.intercept_

    # ------------------------------------------------------------------ persistence
    def to_meta(self) -> dict[str, Any]:
        """JSON-able settings and fitted scalars (the arrays are in :meth:`arrays`)."""
        meta: dict[str, Any] = {"label_window": self.label_window, "mfcc_window": self.mfcc_window,
                                "folds": self.folds, "alpha": self.alpha_}
        if self.features_ is not None:
            meta["features"] = self.features_.to_meta()
        return meta

    def arrays(self) -> dict[str, np.ndarray]:
        """The fitted arrays, keys prefixed ``context_view/`` (empty when off)."""
        if not self.enabled or self.coef_ is None or self.features_ is None:
            return {}
        out = {f"context_view/{k}": v for k, v in self.features_.arrays().items()}
        out.update({"context_view/coef": self.coef_, "context_view/intercept": self.intercept_})
        return out

    @classmethod
    def from_saved(cls, meta: dict[str, Any] | None, arrays: dict[str, np.ndarray]) -> ContextView:
        """The view saved by :meth:`to_meta` / :meth:`arrays` (None: a model saved before the
        view existed, i.e. switched off)."""
        if not meta:
            return cls(0)
        obj = cls(meta["label_window"], meta.get("mfcc_window"), meta.get("folds", 5))
        if not obj.enabled:
            return obj
        sub = {k.split("/", 1)[1]: v for k, v in arrays.items() if k.startswith("context_view/")}
        try:
            obj.features_ = ContextFeatures.from_saved(meta["features"], sub)
            obj.coef_ = np.asarray(sub["coef"], np.float64)
            obj.intercept_ = np.asarray(sub["intercept"], np.float64)
        except KeyError as exc:
            raise ValueError(f"context view: saved model lacks {exc}") from None
        obj.alpha_ = meta.get("alpha")
        if obj.coef_.shape != (obj.features_.n_features, obj.intercept_.shape[0]):
            raise ValueError(f"context view: coef has shape {obj.coef_.shape}, expected "
                             f"({obj.features_.n_features}, {obj.intercept_.shape[0]})")
        return obj
