"""Acoustic features for alignment and recognition: 10 ms frames, not the 40 ms video rate.

Boundaries must be placed to within ~10 ms, so the aligner uses its own features:
13 MFCCs (``librosa.feature.mfcc``: 23 ms Hann window ``n_fft = 512`` at 22.05 kHz,
40 mel bands, ``center=True``) every ``hop = round(0.01 sr)`` samples, plus first and second
differences (``librosa.feature.delta``, width 9): 39 dimensions, then per-utterance
cepstral mean and variance normalisation (CMVN), which removes most of a speaker's or
channel's constant spectral tilt (the other-voice case).

Frame j is centred on sample ``j * hop``; a phone boundary before frame j is placed at
``(j - 1/2) * hop / sr`` seconds, and a training frame j gets the label of the interval
holding ``j * hop / sr``.
"""
from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

__all__ = ["FeatureConfig", "alignment_features", "features_for_warps", "features_from_power", "frame_times", "label_frames",
           "load_audio", "power_spectrum"]

N_MFCC = 13


class FeatureConfig:
    """Feature settings stored with the models (sample rate, hop, FFT size)."""

    def __init__(self, sample_rate: int = 22050, hop_s: float = 0.01, n_fft_s: float = 0.023,
                 n_mfcc: int = N_MFCC, n_mels: int = 40) -> None:
        self.sample_rate = int(sample_rate)
        self.hop = round(hop_s * sample_rate)
        self.n_fft = int(2 ** np.ceil(np.log2(n_fft_s * sample_rate)))
        self.n_mfcc = int(n_mfcc)
        self.n_mels = int(n_mels)

    @property
    def frame_s(self) -> float:
        """Analysis hop in seconds."""
        return self.hop / self.sample_rate

    def to_json(self) -> dict:
        """The settings as a JSON-able dict."""
        return {"sample_rate": self.sample_rate, "hop": self.hop, "n_fft": self.n_fft,
                "n_mfcc": self.n_mfcc, "n_mels": self.n_mels}

    @classmethod
    def from_json(cls, d: dict) -> FeatureConfig:
        """Settings from :meth:`to_json`'s dict."""
        c = cls(d["sample_rate"])
        c.hop, c.n_fft, c.n_mfcc, c.n_mels = int(d["hop"]), int(d["n_fft"]), int(d["n_mfcc"]), int(d["n_mels"])
        return c


def load_audio(path: str | Path, sample_rate: int) -> np.ndarray:
    """Mono float64 waveform of a WAV resampled to ``sample_rate`` (librosa.resample)."""
    from bayes_talk.features.mfcc import load_wav

    y, sr = load_wav(path)
    if sr != sample_rate:
        import librosa

        y = librosa.resample(y, orig_sr=sr, target_sr=sample_rate)
    return y


def alignment_features(y: np.ndarray, cfg: FeatureConfig, where: str = "audio", warp: float = 1.0) -> np.ndarray:
    """(T, 3 * n_mfcc) float64 CMVN-normalised MFCC + delta + delta-delta, T = 1 + n // hop.

    ``warp``: vocal-tract-length normalisation factor: the mel filters are laid out as for
    a sample rate ``warp * sr``, so the filter of centre frequency f reads the audio at
    ``f / warp``: ``warp < 1`` reads a voice whose formants are ``1 / warp`` times higher
    (a shorter vocal tract) as if it were the training voice.
    """
    return features_from_power(power_spectrum(y, cfg, where), cfg, where, warp)


def power_spectrum(y: np.ndarray, cfg: FeatureConfig, where: str = "audio") -> np.ndarray:
    """(1 + n_fft / 2, T) power spectrogram (``librosa.stft``, Hann, centred frames)."""
    import librosa

    y = np.asarray(y, dtype=np.float64)
    if y.ndim != 1 or y.size < cfg.hop:
        raise ValueError(f"{where}: expected a mono waveform of at least {cfg.hop} samples, found shape {y.shape}")
    return np.abs(librosa.stft(y, n_fft=cfg.n_fft, hop_length=cfg.hop, center=True)) ** 2


def features_from_power(spec: np.ndarray, cfg: FeatureConfig, where: str = "audio",
                        warp: float = 1.0) -> np.ndarray:
    """:func:`alignment_features` from a :func:`power_spectrum`."""
    return features_for_warps(spec, cfg, (warp,), where)[0]


def features_for_warps(spec: np.ndarray, cfg: FeatureConfig, warps, where: str = "audio") -> list[np.ndarray]:
    """:func:`alignment_features` of one power spectrogram at several warps.

    The differences of all warps are taken in one ``librosa.feature.delta`` call on the
    stacked cepstra (it filters each row independently; its edge fits dominated the cost
    when called per warp).
    """
    import librosa

    # = librosa.feature.mfcc(y=y, sr=..., n_fft=..., hop_length=..., n_mels=...), with the
    # mel projection as one matrix product (librosa's einsum took 60 ms of the 80 ms)
    ms = [librosa.feature.mfcc(S=librosa.power_to_db(_mel_basis(cfg.sample_rate, cfg.n_fft, cfg.n_mels,
                                                                 float(w)) @ spec), n_mfcc=cfg.n_mfcc)
          for w in warps]
    n = ms[0].shape[1]
    width = min(9, n if n % 2 else n - 1)  # librosa.feature.delta: odd width <= n frames
    if width < 3:
        raise ValueError(f"{where}: too short for alignment ({n} frames of {cfg.frame_s * 1e3:.0f} ms)")
    m = np.vstack(ms)
    d1 = librosa.feature.delta(m, width=width, order=1)
    d2 = librosa.feature.delta(m, width=width, order=2)
    out = []
    for k in range(len(ms)):
        rows = slice(k * cfg.n_mfcc, (k + 1) * cfg.n_mfcc)
        f = np.vstack([m[rows], d1[rows], d2[rows]]).T
        f = f - f.mean(axis=0)
        f = f / np.maximum(f.std(axis=0), 1e-8)
        out.append(np.ascontiguousarray(f, dtype=np.float64))
    return out


@functools.lru_cache(maxsize=64)
def _mel_basis(sr: int, n_fft: int, n_mels: int, warp: float = 1.0) -> np.ndarray:
    import librosa

    if warp == 1.0:
        return librosa.filters.mel(sr=sr, n_fft=n_fft, n_mels=n_mels).astype(np.float64)
    # filters of a (warp * sr) grid on this FFT's bins: centre f lands on bin f n_fft / (warp sr);
    # with warp > 1 the top filters reach beyond Nyquist and are cut there
    return librosa.filters.mel(sr=sr * warp, n_fft=n_fft, n_mels=n_mels).astype(np.float64)


def frame_times(n_frames: int, cfg: FeatureConfig) -> np.ndarray:
    """Centre time (s) of each feature frame."""
    return np.arange(n_frames) * cfg.frame_s


def label_frames(intervals: list[tuple[float, float, str]], n_frames: int, cfg: FeatureConfig) -> list[str]:
    """Phone of each feature frame: the interval holding its centre (``sil`` outside)."""
    t = frame_times(n_frames, cfg)
    starts = np.array([s for s, _, _ in intervals])
    idx = np.clip(np.searchsorted(starts, t, side="right") - 1, 0, len(intervals) - 1)
    out = []
    for j, i in enumerate(idx):
        s, e, p = intervals[i]
        out.append(p if s <= t[j] < e else "sil")
    return out
