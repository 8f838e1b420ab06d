"""HTK .lab / TextGrid round trips, frame-label majority vote, label validation."""
from __future__ import annotations

import numpy as np
import pytest

from bayes_talk.data.labels import (
    frame_labels,
    normalize_phone,
    read_lab,
    read_labels,
    read_textgrid,
    write_lab,
    write_textgrid,
)
from bayes_talk.data.phones import PHONES


def _random_intervals(rng, n=30, grid=1e-7):
    cuts = np.sort(rng.choice(np.arange(1, 40_000_000), size=n, replace=False))
    cuts = np.concatenate([[0], cuts])
    labs = rng.choice(PHONES, size=n)
    return [(int(a) / 1e7, int(b) / 1e7, str(p)) for a, b, p in zip(cuts[:-1], cuts[1:], labs)]


def test_lab_round_trip_lossless(tmp_path):
    rng = np.random.default_rng(0)
    iv = _random_intervals(rng)
    p = tmp_path / "a.lab"
    write_lab(p, iv)
    back = read_lab(p)
    assert back == iv  # exact equality of floats and labels
    text = p.read_bytes()
    write_lab(tmp_path / "b.lab", back)
    assert (tmp_path / "b.lab").read_bytes() == text
    first = text.decode().splitlines()[0].split()
    assert int(first[0]) == 0 and int(first[1]) == round(iv[0][1] * 1e7)


def test_lab_reads_extra_columns_and_rejects_garbage(tmp_path):
    p = tmp_path / "x.lab"
    p.write_text("0 1000000 sil -12.5 word\n1000000 2500000 aa\n")
    assert read_lab(p) == [(0.0, 0.1, "sil"), (0.1, 0.25, "aa")]
    p.write_text("0 0.1 sil\n")
    with pytest.raises(ValueError, match="x.lab"):
        read_lab(p)


def test_textgrid_round_trip_lossless_any_float(tmp_path):
    rng = np.random.default_rng(1)
    t = np.sort(rng.uniform(0, 3, size=25))
    t[0] = 0.0
    labs = rng.choice(PHONES, size=24)
    iv = [(float(a), float(b), str(p)) for a, b, p in zip(t[:-1], t[1:], labs)]
    iv[3] = (iv[3][0], iv[3][1], 'say "hi"')  # quote escaping
    p = tmp_path / "a.TextGrid"
    write_textgrid(p, iv)
    assert read_textgrid(p) == iv
    text = p.read_text()
    assert 'class = "IntervalTier"' in text and "intervals [24]:" in text


SHORT_TG = '''File type = "ooTextFile"
Object class = "TextGrid"

0
0.3
<exists>
2
"TextTier"
"events"
0
0.3
1
0.1
"click"
"IntervalTier"
"phones"
0
0.3
3
0
0.1
""
0.1
0.2
"AH0"
0.2
0.3
"sil"
'''


def test_textgrid_short_format_and_normalisation(tmp_path):
    p = tmp_path / "s.TextGrid"
    p.write_text(SHORT_TG)
    assert read_textgrid(p) == [(0.0, 0.1, ""), (0.1, 0.2, "AH0"), (0.2, 0.3, "sil")]
    assert read_labels(p) == [(0.0, 0.1, "sil"), (0.1, 0.2, "ah"), (0.2, 0.3, "sil")]
    p.write_bytes(SHORT_TG.encode("utf-16"))  # Praat writes UTF-16 for non-ASCII
    assert read_textgrid(p)[1] == (0.1, 0.2, "AH0")


def test_unknown_phone_names_label_and_file(tmp_path):
    p = tmp_path / "bad.lab"
    p.write_text("0 1000000 sil\n1000000 2000000 xq\n")
    with pytest.raises(ValueError, match=r"'xq'.*bad\.lab"):
        read_labels(p)


def test_normalize_phone():
    assert normalize_phone("AH0") == "ah" and normalize_phone("sp") == "sil"
    assert normalize_phone("AX") == "ah" and normalize_phone("") == "sil"


def test_frame_labels_hand_worked():
    # fps 25 -> frames [0,.04) [.04,.08) [.08,.12) [.12,.16)
    iv = [
        (0.000, 0.030, "sil"),   # frame 0: sil 30 ms, m 10 ms -> sil
        (0.030, 0.055, "m"),     # frame 1: m 15, aa 25 -> aa
        (0.055, 0.100, "aa"),    # frame 2: aa 20, p 20 -> tie -> aa (starts earlier)
        (0.100, 0.135, "p"),     # frame 3: p 15, aa 10, (gap) sil 15 -> tie p/sil -> p first
        (0.135, 0.145, "aa"),
    ]
    assert frame_labels(iv, 4) == ["sil", "aa", "aa", "p"]
    # a label split over two intervals in one frame adds up: t 12+12 ms beats s 16 ms
    iv2 = [(0.0, 0.012, "t"), (0.012, 0.028, "s"), (0.028, 0.040, "t")]
    assert frame_labels(iv2, 1) == ["t"]
    # uncovered time counts as sil: 30 ms gap beats 10 ms of aa
    assert frame_labels([(0.0, 0.01, "aa")], 1) == ["sil"]
    # fps is honoured: at 50 fps frame 1 is [0.02, 0.04)
    assert frame_labels([(0.0, 0.021, "b"), (0.021, 0.06, "iy")], 2, fps=50) == ["b", "iy"]


def test_frame_labels_matches_brute_force_counting():
    """Continuous overlap vote == counting 0.1 ms sub-frames (away from exact ties)."""
    rng = np.random.default_rng(3)
    for _ in range(5):
        cuts = np.sort(rng.choice(np.arange(1, 4000), size=30, replace=False)) / 10000.0
        cuts = np.concatenate([[0.0], cuts, [0.4]])
        labs = [str(x) for x in rng.choice(["aa", "b", "s", "iy", "m"], size=len(cuts) - 1)]
        iv = list(zip(cuts[:-1], cuts[1:], labs))
        got = frame_labels(iv, 10)
        sub = (np.arange(4000) + 0.5) / 10000.0
        idx = np.searchsorted(cuts, sub, side="right") - 1
        for k in range(10):
            lab_k = [labs[i] for i in idx[k * 400:(k + 1) * 400]]
            counts = {lab: lab_k.count(lab) for lab in set(lab_k)}
            best = max(counts.values())
            if sum(v == best for v in counts.values()) == 1:
                assert got[k] == max(counts, key=counts.get)
