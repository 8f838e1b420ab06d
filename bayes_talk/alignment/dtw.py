"""DTW alignment: warp espeak-ng's own rendition of the transcript onto the user's audio.

The transcript is synthesised with espeak-ng (:func:`~bayes_talk.alignment.transcript.
synthesise_transcript`: exact phone times); both waveforms get the alignment features
(:mod:`.features`, CMVN MFCC + deltas, 10 ms) and ``librosa.sequence.dtw`` (Euclidean
local cost, steps (1,1), (0,1), (1,0)) finds the cheapest monotone frame correspondence.
A synthetic phone starting before synthetic frame i starts, in the user's audio, before
the first user frame the warping path pairs with i; the boundaries are carried across and
kept strictly increasing (at least one frame per phone).

Cost: the accumulated cost of the path divided by its length (Euclidean distance per
matched frame pair, in CMVN units). This needs no trained model at all.
"""
from __future__ import annotations

import numpy as np

from bayes_talk.alignment.features import FeatureConfig, alignment_features

__all__ = ["dtw_align"]


def dtw_align(user_feats: np.ndarray, synth, cfg: FeatureConfig) -> tuple[list[tuple[str, int, int]], float]:
    """Segments ``[(phone, first frame, end frame)]`` of the user's frames, and the DTW cost.

    ``synth``: the :class:`~bayes_talk.data.speech.SpeechResult` of the transcript.
    """
    import librosa

    y = synth.samples.astype(np.float64) / 32768.0
    if synth.sample_rate != cfg.sample_rate:
        y = librosa.resample(y, orig_sr=synth.sample_rate, target_sr=cfg.sample_rate)
    sf = alignment_features(y, cfg, where="espeak rendition of the transcript")
    T = user_feats.shape[0]
    D, wp = librosa.sequence.dtw(X=sf.T, Y=user_feats.T, metric="euclidean")
    wp = wp[::-1]
    cost = float(D[-1, -1] / len(wp))
    first_user = np.full(sf.shape[0], T, dtype=np.int64)
    np.minimum.at(first_user, wp[:, 0], wp[:, 1])
    K = len(synth.intervals)
    starts = []
    for k, (s, _, _) in enumerate(synth.intervals):
        i = int(np.clip(np.ceil(s / cfg.frame_s + 0.5), 0, sf.shape[0] - 1)) if k else 0
        starts.append(int(first_user[i]) if k else 0)
    # strictly increasing, leaving at least one frame per remaining phone
    for k in range(1, K):
        starts[k] = max(starts[k], starts[k - 1] + 1)
    for k in range(K - 1, 0, -1):
        starts[k] = min(starts[k], T - (K - k))
    ends = starts[1:] + [T]
    return [(p, a, b) for (_, _, p), a, b in zip(synth.intervals, starts, ends)], cost
