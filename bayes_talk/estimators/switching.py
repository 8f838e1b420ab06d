"""The switching shared GPDM as an estimator (deena2010; docs/switching.md).

:class:`SwitchingSGPDM` is the generative model of :mod:`bayes_talk.models.switching`
(``fit``, state lookup, its saved ``state``; ``save`` / ``load`` are the estimator's) with the
inference of :mod:`bayes_talk.synthesis` on top: ``synthesize`` runs deena2010's
Algorithm 1 or 2 (:func:`bayes_talk.synthesis.sequential.synthesize`), ``predict`` returns
its mean, ``predict_dist`` its mean and GP predictive variance. The whole-utterance
posterior is :func:`bayes_talk.posterior.sampling.sample_synthesis` (it takes this
estimator as its model).
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

import numpy as np

from bayes_talk.data.utterance import Utterance
from bayes_talk.estimators.base import Estimator
from bayes_talk.models.switching import SwitchingModel
from bayes_talk.posterior import sampling as synthesis_posterior
from bayes_talk.posterior.methods import INFERENCE
from bayes_talk.synthesis.result import SynthesisResult
from bayes_talk.synthesis.sequential import SEGMENT_MAX_ITER, synthesize

__all__ = ["SwitchingSGPDM"]


class SwitchingSGPDM(SwitchingModel, Estimator):
    """Switching shared GPDM: ``fit`` on utterances, ``synthesize`` / ``predict`` /
    ``predict_dist`` from audio + labels (constructor arguments: :class:`SwitchingConfig
    <bayes_talk.models.switching.SwitchingConfig>`)."""

    #: "posterior": the names of the inference table, a live view (a method added to it is a choice)
    synthesis_options: ClassVar[dict[str, tuple[str, ...]]] = {
        "algorithm": ("optimise", "predict"), "init": ("nn",), "posterior": INFERENCE.keys()}
    post_filter: ClassVar[bool] = True

    def _is_fitted(self) -> bool:
        return bool(self.models_)

    def _get_state(self) -> tuple[dict, dict[str, np.ndarray]]:
        return self.state()

    def _set_state(self, meta: dict, arrays: dict[str, np.ndarray]) -> None:
        self.restore(meta, arrays)

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

    def predict_dist(self, seq: Utterance, posterior: str | None = None, *, n_draws: int | None = None,
                     seed: int = 0, log_warnings: bool = False, init: str = "nn", **kw) -> SynthesisResult:
        """The predictive distribution of ``seq``'s visual features.

        ``posterior`` None: deena2010's sequential path (Algorithm 1, or 2 with
        ``algorithm="predict"``; ``kw`` as :meth:`synthesize`), its mean and GP predictive
        variance, with latents and segments. A method of
        :data:`~bayes_talk.posterior.methods.INFERENCE` (e.g. "laplace"): the
        whole-utterance synthesis posterior,
        :func:`bayes_talk.posterior.sampling.sample_synthesis` with ``n_draws``, ``seed``
        and ``kw``; its failed convergence checks are in ``.warnings`` (logged too with
        ``log_warnings``). ``init``: the initialiser of the path, nearest neighbour ("nn"),
        the only one of the switching model."""
        if init != "nn":
            raise ValueError(f"the switching model initialises by nearest neighbour ('nn'), not {init!r}")
        if posterior is None:
            return self.synthesize(seq.mfcc, seq.labels, **kw)
        self._require_fitted()
        return synthesis_posterior.sample_synthesis(self, seq.mfcc, seq.labels, method=posterior, n_draws=n_draws,
                                                    seed=seed, log_warnings=log_warnings, **kw)
