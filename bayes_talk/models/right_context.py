"""Right-context (anticipatory) switching states: a wrapper around any state model.

deena2010's states carry only *left* context (the VLMM's label history, or the current
phone), but a face anticipates the next phone: coarticulation moves the lips toward the
coming target before its sound starts. Synthesis is offline, so the whole label sequence
is known, and the state of a frame may also name what comes next.

With a base state model (VLMM contexts or phones) giving frame t the state π_t, the
right-context state is

    π'_t = (">q_t",) + π_t,      q_t = the first label after frame t that differs from l_t
                                  ("sil" when the utterance ends first),            (1)

so a state model is trained for each (next phone, base state) pair with enough frames, and
the switching model's suffix back-off (:meth:`SwitchingModel.model_for
<bayes_talk.models.switching.SwitchingModel.model_for>` drops the *first* element) falls
back from π'_t to the base state π_t, then to π_t's own suffixes: right context is given
up first, then the oldest left context. The training subsequences are the base model's
(so every base state keeps its model) plus the same spans under the refined state (1).

Measured on our 40 held-out sentences with phone states (docs/results.md, "Experiment:
right-context (anticipatory) switching states"): posterior NMSE 0.887 → 0.844, ACC
0.345 → 0.384.
"""
from __future__ import annotations

from collections.abc import Sequence

from bayes_talk.models.vlmm import Segment

__all__ = ["RIGHT_MARK", "RightContextStates", "next_different"]

#: prefix of the right-context element of a state tuple (phone labels never start with it)
RIGHT_MARK = ">"
END_LABEL = "sil"


def next_different(labels: Sequence[str]) -> list[str]:
    """q_t of eq. (1) for every frame: the first later label different from l_t, or
    ``"sil"`` if there is none."""
    out = [END_LABEL] * len(labels)
    nxt = END_LABEL
    for t in range(len(labels) - 1, -1, -1):
        if t + 1 < len(labels) and labels[t + 1] != labels[t]:
            nxt = labels[t + 1]
        out[t] = nxt
    return out


class RightContextStates:
    """A base state model (:class:`~bayes_talk.models.vlmm.VLMM` or
    :class:`~bayes_talk.models.switching.PhoneStates`) whose states are prefixed with the
    next phone (eq. 1). ``segment`` and ``training_subsequences`` take the base model's
    ``unknown`` policy; ``fit`` fits the base model."""

    def __init__(self, base) -> None:
        self.base = base

    @property
    def alphabet_(self) -> list[str]:
        """The base model's label alphabet."""
        return self.base.alphabet_

    def fit(self, sequences: Sequence[Sequence[str]]) -> RightContextStates:
        """Fit the base state model; returns ``self``."""
        self.base.fit(sequences)
        return self

    @staticmethod
    def _refine(labels: Sequence[str], segs: list[Segment]) -> list[Segment]:
        nxt = next_different(list(labels))
        return [Segment((RIGHT_MARK + nxt[s.stop - 1], *s.state), s.start, s.stop) for s in segs]

    def segment(self, labels: Sequence[str], unknown: str = "error") -> list[Segment]:
        """The base segmentation with each segment's state refined by eq. (1) at its last frame."""
        return self._refine(labels, self.base.segment(labels, unknown))

    def training_subsequences(self, labels: Sequence[str], unknown: str = "error") -> list[Segment]:
        """The base model's training subsequences, and each again under its refined state."""
        base = list(self.base.training_subsequences(labels, unknown))
        return base + self._refine(labels, base)

    def to_dict(self) -> dict:
        """JSON-able description: ``{"kind": "right-context", "base": <base model's dict>}``."""
        return {"kind": "right-context", "base": self.base.to_dict()}
