"""Per-phone mean face: the "standard HMM" baseline of englebienne2008 §4.

With the frame labels known, the HMM of englebienne2008 reduces to one Gaussian per
phone, and its most likely observation sequence is the mean visual vector of each
frame's phone -- the "obviously wrong model" that nevertheless scores well on error
(englebienne2008 §4):

    ẑ_t = m_{π_t},        m_π = mean{ z_t : π_t = π }  over the training frames.

Test log-likelihood (conditioned on the frame labels only, not on the audio):

    log p(Z | π_{1:T}) = Σ_t log N(z_t; m_{π_t}, diag(s²_{π_t})),

with s²_π the per-phone ML variance of each dimension, floored at ``var_floor`` times the
global variance of that dimension (a phone seen once has zero ML variance).

A label outside the phone set raises ValueError. A valid phone that never occurred in
training is replaced, with a UserWarning, by the package's one unseen-phone policy
(:func:`bayes_talk.data.phones.substitute_unseen`: the most frequent training phone of its
viseme, else the most frequent training phone).
"""
from __future__ import annotations

from typing import ClassVar, Self

import numpy as np

from bayes_talk.data.phones import check_phone, replace_unseen
from bayes_talk.data.utterance import Utterance, check_test
from bayes_talk.estimators.baselines.base import Baseline, check_train

__all__ = ["HMMMean"]


class HMMMean(Baseline):
    """Per-phone mean visual vector (diagonal Gaussian per phone for the likelihood).

    Parameters
    ----------
    var_floor : relative floor of the per-phone variances (fraction of the global variance).
    """

    name: ClassVar[str] = "hmm-mean"
    has_log_likelihood: ClassVar[bool] = True

    def __init__(self, var_floor: float = 1e-3) -> None:
        if not var_floor > 0:
            raise ValueError(f"var_floor must be > 0, got {var_floor}")
        self.var_floor = var_floor

    def fit(self, train: list[Utterance]) -> Self:
        """Per-phone mean and variance of the visual features (global ones for the fallback); returns ``self``."""
        d_y, d_z = check_train(train)
        z = np.concatenate([s.aam for s in train])
        labs: list[str] = []
        for s in train:
            for lab in s.labels:
                check_phone(lab, where=f"sequence {s.name!r}")
            labs.extend(s.labels)
        classes = sorted(set(labs))
        idx = np.searchsorted(np.array(classes), np.array(labs))
        counts = np.bincount(idx, minlength=len(classes)).astype(np.float64)
        sums = np.zeros((len(classes), d_z))
        np.add.at(sums, idx, z)
        means = sums / counts[:, None]
        sq = np.zeros((len(classes), d_z))
        np.add.at(sq, idx, (z - means[idx]) ** 2)
        self.global_mean_ = z.mean(axis=0)
        self.global_var_ = np.maximum(z.var(axis=0), np.finfo(np.float64).tiny)
        floor = self.var_floor * self.global_var_
        self.classes_: list[str] = classes
        self.counts_ = counts.astype(np.int64)
        self.means_ = means
        self.vars_ = np.maximum(sq / counts[:, None], floor)
        self.n_audio_, self.n_visual_ = d_y, d_z
        return self

    def _params(self, seq: Utterance) -> tuple[np.ndarray, np.ndarray]:
        index = {p: i for i, p in enumerate(self.classes_)}
        counts = dict(zip(self.classes_, self.counts_.tolist(), strict=True))
        labels = replace_unseen(seq.labels, counts, where=f"sequence {seq.name!r}", stacklevel=4)
        idx = np.array([index[lab] for lab in labels], dtype=np.int64)
        return self.means_[idx], self.vars_[idx]

    def predict(self, seq: Utterance) -> np.ndarray:
        """ẑ_t = m_{π_t} (unseen phones: :func:`bayes_talk.data.phones.substitute_unseen`)."""
        self._check_fitted()
        check_test(seq)
        return self._params(seq)[0]

    def predict_var(self, seq: Utterance) -> np.ndarray:
        """Per-frame variance: the training variance of each frame's phone (unseen phones as
        in :meth:`predict`)."""
        self._check_fitted()
        check_test(seq)
        return self._params(seq)[1]

    def log_likelihood(self, seq: Utterance) -> float:
        """Σ_t log N(z_t; m_{π_t}, diag s²_{π_t}) -- conditioned on the labels only."""
        self._check_fitted()
        check_test(seq, n_visual=self.n_visual_, need_aam=True)
        mean, var = self._params(seq)
        r = seq.aam - mean
        return float(-0.5 * np.sum(np.log(2 * np.pi * var) + r * r / var))
