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

import warnings
from collections.abc import Mapping, Sequence

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


def substitute_unseen(label: str, counts: Mapping[str, int], where: str = "") -> str:
    """The one unseen-phone policy of the package (every model that reads phone labels).

    A valid phone never seen in training is replaced by the most frequent training phone
    of its MPEG-4 viseme (:data:`PHONE_TO_VISEME`: the same mouth shape), or, when no phone
    of that viseme was seen, by the most frequent training phone overall; ties go to the
    alphabetically first. ``counts``: training frames per phone (phones with count > 0
    are the seen ones). A label outside the phone set raises ValueError (naming ``where``).
    """
    check_phone(label, where)
    seen = sorted(p for p, n in counts.items() if n > 0)
    if not seen:
        raise ValueError("no phones seen in training")
    mates = [p for p in seen if PHONE_TO_VISEME[p] == PHONE_TO_VISEME[label]]
    return max(mates or seen, key=lambda p: counts[p])


def replace_unseen(labels: Sequence[str], counts: Mapping[str, int], where: str = "",
                   stacklevel: int = 3) -> list[str]:
    """``labels`` with every phone unseen in training replaced by :func:`substitute_unseen`,
    with one UserWarning listing the replacements."""
    out, unseen = [], {}
    for lab in labels:
        if counts.get(lab, 0) > 0:
            out.append(lab)
            continue
        out.append(unseen.setdefault(lab, substitute_unseen(lab, counts, where)))
    if unseen:
        pairs = ", ".join(f"{k!r}->{v!r}" for k, v in sorted(unseen.items()))
        loc = f" in {where}" if where else ""
        warnings.warn(f"phones not seen in training{loc} replaced: {pairs}", UserWarning, stacklevel=stacklevel)
    return out
