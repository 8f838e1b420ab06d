"""Phone labels as integer classes: the label encoding of the label-driven models (the
context-window features, SLDS, DPDS, the per-phone mean)."""
from __future__ import annotations

import warnings
from collections import Counter
from typing import Self

import numpy as np

from bayes_talk.data.phones import check_phone, substitute_unseen
from bayes_talk.data.utterance import Utterance

__all__ = ["LabelEncoder"]


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
