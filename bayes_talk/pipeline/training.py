"""From a corpus to a trained model directory (``bayes-talk train``).

The data flow::

    corpus dir ──load_corpus──▶ Utterances (MFCC, AAM params, frame labels)
              ──fit──▶ model (any registered family: a switching SGPDM, the 2009 SGPLVM, a
                       baseline with a predictive distribution; estimators.registry)
              ──save──▶ model directory

A model directory holds ``bayes_talk_model.json`` (the descriptor, :mod:`bayes_talk.base.bundle`:
what kind of model, the audio front end of :mod:`bayes_talk.pipeline.front_end`, the AAM
offset), the estimator in ``estimator/`` (:meth:`Estimator.save
<bayes_talk.estimators.base.Estimator.save>`, the one layout: the band-calibrated wrapper when
trained with a calibration), a copy of the corpus AAM (``aam.json`` + ``aam.npz``) so that
synthesis can render without the corpus, and the aligner, and ends with ``bundle_manifest.json``.
"""
from __future__ import annotations

import inspect
import os
from pathlib import Path

import numpy as np

from bayes_talk import corpus as corpus_store
from bayes_talk.alignment import commands as alignment_commands
from bayes_talk.base import bundle
from bayes_talk.base.bundle import DESCRIPTOR, ESTIMATOR_DIR
from bayes_talk.base.executor import executor_for
from bayes_talk.base.progress import ProgressMapper
from bayes_talk.calibration.bands import CALIBRATED_MODELS, CALIBRATIONS, HOLDOUT_FRACTION
from bayes_talk.data.utterance import Utterance
from bayes_talk.estimators.calibrated import calibrate_model
from bayes_talk.estimators.registry import DEFAULT_MODEL, ESTIMATORS, make_estimator
from bayes_talk.pipeline.front_end import (
    DEFAULT_CMVN,
    FLOOR_DBFS,
    FMAX_HZ,
    LEVEL_DBFS,
    audio_settings,
)

__all__ = ["DEFAULT_CALIBRATED_MODEL", "DEFAULT_CALIBRATION", "DEFAULT_MODEL", "MODEL_KINDS", "aam_offset", "calibrates_bands", "fit_model",
           "model_kinds", "new_model", "select_holdout", "train"]


def model_kinds() -> tuple[str, ...]:
    """The families ``train`` fits and ``synth`` runs: every registered estimator with a
    predictive distribution that is a method, not an evaluation's floor or ceiling."""
    return tuple(name for name, (cls, _) in ESTIMATORS.items() if cls.has_distribution() and not cls.reference)


#: :func:`model_kinds` when this module was imported (``train --model`` choices)
MODEL_KINDS = model_kinds()
#: fraction of the training utterances ``train`` holds out for the band calibration by default
DEFAULT_CALIBRATION = HOLDOUT_FRACTION
#: which model ``train`` saves with a band calibration by default (CALIBRATED_MODELS)
DEFAULT_CALIBRATED_MODEL = "refit"


def new_model(kind: str, **overrides):
    """An untrained model of the given kind (see :data:`MODEL_KINDS`)."""
    if kind in model_kinds():
        return make_estimator(kind, **overrides)
    raise ValueError(f"unknown model kind {kind!r}; choose one of {', '.join(model_kinds())}")


def fit_model(model, train: list[Utterance], workers: int = 1, executor=None, scheduler: str | None = None):
    """Fit, training the switching model's states through ``executor`` (bayes_talk.base.executor:
    "local", "processes", "dask" or an ``Executor``, left open; None: ``workers`` processes,
    or this process when ``workers`` is 1, the default; ``scheduler``: a running dask scheduler), with a
    progress bar of states done / total on a terminal (bayes_talk.base.progress). The model
    does not depend on the executor."""
    if "executor" not in inspect.signature(model.fit).parameters:
        return model.fit(train)
    with executor_for(executor, workers, scheduler) as ex:
        return model.fit(train, executor=ProgressMapper(ex, "training states", "state"))


def train(corpus_dir: str | os.PathLike, kind: str, out_dir: str | os.PathLike, workers: int = 1,
          force: bool = False, holdout: int | None = None,
          holdout_list: str | os.PathLike | None = None, cmvn: str = DEFAULT_CMVN, fmax: float | None = FMAX_HZ,
          floor_dbfs: float | None = FLOOR_DBFS, level_dbfs: float | None = LEVEL_DBFS,
          alignment: bool = True, executor=None, scheduler: str | None = None,
          calibrate_bands: float | None = None, calibrated_model: str = DEFAULT_CALIBRATED_MODEL,
          calibration: str = "noise", **overrides) -> Path:
    """Train a model of ``kind`` on a corpus and save it to ``out_dir``.

    Every utterance is used unless some are held out: ``holdout`` = N, the corpus's last N
    utterances (corpus order), or ``holdout_list``, a file naming them one a line (see
    :func:`select_holdout`). The descriptor records the held-out names (``held_out``).

    ``cmvn``: per-utterance cepstral normalisation (bayes_talk.features.audio; ``DEFAULT_CMVN``, "mean");
    ``fmax``: mel filterbank edge (default ``features.frontend.FMAX_HZ``; None: sr/2, as before).
    ``floor_dbfs``: absolute mel-power floor (default ``features.frontend.FLOOR_DBFS``; None: none, as before).
    ``level_dbfs``: active-speech level every recording is scaled to before its MFCCs
    (default ``features.frontend.LEVEL_DBFS``; None: none, as before).
    The bundle records the audio front end (:func:`bayes_talk.pipeline.front_end.audio_settings`)
    and ends with ``bundle_manifest.json``, the SHA-256 of every file, written
    last (bayes_talk.base.bundle).

    ``alignment``: also fit the aligner / phone recogniser (docs/alignment.md) into the
    same directory, so that ``synth`` runs from a transcript or from audio alone.

    ``executor`` / ``scheduler``: what runs the featurisation and the per-state models
    (:func:`fit_model`; docs/scaling.md); the model does not depend on it. ``workers``:
    processes when no executor is given (default 1: this process; ``bayes-talk train``: 2).
    ``calibrate_bands``: a fraction (e.g. 0.2) of the training utterances to hold out; a
    model trained on the rest synthesises them (Laplace posterior) and ``calibration`` is
    fitted on them (switching models; :func:`~bayes_talk.estimators.calibrated.calibrate_model`):
    "noise", the face's observation term of the model (bayes_talk.synthesis.face_noise: mean
    shrinkage, Student-t scale per phone class, fitted by held-out log score; every inference
    method's predictive ends with it), "bands", the post-hoc four-stage band calibration
    (bayes_talk.calibration.bands; the model saved wrapped with it); None: neither, the GP
    predictive alone. ``calibrated_model``: which model is saved with it
    (:data:`~bayes_talk.calibration.bands.CALIBRATED_MODELS`): "holdout", the model
    trained on the other utterances, the one the calibration was fitted for (one fit);
    "refit", a second model trained on all of them, the factors carried over (two fits);
    "cv", the model trained on all of them with the factors fitted on out-of-fold syntheses
    of every utterance (round(1/calibrate_bands) folds: that many fits more).
    """
    out = Path(out_dir)
    if kind not in model_kinds():
        raise ValueError(f"unknown model kind {kind!r}; choose one of {', '.join(model_kinds())}")
    if out.exists() and any(out.iterdir()) and not force:
        raise FileExistsError(f"{out} is not empty; choose another directory or pass --force")
    if calibrate_bands is not None and (not calibrates_bands(kind) or not 0 < calibrate_bands < 1):
        raise ValueError(f"calibrate_bands: expected a fraction in (0, 1) for a model with a whole-utterance "
                         f"posterior (a switching model), found {calibrate_bands!r} for {kind}")
    if calibrated_model not in CALIBRATED_MODELS:
        raise ValueError(f"calibrated_model: expected one of {', '.join(CALIBRATED_MODELS)}, found {calibrated_model!r}")
    if calibration not in CALIBRATIONS:
        raise ValueError(f"calibration: expected one of {', '.join(CALIBRATIONS)}, found {calibration!r}")
    with executor_for(executor, workers, scheduler) as ex:
        corpus = corpus_store.load_corpus(corpus_dir, cmvn=cmvn, fmax=fmax, floor_dbfs=floor_dbfs, level_dbfs=level_dbfs,
                             executor=ex if executor is not None or ex.parallel else None)
        train_seqs, held_out = select_holdout(corpus.sequences, holdout, holdout_list, where=str(corpus_dir))
        corpus.sequences = train_seqs
        # the aligner is independent of the model: on an engine with workers it is fitted
        # in one of them beside the state models (a plain executor fits it at .result())
        aligner = ex.submit(alignment_commands.fit_alignment, list(corpus.sequences)) if alignment else None
        model = new_model(kind, **overrides)
        if calibrate_bands is not None:
            model = calibrate_model(model, list(corpus.sequences), calibrated_model, calibration,
                                    holdout=calibrate_bands, seed=model.get_params()["seed"], executor=ex)
        else:
            model = fit_model(model, list(corpus.sequences), workers=workers, executor=ex)
        aligner = aligner.result() if aligner is not None else None
    out.mkdir(parents=True, exist_ok=True)
    bundle.begin_bundle(out, DESCRIPTOR)
    audio = audio_settings(corpus, cmvn, fmax, floor_dbfs, level_dbfs)
    cal_info, cal_names = None, []
    if calibrate_bands is not None:
        fitted = model.face_noise_ if calibration == "noise" else model.calibration_
        cal_info = fitted.info
        cal_names = list(cal_info["names"] if calibration == "noise" else fitted.held_out)
    model.save(out / ESTIMATOR_DIR, overwrite=True)
    offset = aam_offset(corpus)
    if corpus.aam is not None:
        corpus.aam.save(out / "aam.npz")
    bundle.write_descriptor(out, {
        "kind": kind, "corpus": str(corpus_dir),   # as given: no machine's directory in a shared model
        "n_train": cal_info["n_fit"] if calibrated_model == "holdout" and cal_info is not None
        else len(corpus.sequences),
        "calibration": None if cal_info is None else {
            "kind": calibration, "model": calibrated_model, "holdout": calibrate_bands,
            "held_out": cal_names},
        "fps": corpus.fps, "aam_offset": offset.tolist(), "has_aam": corpus.aam is not None,
        "held_out": held_out, "audio": audio,
    })
    if aligner is not None:  # labels for test audio without hand-made phone labels
        aligner.save(out)
    bundle.write_bundle_manifest(out)
    return out


def calibrates_bands(kind: str) -> bool:
    """Whether a model of ``kind`` takes a band calibration: it has a whole-utterance
    posterior (bayes_talk.calibration.bands calibrates its bands)."""
    return kind in ESTIMATORS and "posterior" in ESTIMATORS[kind][0].synthesis_options


def select_holdout(sequences: list[Utterance], holdout: int | None = None,
                   holdout_list: str | os.PathLike | None = None,
                   where: str = "corpus") -> tuple[list[Utterance], list[str]]:
    """(training sequences, held-out names): the last ``holdout`` utterances, or those
    named in the file ``holdout_list`` (one name a line; blank lines and ``#`` comments
    skipped). ValueError naming the problem: both given, N outside [0, n - 1], an unknown
    or repeated name, or nothing left to train on."""
    seqs = list(sequences)
    if holdout is not None and holdout_list is not None:
        raise ValueError("give either holdout (a count) or holdout_list (a file), not both")
    if holdout is not None:
        if not isinstance(holdout, (int, np.integer)) or isinstance(holdout, bool) or not 0 <= holdout < len(seqs):
            raise ValueError(f"holdout: expected an integer in [0, {len(seqs) - 1}] for the "
                             f"{len(seqs)} utterances of {where}, found {holdout!r}")
        names = [s.name for s in seqs[len(seqs) - int(holdout):]] if holdout else []
    elif holdout_list is not None:
        path = Path(holdout_list)
        try:
            lines = path.read_text(encoding="utf-8").splitlines()
        except (OSError, UnicodeDecodeError) as exc:
            raise ValueError(f"{path}: cannot read the hold-out list ({exc})") from exc
        names = [ln.split("#", 1)[0].strip() for ln in lines]
        names = [n for n in names if n]
        known = {s.name for s in seqs}
        unknown = [n for n in names if n not in known]
        if unknown:
            raise ValueError(f"{path}: utterance(s) {unknown[:5]} are not in {where} "
                             f"(its names look like {seqs[0].name!r})")
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"{path}: utterance(s) {dup[:5]} listed more than once")
        if len(names) >= len(seqs):
            raise ValueError(f"{path}: holds out all {len(seqs)} utterances of {where}; nothing left to train on")
    else:
        return seqs, []
    out = set(names)
    return [s for s in seqs if s.name not in out], names


def aam_offset(corpus) -> np.ndarray:
    """What to add back to mean-removed AAM parameters before rendering: the AAM's own mean
    parameters plus the average of the removed per-sequence means."""
    means = [s.meta["aam_mean"] for s in corpus.sequences if "aam_mean" in s.meta]
    Dz = corpus.sequences[0].aam.shape[1]
    avg = np.mean(means, axis=0) if means else np.zeros(Dz)
    return np.asarray(avg, dtype=np.float64)
