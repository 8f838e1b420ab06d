"""From a corpus to a trained model directory, and from WAV + labels to a talking face.

The data flow of the command line (``bayes-talk train`` / ``bayes-talk synth``):

    corpus dir ──load_corpus──▶ Sequences (MFCC, AAM params, frame labels)
              ──fit──▶ model (switching SGPDM with VLMM or phone states, or the 2009 SGPLVM)
    WAV + .lab/.TextGrid ──read_utterance──▶ Sequence without visual features
              ──synthesize──▶ AAM trajectory + predictive variance ──AAM.render──▶ frames ──▶ MP4

A model directory holds ``bayes_talk_model.json`` (what kind of model, feature settings,
the AAM offset), the model's own JSON + NPZ files, and a copy of the corpus AAM
(``aam.json`` + ``aam.npz``) so that synthesis can render without the corpus.
"""
from __future__ import annotations

import json
import logging
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bayes_talk.data.sequence import Sequence
from bayes_talk.files import write_json, write_npy, write_npz

log = logging.getLogger(__name__)

MODEL_KINDS = ("ssgpdm-vlmm", "ssgpdm-phone", "sgplvm")
DESCRIPTOR = "bayes_talk_model.json"
DESCRIPTOR_FORMAT = "bayes_talk.trained_model"
DESCRIPTOR_VERSION = 1
LABEL_TOLERANCE_S = 0.08


def read_utterance(wav: str | os.PathLike, labels: str | os.PathLike, fps: float = 25.0) -> Sequence:
    """MFCCs and frame labels of a WAV and its HTK .lab or Praat TextGrid.

    Raises ValueError naming both files when the labels and the audio disagree in length
    by more than two frames.
    """
    from bayes_talk.data.labels import frame_labels, read_labels
    from bayes_talk.features.mfcc import frame_count, load_wav, mfcc

    wav, labels = Path(wav), Path(labels)
    y, sr = load_wav(wav)
    intervals = read_labels(labels)
    dur, end = y.size / sr, intervals[-1][1]
    if abs(end - dur) > LABEL_TOLERANCE_S:
        raise ValueError(f"{labels}: labels end at {end:.3f} s but {wav} lasts {dur:.3f} s "
                         f"(audio and labels must describe the same utterance)")
    T = frame_count(y.size, sr, fps)
    feats = mfcc(y, sr, T, fps=fps, where=str(wav))
    return Sequence(wav.stem, feats, None, frame_labels(intervals, T, fps), audio_path=wav)


def new_model(kind: str, **overrides):
    """An untrained model of the given kind (see :data:`MODEL_KINDS`)."""
    from bayes_talk.models.sgplvm import SGPLVM
    from bayes_talk.models.switching import SwitchingSGPDM

    if kind == "ssgpdm-vlmm":
        return SwitchingSGPDM(states="vlmm", **overrides)
    if kind == "ssgpdm-phone":
        return SwitchingSGPDM(states="phone", **overrides)
    if kind == "sgplvm":
        return SGPLVM(**overrides)
    raise ValueError(f"unknown model kind {kind!r}; choose one of {', '.join(MODEL_KINDS)}")


def fit_model(model, train: list[Sequence], workers: int = 2):
    """Fit, training the switching model's states in ``workers`` processes."""
    from bayes_talk.models.switching import SwitchingSGPDM

    if isinstance(model, SwitchingSGPDM) and workers > 1:
        with ProcessPoolExecutor(workers) as ex:
            return model.fit(train, executor=ex)
    return model.fit(train)


def train(corpus_dir: str | os.PathLike, kind: str, out_dir: str | os.PathLike, workers: int = 2,
          force: bool = False, alignment: bool = True, **overrides) -> Path:
    """Train a model of ``kind`` on every utterance of a corpus and save it to ``out_dir``.

    ``alignment``: also fit the aligner / phone recogniser (docs/alignment.md) into the
    same directory, so that ``synth`` runs from a transcript or from audio alone."""
    from bayes_talk.data.corpus import load_corpus

    out = Path(out_dir)
    if kind not in MODEL_KINDS:
        raise ValueError(f"unknown model kind {kind!r}; choose one of {', '.join(MODEL_KINDS)}")
    if out.exists() and any(out.iterdir()) and not force:
        raise FileExistsError(f"{out} is not empty; choose another directory or pass --force")
    corpus = load_corpus(corpus_dir)
    model = fit_model(new_model(kind, **overrides), list(corpus.sequences), workers)
    out.mkdir(parents=True, exist_ok=True)
    if kind == "sgplvm":
        model.save(out / "sgpdm")
    else:
        model.save(out)
    offset = _aam_offset(corpus)
    if corpus.aam is not None:
        corpus.aam.save(out / "aam.npz")
    write_json(out / DESCRIPTOR, {
        "format": DESCRIPTOR_FORMAT, "version": DESCRIPTOR_VERSION, "kind": kind,
        "corpus": str(Path(corpus_dir).resolve()), "n_train": len(corpus.sequences),
        "fps": corpus.fps, "aam_offset": offset.tolist(), "has_aam": corpus.aam is not None,
    })
    if alignment:  # issue 13: labels for test audio without hand-made phone labels
        from bayes_talk.alignment.commands import fit_alignment

        fit_alignment(corpus.sequences).save(out)
    return out


def _aam_offset(corpus) -> np.ndarray:
    """What to add back to mean-removed AAM parameters before rendering: the AAM's own mean
    parameters plus the average of the removed per-sequence means."""
    means = [s.meta["aam_mean"] for s in corpus.sequences if "aam_mean" in s.meta]
    Dz = corpus.sequences[0].aam.shape[1]
    avg = np.mean(means, axis=0) if means else np.zeros(Dz)
    return np.asarray(avg, dtype=np.float64)


@dataclass
class TrainedModel:
    kind: str
    model: object
    aam: object | None
    offset: np.ndarray
    fps: float


def load_trained(model_dir: str | os.PathLike) -> TrainedModel:
    """Load a directory written by :func:`train`; errors name the file and the problem."""
    from bayes_talk.features.aam import AAM
    from bayes_talk.models.sgplvm import SGPLVM
    from bayes_talk.models.switching import SwitchingSGPDM

    d = Path(model_dir)
    p = d / DESCRIPTOR
    if not p.exists():
        raise FileNotFoundError(f"{d} is not a bayes_talk model directory (no {DESCRIPTOR})")
    try:
        desc = json.loads(p.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{p} is truncated or not JSON ({exc})") from None
    if desc.get("format") != DESCRIPTOR_FORMAT or desc.get("version") != DESCRIPTOR_VERSION:
        raise ValueError(f"{p}: format {desc.get('format')!r} version {desc.get('version')!r}; this "
                         f"bayes_talk reads {DESCRIPTOR_FORMAT!r} version {DESCRIPTOR_VERSION}")
    kind = desc["kind"]
    model = SGPLVM.load(d / "sgpdm") if kind == "sgplvm" else SwitchingSGPDM.load(d)
    aam = AAM.load(d / "aam.npz") if desc.get("has_aam") else None
    return TrainedModel(kind, model, aam, np.asarray(desc["aam_offset"]), float(desc.get("fps", 25.0)))


POSTERIORS = ("map", "laplace", "nuts", "emcee")


def synth(model_dir, wav, labels, out_dir, algorithm: str = "optimise", init: str | None = None,
          force: bool = False, video: bool = True, posterior: str = "map", n_draws: int = 64,
          seed: int = 0, text: str | None = None, transcript: str | os.PathLike | None = None,
          align_method: str | None = None) -> dict[str, Path]:
    """Synthesise a face for WAV + labels; writes the AAM trajectory, its variance, the
    landmarks, the segmentation and an MP4 with the audio into ``out_dir``.

    posterior: "map" (the model's MAP path and GP variance) or, for a switching model, a
    sampler of the synthesis posterior ("laplace", "nuts", "emcee"; docs/uncertainty.md):
    then the trajectory and variance are the posterior mixture's mean and variance, and
    ``bands.npz`` (central 50 % and 90 % bands: lower50, upper50, lower90, upper90) and
    ``diagnostics.json`` (R-hat, ESS, divergences per segment) are written too.

    Without ``labels`` (issue 13): the phone labels come from aligning ``text`` (or the
    ``transcript`` file) to the audio, or, with neither, from the phone recogniser (a
    warning says so); they are written to ``labels.lab`` in ``out_dir``.
    """
    from bayes_talk.video import write_video

    if posterior not in POSTERIORS:
        raise ValueError(f"posterior must be one of {POSTERIORS}, got {posterior!r}")
    tm = load_trained(model_dir)
    if posterior != "map" and tm.kind == "sgplvm":
        raise ValueError(f"--posterior {posterior} needs a switching model; this model is {tm.kind!r} "
                         "(its variances are calibrated on held-out data instead)")
    derived = None
    if labels is None:
        derived = _derived_labels(model_dir, wav, text, transcript, align_method)
    elif text is not None or transcript is not None:
        raise ValueError("give either phone labels (--labels) or a transcript (--text/--transcript), not both")
    utt = read_utterance(wav, labels, tm.fps) if derived is None else _utterance_from_intervals(wav, derived, tm.fps)
    out = Path(out_dir)
    names = {"trajectory": "trajectory.npy", "variance": "variance.npy", "landmarks": "landmarks.npy",
             "segments": "segments.json", "video": "face.mp4"}
    if derived is not None:
        names["labels"] = "labels.lab"
    if posterior != "map":
        names.update(bands="bands.npz", diagnostics="diagnostics.json")
    existing = [n for n in names.values() if (out / n).exists()]
    if existing and not force:
        raise FileExistsError(f"{out} already holds {existing}; choose another directory or pass --force")
    out.mkdir(parents=True, exist_ok=True)
    if tm.kind == "sgplvm":
        res = tm.model.synthesize(utt.mfcc, utt.labels, init=init or "back-constraint")
        segs = []
    else:
        if init not in (None, "nn"):
            raise ValueError(f"the switching model initialises by nearest neighbour; --init {init} "
                             "applies to the sgplvm model")
        if posterior == "map":
            res = tm.model.synthesize(utt.mfcc, utt.labels, algorithm=algorithm)
        else:
            from bayes_talk.synthesis.posterior import sample_synthesis

            res = sample_synthesis(tm.model, utt.mfcc, utt.labels, method=posterior, n_draws=n_draws,
                                   seed=seed, algorithm=algorithm)
        segs = [{"state": list(s.state), "start": s.start, "stop": s.stop} for s in res.segments]
    written = {}
    if derived is not None:
        from bayes_talk.data.labels import write_lab

        write_lab(out / names["labels"], derived)
        written["labels"] = out / names["labels"]
    if posterior != "map":
        q = res.quantiles((0.5, 0.9))
        write_npz(out / names["bands"], {"lower50": q[0.5][0], "upper50": q[0.5][1],
                                         "lower90": q[0.9][0], "upper90": q[0.9][1]})
        write_json(out / names["diagnostics"], {"method": posterior, "n_draws": res.n_draws, "seed": seed,
                                                "summary": res.summary, "segments": res.diagnostics})
        written.update(bands=out / names["bands"], diagnostics=out / names["diagnostics"])
    for key, arr in (("trajectory", res.mean), ("variance", res.var)):
        write_npy(out / names[key], arr)
        written[key] = out / names[key]
    write_json(out / names["segments"], {"segments": segs, "fps": tm.fps})
    written["segments"] = out / names["segments"]
    if tm.aam is not None:
        params = res.mean + tm.offset
        lms, _ = tm.aam.reconstruct(params)
        write_npy(out / names["landmarks"], lms)
        written["landmarks"] = out / names["landmarks"]
        if video:
            write_video(out / names["video"], tm.aam.render(params), tm.fps, audio_path=wav, overwrite=True)
            written["video"] = out / names["video"]
    return written


def _derived_labels(model_dir, wav, text, transcript, align_method) -> list[tuple[float, float, str]]:
    """Phone intervals from the alignment models of ``model_dir`` (aligner or recogniser)."""
    from bayes_talk.alignment.commands import DEFAULT_ALIGN_METHOD, label_audio

    return label_audio(model_dir, wav, text=text, transcript=transcript,
                       method=align_method or DEFAULT_ALIGN_METHOD).intervals


def _utterance_from_intervals(wav, intervals, fps: float = 25.0) -> Sequence:
    """MFCCs and frame labels of a WAV whose phone intervals were derived from its audio."""
    from bayes_talk.data.labels import frame_labels
    from bayes_talk.features.mfcc import frame_count, load_wav, mfcc

    wav = Path(wav)
    y, sr = load_wav(wav)
    T = frame_count(y.size, sr, fps)
    return Sequence(wav.stem, mfcc(y, sr, T, fps=fps, where=str(wav)), None,
                    frame_labels(intervals, T, fps), audio_path=wav)
