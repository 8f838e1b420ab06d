"""Common interface of the published baselines (DESIGN §7).

Every baseline is a small estimator with scikit-learn-like ergonomics:

* ``fit(train: list[Utterance]) -> self`` learns from the audio (``mfcc``), the visual
  features (``aam``) and/or the frame labels of the training sequences;
* ``predict(seq) -> (T, D_z) ndarray`` generates visual features from ``seq.mfcc``
  and/or ``seq.labels`` only -- never from ``seq.aam``;
* ``log_likelihood(seq) -> float`` (only where the model defines one, see
  ``has_log_likelihood``) is the test log-likelihood of the ground-truth ``seq.aam``
  given what the model conditions on (documented per model);
* ``name`` is the registry key.

This module also holds the input checks and the label encoding shared by the
label-driven baselines (SLDS, DPDS, HMM mean).
"""
from __future__ import annotations

import warnings
from abc import ABC, abstractmethod
from collections import Counter
from typing import Any, ClassVar, Self

import numpy as np

from bayes_talk.data.phones import check_phone, substitute_unseen
from bayes_talk.data.utterance import Utterance
from bayes_talk.errors import not_fitted
from bayes_talk.estimators.base import Estimator

__all__ = ["Baseline", "LabelEncoder", "check_test", "check_train"]


class Baseline(Estimator, ABC):
    """Abstract audio/labels -> visual-feature generator (the estimator protocol of
    :mod:`bayes_talk.estimators.base`).

    Saving: every fitted attribute (name ending in ``_``) that is an array goes to the
    NPZ, a number / string / list / dict of those to the JSON, a :class:`LabelEncoder` to both; names in
    ``_derived`` are not saved but rebuilt by :meth:`_rebuild` after loading.
    """

    #: fitted attributes rebuilt from the saved ones by :meth:`_rebuild` (not saved)
    _derived: ClassVar[tuple[str, ...]] = ()

    #: registry key ("voice-puppetry", "slds", "dpds", "hmm-mean")
    name: ClassVar[str] = ""
    #: whether :meth:`log_likelihood` is defined for this model
    has_log_likelihood: ClassVar[bool] = False

    #: visual dimension D_z seen in training (set by ``fit``)
    n_visual_: int
    #: audio dimension D_y seen in training (set by ``fit``)
    n_audio_: int

    @abstractmethod
    def fit(self, train: list[Utterance]) -> Self:
        """Learn the model from training sequences (with ``aam``); returns ``self``."""

    @abstractmethod
    def predict(self, seq: Utterance) -> np.ndarray:
        """Generate the (T, D_z) visual trajectory of ``seq`` (``seq.aam`` is not used)."""

    def log_likelihood(self, seq: Utterance) -> float:
        """Test log-likelihood of ``seq.aam``; not defined for this model."""
        raise NotImplementedError(f"{type(self).__name__} ({self.name}) defines no test log-likelihood")

    def _check_fitted(self) -> None:
        if not hasattr(self, "n_visual_"):
            raise not_fitted(self, "call fit(train) first")

    def _is_fitted(self) -> bool:
        return hasattr(self, "n_visual_")

    def _get_state(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        meta: dict[str, Any] = {}
        arrays: dict[str, np.ndarray] = {}
        for k, v in sorted(vars(self).items()):
            if not k.endswith("_") or k.startswith("_") or k in self._derived:
                continue
            if isinstance(v, np.ndarray):
                arrays[k] = v
            elif isinstance(v, LabelEncoder):
                meta[k] = {"label_encoder": v.classes_}
                arrays[k] = v.counts_
            elif isinstance(v, np.generic):
                meta[k] = v.item()
            elif v is None or isinstance(v, (bool, int, float, str, list, dict)):
                meta[k] = v
            else:
                raise TypeError(f"{type(self).__name__}.{k}: cannot save a {type(v).__name__}; "
                                "list it in _derived and rebuild it in _rebuild")
        return meta, arrays

    def _set_state(self, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> None:
        for k, v in meta.items():
            if isinstance(v, dict) and "label_encoder" in v:
                setattr(self, k, LabelEncoder.from_counts(list(v["label_encoder"]), arrays[k]))
            else:
                setattr(self, k, v)
        for k, a in arrays.items():
            if k not in meta:
                setattr(self, k, np.asarray(a))
        self._rebuild()

    def _rebuild(self) -> None:
        """Recompute the ``_derived`` attributes after loading (nothing by default)."""


def check_train(train: list[Utterance], *, min_sequences: int = 1) -> tuple[int, int]:
    """Validate a training set; return (D_y, D_z).

    Raises ValueError if the list is empty, an item is not a :class:`Utterance`, a sequence
    has no ``aam``, is empty, or the feature dimensions differ between sequences.
    """
    if isinstance(train, Utterance):
        raise ValueError("train must be a list of Utterance objects, got a single Utterance")  # noqa: TRY004
    train = list(train)
    if len(train) < min_sequences:
        raise ValueError(f"need at least {min_sequences} training sequence(s), got {len(train)}")
    d_y = d_z = None
    for s in train:
        if not isinstance(s, Utterance):
            raise ValueError(f"train must contain Utterance objects, got {type(s).__name__}")  # noqa: TRY004
        if s.aam is None:
            raise ValueError(f"training sequence {s.name!r} has no visual features (aam is None)")
        if s.n_frames < 1:
            raise ValueError(f"training sequence {s.name!r} has no frames")
        if d_y is None:
            d_y, d_z = s.mfcc.shape[1], s.aam.shape[1]
        if s.mfcc.shape[1] != d_y:
            raise ValueError(f"sequence {s.name!r}: mfcc has {s.mfcc.shape[1]} columns, expected {d_y}")
        if s.aam.shape[1] != d_z:
            raise ValueError(f"sequence {s.name!r}: aam has {s.aam.shape[1]} columns, expected {d_z}")
    return int(d_y), int(d_z)


def check_test(seq: Utterance, *, n_audio: int | None = None, n_visual: int | None = None,
               need_aam: bool = False) -> None:
    """Validate a test sequence against the fitted dimensions (ValueError on mismatch)."""
    if not isinstance(seq, Utterance):
        raise ValueError(f"expected a Utterance, got {type(seq).__name__}")  # noqa: TRY004
    if seq.n_frames < 1:
        raise ValueError(f"sequence {seq.name!r} has no frames")
    if n_audio is not None and seq.mfcc.shape[1] != n_audio:
        raise ValueError(
            f"sequence {seq.name!r}: mfcc has shape {seq.mfcc.shape}, expected (T, {n_audio})")
    if need_aam:
        if seq.aam is None:
            raise ValueError(f"sequence {seq.name!r} has no ground-truth aam to score")
        if n_visual is not None and seq.aam.shape[1] != n_visual:
            raise ValueError(
                f"sequence {seq.name!r}: aam has shape {seq.aam.shape}, expected (T, {n_visual})")


class LabelEncoder:
    """Map phone labels to the integer indices of the labels seen in training.

    ``fit`` validates every label against the package phone set (``check_phone``) and
    keeps the labels that occur, sorted. ``encode`` maps a label sequence to indices; a
    valid phone never seen in training is replaced (with a ``UserWarning``) by the
    package's one unseen-phone policy, :func:`bayes_talk.data.phones.substitute_unseen`
    (the most frequent training phone of the same MPEG-4 viseme, else the most frequent
    training phone). Labels outside the phone set raise ValueError.
    """

    def fit(self, sequences: list[Utterance]) -> Self:
        """Learn the label set and each label's count from ``sequences``; returns ``self``."""
        counts: Counter[str] = Counter()
        for s in sequences:
            for lab in s.labels:
                check_phone(lab, where=f"sequence {s.name!r}")
            counts.update(s.labels)
        self.classes_: list[str] = sorted(counts)
        self.index_: dict[str, int] = {p: i for i, p in enumerate(self.classes_)}
        self.counts_: np.ndarray = np.array([counts[p] for p in self.classes_], dtype=np.int64)
        return self

    @classmethod
    def from_counts(cls, classes: list[str], counts: np.ndarray) -> LabelEncoder:
        """A fitted encoder from its ``classes_`` and ``counts_`` (e.g. read from a saved model)."""
        counts = np.asarray(counts, dtype=np.int64)
        if len(classes) != counts.shape[0] or counts.ndim != 1:
            raise ValueError(f"{len(classes)} classes but counts of shape {counts.shape}")
        if list(classes) != sorted(set(classes)):
            raise ValueError("classes must be sorted and distinct")
        for lab in classes:
            check_phone(lab, where="label encoder")
        enc = cls()
        enc.classes_ = list(classes)
        enc.index_ = {p: i for i, p in enumerate(enc.classes_)}
        enc.counts_ = counts
        return enc

    @property
    def n_classes(self) -> int:
        """Number of labels seen in training."""
        return len(self.classes_)

    def substitute(self, label: str) -> str:
        """Training phone used in place of an unseen (valid) phone."""
        return substitute_unseen(label, dict(zip(self.classes_, self.counts_.tolist(), strict=True)))

    def encode(self, labels: list[str], where: str = "") -> np.ndarray:
        """Integer indices (int64) of ``labels``; see the class docstring for unseen phones."""
        out = np.empty(len(labels), dtype=np.int64)
        unseen: dict[str, str] = {}
        for t, lab in enumerate(labels):
            i = self.index_.get(lab)
            if i is None:
                check_phone(lab, where=where)
                sub = unseen.setdefault(lab, self.substitute(lab))
                i = self.index_[sub]
            out[t] = i
        if unseen:
            pairs = ", ".join(f"{k!r}->{v!r}" for k, v in sorted(unseen.items()))
            loc = f" in {where}" if where else ""
            warnings.warn(f"phones not seen in training{loc} replaced: {pairs}", UserWarning,
                          stacklevel=3)
        return out
