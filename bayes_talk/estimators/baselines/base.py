"""Common interface of the published baselines (englebienne2008; deena2009 §4.3).

Every baseline is a small estimator with scikit-learn-like ergonomics:

* ``fit(train: list[Utterance]) -> self`` learns from the audio (``mfcc``), the visual
  features (``aam``) and/or the frame labels of the training sequences;
* ``predict(seq) -> (T, D_z) ndarray`` generates visual features from ``seq.mfcc``
  and/or ``seq.labels`` only -- never from ``seq.aam``;
* ``log_likelihood(seq) -> float`` (only where the model defines one, see
  ``has_log_likelihood``) is the test log-likelihood of the ground-truth ``seq.aam``
  given what the model conditions on (documented per model);
* ``name`` is the registry key.

This module also holds the training-input check shared by the baselines; the test-input
check is :func:`bayes_talk.data.utterance.check_test` and the label encoding
:class:`bayes_talk.features.phone_encoding.LabelEncoder`.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, ClassVar, Self

import numpy as np

from bayes_talk.base.errors import not_fitted
from bayes_talk.data.utterance import Utterance
from bayes_talk.estimators.base import Estimator
from bayes_talk.features.phone_encoding import LabelEncoder

__all__ = ["Baseline", "check_train"]


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


