"""A trained-model directory, read back (``bayes-talk synth``, ``align``, ``recognise``):
the descriptor (:func:`bayes_talk.base.bundle.read_descriptor`, every file checked against the
bundle's manifest), the estimator saved in its ``estimator`` sub-directory
(:func:`bayes_talk.estimators.registry.load_estimator`: the class its own descriptor names;
the band-calibrated wrapper when the model was trained with a calibration), the corpus AAM
and the audio front end."""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bayes_talk.base.bundle import DESCRIPTOR, ESTIMATOR_DIR, BundleError, read_descriptor
from bayes_talk.calibration.bands import BandCalibration
from bayes_talk.estimators.base import Estimator
from bayes_talk.estimators.calibrated import BandCalibrated
from bayes_talk.estimators.registry import ESTIMATORS, load_estimator
from bayes_talk.features.aam import AAM
from bayes_talk.features.audio import AudioSettings
from bayes_talk.pipeline.training import model_kinds

__all__ = ["LEGACY_ESTIMATOR_PATHS", "TrainedModel", "load_trained"]

#: where a directory trained by an earlier version kept its estimator instead of ``estimator/``:
#: deena2009's SGPLVM as ``sgpdm.*``, the sparse SGPDM as ``sparse_sgpdm.*``; a switching
#: model as ``model.json`` + ``arrays.npz`` at the top, with ``band_calibration.json`` beside
LEGACY_ESTIMATOR_PATHS = ("sgpdm", "sparse_sgpdm")


@dataclass
class TrainedModel:
    """A loaded model directory: the model's ``kind`` (a registry family), the fitted
    estimator ``synth`` runs (a :class:`~bayes_talk.estimators.calibrated.BandCalibrated`
    when the model was trained with a band calibration), the corpus AAM (or None), the offset
    added back to its mean-removed parameters, the frame rate, the audio front end and the
    training corpus directory as ``train`` was given it (relative to where it ran; None when
    the descriptor has none) and the directory it was loaded from (its aligner and phone
    recogniser are read from there; None for a model not loaded from one)."""

    kind: str
    model: Estimator
    aam: AAM | None
    offset: np.ndarray
    fps: float
    audio: AudioSettings | None = None
    corpus: str | None = None
    directory: Path | None = None

    def training_corpus(self) -> Path:
        """The directory the model was trained on, checked to exist (benchmarks that rebuild the
        training set read it); a clear error when the descriptor names none or it is not here."""
        if self.corpus is None or not Path(self.corpus).is_dir():
            raise FileNotFoundError(f"{DESCRIPTOR}: the training corpus {self.corpus!r} is not a directory here "
                                    "(it is recorded as given to `bayes-talk train`, relative to where that ran)")
        return Path(self.corpus)

    @property
    def calibration(self) -> BandCalibration | None:
        """The model's band calibration (the wrapper's), or None."""
        return self.model.calibration_ if isinstance(self.model, BandCalibrated) else None

    @property
    def uncalibrated(self) -> Estimator:
        """The fitted estimator of the family, without its band calibration (raw bands; the
        generative model that the synthesis functions take)."""
        return self.model.estimator_ if isinstance(self.model, BandCalibrated) else self.model


def _estimator_path(d: Path) -> Path:
    """Where ``d`` keeps its estimator: ``estimator/``, or a place of :data:`LEGACY_ESTIMATOR_PATHS`,
    or (a switching model trained by an earlier version) ``d`` itself."""
    for rel in (ESTIMATOR_DIR, *LEGACY_ESTIMATOR_PATHS):
        if (d / rel).is_dir() or (d / f"{rel}.json").is_file():
            return d / rel
    return d


def load_trained(model_dir: str | os.PathLike) -> TrainedModel:
    """Load a directory written by :func:`bayes_talk.pipeline.training.train`; errors name the file and the problem."""
    d = Path(model_dir)
    desc = read_descriptor(d)
    kind = desc["kind"]
    if kind not in ESTIMATORS:
        raise ValueError(f"{d / DESCRIPTOR}: kind {kind!r} is no registered model family (expected one of "
                         f"{', '.join(model_kinds())})")
    where = _estimator_path(d)
    model = load_estimator(where)
    legacy_cal = BandCalibration.load(d) if where != d / ESTIMATOR_DIR else None
    if legacy_cal is not None:   # the earlier layout: the calibration beside the model
        model = BandCalibrated.wrap(model, legacy_cal)
    cls = ESTIMATORS[kind][0]
    family = model.estimator_ if isinstance(model, BandCalibrated) else model
    if not isinstance(family, cls):
        raise BundleError(f"{d / DESCRIPTOR}: kind {kind!r} is a {cls.__name__}, but the saved estimator is a "
                          f"{type(family).__name__}: the files do not belong together")
    aam = AAM.load(d / "aam.npz") if desc.get("has_aam") else None
    if aam is not None and aam.n_params != len(desc["aam_offset"]):
        raise BundleError(f"{d / 'aam.npz'}: an AAM with {aam.n_params} parameters, but the model in {d} "
                          f"was trained on {len(desc['aam_offset'])}: the AAM does not belong to this model")
    return TrainedModel(kind, model, aam, np.asarray(desc["aam_offset"]), float(desc.get("fps", 25.0)),
                        AudioSettings.from_dict(desc.get("audio"), where=str(d)), desc.get("corpus"), d)
