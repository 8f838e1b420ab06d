"""Every command and code block of README.md and docs/*.md is checked by the tests, so the docs
cannot drift from the code.

How each fenced block is covered:

* ``bash``/``sh`` blocks: every command line is parsed. ``bayes-talk ...`` (also
  ``.venv/bin/bayes-talk`` and ``python -m bayes_talk.app.cli``) goes through the real argument
  parser (:func:`bayes_talk.app.cli.build_parser`), so an unknown sub-command, flag or choice
  fails, and ``evaluate --methods`` names go through :func:`resolve_methods`. A script of the
  repository (``benchmarks/...``, ``notebooks/...``) must exist, and its ``--flags`` must be
  among the script's ``add_argument`` options; ``make`` targets must be in the Makefile;
  paths of the repository named in a command must exist. A command of any other program
  fails the test unless :data:`OTHER_PROGRAMS` names it with a reason. Commands listed in
  :data:`RUN_COMMANDS` are also *run*, on a tiny corpus, with the substitutions that table
  lists (a full-size build or a 250-utterance evaluation does not fit in ``make test``).
* ``python`` blocks: each must be in :data:`PYTHON_BLOCKS`: either run here (on a tiny
  corpus or toy data, with the set-up and substitutions listed there), or mapped to the test
  that runs it verbatim. Every block, run or not, is also compiled and its ``bayes_talk``
  imports resolved and the keyword arguments of its calls to them checked against their
  signatures.
* ``text`` blocks (formats, not commands) must be in :data:`TEXT_BLOCKS` with a reason.
* Inline ``bayes-talk SUBCOMMAND --flag`` spans in the prose: the sub-command and every
  flag must exist.

A new block that none of these tables covers fails :func:`test_every_block_is_covered`.
"""
from __future__ import annotations

import ast
import contextlib
import inspect
import io
import re
import shlex
import sys
import textwrap
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


@dataclass(frozen=True)
class Block:
    """One fenced code block of a Markdown file."""

    path: str        # relative to the repository
    line: int        # line of the opening fence
    lang: str
    text: str

    @property
    def key(self) -> tuple[str, str]:
        """(file, first non-empty line): stable when text above the block moves."""
        first = next((ln.strip() for ln in self.text.splitlines() if ln.strip()), "")
        return self.path, first

    def __str__(self) -> str:
        return f"{self.path}:{self.line} [{self.lang}]"


def doc_blocks() -> list[Block]:
    """Every fenced block of README.md and docs/*.md."""
    out = []
    for p in DOCS:
        text = p.read_text(encoding="utf-8")
        # fences may be indented (a block inside a list item): the same indentation closes it
        for m in re.finditer(r"^([ \t]*)```([\w+-]*)[ \t]*\n(.*?)^\1```", text, re.MULTILINE | re.DOTALL):
            out.append(Block(str(p.relative_to(ROOT)), text[:m.start()].count("\n") + 1, m.group(2),
                             textwrap.dedent(m.group(3))))
    return out


BLOCKS = doc_blocks()
SHELL_LANGS = {"bash", "sh", "shell", "console"}

# ------------------------------------------------------------------------------------------
# Shell commands
# ------------------------------------------------------------------------------------------

#: programs other than bayes-talk, python, make and pip that the docs may name, and why
#: their commands are not checked further
OTHER_PROGRAMS = {
    "mkdir": "shell: making a directory",
    "ln": "shell: linking a corpus's files",
    "dask": "distributed's own CLI (dask scheduler / dask worker); the bayes-talk commands that use "
            "the scheduler are parsed, and tests/base/test_executor.py runs corpus build and training on a "
            "dask cluster",
}

SHELL_PREFIXES = {"nice": 2, "time": 0}          # program -> number of its own arguments to skip


@dataclass(frozen=True)
class Command:
    """One simple command of a shell block."""

    block: Block
    argv: tuple[str, ...]

    @property
    def where(self) -> str:
        return f"{self.block}: {shlex.join(self.argv)}"


def shell_commands(block: Block) -> list[Command]:
    """The simple commands of a shell block: continuation lines joined (as bash does: a
    backslash-newline disappears), comments dropped, split at ``&&``, ``;``, ``|``, ``&``;
    leading ``VAR=value`` assignments recorded and ``$VAR`` expanded in later commands;
    ``nice -n N`` / ``time`` prefixes and the ``for ...; do ...; done`` scaffolding dropped."""
    env: dict[str, str] = {}
    out = []
    for line in block.text.replace("\\\n", "").splitlines():
        lex = shlex.shlex(line, posix=True, punctuation_chars=True)
        lex.whitespace_split = True
        tokens = list(lex)
        segments: list[list[str]] = [[]]
        for tok in tokens:
            if tok in {"&&", "||", ";", "|", "&"}:
                segments.append([])
            else:
                segments[-1].append(tok)
        for seg in segments:
            seg = [re.sub(r"\$(\w+)|\$\{(\w+)\}", lambda m: env.get(m.group(1) or m.group(2), m.group(0)), t)
                   for t in seg]
            while seg and re.fullmatch(r"[A-Za-z_]\w*=.*", seg[0]):
                name, value = seg.pop(0).split("=", 1)
                env[name] = value
            if seg and seg[0] == "for":
                continue                                   # for NAME in WORDS
            while seg and seg[0] in ("do", "done", "then", "fi"):
                seg.pop(0)
            while seg and seg[0] in SHELL_PREFIXES:
                seg = seg[1 + SHELL_PREFIXES[seg[0]]:]
            if seg:
                out.append(Command(block, tuple(seg)))
    return out


COMMANDS = [c for b in BLOCKS if b.lang in SHELL_LANGS for c in shell_commands(b)]


def _is_python(prog: str) -> bool:
    return re.fullmatch(r"(?:.*/)?python(?:3(?:\.\d+)?)?", prog) is not None


def cli_args(argv: tuple[str, ...]) -> list[str] | None:
    """The ``bayes-talk`` arguments of a command, or None when it is not one."""
    prog = argv[0]
    if prog in ("bayes-talk", ".venv/bin/bayes-talk") or prog.endswith("/bayes-talk"):
        return list(argv[1:])
    if _is_python(prog) and argv[1:3] == ("-m", "bayes_talk.app.cli"):
        return list(argv[3:])
    return None


def cli_problems(args: list[str]) -> list[str]:
    """Why the real ``bayes-talk`` parser refuses ``args`` ([] when it accepts them)."""
    from bayes_talk.app.cli import build_parser
    from bayes_talk.evaluation.systems import resolve_methods

    if args == ["--version"]:
        return []
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            ns = build_parser().parse_args(args)
    except SystemExit as exc:
        return [f"the parser exits {exc.code}: {err.getvalue().strip().splitlines()[-1:]}"]
    problems = []
    if getattr(ns, "command", None) == "evaluate" and ns.methods is not None:
        try:
            resolve_methods(ns.methods.split(","))
        except ValueError as exc:
            problems.append(str(exc).split(";")[0])
    return problems


def repo_paths_named(argv) -> list[str]:
    """Arguments (or ``--opt=VALUE`` values) that name a file of the repository's own folders."""
    found = []
    for tok in argv:
        tok = tok.split("=", 1)[-1]
        if re.match(r"(benchmarks|notebooks|docs|tests|bayes_talk)/", tok) and "*" not in tok:
            found.append(tok)
    return found


def script_options(script: Path) -> set[str] | None:
    """The ``--options`` a script's ``add_argument`` calls declare (None: it has no argparse)."""
    tree = ast.parse(script.read_text(encoding="utf-8"))
    opts = set()
    uses_argparse = False
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "add_argument":
            uses_argparse = True
            opts.update(a.value for a in node.args if isinstance(a, ast.Constant) and isinstance(a.value, str)
                        and a.value.startswith("-"))
    return opts if uses_argparse else None


def makefile_targets() -> set[str]:
    text = (ROOT / "Makefile").read_text(encoding="utf-8")
    return {m.group(1) for m in re.finditer(r"^([A-Za-z][\w.-]*)\s*:(?!=)", text, re.MULTILINE)}


def command_problems(cmd: Command) -> list[str]:
    """Why a documented command would not run as written ([] when every check passes)."""
    argv = cmd.argv
    prog = argv[0]
    args = cli_args(argv)
    problems = []
    for rel in repo_paths_named(argv):
        if not (ROOT / rel).exists():
            problems.append(f"{rel} is not in the repository")
    if args is not None:
        return problems + cli_problems(args)
    if _is_python(prog):
        rest = list(argv[1:])
        if rest[:2] == ["-m", "pytest"]:
            return problems
        if not rest or rest[0].startswith("-"):
            return problems + [f"python {' '.join(rest[:2])}: not a form the docs harness knows"]
        script = rest[0]
        path = ROOT / script
        if not path.is_file():
            return problems + [f"{script} is not in the repository"]
        opts = script_options(path)
        own, passed = rest[1:], None
        if "--" in own:   # script options, then a bayes-talk command it runs (benchmarks/analysis/family_variant.py)
            cut = own.index("--")
            own, passed = own[:cut], own[cut + 1:]
        if opts is not None:
            for tok in own:
                flag = tok.split("=", 1)[0]
                if flag.startswith("--") and flag not in opts:
                    problems.append(f"{script} has no option {flag} (it has {', '.join(sorted(opts))})")
        if passed is not None:
            problems += [f"{script} -- bayes-talk: {p}" for p in cli_problems(passed)]
        return problems
    if prog == "make":
        targets = makefile_targets()
        for t in argv[1:]:
            if "=" not in t and not t.startswith("-") and t not in targets:
                problems.append(f"the Makefile has no target {t!r}")
        return problems
    if prog == "pip":
        if "-c" in argv and not (ROOT / argv[argv.index("-c") + 1]).is_file():
            problems.append(f"constraints file {argv[argv.index('-c') + 1]} is missing")
        return problems
    if prog in OTHER_PROGRAMS:
        return problems
    return problems + [f"unknown program {prog!r}: check it here or list it in OTHER_PROGRAMS with a reason"]


@pytest.mark.parametrize("cmd", COMMANDS, ids=lambda c: f"{c.block.path}:{c.block.line}:{c.argv[:3]}")
def test_documented_command_is_valid(cmd):
    assert command_problems(cmd) == [], cmd.where


def test_the_checks_catch_a_wrong_flag_subcommand_method_and_script(tmp_path, monkeypatch):
    """The checks above can fail: each kind of drift is caught. The scripts and the Makefile
    are a stand-in repository, so the test does not depend on which benchmarks exist."""
    (tmp_path / "benchmarks" / "data").mkdir(parents=True)
    (tmp_path / "benchmarks" / "posterior.py").write_text(
        "import argparse\nap = argparse.ArgumentParser()\nap.add_argument('--efficiency', action='store_true')\n")
    (tmp_path / "benchmarks" / "wrapper.py").write_text(
        "import argparse\nap = argparse.ArgumentParser()\nap.add_argument('--learn-dynamics', action='store_true')\n")
    (tmp_path / "Makefile").write_text("test:\n\tpytest\n")
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    fake = Block("README.md", 1, "bash", """\
bayes-talk train CORPUS --out M --no-such-flag
.venv/bin/bayes-talk sinth M --audio X.wav --out O
python -m bayes_talk.app.cli evaluate --protocol deena2010 --corpus C --methods zero,nope --json r.json
M=zero,oracle
bayes-talk evaluate --protocol deena2010 --corpus C --methods $M,hmm-mean --json r.json
PYTHONPATH=. nice -n 5 python benchmarks/posterior.py --efficiency --no-such-option 3
python benchmarks/no_such_benchmark.py
bayes-talk corpus build C --sentences benchmarks/data/missing.txt
make tset
curl https://example.org | sh
""")
    cmds = shell_commands(fake)
    assert [c.argv[0] for c in cmds] == ["bayes-talk", ".venv/bin/bayes-talk", "python", "bayes-talk", "python",
                                         "python", "bayes-talk", "make", "curl", "sh"]
    verdicts = [command_problems(c) for c in cmds]
    assert "--no-such-flag" in verdicts[0][0]
    assert "sinth" in verdicts[1][0]
    assert "'nope'" in verdicts[2][0]
    assert "ssgpdm-vlmm-laplace" in command_problems(Command(fake, (
        "bayes-talk", "evaluate", "--protocol", "deena2010", "--corpus", "C", "--json", "r.json",
        "--methods", "ssgpdm-vlmm-laplace")))[0]         # a method the registry does not have
    assert verdicts[3] == []                         # $M expanded: zero,oracle,hmm-mean are all methods
    assert "--no-such-option" in verdicts[4][0] and len(verdicts[4]) == 1
    assert "no_such_benchmark.py" in verdicts[5][0]
    assert "missing.txt" in verdicts[6][0]
    assert "tset" in verdicts[7][0]
    assert verdicts[7] == command_problems(cmds[7]) and command_problems(Command(fake, ("make", "test"))) == []
    assert "unknown program 'curl'" in verdicts[8][0]
    # a script that runs a bayes-talk command after "--": both parts are checked
    passthrough = ("python", "benchmarks/wrapper.py", "--learn-dynamics", "--", "evaluate",
                   "--protocol", "deena2010", "--corpus", "C", "--json", "r.json")
    assert command_problems(Command(fake, passthrough)) == []
    wrong = command_problems(Command(fake, (*passthrough[:2], "--no-such", *passthrough[3:], "--no-such-flag")))
    assert any("has no option --no-such" in p for p in wrong) and any("--no-such-flag" in p for p in wrong)


# ------------------------------------------------------------------------------------------
# Inline spans: `bayes-talk SUBCOMMAND ... --flag`
# ------------------------------------------------------------------------------------------

#: sub-commands an inline span may start with instead of ``bayes-talk`` (e.g. `synth --raw-bands`)
SUBCOMMAND_SPANS = ("corpus build", "corpus track", "corpus propose", "align-train", "train", "synth", "evaluate",
                    "demo", "align", "recognise")


def inline_cli_spans() -> list[tuple[str, str]]:
    """(file, span) of every inline code span outside fenced blocks that starts with
    ``bayes-talk ``, or with a sub-command followed by a ``--flag`` (given as
    ``bayes-talk SPAN``)."""
    sub = "|".join(map(re.escape, SUBCOMMAND_SPANS))
    out = []
    for p in DOCS:
        text = re.sub(r"^([ \t]*)```.*?^\1```", "", p.read_text(encoding="utf-8"), flags=re.MULTILINE | re.DOTALL)
        for m in re.finditer(r"`((?:\.venv/bin/)?bayes-talk [^`]+)`", text):
            out.append((str(p.relative_to(ROOT)), m.group(1)))
        for m in re.finditer(rf"`((?:{sub})(?: [^`]*)? --[a-z][^`]*)`", text):
            out.append((str(p.relative_to(ROOT)), "bayes-talk " + m.group(1)))
    return out


def _subparsers(parser):
    import argparse

    for a in parser._actions:
        if isinstance(a, argparse._SubParsersAction):
            return a.choices
    return {}


def inline_problems(span: str) -> list[str]:
    """The sub-command path and the ``--flags`` of a span must exist (a span may leave out
    required arguments, so it is not parsed whole)."""
    from bayes_talk.app.cli import build_parser

    tokens = shlex.split(span.replace("…", "").replace("...", ""))[1:]
    parser = build_parser()
    options = set(parser._option_string_actions)
    path = []
    for tok in tokens:
        subs = _subparsers(parser)
        if tok.startswith("-"):
            flag = tok.split("=", 1)[0]
            if re.fullmatch(r"--?[a-z][\w-]*", flag) and flag not in options:
                return [f"`{span}`: {' '.join(path) or 'bayes-talk'} has no option {flag}"]
        elif subs and path[-1:] != ["--"]:
            if tok not in subs:
                if re.fullmatch(r"[a-z][a-z-]*", tok) and not tok.isupper():
                    return [f"`{span}`: no sub-command {tok!r} (valid: {', '.join(subs)})"]
                continue
            parser = subs[tok]
            options |= set(parser._option_string_actions)
            path.append(tok)
    return []


INLINE = inline_cli_spans()


@pytest.mark.parametrize("where,span", INLINE, ids=[f"{w}:{s[:40]}" for w, s in INLINE])
def test_inline_command_names_existing_subcommands_and_flags(where, span):
    assert inline_problems(span) == [], where


def test_inline_check_catches_a_wrong_flag_and_subcommand():
    assert inline_problems("bayes-talk synth MODEL --audio X.wav --out O --raw-bands") == []
    assert "--raw-band" in inline_problems("bayes-talk synth --raw-band")[0]
    assert "'sinth'" in inline_problems("bayes-talk sinth MODEL")[0]
    assert "--n-utterance" in inline_problems("bayes-talk corpus build C --n-utterance 3")[0]


def test_help_epilog_commands_parse():
    """The commands the CLI's own help prints (a first run) are valid too."""
    from bayes_talk.app.cli import EPILOG

    lines = [ln.split("#")[0].strip() for ln in EPILOG.splitlines() if ln.strip().startswith("bayes-talk ")]
    assert len(lines) >= 4
    for ln in lines:
        assert cli_problems(shlex.split(ln)[1:]) == [], ln


# ------------------------------------------------------------------------------------------
# Python blocks
# ------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class PyBlock:
    """How one ```python block is covered: ``run`` here, with ``subs`` applied to its text,
    in a directory holding the tiny CORPUS, MODEL, X.wav and X.lab, after ``setup`` gave it the names it uses
    without defining (USES_TOY, USES_SPLIT); or run verbatim by the test ``mapped`` names."""

    setup: str = ""
    subs: tuple[tuple[str, str], ...] = ()
    mapped: str = ""
    reason: str = ""

    @property
    def run(self) -> bool:
        return not self.mapped


#: names the blocks use without defining them, given by the fixtures below: ``model``,
#: ``mfcc``, ``labels``, ``y``, ``z``, ``post`` (a small switching model of toy data and a
#: Laplace posterior of 12 frames, tests/toydata.py), ``train``/``test`` (the tiny corpus)
USES_TOY = "toy"
USES_SPLIT = "split"

PYTHON_BLOCKS: dict[tuple[str, str], PyBlock] = {
    ("README.md", "from bayes_talk.pipeline import load_trained"): PyBlock(
        subs=(('seed=0)', 'seed=0, n_draws=16)'),)),             # MODEL, X.wav, X.lab: the fixture's
    ("README.md", "from bayes_talk.corpus import load_corpus"): PyBlock(
        mapped="tests/project/test_readme_script.py::test_readme_python_section_runs_as_a_plain_script_on_a_fresh_corpus",
        reason="run verbatim as a plain script on a fresh 16-utterance corpus (the library-call issue)"),
    ("docs/architecture.md", "from sklearn.base import clone"): PyBlock(),
    ("docs/baselines.md", "from bayes_talk.estimators.baselines import REGISTRY          # name -> class"): PyBlock(
        setup=USES_SPLIT, subs=(('REGISTRY["dpds"]()', 'REGISTRY["dpds"](max_iter=10)'),)),
    ("docs/baselines.md", "from bayes_talk.estimators.baselines import ContextRidge, ContextMLP"): PyBlock(
        setup=USES_SPLIT, subs=(("ContextRidge().fit(train)", "ContextRidge(n_splits=2).fit(train)"),
                                ("ContextMLP(seed=0)", "ContextMLP(seed=0, max_epochs=3)"))),
    ("docs/data.md", "import json, shutil, tempfile"): PyBlock(
        subs=(("Path(tempfile.mkdtemp())", 'Path(tempfile.mkdtemp(dir="."))'),)),
    ("docs/data.md", "import json, tempfile"): PyBlock(
        subs=(("Path(tempfile.mkdtemp())", 'Path(tempfile.mkdtemp(dir="."))'), ("n_utterances=3", "n_utterances=2"))),
    ("docs/outputs.md", "import numpy as np"): PyBlock(),       # MODEL_DIR, OUT_DIR: the fixture's
    ("docs/scaling.md", "from bayes_talk.corpus import build_corpus"): PyBlock(
        mapped="tests/base/test_executor.py::test_corpus_build_and_features_on_dask_equal_local",
        reason="a dask LocalCluster costs seconds to start; that test builds a corpus on one (executor=, "
               "a DaskExecutor; the name 'dask' goes through make_executor)"),
    ("docs/scaling.md", "from bayes_talk.base.executor import DaskExecutor"): PyBlock(
        mapped="tests/base/test_executor.py::test_dask_per_state_training_equals_local_bit_for_bit",
        reason="training through a DaskExecutor with two workers (the same model as locally)"),
    ("docs/uncertainty.md", "from bayes_talk.posterior.sampling import sample_synthesis"): PyBlock(
        setup=USES_TOY,
        subs=(('method="laplace" | "nuts" | "emcee" | "map"', 'method="laplace"'), ("n_draws=64", "n_draws=16"),
              ("post.sample(2000)", "post.sample(200)"))),
    ("docs/uncertainty.md", "from bayes_talk.synthesis.joint import make_plan"): PyBlock(setup=USES_TOY),
    ("docs/uncertainty.md", "from bayes_talk.estimators.registry import load_estimator"): PyBlock(
        mapped="tests/estimators/test_face_noise_model.py::test_every_method_ends_with_the_term",
        reason="needs a trained model directory; that test fits the term on held-out toy utterances and checks "
               "predict_dist with and without it, observe and the saved values"),
    ("docs/uncertainty.md", ("from bayes_talk.evaluation.calibration import score_utterance, summarise_calibration, "
                            "plot_calibration")): PyBlock(
        setup=USES_TOY),
    ("docs/vlmm.md", "from bayes_talk.models.vlmm import VLMM"): PyBlock(
        setup=USES_TOY, subs=(("min_count=10", "min_count=4"),)),
}

#: ```text blocks: formats, not commands
TEXT_BLOCKS = {
    ("docs/evaluation.md", ('protocol, quick, description, paper, scheme ("repeats"|"holdout"|"kfold"|"test-corpus"), '
                           "seed,")): "the results JSON's fields (tests/evaluation/test_protocols.py checks the JSON)",
    ("docs/evaluation.md", "calibration: {"): "the calibration record's fields (tests/evaluation/test_calibration.py)",
    ("docs/outputs.md", '{"format": "bayes_talk.synth_frames", "version": 1,'): (
        "the frames.json schema (tests/pipeline/test_exports.py reads the fields back)"),
}


def uncovered(blocks: list[Block]) -> list[str]:
    """The blocks that no check covers."""
    return [str(b) for b in blocks if not (
        b.lang in SHELL_LANGS
        or (b.lang == "python" and b.key in PYTHON_BLOCKS)
        or (b.lang == "text" and b.key in TEXT_BLOCKS))]


def test_every_block_is_covered():
    """A new block fails here until it is run, parsed or mapped; a table entry whose block is
    gone fails too."""
    keys = [b.key for b in BLOCKS if b.lang not in SHELL_LANGS]
    assert len(keys) == len(set(keys)), "two python/text blocks of one file start with the same line"
    assert uncovered(BLOCKS) == [], "blocks no test covers: add them to PYTHON_BLOCKS / TEXT_BLOCKS"
    stale = [k for k in [*PYTHON_BLOCKS, *TEXT_BLOCKS] if k not in set(keys)]
    assert stale == [], "table entries whose block is gone"


def test_a_new_block_is_uncovered_until_listed():
    new = [Block("docs/new.md", 3, "python", "import bayes_talk\n"), Block("docs/new.md", 9, "text", "a: b\n"),
           Block("docs/new.md", 12, "", "bayes-talk demo\n")]
    assert uncovered(new) == ["docs/new.md:3 [python]", "docs/new.md:9 [text]", "docs/new.md:12 []"]
    assert uncovered(BLOCKS[:0] + [Block("docs/new.md", 1, "bash", "bayes-talk demo\n")]) == []


def _mapped_test_exists(nodeid: str) -> bool:
    file, func = nodeid.split("::")
    tree = ast.parse((ROOT / file).read_text(encoding="utf-8"))
    return any(isinstance(n, ast.FunctionDef) and n.name == func for n in tree.body)


@pytest.mark.parametrize("key", [k for k, v in PYTHON_BLOCKS.items() if v.mapped], ids=lambda k: f"{k[0]}")
def test_mapped_block_names_an_existing_test(key):
    assert _mapped_test_exists(PYTHON_BLOCKS[key].mapped), PYTHON_BLOCKS[key].mapped


def block_source(block: Block) -> str:
    spec = PYTHON_BLOCKS[block.key]
    code = block.text
    for old, new in spec.subs:
        assert old in code, f"{block}: substitution {old!r} no longer matches"
        code = code.replace(old, new)
    return code


def api_problems(code: str) -> list[str]:
    """Imports of ``bayes_talk`` that do not resolve, and keyword arguments that the called
    ``bayes_talk`` function or class does not take."""
    import importlib

    tree = ast.parse(code)
    bound: dict[str, object] = {}
    problems = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "bayes_talk":
            try:
                mod = importlib.import_module(node.module)
            except ImportError as exc:
                problems.append(f"import {node.module}: {exc}")
                continue
            for alias in node.names:
                if not hasattr(mod, alias.name):
                    problems.append(f"{node.module} has no {alias.name}")
                else:
                    bound[alias.asname or alias.name] = getattr(mod, alias.name)
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in bound:
            obj = bound[node.func.id]
            try:
                sig = inspect.signature(obj)
            except (TypeError, ValueError):
                continue
            if any(p.kind is p.VAR_KEYWORD for p in sig.parameters.values()):
                continue
            for kw in node.keywords:
                if kw.arg is not None and kw.arg not in sig.parameters:
                    problems.append(f"{node.func.id}() takes no keyword {kw.arg!r}")
    return problems


PY = [b for b in BLOCKS if b.lang == "python" and b.key in PYTHON_BLOCKS]


@pytest.mark.parametrize("block", PY, ids=str)
def test_python_block_compiles_and_its_api_exists(block):
    code = block_source(block)
    compile(code, str(block), "exec")
    assert api_problems(code) == [], block


def test_api_check_catches_a_renamed_function_and_keyword():
    assert api_problems("from bayes_talk.corpus import load_corpus\nload_corpus('C', n_workers=1)\n") == []
    assert api_problems("from bayes_talk.corpus import load_corpora\n") == ["bayes_talk.corpus has no load_corpora"]
    assert api_problems("from bayes_talk.corpus import load_corpus\nload_corpus('C', n_jobs=2)\n") == [
        "load_corpus() takes no keyword 'n_jobs'"]


# --- running them on a tiny corpus -----------------------------------------------------------

#: the fast settings of tests/estimators/test_estimators.py
SMALL = {"latent_dim": 2, "max_iter": 15, "min_count": 4, "max_frames_per_state": 60, "fallback_frames": 80}


@pytest.fixture(scope="module")
def docs_work(tmp_path_factory):
    """A working directory holding CORPUS (8 utterances, 64 px), MODEL (a small deena2010
    switching model of it, no aligner, no calibration) and OUT (a Laplace synthesis of the
    corpus's last utterance, no video): what the docs' placeholders stand for."""
    from bayes_talk.corpus import build_corpus
    from bayes_talk.pipeline import synth, train

    work = tmp_path_factory.mktemp("docs")
    build_corpus(work / "CORPUS", n_utterances=8, seed=0, image_size=64)
    train(work / "CORPUS", "ssgpdm-vlmm", work / "MODEL", holdout=1, alignment=False, **SMALL)
    utt = work / "CORPUS" / "utterances"
    for ext in ("wav", "lab"):
        (work / f"X.{ext}").write_bytes((utt / f"utt0007.{ext}").read_bytes())
    synth(work / "MODEL", work / "X.wav", work / "X.lab", work / "OUT", posterior="laplace", video=False,
          n_draws=16)
    return work


@pytest.fixture(scope="module")
def toy_names():
    """``model``, ``mfcc``, ``labels``, ``y``, ``z``, ``post``, ``results``,
    ``test_sequences``, ``train_label_sequences`` for the blocks marked USES_TOY."""
    from toydata import make_utterances

    from bayes_talk.estimators.switching import SwitchingSGPDM
    from bayes_talk.posterior.sampling import sample_synthesis

    train = make_utterances(24, seed=0)
    u = make_utterances(3, seed=1, mean_len=20)[0]
    model = SwitchingSGPDM(states="vlmm", **SMALL).fit(train)
    u12 = type(u)(**{**vars(u), "mfcc": u.mfcc[:12], "labels": u.labels[:12], "aam": u.aam[:12]})
    post = sample_synthesis(model, u12.mfcc, u12.labels, method="laplace", n_draws=16, seed=0, log_warnings=False)
    return {"model": model, "mfcc": u12.mfcc, "labels": u12.labels, "y": u12.aam, "z": u12.aam, "post": post,
            "results": [post], "test_sequences": [u12], "train_label_sequences": [s.labels for s in train]}


RUN_PY = [b for b in PY if PYTHON_BLOCKS[b.key].run]


@pytest.mark.slow
@pytest.mark.parametrize("block", RUN_PY, ids=str)
def test_python_block_runs(block, docs_work, request, monkeypatch, tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    spec = PYTHON_BLOCKS[block.key]
    code = block_source(block).replace('"MODEL_DIR"', f'"{docs_work / "MODEL"}"')
    code = code.replace('"OUT_DIR/', f'"{docs_work / "OUT"}/')
    for name in ("CORPUS", "MODEL", "X.wav", "X.lab"):
        (tmp_path / name).symlink_to(docs_work / name)
    monkeypatch.chdir(tmp_path)
    ns: dict = {"__name__": "__main__"}
    if spec.setup == USES_TOY:
        ns.update(request.getfixturevalue("toy_names"))
    elif spec.setup == USES_SPLIT:
        from bayes_talk.corpus import load_corpus

        seqs = load_corpus("CORPUS").sequences
        ns.update(train=seqs[:-3], test=seqs[-3:])
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(code, str(block), "exec"), ns)  # noqa: S102 (the docs' own code)
    sys.stdout.write(out.getvalue())


# --- shell commands run on the tiny corpus ---------------------------------------------------

#: documented commands that are run, with the reviewed substitutions that make them fit in
#: ``make test`` (the placeholders CORPUS, MODEL, X.wav, X.lab, OUT name the docs_work files)
RUN_COMMANDS: dict[tuple[str, str], tuple[tuple[str, str], ...]] = {
    ("README.md", "bayes-talk --version"): (),
    ("README.md", "bayes-talk corpus build CORPUS --n-utterances 300 --seed 0"): (
        ("CORPUS", "CORPUS2"), ("300", "3"), ("--seed 0", "--seed 0 --image-size 64")),
    ("README.md", "bayes-talk synth MODEL --audio X.wav --labels X.lab --out OUT"): (
        ("OUT", "OUT_README"), ("--out", "--no-video --draws 16 --out")),
    ("docs/uncertainty.md", "bayes-talk synth MODEL --audio X.wav --labels X.lab --out RAW --raw-bands"): (
        ("--raw-bands", "--raw-bands --no-video --draws 16"),),
    ("README.md", ("bayes-talk evaluate --protocol deena2010 --corpus CORPUS --quick --methods zero,oracle,hmm-mean "
                  "--json ceiling.json")): (
        ("--quick", "--quick --min-utterances 8 --oracle-draws 2 --no-figures"),),
}


def _normal(cmd: Command) -> str:
    args = cli_args(cmd.argv)
    return shlex.join(["bayes-talk", *args]) if args is not None else shlex.join(cmd.argv)


def test_run_table_matches_documented_commands():
    documented = {(c.block.path, _normal(c)) for c in COMMANDS}
    assert [k for k in RUN_COMMANDS if k not in documented] == []


@pytest.mark.slow
@pytest.mark.parametrize("key", list(RUN_COMMANDS), ids=lambda k: k[1][:60])
def test_documented_command_runs_on_a_tiny_corpus(key, docs_work, monkeypatch, capsys):
    from bayes_talk.app.cli import main

    line = key[1]
    for old, new in RUN_COMMANDS[key]:
        assert old in line
        line = line.replace(old, new)
    monkeypatch.chdir(docs_work)
    args = shlex.split(line)[1:]
    if args == ["--version"]:
        with pytest.raises(SystemExit) as exc:
            main(args)
        assert exc.value.code == 0
        from bayes_talk import __version__

        assert capsys.readouterr().out.strip() == f"bayes-talk {__version__}"
        return
    assert main(args) == 0
    if args[0] == "synth":
        out = docs_work / args[args.index("--out") + 1]
        assert (out / "trajectory.npy").is_file() and (out / "bands.npz").is_file()
    if args[0] == "evaluate":
        import json

        r = json.loads((docs_work / args[args.index("--json") + 1]).read_text())
        assert set(r["methods"]) == {"zero", "oracle", "hmm-mean"}
    if args[:2] == ["corpus", "build"]:
        assert (docs_work / args[2] / "manifest.json").is_file()



# ------------------------------------------------------------------------------------------
# Numbers the docs quote from the code
# ------------------------------------------------------------------------------------------

def test_docs_quote_the_label_tolerance_the_code_applies():
    """docs/data.md once said 40 ms while the code allowed 80 ms."""
    from bayes_talk.data.checks import LABEL_TOLERANCE_S

    ms = f"{LABEL_TOLERANCE_S * 1000:.0f} ms"
    text = (ROOT / "docs" / "data.md").read_text(encoding="utf-8")
    row = next(ln for ln in text.splitlines() if ln.startswith("| labels vs audio |"))
    assert f"({ms})" in row and "LABEL_TOLERANCE_S" in row
    arch = (ROOT / "docs" / "architecture.md").read_text(encoding="utf-8")
    assert f"`data.checks.LABEL_TOLERANCE_S` = {LABEL_TOLERANCE_S:g} s" in arch
