"""The audio front end of a trained model, built in one place: the
settings ``train`` records in the model's bundle (:class:`bayes_talk.features.audio.AudioSettings`:
sample rate, MFCC settings, cepstral and level normalisation, mel edge and floor, feature statistics)
and the one computation of an utterance's features from a WAV with them, given its phone
labels (:func:`read_utterance`) or phone intervals derived from its audio
(:func:`utterance_from_intervals`). ``synth`` calls them with :func:`front_end`'s keywords,
so that new audio is featurised exactly as the training corpus was."""
from __future__ import annotations

import os
from pathlib import Path

from bayes_talk.data.checks import check_audio_vs_labels
from bayes_talk.data.labels import frame_labels, read_labels
from bayes_talk.data.utterance import Utterance
from bayes_talk.features.audio import DEFAULT_CMVN, AudioSettings, feature_statistics
from bayes_talk.features.audio import cmvn as apply_cmvn
from bayes_talk.features.frontend import FLOOR_DBFS, FMAX_HZ, LEVEL_DBFS
from bayes_talk.features.mfcc import frame_count, load_wav, mfcc

__all__ = ["DEFAULT_CMVN", "FLOOR_DBFS", "FMAX_HZ", "LEVEL_DBFS", "audio_settings", "corpus_front_end", "front_end",
           "read_utterance", "utterance_from_intervals"]


def audio_settings(corpus, cmvn: str = DEFAULT_CMVN, fmax: float | None = FMAX_HZ,
                   floor_dbfs: float | None = FLOOR_DBFS, level_dbfs: float | None = LEVEL_DBFS) -> dict:
    """The front end of a model trained on ``corpus`` (its sample rate and frame rate, the
    fixed MFCC settings, ``cmvn``, ``fmax``, ``floor_dbfs``, ``level_dbfs``) with the
    statistics of its features, as the bundle's descriptor records it (``audio``)."""
    audio = AudioSettings(sample_rate=int(corpus.sample_rate), fps=float(corpus.fps), cmvn=cmvn, fmax=fmax,
                          floor_dbfs=floor_dbfs, level_dbfs=level_dbfs).to_dict()
    audio["feature_statistics"] = feature_statistics([s.mfcc for s in corpus.sequences])
    return audio


def front_end(settings: AudioSettings) -> dict:
    """The keywords of :func:`read_utterance` / :func:`utterance_from_intervals` that
    featurise audio as a model with these ``settings`` was trained (all but ``fps``)."""
    return {"sample_rate": settings.sample_rate, "cmvn": settings.cmvn, "fmax": settings.fmax,
            "floor_dbfs": settings.floor_dbfs, "level_dbfs": settings.level_dbfs}


def corpus_front_end(settings: AudioSettings) -> dict:
    """The keywords of :func:`bayes_talk.corpus.load_corpus` that featurise a (test) corpus as
    a model with these ``settings`` was trained: its cepstral normalisation, mel edge, floor
    and level."""
    return {"cmvn": settings.cmvn, "fmax": settings.fmax, "floor_dbfs": settings.floor_dbfs,
            "level_dbfs": settings.level_dbfs}


def read_utterance(wav: str | os.PathLike, labels: str | os.PathLike, fps: float = 25.0, *,
                   sample_rate: int | None = None, cmvn: str = "off", tier: str | None = None,
                   fmax: float | None = None, floor_dbfs: float | None = None,
                   level_dbfs: float | None = None) -> Utterance:
    """MFCCs and frame labels of a WAV and its HTK .lab or Praat TextGrid.

    ``sample_rate``: resample the audio to it (the model's training rate; one log line);
    ``cmvn``: the model's cepstral normalisation (:func:`bayes_talk.features.audio.cmvn`); ``tier``:
    the TextGrid tier holding the phones; ``fmax``: the model's mel filterbank edge (None:
    sr/2, the front end of models trained before it was recorded); ``floor_dbfs``: its
    absolute mel-power floor (None: none, likewise); ``level_dbfs``: the active-speech level
    the audio is scaled to (:func:`bayes_talk.features.audio.normalise_level`; None: none,
    likewise). Raises ValueError
    naming both files when the labels and the audio disagree in length by more than two
    frames.
    """
    wav, labels = Path(wav), Path(labels)
    y, sr = load_wav(wav, sample_rate)
    intervals = read_labels(labels, tier=tier)
    check_audio_vs_labels(wav, labels, y.size / sr, intervals[-1][1])
    T = frame_count(y.size, sr, fps)
    feats = apply_cmvn(mfcc(y, sr, T, fps=fps, where=str(wav), fmax=fmax, floor_dbfs=floor_dbfs,
                            level_dbfs=level_dbfs), cmvn)
    return Utterance(wav.stem, feats, None, frame_labels(intervals, T, fps), audio_path=wav)


def utterance_from_intervals(wav, intervals, fps: float = 25.0, *, sample_rate: int | None = None,
                              cmvn: str = "off", fmax: float | None = None,
                              floor_dbfs: float | None = None, level_dbfs: float | None = None) -> Utterance:
    """MFCCs (the model's front end, as :func:`read_utterance`) and frame labels of a WAV
    whose phone intervals were derived from its audio."""
    wav = Path(wav)
    y, sr = load_wav(wav, sample_rate)
    T = frame_count(y.size, sr, fps)
    feats = apply_cmvn(mfcc(y, sr, T, fps=fps, where=str(wav), fmax=fmax, floor_dbfs=floor_dbfs,
                            level_dbfs=level_dbfs), cmvn)
    return Utterance(wav.stem, feats, None, frame_labels(intervals, T, fps), audio_path=wav)
