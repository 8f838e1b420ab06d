"""One table of inference methods: the library's dispatch, the CLI, the pipeline and
docs/uncertainty.md all read :data:`bayes_talk.posterior.methods.INFERENCE`, and every method
has the one interface (an ``Options`` dataclass and ``run``)."""
from __future__ import annotations

import dataclasses
import inspect
import subprocess
import sys
from pathlib import Path

import pytest

from bayes_talk.posterior.methods import DEFAULT_DRAWS, INFERENCE, check_method, markdown_table

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("name", list(INFERENCE))
def test_every_method_has_the_one_interface(name):
    spec = INFERENCE[name]
    module = spec.load()
    assert dataclasses.is_dataclass(module.Options), name
    assert list(inspect.signature(module.run).parameters) == ["context", "options"], name
    defaults = spec.make_options()                      # every option has a default that passes its checks
    assert spec.options == dataclasses.asdict(defaults)
    with pytest.raises(ValueError, match=rf"\['no_such_option'\] are not options of '{name}'"):
        spec.make_options({"no_such_option": 1})


def test_the_table_imports_neither_torch_nor_the_methods():
    code = ("import sys; import bayes_talk.posterior.methods as m; "
            "print(sorted(k for k in sys.modules if k in ('torch', 'pyro') or k.startswith('bayes_talk.posterior.methods.')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120)
    assert out.stdout.strip() == "[]"


def test_cli_choices_are_the_table():
    from bayes_talk.app.cli import build_parser

    sub = next(a for a in build_parser()._subparsers._group_actions)
    synth = sub.choices["synth"]
    posterior = next(a for a in synth._actions if "--posterior" in a.option_strings)
    assert tuple(posterior.choices) == tuple(INFERENCE)


def test_library_reads_the_table():
    from bayes_talk.estimators.switching import SwitchingSGPDM

    assert tuple(SwitchingSGPDM.synthesis_options["posterior"]) == tuple(INFERENCE)
    assert DEFAULT_DRAWS == {n: m.draws for n, m in INFERENCE.items()}


def test_unknown_method_names_the_valid_ones():
    with pytest.raises(ValueError, match=r"posterior must be one of \('map', 'laplace'.*got 'hmc'"):
        check_method("hmc")


def test_docs_show_the_table():
    text = (ROOT / "docs" / "uncertainty.md").read_text(encoding="utf-8")
    assert markdown_table() in text, "docs/uncertainty.md: regenerate the table with methods.markdown_table()"
