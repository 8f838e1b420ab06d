"""The held-out sentence lists share no template with the training list or the development
set: every sentence's content words overlap every reference sentence's by a Jaccard index
below 0.3 (:func:`bayes_talk.data.text_check.template_overlap`)."""
from __future__ import annotations

from pathlib import Path

import pytest

from bayes_talk.data.text_check import content_words, template_overlap

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "benchmarks" / "data"
TRAINING = ROOT / "bayes_talk" / "data" / "sentences.txt"
DEVELOPMENT = DATA / "heldout_sentences.txt"
#: test sets written to share no template with the training list and the development set
INDEPENDENT_TEST_SETS = ("test4_sentences.txt",)


def _lines(path: Path) -> list[str]:
    return [s.strip() for s in path.read_text(encoding="utf-8").splitlines() if s.strip()]


@pytest.mark.parametrize("name", INDEPENDENT_TEST_SETS)
@pytest.mark.parametrize("reference", [TRAINING, DEVELOPMENT], ids=["training", "development"])
def test_a_test_set_shares_no_template_with_training_or_development(name, reference):
    sentences = _lines(DATA / name)
    assert len(sentences) == 40 and len(set(sentences)) == 40
    j, s, r = template_overlap(sentences, _lines(reference))
    assert j < 0.3, f"{name}: {s!r} shares a template with {reference.name}'s {r!r} (Jaccard {j:.2f})"


def test_the_overlap_sees_a_paraphrase_and_passes_unrelated_sentences():
    j, _, _ = template_overlap(["The pilot announced a short delay because of heavy fog."],
                               ["The pilot announced a short delay because of the storm."])
    assert j >= 0.5
    assert template_overlap(["Camels carried salt across the desert."], ["She usually takes the early bus."])[0] == 0
    assert content_words("The cousin's scarf is purple") == {"cousin", "scarf", "purple"}
