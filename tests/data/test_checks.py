"""One audio-versus-labels tolerance and one unseen-phone policy (issue 11)."""
from __future__ import annotations

import pytest

from bayes_talk.corpus.layouts import check_item_audio
from bayes_talk.data.checks import LABEL_TOLERANCE_S, check_audio_vs_labels
from bayes_talk.data.phones import replace_unseen, substitute_unseen


def test_tolerance_is_two_frames_and_shared_by_the_corpus_loader():
    assert LABEL_TOLERANCE_S == pytest.approx(2 / 25)
    sr = 16000
    check_item_audio("a.wav", "a.lab", 2 * sr, sr, [(0.0, 2.07, "sil")])
    with pytest.raises(ValueError, match=r"a\.lab: labels end at 2\.090 s but a\.wav lasts 2\.000 s "
                                         r"\(32000 samples at 16000 Hz\)"):
        check_item_audio("a.wav", "a.lab", 2 * sr, sr, [(0.0, 2.09, "sil")])


def test_within_tolerance_passes_beyond_it_names_both_files():
    check_audio_vs_labels("a.wav", "a.lab", 2.00, 2.07)
    check_audio_vs_labels("a.wav", "a.lab", 2.07, 2.00)
    with pytest.raises(ValueError, match=r"a\.lab: labels end at 2\.090 s but a\.wav lasts 2\.000 s"):
        check_audio_vs_labels("a.wav", "a.lab", 2.00, 2.09)
    with pytest.raises(ValueError, match="32000 samples"):
        check_audio_vs_labels("a.wav", "a.lab", 2.00, 1.9, detail="32000 samples at 16000 Hz")


def test_unseen_phone_policy_viseme_mate_then_most_frequent():
    counts = {"m": 2, "p": 5, "aa": 9, "sil": 9, "iy": 0}
    assert substitute_unseen("b", counts) == "p"          # viseme p_b_m: the most frequent mate
    assert substitute_unseen("iy", counts) == "aa"        # no mate seen (iy has 0 frames): most frequent
    assert substitute_unseen("zh", {"sil": 1, "aa": 1}) == "aa"  # ties alphabetical
    with pytest.raises(ValueError, match="unknown phone label 'qq' in test"):
        substitute_unseen("qq", counts, where="test")
    with pytest.warns(UserWarning, match=r"replaced: 'b'->'p', 'iy'->'aa'"):
        assert replace_unseen(["b", "aa", "iy", "b"], counts) == ["p", "aa", "aa", "p"]
