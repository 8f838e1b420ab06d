"""What the built-in corpus's speech synthesiser can pronounce, checked before any work.

The corpus's phone set is English ARPAbet 39 (+ ``sil``) and espeak-ng's phonemes are
mapped to it by :mod:`bayes_talk.data.espeak_phones`, a table for English voices only.
So ``corpus build`` accepts the English voices of the bundled espeak-ng (:func:`english_voices`:
``en``, ``en-us``, ``en-gb``, ``en-gb-scotland``, ...) and sentences written in Latin script:
other scripts (CJK, Cyrillic, Greek, Arabic, ...) would be read out letter by letter as
"Chinese letter ..." and are refused, naming the sentence and the first such letter.
"""
from __future__ import annotations

import re
import unicodedata

__all__ = ["check_pronounceable", "check_voice", "content_words", "english_voices", "is_english_voice",
           "template_overlap"]

#: function words left out of :func:`content_words`: two sentences built on one template
#: ("The pilot announced a short delay because of ...") share their content words, not these
FUNCTION_WORDS = frozenset(["a", "an", "the", "and", "or", "but", "nor", "of", "to", "in", "on", "at", "for", "from", "by", "with", "into", "onto", "over", "under", "after", "before", "until", "while", "when", "whenever", "every", "each", "his", "her", "its", "their", "our", "my", "your", "he", "she", "it", "they", "we", "you", "i", "me", "us", "them", "him", "is", "are", "was", "were", "be", "been", "being", "has", "have", "had", "do", "does", "did", "this", "that", "these", "those", "as", "than", "then", "so", "not", "no", "any", "many", "some", "all", "one", "two", "very", "too", "up", "down", "off", "out", "about", "across", "along", "near", "beside", "above", "below", "around", "through", "how", "often", "long", "last"])


def is_english_voice(voice: str) -> bool:
    """Whether an eSpeak voice name is an English voice."""
    name = str(voice).strip().lower().rsplit("/", 1)[-1].split("+", 1)[0]   # "en+f3": voice + variant
    return name == "en" or name.startswith("en-")


def english_voices() -> list[str]:
    """The English voice names of the bundled espeak-ng (voice files and the language codes
    they declare, :func:`bayes_talk.data.speech.espeak_voices`), ``en`` first."""
    from bayes_talk.data.speech import espeak_voices

    return sorted((v for v in espeak_voices() if is_english_voice(v)), key=lambda v: (v != "en", v))


def check_voice(voice: str) -> str:
    """``voice`` if it is an English espeak-ng voice name (a voice or language of
    :func:`english_voices`, optionally with a ``+variant`` of the bundled data), else
    ValueError saying which are."""
    from bayes_talk.data.speech import espeak_variants

    voices = english_voices()
    if not is_english_voice(voice):
        raise ValueError(f"voice {voice!r} is not supported: the corpus's phone set is English "
                         "(ARPAbet 39), so only English espeak-ng voices can be used: " + ", ".join(voices))
    name, _, variant = str(voice).partition("+")
    if name.strip().lower().rsplit("/", 1)[-1] not in voices:   # gmw/en: espeak-ng's own path
        raise ValueError(f"voice {voice!r}: espeak-ng has no English voice {name.strip()!r}; its English "
                         "voices are " + ", ".join(voices) + " (a variant may follow: en+f3)")
    if variant and variant not in espeak_variants():
        raise ValueError(f"voice {voice!r}: espeak-ng has no variant {variant!r}; it has "
                         + ", ".join(espeak_variants()))
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


def content_words(text: str) -> frozenset[str]:
    """The lower-cased words of ``text`` of three or more letters that are not in
    :data:`FUNCTION_WORDS` (a possessive 's dropped)."""
    words = re.findall(r"[a-z']+", text.lower().replace("'s", ""))
    return frozenset(w for w in words if len(w) > 2 and w not in FUNCTION_WORDS)


def template_overlap(sentences: list[str], reference: list[str]) -> tuple[float, str, str]:
    """The largest content-word Jaccard index |A ∩ B| / |A ∪ B| between a sentence of
    ``sentences`` and one of ``reference``, with the two sentences: a held-out set whose
    largest overlap with the training list and the development set is below 0.3 shares no
    sentence template with them (a paraphrase such as "The lighthouse keeper counted every
    passing ship before dawn." / "... counted seventeen ships before midnight." scores 0.33)."""
    best = (0.0, "", "")
    ref = [(r, content_words(r)) for r in reference]
    for s in sentences:
        a = content_words(s)
        for r, b in ref:
            union = a | b
            j = len(a & b) / len(union) if union else 0.0
            if j > best[0]:
                best = (j, s, r)
    return best
