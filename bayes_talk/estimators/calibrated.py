"""An estimator with band-calibrated predictive bands, wrapping another,
as scikit-learn's ``CalibratedClassifierCV`` wraps a classifier.

:class:`BandCalibrated` holds a fitted estimator with a whole-utterance posterior (a
switching SGPDM) and the :class:`~bayes_talk.calibration.bands.BandCalibration`
of one of its inference methods (stages 0-3: mean shrinkage, band scale, level map, pool
with the constant band; fitted on held-out *training* utterances by
:func:`~bayes_talk.calibration.bands.fit_band_calibration`). Its ``predict_dist``
is the wrapped estimator's, recalibrated when the result is of the calibrated method
(``result.method == calibration.method``) and returned as it is otherwise (e.g. the
sequential path, or another sampler). It saves and loads as every estimator
(:meth:`Estimator.save <bayes_talk.estimators.base.Estimator.save>`): the calibration in its
descriptor (:meth:`BandCalibration.to_dict`; every calibration format, versions 1-5, is
read), the wrapped estimator in the sub-directory ``estimator``.
"""
from __future__ import annotations

from typing import Any, ClassVar, Self

import numpy as np

from bayes_talk.calibration import bands as band_calibration
from bayes_talk.calibration.bands import HOLDOUT_FRACTION, BandCalibration
from bayes_talk.data.utterance import Utterance
from bayes_talk.estimators.base import Estimator
from bayes_talk.posterior.methods import DEFAULT_DRAWS
from bayes_talk.synthesis.result import SynthesisResult

__all__ = ["BandCalibrated"]


class BandCalibrated(Estimator):
    """``estimator`` (unfitted for :meth:`fit`, fitted for :meth:`wrap`) with the band
    calibration of its ``method`` posterior, fitted on ``holdout`` of the training
    utterances with ``n_draws`` draws and seed ``seed``."""

    name: ClassVar[str] = "band-calibrated"

    @property
    def synthesis_options(self) -> dict[str, tuple[str, ...]]:  # type: ignore[override]
        """The wrapped estimator's choices (``synth`` offers them)."""
        return self.estimator.synthesis_options

    @property
    def post_filter(self) -> bool:  # type: ignore[override]
        """Whether ``synth`` low-passes the wrapped estimator's mean."""
        return self.estimator.post_filter

    def __init__(self, estimator: Estimator, method: str = "laplace", holdout: float = HOLDOUT_FRACTION,
                 n_draws: int = DEFAULT_DRAWS["laplace"], seed: int = 0) -> None:
        self.estimator, self.method, self.holdout = estimator, method, holdout
        self.n_draws, self.seed = n_draws, seed

    @classmethod
    def wrap(cls, estimator: Estimator, calibration: BandCalibration) -> Self:
        """A fitted estimator and its fitted calibration as one estimator (nothing is refitted)."""
        obj = cls(estimator, method=calibration.method)
        obj.estimator_, obj.calibration_ = estimator, calibration
        return obj

    def fit(self, train: list[Utterance], executor=None, progress=None) -> Self:
        """Fit the estimator on all of ``train`` (through ``executor`` where its ``fit`` takes
        one), then the calibration (one more fit on ``1 - holdout`` of ``train``, the rest
        synthesised: :func:`~bayes_talk.calibration.bands.fit_band_calibration`)."""
        fit_kw = {} if executor is None else {"executor": executor}
        self.estimator_ = self.estimator.fit(list(train), **fit_kw)
        self.calibration_ = band_calibration.fit_band_calibration(
            self.estimator_, train, method=self.method, holdout=self.holdout, n_draws=self.n_draws, seed=self.seed,
            executor=executor, progress=progress)
        return self

    def predict(self, utt: Utterance) -> np.ndarray:
        """The wrapped estimator's mean trajectory (its own path, never recalibrated)."""
        self._require_fitted()
        return self.estimator_.predict(utt)

    def calibrate(self, result: SynthesisResult) -> SynthesisResult:
        """``result`` recalibrated when it is of the calibrated method, else unchanged."""
        self._require_fitted()
        return self.calibration_.apply(result) if result.method == self.calibration_.method else result

    def predict_dist(self, utt: Utterance, **options: Any) -> SynthesisResult:
        """The wrapped estimator's ``predict_dist(utt, **options)``, recalibrated
        (:meth:`calibrate`)."""
        self._require_fitted()
        return self.calibrate(self.estimator_.predict_dist(utt, **options))

    def saved_estimators(self) -> dict[str, Estimator]:
        """The fitted wrapped estimator, saved in the sub-directory ``estimator``."""
        return {"estimator": self.estimator_}

    def _get_state(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        return {"calibration": self.calibration_.to_dict()}, {}

    def _set_state(self, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> None:
        self.calibration_ = BandCalibration.from_dict(meta["calibration"], where="calibration")
