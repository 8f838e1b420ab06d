"""Named errors of the alignment package (all are ``ValueError`` subclasses, so the command
line reports them as ``bayes-talk: error: ...`` and writes nothing)."""
from __future__ import annotations

__all__ = ["AlignmentError", "EmptyTranscriptError", "MissingAlignmentModelError",
           "TranscriptTooLongError", "UnpronounceableWordError"]


class AlignmentError(ValueError):
    """Base class: a transcript or audio that cannot be aligned or recognised."""


class EmptyTranscriptError(AlignmentError):
    """The transcript holds no word (empty, blank, or punctuation only)."""


class UnpronounceableWordError(AlignmentError):
    """Transcript words outside the model language's script (espeak would spell them out
    letter by letter or name the script, not say them)."""


class TranscriptTooLongError(AlignmentError):
    """The transcript does not fit the audio: more phones than frames, or an alignment
    cost above :data:`bayes_talk.alignment.forced.MAX_ALIGNMENT_COST`."""


class MissingAlignmentModelError(AlignmentError):
    """A model directory without the alignment models (``alignment.json``/``.npz``)."""
