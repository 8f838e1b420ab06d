"""One audio-versus-labels tolerance for the corpus loader and synthesis (issue 11)."""
from __future__ import annotations

import pytest

from bayes_talk.data import corpus
from bayes_talk.data.checks import LABEL_TOLERANCE_S, check_audio_vs_labels


def test_tolerance_is_two_frames_and_shared_by_the_corpus_loader():
    assert LABEL_TOLERANCE_S == pytest.approx(2 / 25)
    assert corpus._LABEL_TOL_S == LABEL_TOLERANCE_S


def test_within_tolerance_passes_beyond_it_names_both_files():
    check_audio_vs_labels("a.wav", "a.lab", 2.00, 2.07)
    check_audio_vs_labels("a.wav", "a.lab", 2.07, 2.00)
    with pytest.raises(ValueError, match=r"a\.lab: labels end at 2\.090 s but a\.wav lasts 2\.000 s"):
        check_audio_vs_labels("a.wav", "a.lab", 2.00, 2.09)
    with pytest.raises(ValueError, match="32000 samples"):
        check_audio_vs_labels("a.wav", "a.lab", 2.00, 1.9, detail="32000 samples at 16000 Hz")
