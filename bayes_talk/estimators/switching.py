"""The switching shared GPDM as an estimator (deena2010; docs/switching.md).

:class:`SwitchingSGPDM` is the generative model of :mod:`bayes_talk.models.switching`
(``fit``, state lookup, ``save`` / ``load`` of ``model.json`` + ``arrays.npz``) with the
inference of :mod:`bayes_talk.synthesis` on top: ``synthesize`` runs deena2010's
Algorithm 1 or 2 (:func:`bayes_talk.synthesis.sequential.synthesize`), ``predict`` returns
its mean, ``predict_dist`` its mean and GP predictive variance. The whole-utterance
posterior is :func:`bayes_talk.synthesis.posterior.sample_synthesis` (it takes this
estimator as its model).
"""
from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from bayes_talk.data.utterance import Utterance
from bayes_talk.estimators.base import Estimator
from bayes_talk.models.switching import SwitchingModel
from bayes_talk.synthesis.result import SynthesisResult
from bayes_talk.synthesis.sequential import SEGMENT_MAX_ITER, synthesize

__all__ = ["MEAN_FUNCTION_FILE", "SwitchingSGPDM"]

#: base name of the saved mean function (``.json`` + ``.npz``) in a model directory
MEAN_FUNCTION_FILE = "mean_function"


class SwitchingSGPDM(SwitchingModel, Estimator):
    """Switching shared GPDM: ``fit`` on utterances, ``synthesize`` / ``predict`` /
    ``predict_dist`` from audio + labels (constructor arguments: :class:`SwitchingConfig
    <bayes_talk.models.switching.SwitchingConfig>`)."""

    def _is_fitted(self) -> bool:
        return bool(self.models_)

    # -------------------------------------------------- the explicit mean function
    def fit(self, train: Sequence[Utterance], executor=None) -> SwitchingSGPDM:
        """:meth:`SwitchingModel.fit <bayes_talk.models.switching.SwitchingModel.fit>`;
        with ``mean_function="context-ridge"`` first the context ridge
        (:class:`~bayes_talk.baselines.context.ContextRidge`, windows and penalties by
        grouped cross-validation) on ``train``, then the state models on its out-of-fold
        residuals z_t − ĥ(x_t) (:func:`~bayes_talk.baselines.context.out_of_fold`)."""
        if self.mean_function is None:
            self.mean_model_ = None
            return super().fit(train, executor=executor)
        from bayes_talk.baselines.context import ContextRidge, out_of_fold

        train = list(train)
        self.mean_model_ = ContextRidge().fit(train)
        oof = out_of_fold(train, *self.mean_model_.windows_)
        residual = [dataclasses.replace(s, aam=s.aam - h) for s, h in zip(train, oof, strict=True)]
        return super().fit(residual, executor=executor)

    def visual_offset(self, mfcc: np.ndarray, labels: Sequence[str]) -> np.ndarray | None:
        """ĥ(x_t), the context ridge's prediction for this audio (T, D_z), or None without
        a mean function (see :class:`~bayes_talk.models.switching.SwitchingConfig`)."""
        if getattr(self, "mean_model_", None) is None:
            return None
        utt = Utterance(name="synthesis", mfcc=np.asarray(mfcc, np.float64), aam=None, labels=list(labels))
        return self.mean_model_.predict(utt)

    def save(self, directory: str | Path) -> Path:
        """``model.json`` + ``arrays.npz`` (and ``mean_function.json`` + ``.npz`` with a
        mean function) in ``directory``."""
        directory = super().save(directory)
        if getattr(self, "mean_model_", None) is not None:
            self.mean_model_.save(Path(directory) / MEAN_FUNCTION_FILE, overwrite=True)
        return directory

    @classmethod
    def load(cls, directory: str | Path) -> SwitchingSGPDM:
        """Read a model written by :meth:`save`."""
        obj = super().load(directory)
        obj.mean_model_ = None
        if obj.mean_function is not None:
            from bayes_talk.baselines.context import ContextRidge

            obj.mean_model_ = ContextRidge.load(Path(directory) / MEAN_FUNCTION_FILE)
        return obj

    def synthesize(self, mfcc: np.ndarray, labels: Sequence[str], algorithm: str = "optimise",
                   smoothness: str | bool = True, lowpass_hz: float | None = None,
                   max_iter: int | None = None) -> SynthesisResult:
        """Visual features for new audio: see :func:`bayes_talk.synthesis.sequential.synthesize`
        (``max_iter`` None: its ``SEGMENT_MAX_ITER``)."""
        self._require_fitted()
        return synthesize(self, mfcc, labels, algorithm=algorithm, smoothness=smoothness,
                          lowpass_hz=lowpass_hz, max_iter=SEGMENT_MAX_ITER if max_iter is None else max_iter)

    def predict(self, seq: Utterance, **kw) -> np.ndarray:
        """Mean AAM trajectory for a test utterance (uses its mfcc and labels only)."""
        return self.synthesize(seq.mfcc, seq.labels, **kw).mean

    def predict_dist(self, seq: Utterance, **kw) -> SynthesisResult:
        """Algorithm 1's mean and GP predictive variance (with latents and segments)."""
        return self.synthesize(seq.mfcc, seq.labels, **kw)
