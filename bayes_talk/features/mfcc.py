"""MFCC audio features at the video frame rate (deena2010 §3.3).

20 coefficients from a 60 ms Hann window every 40 ms (25 Hz), computed with librosa
(40 mel bands of the power spectrum, ``librosa.feature.melspectrogram``; ``power_to_db``;
DCT-II ortho, ``librosa.feature.mfcc``).

Level. The waveform is first scaled so that its active-speech level is ``level_dbfs``
(:func:`bayes_talk.features.audio.normalise_level`; default ``LEVEL_DBFS``, -20 dBFS), so
that what follows -- the absolute floor in particular -- sees every recording at the same
speech level, whatever its gain. ``level_dbfs=None``: the waveform as it is (models
trained before it).

Absolute floor. Before the logarithm each mel band's power S_b is raised to at least
the expected power of white noise of rms σ = 10^(FLOOR_DBFS/20) in that band,

    S_b ← max(S_b, σ² · Σ_n w_n² · Σ_k M_bk)

(w the analysis window, M the mel filterbank: E|X_k|² = σ² Σ_n w_n² for white noise), so
digital silence and noise below the floor give the same features whatever the
utterance's loudness (``power_to_db``'s own floor is relative: 80 dB below the loudest
frame). ``floor_dbfs=None``: no floor (models trained before it).

Alignment with video. Video frame k shows the interval ``[k/fps, (k+1)/fps)`` =
``[0.04k, 0.04k + 0.04)`` s. Audio frame k is the 60 ms window centred on that interval's
centre ``0.04k + 0.02`` s, i.e. it spans ``[0.04k - 0.01, 0.04k + 0.05)``: 10 ms of context
on each side. In samples, with ``hop = sr / fps`` (882 at 22050 Hz) and ``win = 0.06 sr``
(1323), window k starts at sample ``hop*k - pad`` with ``pad = (win - hop) // 2`` (220);
when ``win - hop`` is odd the window centre sits half a sample (23 µs at 22050 Hz) after
the interval centre. The signal is zero-padded by ``pad`` samples on the left and as many
as needed on the right, and framed with ``center=False`` and ``n_fft = win`` (so the
window is not re-centred inside a longer FFT frame).

Frame count (shared with the video side): ``n_frames = floor(n_samples * fps / sr)`` =
``n_samples // hop`` -- only whole 40 ms intervals are kept. The built-in corpus pads
every waveform to a whole number of frames, so nothing is dropped there.

``sr / fps`` must be an integer (true for 8, 11.025, 16, 22.05, 44.1, 48 kHz at 25 fps).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from bayes_talk.features.audio import downmix, load_audio, normalise_level
from bayes_talk.features.frontend import FLOOR_DBFS, FMAX_HZ, LEVEL_DBFS, N_MELS, N_MFCC, WINDOW_S

__all__ = ["FLOOR_DBFS", "FMAX_HZ", "LEVEL_DBFS", "N_MFCC", "frame_count", "load_wav", "mfcc", "mfcc_from_wav",
           "noise_power", "samples_per_frame"]


def samples_per_frame(sample_rate: int, fps: float = 25.0) -> int:
    """``sample_rate / fps`` as an int; ValueError if it is not a whole number."""
    if sample_rate <= 0:
        raise ValueError(f"sample rate: expected > 0 Hz, found {sample_rate}")
    hop = sample_rate / fps
    if hop != int(hop):
        raise ValueError(
            f"sample rate {sample_rate} Hz is not a whole number of samples per frame at "
            f"{fps} fps (expected sample_rate divisible by fps, e.g. 16000, 22050, 44100, 48000)"
        )
    return int(hop)


def frame_count(n_samples: int, sample_rate: int, fps: float = 25.0) -> int:
    """Number of whole frames in ``n_samples``: ``floor(n_samples * fps / sample_rate)``."""
    return int(n_samples) // samples_per_frame(sample_rate, fps)


def mfcc(y: np.ndarray, sample_rate: int, n_frames: int | None = None, *, fps: float = 25.0,
         n_mfcc: int = N_MFCC, window_s: float = WINDOW_S, n_mels: int = N_MELS,
         where: str = "audio", fmax: float | None = FMAX_HZ,
         floor_dbfs: float | None = FLOOR_DBFS, level_dbfs: float | None = LEVEL_DBFS) -> np.ndarray:
    """MFCCs aligned to video frames; returns ``(n_frames, n_mfcc)`` float64.

    ``y``: mono waveform (float in [-1, 1], or int16 scaled by 1/32768; a 2-D (n, channels)
    array is downmixed by :func:`bayes_talk.features.audio.downmix`). ``n_frames``: default
    :func:`frame_count`; a smaller value truncates, a larger one is an error. ``where`` names the source in errors.
    ``fmax``: the mel filterbank's upper edge (None: sr/2); ``floor_dbfs``: the absolute
    floor (module docstring; None: none); ``level_dbfs``: the active-speech level the whole
    of ``y`` is scaled to first (module docstring; None: none).
    """
    y = np.asarray(y)
    if y.dtype == np.int16:
        y = y.astype(np.float64) / 32768.0
    y = np.asarray(y, dtype=np.float64)
    if y.ndim == 2:
        y = downmix(y, where)
    if y.ndim != 1:
        raise ValueError(f"{where}: expected a 1-D waveform (or (n, channels)), found shape {y.shape}")
    if y.size == 0:
        raise ValueError(f"{where}: empty audio (0 samples)")
    if not np.all(np.isfinite(y)):
        raise ValueError(f"{where}: audio contains NaN or inf")
    hop = samples_per_frame(int(sample_rate), fps)
    y = normalise_level(y, int(sample_rate), level_dbfs)
    win = round(window_s * sample_rate)
    if win < hop:
        raise ValueError(f"window_s: expected >= 1/fps, found {window_s}")
    available = y.size // hop
    if n_frames is None:
        n_frames = available
    if n_frames > available:
        raise ValueError(
            f"{where}: {n_frames} frames requested but the audio holds only {available} whole "
            f"frames ({y.size} samples at {sample_rate} Hz)"
        )
    if n_frames <= 0:
        raise ValueError(f"{where}: audio shorter than one frame ({y.size} samples at {sample_rate} Hz)")
    import librosa

    pad = (win - hop) // 2
    need = (n_frames - 1) * hop + win
    right = max(0, need - pad - y.size)
    yp = np.concatenate([np.zeros(pad), y, np.zeros(right)])
    top = None if fmax is None else min(float(fmax), sample_rate / 2)
    S = librosa.feature.melspectrogram(y=yp, sr=sample_rate, n_fft=win, win_length=win, hop_length=hop,
                                       window="hann", center=False, n_mels=n_mels, fmax=top, power=2.0)
    if floor_dbfs is not None:
        S = np.maximum(S, noise_power(float(floor_dbfs), sample_rate, win, n_mels, top)[:, None])
    m = librosa.feature.mfcc(S=librosa.power_to_db(S), n_mfcc=n_mfcc)
    out = np.ascontiguousarray(m.T[:n_frames], dtype=np.float64)
    if out.shape[0] != n_frames:  # pragma: no cover - guarded by the padding above
        raise RuntimeError(f"{where}: librosa returned {out.shape[0]} frames, expected {n_frames}")
    return out


def noise_power(dbfs: float, sample_rate: int, win: int, n_mels: int = N_MELS, fmax: float | None = None
                ) -> np.ndarray:
    """(n_mels,) expected mel power of white noise of rms 10^(dbfs/20) in a Hann window of
    ``win`` samples: σ² Σ_n w_n² Σ_k M_bk (module docstring), the floor of :func:`mfcc`."""
    import librosa

    window = librosa.filters.get_window("hann", win, fftbins=True)
    basis = librosa.filters.mel(sr=sample_rate, n_fft=win, n_mels=n_mels, fmax=fmax)
    return 10.0 ** (float(dbfs) / 10.0) * float(np.sum(window ** 2)) * basis.sum(axis=1)


def load_wav(path: str | Path, target_sr: int | None = None) -> tuple[np.ndarray, int]:
    """Read a WAV (any soundfile-readable file) as float64 mono in [-1, 1] and its rate.

    Several channels are downmixed by :func:`bayes_talk.features.audio.downmix` (average when
    correlated, else the loudest channel); ``target_sr``: resample to it (one log line).
    Errors name the file: unreadable, empty, or non-finite audio raise ValueError.
    """
    return load_audio(path, target_sr)


def mfcc_from_wav(path: str | Path, n_frames: int | None = None, fps: float = 25.0) -> np.ndarray:
    """:func:`mfcc` of a WAV file; errors name the file."""
    y, sr = load_wav(path)
    return mfcc(y, sr, n_frames, fps=fps, where=str(path))
