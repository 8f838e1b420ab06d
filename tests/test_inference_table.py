"""One table of inference methods (issue 26, item 2): the CLI, the pipeline, the library and
docs/uncertainty.md all read :data:`bayes_talk.posterior.methods.INFERENCE`."""
from __future__ import annotations

from pathlib import Path

import pytest

from bayes_talk.posterior.methods import DEFAULT_DRAWS, INFERENCE, check_method, markdown_table

ROOT = Path(__file__).resolve().parent.parent


def test_every_runner_resolves_to_a_callable():
    for m in INFERENCE.values():
        assert callable(m.load()), m.name


def test_cli_choices_are_the_table():
    from bayes_talk.app.cli import build_parser

    sub = next(a for a in build_parser()._subparsers._group_actions)
    synth = sub.choices["synth"]
    posterior = next(a for a in synth._actions if "--posterior" in a.option_strings)
    assert tuple(posterior.choices) == tuple(INFERENCE)


def test_library_reads_the_table():
    from bayes_talk.posterior.sampling import POSTERIOR_METHODS

    assert POSTERIOR_METHODS == tuple(INFERENCE)
    assert DEFAULT_DRAWS == {n: m.draws for n, m in INFERENCE.items()}


def test_unknown_method_names_the_valid_ones():
    with pytest.raises(ValueError, match=r"posterior must be one of \('map', 'laplace'.*got 'hmc'"):
        check_method("hmc")


def test_docs_show_the_table():
    text = (ROOT / "docs" / "uncertainty.md").read_text(encoding="utf-8")
    assert markdown_table() in text, "docs/uncertainty.md: regenerate the table with defaults.markdown_table()"
