"""The command line's help: version, description, every default shown once, every
positional argument explained (issue 28)."""
from __future__ import annotations

import argparse
import tomllib
from pathlib import Path

import pytest

from bayes_talk import __version__
from bayes_talk.app.cli import build_parser, main

ROOT = Path(__file__).resolve().parents[2]


def _actions(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()):
    for a in parser._actions:
        if isinstance(a, argparse._SubParsersAction):
            for name, sp in a.choices.items():
                yield from _actions(sp, (*path, name))
        else:
            yield path, parser, a


def _help(parser: argparse.ArgumentParser, action: argparse.Action) -> str:
    fmt = parser._get_formatter()
    return fmt._expand_help(action) if action.help else ""


def test_version_is_printed_and_matches_the_package_metadata(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.strip() == f"bayes-talk {__version__}"
    meta = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    assert meta["project"]["version"] == __version__


def test_top_level_help_describes_the_program_and_a_first_run(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    out = capsys.readouterr().out
    assert "talking face" in out and "uncertainty" in out
    for cmd in ("corpus build", "train", "synth", "evaluate", "demo"):
        assert f"bayes-talk {cmd}" in out


def test_every_default_is_shown_once_including_zero():
    shown, zeros = 0, 0
    for path, parser, a in _actions(build_parser()):
        if a.help == argparse.SUPPRESS or a.required or any(a.default is x for x in (None, False, argparse.SUPPRESS)):
            continue
        h = _help(parser, a)
        where = f"{' '.join(path)} {'/'.join(a.option_strings) or a.dest}"
        assert f"(default: {a.default})" in h, where
        assert h.lower().count("default") == 1, f"{where}: {h!r}"
        shown += 1
        zeros += a.default == 0
    assert shown > 20 and zeros >= 3     # --seed 0 and friends are among them


def test_every_positional_argument_has_help():
    missing = [f"{' '.join(p)} {a.dest}" for p, _, a in _actions(build_parser())
               if not a.option_strings and not a.help]
    assert not missing, missing


def test_the_log_handler_writes_to_the_current_stderr_never_a_closed_one(capsys):
    """main() called in-process under a replaced stderr (pytest's capsys, a notebook) that is
    closed afterwards: later records -- dask's at a cluster's shutdown -- printed "--- Logging
    error --- ValueError: I/O operation on closed file" tracebacks."""
    import contextlib
    import io
    import logging

    from bayes_talk.app import cli

    first = io.StringIO()
    try:
        with contextlib.redirect_stderr(first):
            cli._log_to_stderr(logging.WARNING, "bayes-talk: %(levelname)s: %(message)s")
        first.close()
        logging.getLogger("distributed.nanny").warning("after that stream closed")
        err = capsys.readouterr().err
        assert "bayes-talk: WARNING: after that stream closed" in err
        assert "Logging error" not in err and "closed file" not in err
    finally:
        logging.getLogger().removeHandler(cli._HANDLER)
        cli._HANDLER = None


def test_hmmlearn_convergence_chatter_is_kept_out_of_the_output_unless_verbose(tmp_path, capsys, monkeypatch):
    import logging

    from bayes_talk.app import cli

    def chatty(args):
        logging.getLogger("hmmlearn.base").warning("Model is not converging.  Current: -1 is not greater than -0.9")
        logging.getLogger("bayes_talk.test").warning("a warning of ours")
        return 0

    monkeypatch.setattr(cli, "_cmd_demo", chatty)
    try:
        assert main(["demo", "--out", str(tmp_path)]) == 0
        err = capsys.readouterr().err
        assert "a warning of ours" in err and "not converging" not in err
        assert main(["-v", "demo", "--out", str(tmp_path)]) == 0
        assert "not converging" in capsys.readouterr().err
    finally:
        logging.getLogger().removeHandler(cli._HANDLER)
        cli._HANDLER = None
        logging.getLogger("hmmlearn").setLevel(logging.NOTSET)


def test_worker_processes_log_as_the_command_line_says(tmp_path, capfd, monkeypatch):
    """The aligner's fit in ``train`` runs in a worker process: hmmlearn's chatter there is
    held back unless -v as in the main process, and the worker's warnings come in the command
    line's one-line format instead of Python's bare last-resort output."""
    import logging
    import warnings

    from bayes_talk.app import cli
    from bayes_talk.base.executor import ProcessExecutor

    def in_workers(args):
        with ProcessExecutor(2) as ex:
            ex.map(logging.getLogger("hmmlearn.base").warning, ["Model is not converging.  Current: -1"])
            ex.map(logging.getLogger("bayes_talk.test").warning, ["a warning of ours"])
            ex.map(warnings.warn, ["a library warning"])
        return 0

    monkeypatch.setattr(cli, "_cmd_demo", in_workers)
    try:
        assert main(["demo", "--out", str(tmp_path)]) == 0
        err = capfd.readouterr().err
        assert "bayes-talk: WARNING: a warning of ours" in err
        assert "bayes-talk: WARNING: UserWarning: a library warning" in err
        assert "not converging" not in err
        assert main(["-v", "demo", "--out", str(tmp_path)]) == 0
        err = capfd.readouterr().err
        assert "hmmlearn.base WARNING: Model is not converging" in err
    finally:
        logging.getLogger().removeHandler(cli._HANDLER)
        cli._HANDLER = None
        logging.getLogger("hmmlearn").setLevel(logging.NOTSET)
        logging.captureWarnings(False)
