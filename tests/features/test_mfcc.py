"""MFCC frame count, alignment with video frames, validation."""
from __future__ import annotations

import numpy as np
import pytest
import soundfile as sf

from bayes_talk.features.mfcc import frame_count, mfcc, mfcc_from_wav

SR = 22050
HOP = 882


def test_frame_count_rule():
    assert frame_count(HOP * 10, SR) == 10
    assert frame_count(HOP * 10 + HOP - 1, SR) == 10
    assert frame_count(16000 * 2 + 639, 16000) == 50
    with pytest.raises(ValueError, match="22051"):
        frame_count(1000, 22051)


@pytest.mark.parametrize("sr", [22050, 16000])
def test_shape_and_count(sr):
    rng = np.random.default_rng(0)
    n = int(sr * 1.234)
    m = mfcc(rng.normal(scale=0.1, size=n), sr)
    assert m.shape == (int(np.floor(n * 25 / sr)), 20) and m.dtype == np.float64
    assert np.all(np.isfinite(m))


def test_alignment_burst_centred_on_its_frame():
    """A tone confined to video frame k's 40 ms lights up frame k most, and frames k-1 and
    k+1 (which see 10 ms of it through their 60 ms windows) equally; k+-2 see nothing."""
    y = np.zeros(HOP * 12)
    k = 5
    y[HOP * k:HOP * (k + 1)] = 0.5 * np.sin(2 * np.pi * 1000 * np.arange(HOP) / SR)
    c0 = mfcc(y, SR)[:, 0]  # c0 ~ log energy
    floor = c0[0]
    assert np.argmax(c0) == k
    assert c0[k - 1] > floor + 50 and c0[k + 1] > floor + 50
    assert abs(c0[k - 1] - c0[k + 1]) < 0.02 * abs(c0[k] - floor)
    for j in (k - 2, k + 2):
        assert c0[j] == pytest.approx(floor)


def test_truncation_and_errors(tmp_path):
    y = np.random.default_rng(1).normal(scale=0.1, size=HOP * 8)
    full = mfcc(y, SR)
    assert np.allclose(mfcc(y, SR, n_frames=5), full[:5])
    with pytest.raises(ValueError, match="9 frames requested"):
        mfcc(y, SR, n_frames=9)
    with pytest.raises(ValueError, match="empty"):
        mfcc(np.zeros(0), SR)
    bad = y.copy()
    bad[3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        mfcc(bad, SR)
    p = tmp_path / "notawav.wav"
    p.write_text("hello")
    with pytest.raises(ValueError, match="notawav.wav"):
        mfcc_from_wav(p)
    p2 = tmp_path / "ok.wav"
    sf.write(p2, (y * 32767).astype(np.int16), SR, subtype="PCM_16")
    assert np.allclose(mfcc_from_wav(p2), full, atol=1e-2 * np.abs(full).max())


def test_absolute_floor_makes_digital_silence_and_inaudible_noise_alike():
    """Issue 27: with the floor, −60 dBFS white noise leaves the features of a digitally
    silent stretch unchanged (without it they move by tens of dB); the floor is the
    expected mel power of white noise at its level (σ² Σ w² Σ_k M_bk, checked against
    librosa's own mel spectrogram of such noise); ``floor_dbfs=None`` is librosa's MFCC."""
    import librosa

    from bayes_talk.features.mfcc import noise_power

    sr = 22050
    rng = np.random.default_rng(0)
    t = np.arange(2 * sr) / sr
    speech = 0.1 * np.sin(2 * np.pi * 180 * t) * (1 + 0.3 * rng.standard_normal(t.size))
    y = np.concatenate([np.zeros(sr // 2), speech, np.zeros(sr // 2)])
    noisy = y + 10 ** (-60 / 20) * rng.standard_normal(y.size)
    edge = slice(0, 10)                                    # 0.4 s of digital silence
    np.testing.assert_array_equal(mfcc(y, sr)[edge], mfcc(noisy, sr)[edge])
    assert np.abs(mfcc(y, sr, floor_dbfs=None)[edge] - mfcc(noisy, sr, floor_dbfs=None)[edge]).max() > 20
    # the floor is what white noise at that level puts into each mel band, on average
    win, hop = round(0.06 * sr), sr // 25
    noise = 10 ** (-30 / 20) * rng.standard_normal(40 * sr)
    S = librosa.feature.melspectrogram(y=noise, sr=sr, n_fft=win, hop_length=hop, window="hann", center=False,
                                       n_mels=40, fmax=7600.0)
    np.testing.assert_allclose(S.mean(axis=1), noise_power(-30.0, sr, win, 40, 7600.0), rtol=0.08)
    # without the floor: librosa's MFCC of the same padded frames
    pad = (win - hop) // 2
    yp = np.concatenate([np.zeros(pad), y, np.zeros(win)])
    ref = librosa.feature.mfcc(y=yp, sr=sr, n_mfcc=20, n_fft=win, hop_length=hop, window="hann", center=False,
                               n_mels=40, fmax=7600.0).T
    got = mfcc(y, sr, floor_dbfs=None)
    np.testing.assert_allclose(got, ref[:got.shape[0]], atol=1e-9)
