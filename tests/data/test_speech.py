"""espeak-ng synthesis: reproducibility, timings, phone mapping."""
from __future__ import annotations

import itertools

import numpy as np
import pytest

from bayes_talk.data.espeak_phones import ESPEAK_TO_ARPABET, espeak_to_arpabet
from bayes_talk.data.phones import PHONES
from bayes_talk.data.speech import SpeechRequest, jittered_requests, synthesize_many

TEXT = "House of representatives has approved legislation."


@pytest.fixture(scope="module")
def results():
    reqs = [SpeechRequest(TEXT), SpeechRequest(TEXT), SpeechRequest(TEXT, rate=200, pitch=30)]
    return synthesize_many(reqs, n_workers=2)


def test_fresh_process_gives_identical_audio(results):
    a, b, c = results
    assert a.samples.dtype == np.int16 and a.sample_rate == 22050
    assert a.samples.tobytes() == b.samples.tobytes()
    assert a.intervals == b.intervals
    # rate 200 wpm is faster than the default 175
    assert c.samples.shape[0] < a.samples.shape[0]


def test_intervals_cover_padded_audio(results):
    r = results[0]
    sr = r.sample_rate
    n = r.samples.shape[0]
    assert n % 882 == 0  # padded to whole 40 ms frames
    iv = r.intervals
    assert iv[0][0] == 0.0 and iv[-1][1] == n / sr
    assert iv[0][2] == "sil" and iv[-1][2] == "sil"
    assert iv[0][1] >= 0.2 and iv[-1][1] - iv[-1][0] >= 0.2
    for (s0, e0, _), (s1, _, _) in itertools.pairwise(iv):
        assert e0 == s1 and s0 < e0
    assert all(p in PHONES for _, _, p in iv)
    # the lead silence really is silent, speech is not
    lead = round(0.2 * sr)
    assert np.all(r.samples[:lead] == 0)
    assert np.abs(r.samples[lead:]).max() > 1000
    # boundaries sit on samples
    for s, e, _ in iv:
        assert abs(s * sr - round(s * sr)) < 1e-6


def test_expected_phones(results):
    phones = [p for _, _, p in results[0].intervals if p != "sil"]
    # House of representatives: hh aw s ...
    assert phones[:3] == ["hh", "aw", "s"]
    assert phones[-3:] == ["sh", "ah", "n"]
    assert len(phones) == 38


def test_unknown_espeak_code_raises_naming_it():
    with pytest.raises(ValueError, match=r"'Q\^'"):
        espeak_to_arpabet("Q^")
    assert espeak_to_arpabet("'aU") == ("aw",)  # stress mark stripped
    assert espeak_to_arpabet("@L") == ("ah", "l")
    assert all(set(v) <= set(PHONES) for v in ESPEAK_TO_ARPABET.values())


def test_jitter_is_seeded_and_prefix_stable():
    texts = ["one two three four five", "six seven eight nine ten", "a b c d e"]
    a = jittered_requests(texts, seed=3)
    b = jittered_requests(texts[:2], seed=3)
    c = jittered_requests(texts, seed=4)
    assert a[:2] == b
    assert [(r.rate, r.pitch) for r in a] != [(r.rate, r.pitch) for r in c]
    assert all(160 <= r.rate <= 190 and 42 <= r.pitch <= 58 for r in a)


def test_bad_requests():
    with pytest.raises(ValueError, match="text"):
        SpeechRequest("   ")
    with pytest.raises(ValueError, match="rate"):
        SpeechRequest("hello there", rate=10)
    with pytest.raises(ValueError, match="voice 'no-such-voice'"):
        synthesize_many([SpeechRequest("hello there", voice="no-such-voice")], n_workers=1)




def test_every_voice_the_build_help_names_speaks(capsys):
    """`corpus build --help` once suggested --voice en-gb, which espeak-ng could not find (its
    British voice's file is "en"; en-gb is only the language code it declares): every voice
    the help lists must be accepted and synthesise, en-gb among them; a name that is neither
    a voice file nor a declared language is refused up front, listing the voices."""
    import re

    from bayes_talk.app.cli import main
    from bayes_talk.data.text_check import check_voice

    with pytest.raises(SystemExit):
        main(["corpus", "build", "--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    listed = re.search(r"--voice VOICE English espeak-ng voice: (.*?);", help_text).group(1)
    voices = [v.replace("- ", "-") for v in listed.split(", ")]   # argparse wraps at hyphens
    assert {"en", "en-gb", "en-us", "en-gb-scotland"} <= set(voices)
    results = synthesize_many([SpeechRequest(text="Hello there.", voice=check_voice(v)) for v in voices],
                              n_workers=2)
    assert all(r.samples.size > 0 and {"l", "ow"} <= {p for _, _, p in r.intervals} for r in results)
    assert [r.request.voice for r in results] == voices       # the request keeps the name given
    variant = synthesize_many([SpeechRequest(text="Hello there.", voice="en-gb+f3")])[0]
    assert not np.array_equal(variant.samples, results[voices.index("en-gb")].samples)
    with pytest.raises(ValueError, match=r"no English voice 'en-xx'.*en-gb-scotland"):
        check_voice("en-xx")
    with pytest.raises(ValueError, match="no variant 'nosuch'"):
        check_voice("en+nosuch")
