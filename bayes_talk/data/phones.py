"""The one phone set of the package (ARPAbet 39 + ``sil``) and its viseme table.

Phones are lower-case ARPAbet without stress digits. Visemes follow MPEG-4 FBA
(ISO/IEC 14496-2, viseme numbers 0-14):

====  ==========  ==========================
 id   name        phones
====  ==========  ==========================
 0    none        sil
 1    p_b_m       p b m
 2    f_v         f v
 3    th_dh       th dh
 4    t_d         t d
 5    k_g         k g ng hh
 6    ch_jh_sh    ch jh sh zh
 7    s_z         s z
 8    n_l         n l
 9    r           r er
 10   A           aa ae ah aw ay
 11   E           eh ey
 12   I           ih iy y
 13   O           ao ow oy
 14   U           uh uw w
====  ==========  ==========================

MPEG-4 lists only the consonant groups and five vowels; the placement of the remaining
ARPAbet phones (``ng hh`` with the velars, ``zh`` with the post-alveolars, ``er`` with
``r``, diphthongs by their first, longer target, the glides ``w y`` with the vowel
they start from) is ours.
"""
from __future__ import annotations

SILENCE = "sil"

#: ARPAbet 39 phones + silence, in a fixed order (index = integer code).
PHONES: tuple[str, ...] = (
    "sil",
    "aa", "ae", "ah", "ao", "aw", "ay", "eh", "er", "ey", "ih", "iy", "ow", "oy", "uh", "uw",
    "b", "ch", "d", "dh", "f", "g", "hh", "jh", "k", "l", "m", "n", "ng", "p", "r", "s",
    "sh", "t", "th", "v", "w", "y", "z", "zh",
)
PHONE_INDEX: dict[str, int] = {p: i for i, p in enumerate(PHONES)}

VISEME_NAMES: tuple[str, ...] = (
    "none", "p_b_m", "f_v", "th_dh", "t_d", "k_g", "ch_jh_sh", "s_z", "n_l", "r",
    "A", "E", "I", "O", "U",
)

_VISEME_GROUPS: dict[int, tuple[str, ...]] = {
    0: ("sil",),
    1: ("p", "b", "m"),
    2: ("f", "v"),
    3: ("th", "dh"),
    4: ("t", "d"),
    5: ("k", "g", "ng", "hh"),
    6: ("ch", "jh", "sh", "zh"),
    7: ("s", "z"),
    8: ("n", "l"),
    9: ("r", "er"),
    10: ("aa", "ae", "ah", "aw", "ay"),
    11: ("eh", "ey"),
    12: ("ih", "iy", "y"),
    13: ("ao", "ow", "oy"),
    14: ("uh", "uw", "w"),
}

#: phone -> MPEG-4 viseme id
PHONE_TO_VISEME: dict[str, int] = {p: v for v, ps in _VISEME_GROUPS.items() for p in ps}

VOWELS: frozenset[str] = frozenset(
    ("aa", "ae", "ah", "ao", "aw", "ay", "eh", "er", "ey", "ih", "iy", "ow", "oy", "uh", "uw")
)
BILABIALS: frozenset[str] = frozenset(("p", "b", "m"))
LABIODENTALS: frozenset[str] = frozenset(("f", "v"))

assert len(PHONES) == 40 and set(PHONE_TO_VISEME) == set(PHONES)


def check_phone(label: str, where: str = "") -> str:
    """Return ``label`` if it is in the phone set, else raise a ValueError naming it."""
    if label not in PHONE_INDEX:
        loc = f" in {where}" if where else ""
        raise ValueError(
            f"unknown phone label {label!r}{loc}; expected one of ARPAbet 39 + 'sil': "
            + " ".join(PHONES)
        )
    return label
