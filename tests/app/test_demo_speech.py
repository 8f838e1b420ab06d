"""``make demo`` builds its corpus with the speech generator the audio-information
measurement favours (issue 25), and falls back to espeak, saying why, without VocalTractLab."""
from __future__ import annotations

import pytest

from bayes_talk.app import demo


def test_demo_prefers_the_articulatory_generator(monkeypatch):
    from bayes_talk.data import articulatory

    assert demo.DEMO_SPEECH == "vtl"
    monkeypatch.setattr(articulatory, "require_vtl", lambda: object())
    speech, why = demo.demo_speech()
    assert speech == "vtl" and "audio_information" in why


def test_demo_falls_back_to_espeak_without_vtl(monkeypatch):
    from bayes_talk.data import articulatory

    def missing():
        raise RuntimeError(articulatory._INSTALL_HINT)

    monkeypatch.setattr(articulatory, "require_vtl", missing)
    speech, why = demo.demo_speech()
    assert speech == "espeak"
    assert "falling back to espeak" in why and "pip install 'bayes_talk[articulatory]'" in why


def test_demo_speech_rejects_an_unknown_generator():
    assert demo.demo_speech("espeak")[0] == "espeak"
    with pytest.raises(ValueError, match=r"expected one of \['espeak', 'vtl'\], found 'festival'"):
        demo.demo_speech("festival")
