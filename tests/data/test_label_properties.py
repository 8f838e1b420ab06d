"""Property tests (hypothesis) of the HTK .lab and Praat TextGrid readers: any text gives a
parsed, valid interval list or a ValueError that names the file -- nothing else."""
from __future__ import annotations

import tempfile
from pathlib import Path

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bayes_talk.data.labels import read_lab, read_labels, read_textgrid

SETTINGS = settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow])

_TG_WORDS = ['File type = "ooTextFile"', 'Object class = "TextGrid"', "xmin = 0", "xmax = 1",
             "xmax = 0.5", "tiers? <exists>", "tiers? <absent>", "size = 1", "size = 2", "size = 1.5",
             "size = -1", "item []:", "item [1]:", 'class = "IntervalTier"', 'class = "TextTier"',
             'class = "Other"', 'name = "phones"', 'name = "words"', "intervals: size = 1",
             "intervals: size = 2", "points: size = 1", "intervals [1]:", "xmin = 0.25", "xmax = 1e999",
             'text = "aa"', 'text = "the"', 'text = ""', 'text = "s""il"', "number = 0.5", 'mark = "x"',
             '"', "!", "1e5", "nan", "-0", "0.1"]
_LAB_WORDS = ["0", "1000000", "2500000", "-5", "1.5", "aa", "sil", "SIL", "AH0", "xyz", "///", "sp", "\t", " ",
              "999999999999999999999", "nan"]


def _check(read, text: str, suffix: str, encoding: str = "utf-8") -> None:
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / f"x{suffix}"
        p.write_bytes(text.encode(encoding, errors="surrogatepass"))
        try:
            out = read(p)
        except ValueError as exc:
            assert str(p) in str(exc), f"error does not name the file: {exc}"
            return
        assert isinstance(out, list) and out
        prev = float("-inf")
        for s, e, lab in out:
            assert isinstance(lab, str) and s < e and s >= prev - 1e-9
            prev = e


@SETTINGS
@given(st.text(max_size=300))
def test_random_text_lab(text):
    _check(read_lab, text, ".lab")
    _check(read_labels, text, ".lab")


@SETTINGS
@given(st.lists(st.lists(st.sampled_from(_LAB_WORDS), min_size=0, max_size=5).map(" ".join), max_size=8)
       .map("\n".join))
def test_lab_like_text(text):
    _check(read_lab, text, ".lab")
    _check(read_labels, text, ".lab")


@SETTINGS
@given(st.text(max_size=300))
def test_random_text_textgrid(text):
    _check(read_textgrid, text, ".TextGrid")


@SETTINGS
@given(st.lists(st.sampled_from(_TG_WORDS), max_size=40).map("\n".join))
def test_textgrid_like_text(text):
    _check(read_textgrid, text, ".TextGrid")
    _check(read_labels, text, ".TextGrid")


_VALID_TG = ['File type = "ooTextFile"', 'Object class = "TextGrid"', "xmin = 0", "xmax = 1", "tiers? <exists>",
             "size = 1", "item []:", "item [1]:", 'class = "IntervalTier"', 'name = "phones"', "xmin = 0",
             "xmax = 1", "intervals: size = 2", "intervals [1]:", "xmin = 0", "xmax = 0.5", 'text = "aa"',
             "intervals [2]:", "xmin = 0.5", "xmax = 1", 'text = "sil"']


@SETTINGS
@given(st.lists(st.tuples(st.integers(0, len(_VALID_TG) - 1), st.sampled_from(_TG_WORDS + [""])), max_size=4),
       st.booleans())
def test_mutated_valid_textgrid(mutations, utf16):
    """A valid TextGrid with up to 4 lines replaced (or emptied): parsed or named error."""
    lines = list(_VALID_TG)
    for i, w in mutations:
        lines[i] = w
    _check(read_labels, "\n".join(lines), ".TextGrid", encoding="utf-16" if utf16 else "utf-8")


_NUMERIC = [i for i, ln in enumerate(_VALID_TG) if ln.split("=")[-1].strip()[:1].isdigit()]
_BAD_NUMBERS = ["1.5", "-1", "1e999", "-1e999", "0", "3", "0.75", "1e-300", "nan", "x", "", "99999999999999999999"]


@SETTINGS
@given(st.lists(st.tuples(st.sampled_from(_NUMERIC), st.sampled_from(_BAD_NUMBERS)), min_size=1, max_size=3))
def test_textgrid_with_odd_numbers(mutations):
    """Counts and times replaced by fractions, negatives, overflow, NaN or garbage."""
    lines = list(_VALID_TG)
    for i, v in mutations:
        lines[i] = lines[i].split("=")[0] + "= " + v
    _check(read_labels, "\n".join(lines), ".TextGrid")


def test_the_unmutated_textgrid_parses():
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "x.TextGrid"
        p.write_text("\n".join(_VALID_TG))
        assert read_labels(p) == [(0.0, 0.5, "aa"), (0.5, 1.0, "sil")]
