"""What the built-in corpus's speech synthesiser can pronounce, checked before any work.

The corpus's phone set is English ARPAbet 39 (+ ``sil``) and espeak-ng's phonemes are
mapped to it by :mod:`bayes_talk.data.espeak_phones`, a table for English voices only.
So ``corpus build`` accepts the English espeak-ng voices (names ``en`` and ``en-...``,
e.g. ``en-us``, ``en-gb``, ``en-gb-scotland``) and sentences written in Latin script:
other scripts (CJK, Cyrillic, Greek, Arabic, ...) would be read out letter by letter as
"Chinese letter ..." and are refused, naming the sentence and the first such letter.
"""
from __future__ import annotations

import unicodedata

__all__ = ["check_pronounceable", "check_voice", "is_english_voice"]


def is_english_voice(voice: str) -> bool:
    """Whether an eSpeak voice name is an English voice."""
    name = str(voice).strip().lower().rsplit("/", 1)[-1].split("+", 1)[0]   # "en+f3": voice + variant
    return name == "en" or name.startswith("en-")


def check_voice(voice: str) -> str:
    """``voice`` if it is an English espeak-ng voice name, else ValueError saying which are."""
    if not is_english_voice(voice):
        raise ValueError(f"voice {voice!r} is not supported: the corpus's phone set is English "
                         "(ARPAbet 39), so only English espeak-ng voices can be used: en, en-us, en-gb, "
                         "en-gb-scotland, en-gb-x-rp, en-029, ...")
    return voice


def check_pronounceable(texts: list[str], voice: str, source: str = "sentences") -> None:
    """ValueError naming the first sentence with a letter outside the Latin script."""
    for i, text in enumerate(texts, 1):
        for ch in text:
            if ch.isalpha() and not unicodedata.name(ch, "").startswith("LATIN"):
                script = unicodedata.name(ch, "UNKNOWN").split()[0].title()
                raise ValueError(f"{source}: sentence {i} {text!r} contains {script} letter {ch!r}, "
                                 f"which voice {voice!r} cannot pronounce (it would spell it out); "
                                 "use Latin-script English text")
