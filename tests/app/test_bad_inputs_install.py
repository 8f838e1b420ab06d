"""Bad inputs a new user tried (issue 28): each gets a named error before any work, or a
warning where the result is degraded."""
from __future__ import annotations

import os
from pathlib import Path
from types import SimpleNamespace

import pytest

from bayes_talk.app.cli import main


def _unwritable_dir(tmp_path: Path) -> Path:
    """A directory nothing can be created in: mode 0555 for a normal user; root ignores modes,
    so for root a path under /sys/kernel (read-only to everyone)."""
    if os.geteuid() != 0:
        d = tmp_path / "ro"
        d.mkdir()
        d.chmod(0o555)
        return d / "out"
    d = Path("/sys/kernel")
    if not d.is_dir() or os.access(d, os.W_OK) and _can_create(d):
        pytest.skip("no unwritable directory available to root here")
    return d / "bayes_talk_out"


def _can_create(d: Path) -> bool:
    try:
        (d / ".bayes_talk_probe").touch()
    except OSError:
        return False
    (d / ".bayes_talk_probe").unlink()
    return True


@pytest.fixture
def no_model_load(monkeypatch):
    """synth must refuse before it loads the model (and so before the synthesis)."""
    from bayes_talk.pipeline import talking_face

    def boom(*a, **k):
        raise AssertionError("the model was loaded before the output was checked")

    monkeypatch.setattr(talking_face, "load_trained", boom)


def test_synth_out_an_existing_file_is_refused_by_name_before_any_work(tmp_path, capsys, no_model_load):
    f = tmp_path / "result.mp4"
    f.write_bytes(b"x")
    argv = ["synth", str(tmp_path / "model"), "--audio", "a.wav", "--labels", "a.lab", "--out", str(f)]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"--out {f}: is a file, not a directory" in err and "Errno" not in err
    assert f.read_bytes() == b"x"


def test_synth_out_an_unwritable_directory_is_refused_by_name_before_any_work(tmp_path, capsys, no_model_load):
    out = _unwritable_dir(tmp_path)
    argv = ["synth", str(tmp_path / "model"), "--audio", "a.wav", "--labels", "a.lab", "--out", str(out)]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"--out {out}: cannot write into" in err and "choose a writable directory" in err
    assert ".bayes_talk_probe" not in err and not out.exists()


def test_check_output_dir_creates_nothing_and_accepts_new_and_existing_directories(tmp_path):
    from bayes_talk.base.bundle import check_output_dir

    assert check_output_dir(tmp_path / "a" / "b") == tmp_path / "a" / "b"
    assert not (tmp_path / "a").exists()
    assert check_output_dir(tmp_path) == tmp_path and list(tmp_path.iterdir()) == []
    (tmp_path / "f").write_text("x")
    with pytest.raises(ValueError, match="is a file, so the directory cannot be created"):
        check_output_dir(tmp_path / "f" / "out")




def test_evaluate_on_too_few_utterances_names_min_utterances(tmp_path, monkeypatch):
    import bayes_talk.corpus as corpus_mod
    from bayes_talk.evaluation import harness

    fake = SimpleNamespace(sequences=[object()] * 30, aam_path=None, manifest={})
    monkeypatch.setattr(corpus_mod, "load_corpus", lambda *a, **k: fake)

    def no_training(*a, **k):
        raise AssertionError("trained on a corpus that is too small")

    monkeypatch.setattr(harness, "run_protocol", no_training)
    with pytest.raises(ValueError) as exc:
        harness.evaluate("deena2010", tmp_path / "c", tmp_path / "r.json", quick=True)
    msg = str(exc.value)
    assert "needs at least 120 utterances" in msg and "has 30" in msg and "--min-utterances 30" in msg


# --- audio that is clipped, silent or noise -------------------------------------------------

@pytest.fixture(scope="module")
def speech_wav(tmp_path_factory) -> Path:
    """A real utterance (espeak-ng), 16-bit."""
    from bayes_talk.data.speech import SpeechRequest, synthesize, write_wav

    res = synthesize(SpeechRequest("The quick brown fox jumps over the lazy dog."))
    path = tmp_path_factory.mktemp("speech") / "speech.wav"
    write_wav(path, res.samples, res.sample_rate)
    return path


def _write(path: Path, y, sr: int) -> Path:
    import numpy as np
    import soundfile as sf

    sf.write(str(path), np.clip(y, -1, 1), sr, subtype="PCM_16")
    return path


def test_clipped_audio_warns_with_the_fraction(speech_wav, tmp_path):
    import warnings

    import numpy as np
    import soundfile as sf

    from bayes_talk.features.audio import load_audio

    y, sr = sf.read(str(speech_wav))
    y = y / np.abs(y).max()
    with warnings.catch_warnings():
        warnings.simplefilter("error")                  # the clean recording: no warning
        load_audio(speech_wav)
    gain = np.quantile(np.abs(y), 1 - 0.004)           # +x dB that puts 0.4 % of the samples at full scale
    loud = _write(tmp_path / "loud.wav", y / gain, sr)
    with pytest.warns(UserWarning, match=r"loud\.wav: 0\.[3-5]\d % of the samples are at full scale \(clipped"):
        load_audio(loud)
    hot = tmp_path / "hot.wav"                          # floating point beyond full scale: nothing clipped
    sf.write(str(hot), 2 * y, sr, subtype="FLOAT")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert np.abs(load_audio(hot)[0]).max() > 1.5


def test_silence_and_white_noise_hold_no_speech_and_speech_does(speech_wav, tmp_path):
    import numpy as np
    import soundfile as sf

    from bayes_talk.features.audio import speech_problem

    y, sr = sf.read(str(speech_wav))
    rng = np.random.default_rng(0)
    assert speech_problem(y, sr) is None
    noisy = y + rng.normal(scale=np.sqrt(np.mean(y ** 2) / 10), size=y.size)   # 10 dB SNR: still speech
    assert speech_problem(noisy, sr) is None
    assert speech_problem(np.zeros(sr), sr).startswith("silent (no signal at all")
    assert speech_problem(1e-4 * rng.normal(size=sr), sr).startswith("silent (peak")
    assert speech_problem(0.3 * rng.normal(size=3 * sr), sr).startswith("noise-like (0 % of its frames tonal")


def test_synth_refuses_to_recognise_phones_in_noise_and_warns_with_labels(tmp_path, monkeypatch):
    import numpy as np

    import bayes_talk.pipeline as pl
    from bayes_talk.pipeline import talking_face

    sr = 22050
    noise = _write(tmp_path / "noise.wav", 0.2 * np.random.default_rng(1).normal(size=2 * sr), sr)
    audio = SimpleNamespace(sample_rate=sr, cmvn="mean", fmax=None, floor_dbfs=None, level_dbfs=None)
    model = pl.new_model("ssgpdm-phone-rc")   # unfitted: synth must stop before using it
    monkeypatch.setattr(talking_face, "load_trained", lambda d: SimpleNamespace(kind="ssgpdm-phone-rc", model=model,
                                                                        audio=audio, fps=25.0))

    def recogniser(*a, **k):
        raise AssertionError("the recogniser ran on noise")

    monkeypatch.setattr(talking_face, "_derived_labels", recogniser)
    with pytest.raises(ValueError, match=r"noise\.wav: no speech found, the audio is noise-like.*--labels"):
        pl.synth(tmp_path / "model", noise, None, tmp_path / "out")

    def stop(*a, **k):
        raise RuntimeError("stop after the check")

    monkeypatch.setattr(talking_face, "read_utterance", stop)
    lab = tmp_path / "noise.lab"
    lab.write_text("0 20000000 sil\n")
    with (pytest.warns(UserWarning, match=r"no speech found, the audio is noise-like.*: the face follows the given"),
          pytest.raises(RuntimeError, match="stop after the check")):
        pl.synth(tmp_path / "model", noise, lab, tmp_path / "out2")


def _lag(a, b, maxlag: int = 3000) -> int:
    import numpy as np

    n = min(len(a), len(b)) - maxlag
    return max(range(-maxlag, maxlag), key=lambda k: float(np.dot(a[maxlag:n], b[maxlag + k:n + k])))


def test_mp3_with_a_gapless_header_is_aligned_and_one_without_warns(speech_wav, tmp_path):
    import subprocess
    import warnings

    import imageio_ffmpeg
    import soundfile as sf

    from bayes_talk.features.audio import load_audio

    ff = imageio_ffmpeg.get_ffmpeg_exe()
    y, sr = sf.read(str(speech_wav))
    tagged, bare = tmp_path / "tagged.mp3", tmp_path / "bare.mp3"
    for path, extra in ((tagged, []), (bare, ["-write_xing", "0"])):
        subprocess.run([ff, "-y", "-v", "error", "-i", str(speech_wav), "-codec:a", "libmp3lame", "-b:a", "128k",
                        *extra, str(path)], check=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        z, zsr = load_audio(tagged)
    assert zsr == sr and len(z) == len(y) and _lag(y, z) == 0            # delay and padding removed
    with pytest.warns(UserWarning, match=r"bare\.mp3: an MP3 without a gapless .* probably late"):
        z, _ = load_audio(bare)
    assert _lag(y, z) == 1105                                         # what the warning is about
