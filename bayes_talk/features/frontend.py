"""The fixed settings of the MFCC front end, shared by :mod:`bayes_talk.features.mfcc`
(which computes the features) and :mod:`bayes_talk.features.audio` (which records them in a
model's bundle as :class:`~bayes_talk.features.audio.AudioSettings`).

A module of its own so that the audio loader and the MFCC code do not import each other.
"""
from __future__ import annotations

__all__ = ["ACTIVITY_MARGIN_DB", "FLOOR_DBFS", "FMAX_HZ", "LEVEL_DBFS", "LEVEL_FRAME_S", "N_MELS", "N_MFCC",
           "WINDOW_S"]

#: cepstral coefficients per frame (D_y = 20, deena2010 §3.3)
N_MFCC = 20
#: analysis window (s), centred on each 40 ms video frame
WINDOW_S = 0.060
#: mel bands
N_MELS = 40
#: upper edge of the mel filterbank (Hz): 7.6 kHz, inside the pass band of a 16 kHz
#: recording (soxr keeps ~0.95 of its 8 kHz Nyquist), so that a model's features do not
#: change with the recording's rate (with the edge at sr/2, 8 kHz audio moved the synthesised
#: trajectory by 0.23 of what silence does at 16 kHz, benchmarks/robustness.py).
#: ``fmax=None`` gives sr/2 (what models that do not record it were trained with).
FMAX_HZ = 7600.0
#: absolute floor of the mel power spectrum: every band's power is raised to at
#: least the expected power of white noise at this level (dB relative to full scale, rms),
#: so that digital silence and inaudible noise (−60 dBFS) give the same features. Without
#: it the features of silence are set by ``power_to_db``'s floor 80 dB below the
#: utterance's loudest frame, and −60 dBFS of noise in a digitally silent stretch moved
#: the synthesised face by up to 1.5 sd (benchmarks/synth_stability.py). ``None``: no
#: floor (what models that do not record it were trained with).
FLOOR_DBFS = -50.0
#: the active-speech level (dBFS) every recording is scaled to before its MFCCs are computed
#: (:func:`bayes_talk.features.audio.normalise_level`), so that the absolute floor above sits
#: at the same distance below the speech whatever the recording's gain. Without it the floor
#: sits 6 dB nearer the speech of a recording 6 dB quieter, covers more of its mel bands,
#: and the per-utterance mean removal no longer takes the gain out: held-out sentences 6 dB
#: quieter moved the default model's trajectory by 0.25 of its standard deviation, 20 dB
#: quieter by 0.55 (docs/audio.md, "Gain"). -20 dBFS is the level of the built-in corpus's
#: recordings (median -19.4 dBFS, range -21.5 to -16.8 over 250 utterances), so the
#: features of its utterances barely change. ``None``: no level normalisation (what models
#: that do not record it were trained with).
LEVEL_DBFS = -20.0
#: the margin M of the active-speech level (dB), ITU-T P.56's: the level is the mean power of
#: the frames louder than (level - M)
ACTIVITY_MARGIN_DB = 15.9
#: length of the (non-overlapping) frames whose powers the active-speech level is computed from (s)
LEVEL_FRAME_S = 0.03
