"""An estimator with band-calibrated predictive bands, wrapping another,
as scikit-learn's ``CalibratedClassifierCV`` wraps a classifier.

:class:`BandCalibrated` holds a fitted estimator with a whole-utterance posterior (a
switching SGPDM) and the :class:`~bayes_talk.calibration.bands.BandCalibration`
of one of its inference methods (stages 0-3: mean shrinkage, band scale, level map, pool
with the constant band; fitted on held-out *training* utterances by
:func:`~bayes_talk.calibration.bands.fit_band_calibration`). Its ``predict_dist``
is the wrapped estimator's, recalibrated whatever inference method made it (one wrapper for
every method alike). It is the opt-in post-hoc alternative (``train --calibration bands``);
the default calibration is the observation term inside the model (:func:`calibrate_model`). It saves and loads as every estimator
(:meth:`Estimator.save <bayes_talk.estimators.base.Estimator.save>`): the calibration in its
descriptor (:meth:`BandCalibration.to_dict`; every calibration format, versions 1-5, is
read), the wrapped estimator in the sub-directory ``estimator``.
"""
from __future__ import annotations

from typing import Any, ClassVar, Self

import numpy as np

from bayes_talk.calibration import bands as band_calibration
from bayes_talk.calibration.bands import (
    CALIBRATIONS,
    HOLDOUT_FRACTION,
    BandCalibration,
    calibrated_fit,
)
from bayes_talk.calibration.noise_fit import held_out_fitter
from bayes_talk.data.utterance import Utterance
from bayes_talk.estimators.base import Estimator
from bayes_talk.posterior.methods import DEFAULT_DRAWS
from bayes_talk.synthesis.result import SynthesisResult

__all__ = ["CALIBRATIONS", "BandCalibrated", "calibrate_model"]


def calibrate_model(model, train: list[Utterance], calibrated_model: str = "refit", calibration: str = "noise",
                    holdout: float = HOLDOUT_FRACTION, n_draws: int = DEFAULT_DRAWS["laplace"], seed: int = 0,
                    method: str = "laplace", executor=None, progress=None, fit=None,
                    ablations: bool = False) -> Estimator:
    """The model to ship, trained on ``train`` with what ``calibration`` fits on held-out
    training utterances (:data:`CALIBRATIONS`) by the scheme ``calibrated_model``
    (:data:`~bayes_talk.calibration.bands.CALIBRATED_MODELS`; the held-out syntheses by the
    posterior ``method`` with ``n_draws`` draws): "noise", the switching model with its
    observation term set (:meth:`SwitchingSGPDM.with_face_noise`; ``ablations``: the
    term's ablations fitted too, for ``evaluate``); "bands", the model wrapped with its band
    calibration (:class:`BandCalibrated`). ``train``, ``demo`` and ``evaluate`` call this."""
    if calibration not in CALIBRATIONS:
        raise ValueError(f"calibration: expected one of {', '.join(CALIBRATIONS)}, found {calibration!r}")
    kw = {"method": method, "holdout": holdout, "n_draws": n_draws, "seed": seed, "executor": executor,
          "progress": progress, "fit": fit}
    if calibration == "noise":
        shipped, noise = calibrated_fit(model, train, calibrated_model, fitter=held_out_fitter(ablations), **kw)
        return shipped.with_face_noise(noise)
    shipped, cal = calibrated_fit(model, train, calibrated_model, **kw)
    return BandCalibrated.wrap(shipped, cal)


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
        """``result`` recalibrated, whatever inference method made it (the calibration was
        fitted on ``calibration_.method``'s held-out syntheses)."""
        self._require_fitted()
        return self.calibration_.apply(result)

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
