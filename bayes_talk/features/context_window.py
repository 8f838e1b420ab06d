"""The context-window features of the context regressions: one-hot phone
labels and standardised MFCCs in windows of ±L / ±M frames around each frame
(:mod:`bayes_talk.estimators.baselines.context` describes the method)."""
from __future__ import annotations

from collections.abc import Sequence as Seq
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp

from bayes_talk.data.phones import SILENCE
from bayes_talk.data.utterance import Utterance, check_test
from bayes_talk.features.phone_encoding import LabelEncoder

__all__ = ["LABEL_WINDOWS", "MFCC_WINDOWS", "ContextFeatures", "Window", "stack_context", "window_grid"]

#: default grids of the cross-validated window half-widths
LABEL_WINDOWS: tuple[int, ...] = (2, 4, 8)
MFCC_WINDOWS: tuple[int | None, ...] = (None, 4)

Window = int | None


def window_grid(value: Window | Seq[Window], what: str, allow_none: bool = True) -> tuple[Window, ...]:
    """The candidate half-widths given as one value or a sequence (ValueError if invalid)."""
    vals = list(value) if isinstance(value, (list, tuple)) else [value]
    if not vals:
        raise ValueError(f"{what}: empty grid")
    for v in vals:
        if v is None:
            if not allow_none:
                raise ValueError(f"{what}: None is not allowed")
            continue
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 0:
            raise ValueError(f"{what} must be a non-negative integer{' or None' if allow_none else ''}, "
                             f"got {v!r}")
    return tuple(dict.fromkeys(None if v is None else int(v) for v in vals))


@dataclass
class ContextFeatures:
    """The map (CTX) from an utterance to its (T, F) context matrix.

    encoder: fitted label encoder (P = ``encoder.n_classes``); label_window: L or None;
    mfcc_window: M or None; mfcc_mean, mfcc_scale: (D_y,) training standardisation.
    """

    encoder: LabelEncoder
    label_window: int | None
    mfcc_window: int | None
    mfcc_mean: np.ndarray
    mfcc_scale: np.ndarray

    @classmethod
    def fit(cls, train: list[Utterance], label_window: int | None, mfcc_window: int | None) -> ContextFeatures:
        """Encoder and MFCC statistics from the training utterances only."""
        if label_window is None and mfcc_window is None:
            raise ValueError("label_window and mfcc_window cannot both be None (no inputs)")
        y = np.concatenate([s.mfcc for s in train])
        scale = y.std(axis=0)
        scale[scale <= 0] = 1.0
        return cls(LabelEncoder().fit(train), label_window, mfcc_window, y.mean(axis=0), scale)

    @property
    def n_features(self) -> int:
        """Number of columns of :meth:`transform`'s output."""
        P, Dy = self.encoder.n_classes, self.mfcc_mean.shape[0]
        lab = 0 if self.label_window is None else (2 * self.label_window + 1) * P
        aud = 0 if self.mfcc_window is None else (2 * self.mfcc_window + 1) * Dy
        return lab + aud

    def columns(self, label_window: int | None, mfcc_window: int | None) -> np.ndarray:
        """Column indices, within this (wider) context, of the context (label_window, mfcc_window)."""
        P, Dy = self.encoder.n_classes, self.mfcc_mean.shape[0]
        cols = []
        L = self.label_window or 0
        if label_window is not None:
            if self.label_window is None or label_window > L:
                raise ValueError(f"label window {label_window} is not inside {self.label_window}")
            for k in range(-label_window, label_window + 1):
                cols.append(np.arange(P) + (k + L) * P)
        if mfcc_window is not None:
            if self.mfcc_window is None or mfcc_window > self.mfcc_window:
                raise ValueError(f"MFCC window {mfcc_window} is not inside {self.mfcc_window}")
            base = 0 if self.label_window is None else (2 * L + 1) * P
            for k in range(-mfcc_window, mfcc_window + 1):
                cols.append(base + np.arange(Dy) + (k + self.mfcc_window) * Dy)
        return np.concatenate(cols) if cols else np.zeros(0, dtype=np.int64)

    def transform(self, seq: Utterance, sparse: bool = False) -> np.ndarray | sp.csr_matrix:
        """(T, F) context matrix (CTX) of ``seq`` (labels and mfcc; never ``aam``)."""
        T = seq.n_frames
        blocks: list[Any] = []
        if self.label_window is not None:
            L, P = self.label_window, self.encoder.n_classes
            idx = self.encoder.encode(seq.labels, where=f"sequence {seq.name!r}")
            pad = self.encoder.index_.get(SILENCE, -1)
            padded = np.concatenate([np.full(L, pad), idx, np.full(L, pad)])
            W = 2 * L + 1
            # column of frame t in block j (offset j − L): j·P + π_{t+j−L}
            cls = np.stack([padded[j:j + T] for j in range(W)], axis=1)       # (T, W)
            col = cls + P * np.arange(W)[None, :]
            rows = np.repeat(np.arange(T), W)
            keep = (cls >= 0).ravel()
            blocks.append(sp.csr_matrix((np.ones(int(keep.sum())), (rows[keep], col.ravel()[keep])),
                                        shape=(T, W * P)))
        if self.mfcc_window is not None:
            M = self.mfcc_window
            ys = (seq.mfcc - self.mfcc_mean) / self.mfcc_scale
            ys = np.pad(ys, ((M, M), (0, 0)), mode="edge")
            blocks.append(sp.csr_matrix(np.hstack([ys[j:j + T] for j in range(2 * M + 1)])))
        X = sp.hstack(blocks, format="csr") if len(blocks) > 1 else blocks[0].tocsr()
        return X if sparse else X.toarray()

    def check(self, seq: Utterance) -> None:
        """Validate a test utterance against the training audio dimension."""
        check_test(seq, n_audio=self.mfcc_mean.shape[0])

    # -- persistence
    def to_meta(self) -> dict[str, Any]:
        """JSON-able description of the fitted windows (saved with the model)."""
        return {"label_window": self.label_window, "mfcc_window": self.mfcc_window,
                "classes": list(self.encoder.classes_)}

    def arrays(self) -> dict[str, np.ndarray]:
        """The fitted arrays (saved with the model)."""
        return {"class_counts": self.encoder.counts_, "mfcc_mean": self.mfcc_mean,
                "mfcc_scale": self.mfcc_scale}

    @classmethod
    def from_saved(cls, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> ContextFeatures:
        """Features restored from :meth:`to_meta` and :meth:`arrays`."""
        enc = LabelEncoder.from_counts(list(meta["classes"]), arrays["class_counts"])
        lw = window_grid(meta["label_window"], "label_window")[0]
        mw = window_grid(meta["mfcc_window"], "mfcc_window")[0]
        mean = np.asarray(arrays["mfcc_mean"], dtype=np.float64)
        scale = np.asarray(arrays["mfcc_scale"], dtype=np.float64)
        if mean.ndim != 1 or scale.shape != mean.shape:
            raise ValueError(f"mfcc_mean {mean.shape} and mfcc_scale {scale.shape} must be equal 1-D shapes")
        return cls(enc, lw, mw, mean, scale)


def stack_context(feats: ContextFeatures, train: list[Utterance]) -> tuple[sp.csr_matrix, np.ndarray, np.ndarray]:
    """(X sparse (N, F), Z (N, D_z), groups (N,) utterance names) of the training frames."""
    X = sp.vstack([feats.transform(s, sparse=True) for s in train], format="csr")
    Z = np.concatenate([s.aam for s in train])
    groups = np.concatenate([np.full(s.n_frames, s.name, dtype=object) for s in train]).astype(str)
    return X, Z, groups
