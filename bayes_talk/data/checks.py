"""Checks of one utterance's inputs at the boundary, shared by the corpus loader
(:mod:`bayes_talk.corpus`) and synthesis from a WAV (:func:`bayes_talk.pipeline.read_utterance`).

Audio versus labels: the phone labels must end where the audio ends, within
:data:`LABEL_TOLERANCE_S` = 0.08 s, two video frames at 25 fps. Label tools round
boundaries to their own frame rate (10 ms for HTK, a frame for video-based tools) and
audio exports pad or trim a few milliseconds; more than two frames of disagreement means
the two files do not describe the same utterance (a shift that large moves every
phone's visual target by a frame or more). The corpus loader and the pipeline share this
one tolerance, so a corpus that synthesis accepts is not refused at training.
"""
from __future__ import annotations

from pathlib import Path

__all__ = ["LABEL_TOLERANCE_S", "check_audio_vs_labels"]

#: largest accepted |labels end - audio duration| in seconds (two frames at 25 fps)
LABEL_TOLERANCE_S = 0.08


def check_audio_vs_labels(wav: str | Path, labels: str | Path, duration_s: float, end_s: float,
                          detail: str = "") -> None:
    """ValueError naming both files when labels ending at ``end_s`` and audio lasting
    ``duration_s`` disagree by more than :data:`LABEL_TOLERANCE_S`; ``detail`` is added
    to the message (e.g. the sample count)."""
    if abs(end_s - duration_s) > LABEL_TOLERANCE_S + 1e-9:
        extra = f" ({detail})" if detail else ""
        raise ValueError(f"{labels}: labels end at {end_s:.3f} s but {wav} lasts {duration_s:.3f} s{extra}; "
                         f"expected agreement within {LABEL_TOLERANCE_S:.2f} s (audio and labels must "
                         "describe the same utterance)")
