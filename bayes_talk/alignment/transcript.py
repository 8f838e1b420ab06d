"""Transcript -> phone sequence through espeak-ng's own grapheme-to-phoneme conversion.

The built corpus labels its audio with the phones espeak-ng reports while synthesising
(:mod:`bayes_talk.data.speech`, mapped to ARPAbet by :mod:`bayes_talk.data.espeak_phones`).
Synthesising the user's transcript the same way gives the *same* mapping -- the phone
sequence, and as a by-product a synthetic utterance with exact phone times (used by the
DTW aligner, :mod:`bayes_talk.alignment.dtw`).

Checks at the boundary (each a named error, nothing is synthesised):

* :class:`EmptyTranscriptError` -- no word (empty, blank or punctuation only);
* :class:`UnpronounceableWordError` -- a word with a letter outside the Latin script. The
  bundled espeak-ng ``en`` voices do not switch language: they spell Cyrillic letter by
  letter and read CJK characters as "Chinese letter" (measured), which is not what the
  speaker said. Digits are allowed (espeak reads numbers); accented Latin letters too.
"""
from __future__ import annotations

import re
import unicodedata
from pathlib import Path

from bayes_talk.alignment.errors import EmptyTranscriptError, UnpronounceableWordError

__all__ = ["check_transcript", "read_transcript", "synthesise_transcript", "transcript_phones"]

_WORD = re.compile(r"\S+")


def _is_latin_letter(ch: str) -> bool:
    return unicodedata.name(ch, "").startswith("LATIN")


def check_transcript(text: str, where: str = "transcript") -> list[str]:
    """The transcript's words; raise a named error for an empty or unpronounceable one."""
    if not isinstance(text, str):
        raise EmptyTranscriptError(f"{where}: expected text, found {type(text).__name__}")
    words = [w for w in _WORD.findall(text) if any(ch.isalnum() for ch in w)]
    if not words:
        raise EmptyTranscriptError(f"{where}: empty transcript (no words in {text!r}); "
                                   "alignment needs the words that were said")
    bad = [w for w in words if any(ch.isalpha() and not _is_latin_letter(ch) for ch in w)]
    if bad:
        raise UnpronounceableWordError(
            f"{where}: word(s) {bad[:5]} cannot be pronounced in English by espeak-ng (letters "
            "outside the Latin script; espeak would spell them letter by letter); transliterate them")
    return words


def read_transcript(path: str | Path) -> str:
    """Read a UTF-8 transcript file (newlines become spaces); errors name the file."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{p}: cannot read transcript ({exc})") from exc
    text = " ".join(text.split())
    check_transcript(text, where=str(p))
    return text


def synthesise_transcript(text: str, voice: str = "en", where: str = "transcript"):
    """espeak-ng synthesis of ``text`` at the default rate and pitch, no frame padding:
    a :class:`bayes_talk.data.speech.SpeechResult` (samples, ARPAbet intervals)."""
    from bayes_talk.data.speech import SpeechRequest, synthesize

    check_transcript(text, where)
    try:
        return synthesize(SpeechRequest(text=text, voice=voice, fps=0))
    except ValueError as exc:  # an espeak mnemonic without ARPAbet mapping
        raise UnpronounceableWordError(f"{where}: espeak-ng cannot pronounce {text!r} with the "
                                       f"model's phone set ({exc})") from exc


def transcript_phones(text: str, voice: str = "en", where: str = "transcript") -> list[str]:
    """The ARPAbet phone sequence of ``text`` (``sil`` at both ends and at pauses)."""
    return [p for _, _, p in synthesise_transcript(text, voice, where).intervals]
