"""A trained-model directory, read back (``bayes-talk synth``, ``align``, ``recognise``):
the descriptor (:func:`bayes_talk.bundle.read_descriptor`, every file checked against the
bundle's manifest), the model through its registered estimator class
(:data:`bayes_talk.estimators.registry.ESTIMATORS`; ``bundle_path`` says where its files
are), the corpus AAM, the audio front end and the band calibration."""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bayes_talk.audio import AudioSettings
from bayes_talk.bundle import DESCRIPTOR, BundleError, read_descriptor
from bayes_talk.estimators.registry import ESTIMATORS
from bayes_talk.features.aam import AAM
from bayes_talk.pipeline.training import model_kinds
from bayes_talk.synthesis.band_calibration import BandCalibration

__all__ = ["TrainedModel", "load_trained"]


@dataclass
class TrainedModel:
    """A loaded model directory: the model's ``kind`` (a registry family), the fitted
    estimator, the corpus AAM (or None), the offset added back to its mean-removed
    parameters, the frame rate, the audio front end and the band calibration (or None)."""

    kind: str
    model: object
    aam: object | None
    offset: np.ndarray
    fps: float
    audio: object = None  # bayes_talk.audio.AudioSettings
    calibration: object = None  # bayes_talk.synthesis.band_calibration.BandCalibration, if trained with one


def load_trained(model_dir: str | os.PathLike) -> TrainedModel:
    """Load a directory written by :func:`bayes_talk.pipeline.training.train`; errors name the file and the problem."""
    d = Path(model_dir)
    desc = read_descriptor(d)
    kind = desc["kind"]
    if kind not in ESTIMATORS:
        raise ValueError(f"{d / DESCRIPTOR}: kind {kind!r} is no registered model family (expected one of "
                         f"{', '.join(model_kinds())})")
    cls = ESTIMATORS[kind][0]
    model = cls.load(d / cls.bundle_path)
    aam = AAM.load(d / "aam.npz") if desc.get("has_aam") else None
    if aam is not None and aam.n_params != len(desc["aam_offset"]):
        raise BundleError(f"{d / 'aam.npz'}: an AAM with {aam.n_params} parameters, but the model in {d} "
                          f"was trained on {len(desc['aam_offset'])}: the AAM does not belong to this model")
    return TrainedModel(kind, model, aam, np.asarray(desc["aam_offset"]), float(desc.get("fps", 25.0)),
                        AudioSettings.from_dict(desc.get("audio"), where=str(d)), BandCalibration.load(d))
