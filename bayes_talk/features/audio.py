"""Audio from real recordings: downmix, resampling and cepstral normalisation.

Everything that makes the MFCC features of :mod:`bayes_talk.features.mfcc` independent of
how a recording was made, applied identically when a model is trained (``load_corpus``)
and when it synthesises (``pipeline.read_utterance``):

* **Downmix** (:func:`downmix`). A multi-channel recording becomes one channel by this
  rule: if every channel is strongly positively correlated with the loudest one (Pearson
  r >= ``CORRELATED_R`` = 0.5) the channels carry the same source and are *averaged*
  (noise averages out, level kept); otherwise the *loudest channel* (largest mean square)
  is kept. So a recording with one silent (or uncorrelated, or phase-inverted) channel is
  not halved or cancelled, and dual-mono stays what it is.
* **Resampling** (:func:`resample`). The sample rate a model was trained at is recorded
  in its bundle; audio at another rate is resampled to it with ``soxr`` (VHQ), with one
  INFO/WARNING log line. Without it the mel filterbank (0..sr/2) would cover other
  frequencies and the features would move as much as with silence.
* **Level normalisation** (:func:`normalise_level`). Each recording is scaled so that its
  active-speech level (:func:`active_level`) is ``LEVEL_DBFS`` (-20 dBFS) before its MFCCs
  are computed. The active-speech level follows ITU-T P.56 (method B's definition, on
  frames): the mean power of the frames louder than a threshold that lies
  ``ACTIVITY_MARGIN_DB`` (15.9 dB) below that mean, over 30 ms frames (``LEVEL_FRAME_S``;
  P.56 smooths a sample envelope with a 30 ms time constant and a 200 ms hangover instead).
  The frames are ranked by power; the k loudest are taken, k the first for which the next
  frame's power lies more than 15.9 dB below their mean power (all frames when none does),
  so that they are exactly the frames above (their level - 15.9 dB). A gain g
  multiplies every frame's power by g², so it selects the same frames and moves the level
  by exactly 20 log10 g dB: the normalised waveform does not depend on the gain (up to the
  recording's quantisation), and so neither does anything computed from it, the absolute
  floor's effect included. Pauses and silence do not count, so a sentence with long pauses
  is not boosted; digital silence (no frame with power) is left as it is. The reference
  level is a model setting recorded in the bundle (``level_dbfs``; models trained before it
  was recorded read as None, no normalisation).
* **Cepstral mean (and variance) normalisation** (:func:`cmvn`), per utterance: subtract
  each coefficient's mean over the utterance (``"mean"``), and also divide by its standard
  deviation (``"mean+var"``). A gain change g scales every mel-band power by g², i.e. adds
  20 log10 g dB to every log band energy; the orthonormal DCT-II maps a constant to c0 only,
  so gain is exactly a shift of c0 -- which the mean removal takes out, in every mel band
  above the absolute floor (a band at the floor does not move with the gain: hence the
  level normalisation before it). The option is a
  model setting recorded in the bundle (``"mean"`` by default for new models; models
  trained before it was recorded read as ``"off"``).
* **Level and content checks**. :func:`load_audio` warns when more than
  ``CLIP_FRACTION`` (0.1 %) of the samples sit at full scale (|x| >= ``CLIP_LEVEL``): the
  waveform was clipped, its spectrum carries distortion harmonics and the face follows
  them (a +6 dB gain that clipped 0.4 % of the samples moved the trajectory by up to 1.4
  sd). :func:`speech_problem` says when a recording holds no speech: silent (peak below
  ``SILENCE_DBFS``, -60 dBFS) or noise-like (fewer than ``VOICED_MIN`` = 5 % of its
  frames within 40 dB of the loudest have a spectral flatness below ``TONAL_FLATNESS`` =
  0.1; voiced speech is harmonic, so not flat: 79-93 % of the frames of the built-in
  corpus's utterances are tonal, 29-31 % with white noise added at 10 dB SNR, 10-14 % at
  5 dB, 0-2 % at 0 dB (flagged), 0 % of white noise alone). Coloured stationary noise can
  pass it: it is a check for the obvious cases.
* **MP3**. An MP3 encoder delays the audio (LAME: 576 samples, plus 529 of the decoder)
  and pads its end; a gapless header (the Xing/Info "LAME" tag of the first frame) records
  both, and libsndfile (through soundfile) removes them: measured, an ffmpeg/LAME MP3 of a
  corpus utterance decodes to the original length, 0 samples off. Without that header no
  decoder can know the delay: the same MP3 without it decoded 1105 samples (50 ms at
  22.05 kHz) late, against labels made from the original. :func:`load_audio` warns then.
"""
from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from bayes_talk.features.frontend import (
    ACTIVITY_MARGIN_DB,
    FLOOR_DBFS,
    FMAX_HZ,
    LEVEL_DBFS,
    LEVEL_FRAME_S,
    N_MELS,
    N_MFCC,
    WINDOW_S,
)

__all__ = ["CLIP_FRACTION", "CLIP_LEVEL", "CMVN_MODES", "CORRELATED_R", "DEFAULT_CMVN", "AudioSettings",
           "active_level", "clipped_fraction", "cmvn", "downmix", "feature_statistics", "load_audio",
           "mp3_without_gapless_header", "normalise_level", "resample", "speech_problem"]

log = logging.getLogger(__name__)

CMVN_MODES = ("off", "mean", "mean+var")
DEFAULT_CMVN = "mean"
CORRELATED_R = 0.5
_VAR_FLOOR = 1e-8
#: a sample at or above this magnitude is at full scale (16-bit full scale is 32767/32768)
CLIP_LEVEL = 0.9999
#: more than this fraction of samples at full scale: warn that the audio is clipped
CLIP_FRACTION = 0.001
#: a recording whose peak is below this level (dBFS) is silent
SILENCE_DBFS = -60.0
#: frames with a spectral flatness below this are tonal (voiced speech is harmonic)
TONAL_FLATNESS = 0.1
#: fewer tonal frames than this fraction (of the frames within 40 dB of the loudest): no speech
VOICED_MIN = 0.05


def clipped_fraction(y: np.ndarray) -> float:
    """The fraction of samples of ``y`` (full scale 1) at full scale: :data:`CLIP_LEVEL` <=
    |y| <= 1. Samples of a floating-point file beyond 1 were not clipped (they are read as
    they are) and do not count."""
    a = np.abs(np.asarray(y))
    return float(np.mean((a >= CLIP_LEVEL) & (a <= 1.0))) if a.size else 0.0


def mp3_without_gapless_header(path: str | Path) -> bool:
    """True when ``path`` is an MP3 whose first frame has no Xing/Info (LAME) tag: its
    encoder delay and padding cannot be removed by the decoder (module docstring)."""
    with open(path, "rb") as f:
        head = f.read(10)
        start = 0
        if len(head) == 10 and head[:3] == b"ID3":     # skip an ID3v2 tag (syncsafe size)
            size = (head[6] & 0x7F) << 21 | (head[7] & 0x7F) << 14 | (head[8] & 0x7F) << 7 | head[9] & 0x7F
            start = 10 + size + (10 if head[5] & 0x10 else 0)
        f.seek(start)
        data = f.read(16384)
    for i in range(len(data) - 1):                     # the first frame sync: 11 set bits
        if data[i] == 0xFF and data[i + 1] & 0xE0 == 0xE0:
            return b"Xing" not in data[i:i + 200] and b"Info" not in data[i:i + 200]
    return False


def speech_problem(y: np.ndarray, sr: int) -> str | None:
    """None when ``y`` may hold speech, else what it holds instead ("silent (...)" or
    "noise-like (...)"), by the rule in the module docstring."""
    import librosa

    y = np.asarray(y, dtype=np.float64)
    peak = float(np.max(np.abs(y))) if y.size else 0.0
    if peak <= 10 ** (SILENCE_DBFS / 20):
        level = "no signal at all" if peak == 0 else f"peak {20 * np.log10(peak):.0f} dBFS"
        return f"silent ({level}, below {SILENCE_DBFS:.0f} dBFS)"
    n_fft = 1024 if y.size >= 1024 else 1 << int(np.log2(max(y.size, 16)))
    S = np.abs(librosa.stft(y, n_fft=n_fft, hop_length=n_fft // 4)) ** 2
    rms = np.sqrt(S.mean(axis=0))
    loud = rms >= rms.max() * 1e-2                    # within 40 dB of the loudest frame
    flat = librosa.feature.spectral_flatness(S=S, power=1.0)[0][loud]
    tonal = float(np.mean(flat < TONAL_FLATNESS)) if flat.size else 0.0
    if tonal < VOICED_MIN:
        return (f"noise-like ({100 * tonal:.0f} % of its frames tonal, fewer than {100 * VOICED_MIN:.0f} %; "
                "voiced speech is harmonic)")
    return None


def downmix(y: np.ndarray, where: str = "audio") -> np.ndarray:
    """One channel from ``(n,)`` or ``(n, channels)`` audio by the rule in the module docstring."""
    y = np.asarray(y, dtype=np.float64)
    if y.ndim == 1:
        return y
    if y.ndim != 2:
        raise ValueError(f"{where}: expected (n,) or (n, channels) audio, found shape {y.shape}")
    if y.shape[1] == 1:
        return y[:, 0]
    power = np.mean(y ** 2, axis=0)
    loud = int(np.argmax(power))
    if power[loud] == 0.0:
        return y[:, loud]
    ref = y[:, loud] - y[:, loud].mean()
    for c in range(y.shape[1]):
        if c == loud:
            continue
        x = y[:, c] - y[:, c].mean()
        denom = np.sqrt(np.sum(x ** 2) * np.sum(ref ** 2))
        if denom == 0.0 or np.sum(x * ref) / denom < CORRELATED_R:
            log.info("%s: channels differ (not correlated); using channel %d, the loudest", where, loud)
            return y[:, loud]
    return y.mean(axis=1)


def resample(y: np.ndarray, sr: int, target_sr: int) -> np.ndarray:
    """``y`` at ``sr`` Hz resampled to ``target_sr`` Hz (soxr, very high quality)."""
    if int(sr) == int(target_sr):
        return np.asarray(y, dtype=np.float64)
    import soxr

    return np.asarray(soxr.resample(np.asarray(y, dtype=np.float64), int(sr), int(target_sr),
                                    quality="VHQ"), dtype=np.float64)


def load_audio(path: str | Path, target_sr: int | None = None) -> tuple[np.ndarray, int]:
    """Read an audio file as float64 mono (see :func:`downmix`); if ``target_sr`` is given
    and differs from the file's rate, resample to it and say so on one log line.

    Errors (ValueError) name the file: unreadable, empty, or non-finite audio.
    """
    import soundfile as sf

    path = Path(path)
    try:
        y, sr = sf.read(str(path), dtype="float64", always_2d=True)
    except Exception as exc:  # soundfile raises LibsndfileError / RuntimeError / OSError
        raise ValueError(f"{path}: cannot read audio ({exc})") from exc
    if y.size == 0:
        raise ValueError(f"{path}: empty audio (0 samples)")
    if path.suffix.lower() == ".mp3" and mp3_without_gapless_header(path):
        import warnings

        warnings.warn(f"{path}: an MP3 without a gapless (Xing/Info LAME) header: the decoder cannot remove "
                      "the encoder delay, so the audio is probably late against labels made from the original "
                      "(LAME: 1105 samples, 50 ms at 22.05 kHz). Use the original WAV, or an MP3 written with "
                      "that header (LAME's and ffmpeg's default)", UserWarning)
    if not np.all(np.isfinite(y)):
        raise ValueError(f"{path}: audio contains NaN or inf")
    clipped = clipped_fraction(y)
    if clipped > CLIP_FRACTION:
        import warnings

        warnings.warn(f"{path}: {100 * clipped:.2f} % of the samples are at full scale (clipped; more than "
                      f"{100 * CLIP_FRACTION:.1f} %): the features carry the distortion and the face follows "
                      "it; record or export at a lower level", UserWarning)
    y = downmix(y, str(path))
    sr = int(sr)
    if target_sr is not None and sr != int(target_sr):
        log.warning("%s: %d Hz audio resampled to %d Hz, the model's training rate", path, sr, int(target_sr))
        y, sr = resample(y, sr, int(target_sr)), int(target_sr)
    return y, sr


def active_level(y: np.ndarray, sr: int) -> float | None:
    """The active-speech level of the mono waveform ``y`` (full scale 1) at ``sr`` Hz, in dBFS
    (10 log10 of a mean power; a full-scale sine is -3 dBFS), by the P.56-style rule of the
    module docstring; None when no frame has any power (digital silence). Audio shorter than
    one frame is one frame."""
    y = np.asarray(y, dtype=np.float64)
    if y.ndim != 1:
        raise ValueError(f"active level: expected a 1-D waveform, found shape {y.shape}")
    frame = max(1, round(LEVEL_FRAME_S * int(sr)))
    n = y.size // frame
    power = (y[: n * frame].reshape(n, frame) ** 2).mean(axis=1) if n else np.array([np.mean(y ** 2)])
    power = np.sort(power[power > 0])[::-1]
    if power.size == 0:
        return None
    mean = np.cumsum(power) / np.arange(1, power.size + 1)   # of the k loudest frames, k = 1..n
    # the first k whose next frame lies more than the margin below their mean: the k loudest
    # are then exactly the frames above (their level - margin)
    below = np.flatnonzero(10 * np.log10(mean[:-1] / power[1:]) > ACTIVITY_MARGIN_DB)
    k = int(below[0]) if below.size else power.size - 1
    return float(10 * np.log10(mean[k]))


def normalise_level(y: np.ndarray, sr: int, level_dbfs: float | None = LEVEL_DBFS) -> np.ndarray:
    """``y`` scaled so that its :func:`active_level` is ``level_dbfs`` (dBFS); unchanged when
    ``level_dbfs`` is None or ``y`` is digitally silent. The result may exceed full scale
    (it is a float waveform, not written out)."""
    y = np.asarray(y, dtype=np.float64)
    if level_dbfs is None:
        return y
    level = active_level(y, sr)
    if level is None:
        return y
    return y * 10.0 ** ((float(level_dbfs) - level) / 20.0)


def cmvn(features: np.ndarray, mode: str = DEFAULT_CMVN) -> np.ndarray:
    """Per-utterance cepstral normalisation of ``(T, D)`` features.

    ``"off"``: unchanged; ``"mean"``: ``y_t - mean_t(y)``; ``"mean+var"``: that divided by
    the per-coefficient standard deviation over the utterance (floored at 1e-4).
    """
    if mode not in CMVN_MODES:
        raise ValueError(f"cmvn: expected one of {CMVN_MODES}, found {mode!r}")
    f = np.asarray(features, dtype=np.float64)
    if mode == "off":
        return f
    out = f - f.mean(axis=0, keepdims=True)
    if mode == "mean+var":
        out = out / np.sqrt(np.maximum(f.var(axis=0, keepdims=True), _VAR_FLOOR))
    return out


def feature_statistics(features: list[np.ndarray]) -> dict[str, list[float]]:
    """Per-dimension mean and standard deviation over all frames of ``features`` (what a
    model saw in training; recorded in its bundle to diagnose mismatched inputs)."""
    allf = np.vstack([np.asarray(f, dtype=np.float64) for f in features])
    return {"mean": allf.mean(axis=0).tolist(), "std": allf.std(axis=0).tolist(),
            "n_frames": int(allf.shape[0])}


@dataclass(frozen=True)
class AudioSettings:
    """The audio front end a model was trained with (recorded in its bundle)."""

    sample_rate: int
    fps: float = 25.0
    n_mfcc: int = N_MFCC
    window_s: float = WINDOW_S
    n_mels: int = N_MELS
    cmvn: str = DEFAULT_CMVN
    #: mel filterbank upper edge (Hz); None: sr/2 (models that do not record it)
    fmax: float | None = FMAX_HZ
    #: absolute mel-power floor (dBFS, :data:`bayes_talk.features.frontend.FLOOR_DBFS`); None: none
    floor_dbfs: float | None = FLOOR_DBFS
    #: active-speech level the audio is scaled to (dBFS, :data:`bayes_talk.features.frontend.LEVEL_DBFS`;
    #: :func:`normalise_level`); None: no level normalisation (models that do not record it)
    level_dbfs: float | None = LEVEL_DBFS

    def __post_init__(self) -> None:
        if self.cmvn not in CMVN_MODES:
            raise ValueError(f"cmvn: expected one of {CMVN_MODES}, found {self.cmvn!r}")

    def to_dict(self) -> dict:
        """The settings as a JSON-able dict (recorded in a model's bundle)."""
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict | None, fallback_rate: int = 22050, where: str = "model") -> AudioSettings:
        """Settings from a bundle; a model that predates recorded settings reads as the
        built-in corpus's front end of then (22050 Hz, mel bands up to sr/2, no cepstral or
        level normalisation, no floor), with a warning; a setting a model does not record is
        off (None), as it was when the model was trained."""
        if not d:
            log.warning("%s records no audio settings (trained before they were recorded); assuming "
                        "%d Hz, mel bands up to sr/2, no cepstral normalisation", where, fallback_rate)
            return cls(sample_rate=int(fallback_rate), cmvn="off", fmax=None, floor_dbfs=None, level_dbfs=None)
        known = {k: d[k] for k in ("sample_rate", "fps", "n_mfcc", "window_s", "n_mels", "cmvn", "fmax")
                 if k in d}
        known["floor_dbfs"] = d.get("floor_dbfs")   # absent from older models: they had no floor
        known["level_dbfs"] = d.get("level_dbfs")   # likewise: no level normalisation
        return cls(**known)
