"""HMM forced alignment of a known phone sequence to audio (the default aligner).

The transcript's phones (espeak-ng G2P, :mod:`bayes_talk.alignment.transcript`) are
chained left to right, each phone by its three-state HMM (:mod:`.phone_hmm`), and the
best path through the chain (:func:`~bayes_talk.alignment.viterbi.viterbi_chain`) gives
every phone's first and last frame.

Alignment cost (the "transcript much longer than the audio" check). With ``L_forced`` the
chain's Viterbi log-likelihood and ``L_free = sum_t max_s log b_s(x_t)`` the best any
state sequence could score frame by frame (no transitions; an upper bound of every path's
emission score), ::

    cost = (L_free - L_forced) / T      [nats per 10 ms frame]

measures how far the transcript forces the audio away from the phones it sounds like.
Measured thresholds: see :data:`MAX_ALIGNMENT_COST` and docs/alignment.md. A chain with
more states than the audio has frames is refused before decoding.
"""
from __future__ import annotations

import numpy as np

from bayes_talk.alignment.errors import TranscriptTooLongError
from bayes_talk.alignment.phone_hmm import N_STATES, PhoneHMMs
from bayes_talk.alignment.viterbi import viterbi_chain

__all__ = ["MAX_ALIGNMENT_COST", "force_align"]

#: alignment cost (nats per frame) above which a transcript is refused. Measured with the
#: models trained on data/v1/train250 (20 utterances each, docs/alignment.md): true
#: transcripts cost 2.7-8.0 (training voice, heldout40) and 6.7-24.5 (voice en+f3, rate 215,
#: pitch 70); the same audio with its sentence said twice in the transcript 52.6-74.8 and
#: 64.7-98.4; three times or more does not fit in the frames at all. Another sentence of
#: similar length costs 23.6-45.3 (this check is not meant to catch that).
MAX_ALIGNMENT_COST = 45.0


def force_align(logb: np.ndarray, phones: list[str], hmms: PhoneHMMs, where: str = "audio",
                max_cost: float | None = MAX_ALIGNMENT_COST) -> tuple[list[tuple[str, int, int]], float]:
    """Align ``phones`` to the frames whose state emissions are ``logb`` (T, P * N_STATES).

    Returns ``[(phone, first frame, end frame), ...]`` and the alignment cost (nats/frame).
    Raises :class:`TranscriptTooLongError` when the chain has more states than frames or
    the cost exceeds ``max_cost`` (None: no check).
    """
    T = logb.shape[0]
    index = {p: i for i, p in enumerate(hmms.phones)}
    missing = sorted({p for p in phones if p not in index})
    if missing:
        raise ValueError(f"{where}: phones {missing} are not in the alignment model's phone set")
    ids = np.array([index[p] for p in phones])
    S = len(ids) * N_STATES
    if S > T:
        raise TranscriptTooLongError(
            f"{where}: the transcript has {len(ids)} phones, which need at least {S} frames of "
            f"{1e3 * 0.01:.0f} ms, but the audio has {T}: the transcript is much longer than the audio")
    cols = (ids[:, None] * N_STATES + np.arange(N_STATES)[None, :]).ravel()
    path, score = viterbi_chain(logb[:, cols], hmms.log_stay_[ids].ravel(), hmms.log_move_[ids].ravel())
    cost = (float(logb.max(axis=1).sum()) - score) / T
    if max_cost is not None and not cost <= max_cost:
        raise TranscriptTooLongError(
            f"{where}: alignment cost {cost:.2f} nats/frame exceeds the threshold {max_cost:g} "
            "(docs/alignment.md): the transcript does not match the audio (much longer, or other words)")
    ph = path // N_STATES
    segs = []
    for k in range(len(ids)):
        frames = np.nonzero(ph == k)[0]
        segs.append((phones[k], int(frames[0]), int(frames[-1]) + 1))
    return segs, float(cost)
