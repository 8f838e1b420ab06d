"""synth says each warning about its audio once (issue 28): the speech check before the
recogniser reads the file too, but leaves clipping / MP3 warnings to the feature load."""
from __future__ import annotations

import warnings

import numpy as np
import pytest
import soundfile as sf

from bayes_talk.pipeline import read_utterance
from bayes_talk.pipeline.talking_face import _check_speech


@pytest.fixture(scope="module")
def clipped(tmp_path_factory):
    from bayes_talk.data.speech import SpeechRequest, synthesize

    res = synthesize(SpeechRequest("The quick brown fox jumps over the lazy dog."))
    y = res.samples / np.abs(res.samples).max()
    y = np.clip(y / np.quantile(np.abs(y), 1 - 0.004), -1, 1)      # 0.4 % of the samples at full scale
    path = tmp_path_factory.mktemp("clip") / "loud.wav"
    sf.write(str(path), y, res.sample_rate, subtype="PCM_16")
    (path.with_suffix(".lab")).write_text(f"0 {int(len(y) / res.sample_rate * 1e7)} sil\n")
    return path


def _caught(fn) -> list[str]:
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        fn()
    return [str(w.message) for w in got]


def test_the_clipping_warning_comes_once_from_the_feature_load(clipped):
    check = _caught(lambda: _check_speech(clipped, recognise=True))
    assert check == []
    load = _caught(lambda: read_utterance(clipped, clipped.with_suffix(".lab"), 25.0))
    assert sum("at full scale" in m for m in load) == 1


def test_the_speech_check_still_warns_about_silence_with_labels(tmp_path):
    silent = tmp_path / "silent.wav"
    sf.write(str(silent), np.zeros(22050), 22050, subtype="PCM_16")
    msgs = _caught(lambda: _check_speech(silent, recognise=False))
    assert len(msgs) == 1 and "no speech found" in msgs[0]
    with pytest.raises(ValueError, match="no speech found"):
        _check_speech(silent, recognise=True)
