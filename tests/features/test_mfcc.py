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
    k+1 (which see 10 ms of it through their 60 ms windows) equally; k+-2 see nothing. (At
    its own level, -9 dBFS: normalised to -20 dBFS the neighbours sit 38 dB above the floor.)"""
    y = np.zeros(HOP * 12)
    k = 5
    y[HOP * k:HOP * (k + 1)] = 0.5 * np.sin(2 * np.pi * 1000 * np.arange(HOP) / SR)
    c0 = mfcc(y, SR, level_dbfs=None)[:, 0]  # c0 ~ log energy
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
    librosa's own mel spectrogram of such noise); ``floor_dbfs=None, level_dbfs=None`` is
    librosa's MFCC."""
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
    got = mfcc(y, sr, floor_dbfs=None, level_dbfs=None)
    np.testing.assert_allclose(got, ref[:got.shape[0]], atol=1e-9)


def _speech_like(sr: int, seed: int) -> np.ndarray:
    """Two 'words' (harmonic bursts with a falling spectrum, noisy amplitude) between
    stretches of digital silence: 0.3 s + 0.9 s + 0.3 s + 0.6 s + 0.3 s."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(0.9 * sr)) / sr

    def word(n):
        tone = sum(np.sin(2 * np.pi * 140 * h * t[:n]) / h ** 1.5 for h in range(1, 30))
        return 0.1 * tone * (1 + 0.3 * rng.standard_normal(n)) * np.hanning(n)

    gap = np.zeros(int(0.3 * sr))
    return np.concatenate([gap, word(int(0.9 * sr)), gap, 0.3 * word(int(0.6 * sr)), gap])


def test_active_level_is_the_mean_power_of_the_active_frames_and_moves_with_the_gain_exactly():
    from bayes_talk.features.audio import active_level, normalise_level

    sr = 16000
    frame = round(0.03 * sr)
    tone = 0.5 * np.sin(2 * np.pi * 1000 * np.arange(40 * frame) / sr)      # mean power 0.125: -9.03 dBFS
    y = np.concatenate([np.zeros(100 * frame), tone, np.zeros(60 * frame)])
    assert active_level(y, sr) == pytest.approx(10 * np.log10(0.125), abs=1e-6)   # the pauses do not count
    # noise 50 dB below the tone in the pauses is under the threshold 15.9 dB below: not counted either
    rng = np.random.default_rng(1)
    noisy = y + 10 ** ((-9.03 - 50) / 20) * rng.standard_normal(y.size)
    assert active_level(noisy, sr) == pytest.approx(10 * np.log10(0.125), abs=0.01)
    # a stationary signal is active throughout: its level is its mean power
    white = 0.1 * rng.standard_normal(sr)
    assert active_level(white, sr) == pytest.approx(10 * np.log10(np.mean(white ** 2)), abs=0.5)
    speech = _speech_like(sr, 2)
    ref = active_level(speech, sr)
    for g_db in (-40.0, -20.0, -6.0, 6.0):
        g = 10 ** (g_db / 20)
        assert active_level(g * speech, sr) == pytest.approx(ref + g_db, abs=1e-9)
        np.testing.assert_allclose(normalise_level(g * speech, sr, -20.0), normalise_level(speech, sr, -20.0),
                                   rtol=1e-9, atol=1e-15)
    assert active_level(normalise_level(speech, sr, -26.0), sr) == pytest.approx(-26.0, abs=1e-9)
    # digital silence has no level and is left as it is; None switches the normalisation off
    assert active_level(np.zeros(sr), sr) is None
    np.testing.assert_array_equal(normalise_level(np.zeros(sr), sr, -20.0), np.zeros(sr))
    np.testing.assert_array_equal(normalise_level(speech, sr, None), speech)
    assert active_level(np.array([0.5]), sr) == pytest.approx(10 * np.log10(0.25))   # shorter than a frame
    with pytest.raises(ValueError, match="1-D waveform"):
        active_level(np.zeros((10, 2)), sr)


def test_level_normalisation_makes_the_features_of_a_quieter_recording_the_same():
    """With the absolute floor, the features of the same recording 6 or 20 dB quieter differ
    (more of its mel bands sit at the floor; the mean removal takes out only a shift of the
    bands above it); scaled to the reference active level first, they are the same: to
    rounding for a float waveform, to the 16-bit quantisation noise of the quieter
    recordings (which the normalisation raises with the speech) for int16 ones."""
    from bayes_talk.features.audio import cmvn

    sr = 22050
    speech = _speech_like(sr, 4)

    def moved(level, make):
        feats = {g: cmvn(mfcc(make(speech * 10 ** (g / 20)), sr, level_dbfs=level)) for g in (0, -6, -20)}
        sd = feats[0].std(axis=0)
        return [float(np.mean(np.sqrt(np.mean((feats[g] - feats[0]) ** 2, axis=0)) / sd)) for g in (-6, -20)]

    def pcm16(y):
        return np.round(y * 32767).astype(np.int16)

    assert max(moved(-20.0, lambda y: y)) < 1e-9
    assert max(moved(-20.0, pcm16)) < 0.03
    assert min(moved(None, lambda y: y)) > 0.1
    assert min(moved(None, pcm16)) > 0.1
