"""espeak-ng phoneme mnemonics (voice ``en``) -> ARPAbet 39 + ``sil``.

espeak-ng reports phonemes by its own ASCII mnemonics (Kirshenbaum-like). The ``en``
voice is British English (RP-like, non-rhotic): ``car`` is ``k A@``, ``lot`` is ``l 0 t``.
We map each mnemonic to the ARPAbet phone(s) a CMU-dictionary transcription of the same
word would use, because the downstream models and viseme table speak ARPAbet.

=====================  ==============  ============================================
espeak                 ARPAbet         note
=====================  ==============  ============================================
``_ _: _! _^_ _| ...``  sil             pauses
``@ @- @2 @5 @# a# V``  ah             schwa and strut (ARPAbet 39 folds ax into ah)
``3 3: VR``            er              schwa-r, nurse
``@L``                 ah l            syllabic l ("bottle"): interval split in 2
``a a2``               ae              trap
``aa A: A@ A# A~``     aa              bath/palm/start (RP long a)
``0 0# 02``            aa              lot (US "lot" vowel)
``E E# E2 e# e@``      eh              dress, square
``e: eI``              ey
``I I# I2 I2# IR``     ih              kit, reduced i
``i i: i@ i@3``        iy / ih         happy/fleece -> iy; near (i@) -> ih
``O O: O2 O@ o@ O~``   ao              thought, north, force
``o: oU oU#``          ow
``OI``                 oy
``U U@``               uh              foot, cure
``u:``                 uw
``aU aU@``             aw
``aI aI@ aI3``         ay
``p b t d k g``        same            ``t# t2 d#`` (flaps, taps) -> t / d
``f v s z h m n l w``  f v s z hh ...  ``z# z/2`` -> z; ``w#`` -> w; ``l/ l/2 l#`` -> l
``T D S Z``            th dh sh zh
``N``                  ng
``tS dZ``              ch jh
``r r- r/ R *``        r
``j``                  y
``;``                  y               linking glide between a front vowel and the next
                                       vowel ("the_early", "happy_in"), ~45 ms
``m- n- N-``           m n ng          syllabic nasals
``?``                  t               glottal stop (a glottalised /t/ in English)
``x``                  k               loch (loan words)
``C``                  hh              palatal fricative (loan words; "huge")
=====================  ==============  ============================================

Stress marks prefixed to a mnemonic in phoneme events (``'aU``: primary, ``,`` secondary,
``%`` unstressed, ``=``) are stripped first. Anything not in the table raises a ``ValueError`` naming the code: there is no silent
default. Codes were collected by synthesising the built-in sentence list with voice
``en`` (see ``tests/data/test_speech.py``); other voices (``en-us`` ...) use other codes and
may need additions.
"""
from __future__ import annotations

from bayes_talk.data.phones import check_phone

__all__ = ["ESPEAK_TO_ARPABET", "espeak_to_arpabet"]

#: stress marks espeak prefixes to a vowel's mnemonic in phoneme events (primary,
#: secondary, unstressed); stress is not part of ARPAbet 39, so they are stripped.
_STRESS_MARKS = "',%="

_PAUSES = ("_", "_:", "_!", "_^_", "_|", "_::", "_;_", "||", "_X1")

#: espeak mnemonic -> tuple of ARPAbet phones (usually one).
ESPEAK_TO_ARPABET: dict[str, tuple[str, ...]] = {
    **{p: ("sil",) for p in _PAUSES},
    # vowels
    "@": ("ah",), "@2": ("ah",), "@5": ("ah",), "@#": ("ah",), "a#": ("ah",), "a#2": ("ah",),
    "V": ("ah",), "@-": ("ah",),
    "3": ("er",), "3:": ("er",), "VR": ("er",),
    "@L": ("ah", "l"),
    "a": ("ae",), "a2": ("ae",),
    "aa": ("aa",), "A:": ("aa",), "A@": ("aa",), "A#": ("aa",), "A~": ("aa",),
    "0": ("aa",), "0#": ("aa",), "02": ("aa",),
    "E": ("eh",), "E#": ("eh",), "E2": ("eh",), "e#": ("eh",), "e@": ("eh",),
    "e:": ("ey",), "eI": ("ey",),
    "I": ("ih",), "I#": ("ih",), "I2": ("ih",), "I2#": ("ih",), "IR": ("ih",),
    "i": ("iy",), "i:": ("iy",), "i@": ("ih",), "i@3": ("ih",),
    "O": ("ao",), "O:": ("ao",), "O2": ("ao",), "O@": ("ao",), "o@": ("ao",), "O~": ("ao",),
    "o:": ("ow",), "oU": ("ow",), "oU#": ("ow",),
    "OI": ("oy",),
    "U": ("uh",), "U@": ("uh",),
    "u:": ("uw",),
    "aU": ("aw",), "aU@": ("aw",),
    "aI": ("ay",), "aI@": ("ay",), "aI3": ("ay",),
    # consonants
    "p": ("p",), "b": ("b",), "t": ("t",), "t#": ("t",), "t2": ("t",), "d": ("d",),
    "d#": ("d",), "k": ("k",), "g": ("g",), "?": ("t",),
    "f": ("f",), "v": ("v",), "T": ("th",), "D": ("dh",), "s": ("s",), "z": ("z",),
    "z#": ("z",), "z/2": ("z",), "S": ("sh",), "Z": ("zh",), "h": ("hh",), "x": ("k",),
    "C": ("hh",),
    "tS": ("ch",), "dZ": ("jh",),
    "m": ("m",), "n": ("n",), "N": ("ng",), "m-": ("m",), "n-": ("n",), "N-": ("ng",),
    "l": ("l",), "l/": ("l",), "l/2": ("l",), "l#": ("l",),
    "r": ("r",), "r-": ("r",), "r/": ("r",), "R": ("r",), "*": ("r",),
    "w": ("w",), "w#": ("w",), "j": ("y",), ";": ("y",),
}

for _code, _phones in ESPEAK_TO_ARPABET.items():
    for _p in _phones:
        check_phone(_p, f"ESPEAK_TO_ARPABET[{_code!r}]")


def espeak_to_arpabet(code: str, where: str = "") -> tuple[str, ...]:
    """ARPAbet phone(s) for one espeak mnemonic; raise ValueError naming an unknown code."""
    key = code.lstrip(_STRESS_MARKS)
    try:
        return ESPEAK_TO_ARPABET[key]
    except KeyError:
        loc = f" in {where}" if where else ""
        raise ValueError(
            f"espeak-ng produced phoneme {code!r}{loc}, which has no equivalent in bayes_talk's "
            "English phone set (ARPAbet 39); rephrase or drop that sentence, and use an English voice"
        ) from None
