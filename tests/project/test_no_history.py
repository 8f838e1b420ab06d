"""The README, the documentation and the package describe the product as it is, not how it
came to be: no "session N", no issue or pull-request numbers, no result files named by a
session (``..._s36.json``), no citation of design notes that are not in the repository
(``DESIGN.md``, ``FACTS.md``), no absolute paths of a development machine (``/work/``,
``/root/``) and no dates of work. That history lives in git and CHANGELOG.md.

Each text is checked line by line with :data:`PATTERNS`; the checker itself is tested on
planted examples (it must flag them) and on legitimate text (it must pass it).
"""
from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

#: what counts as a development-history reference: name -> pattern
PATTERNS: dict[str, re.Pattern[str]] = {
    "session": re.compile(r"\b[Ss]essions?[ -]?[0-9]+"),
    "issue number": re.compile(r"\b[Ii]ssues?[ -]?#?[0-9]+"),
    "pull-request / issue tag": re.compile(r"(?<![\w&#@])#[0-9]+\b"),
    "result file named by a session": re.compile(r"\w_s[0-9]+(?:_[\w-]*)?\.json\b"),
    "design notes outside the repository": re.compile(r"\b(?:DESIGN|FACTS)\.md\b|\bDESIGN\s*§"),
    "machine path": re.compile(r"(?<![\w.~-])/(?:work|root)/"),
    "date of work": re.compile(r"\b20[0-9]{2}-[01][0-9]-[0-3][0-9]\b"),
}


def history_references(text: str) -> list[tuple[int, str, str]]:
    """(line number, kind, matched text) of every development-history reference in ``text``."""
    found = []
    for no, line in enumerate(text.splitlines(), 1):
        for kind, pattern in PATTERNS.items():
            found.extend((no, kind, m.group(0)) for m in pattern.finditer(line))
    return found


def checked_files(*tops: str) -> list[Path]:
    """The text files under ``tops`` (files or directories relative to the repository) that
    the check covers: markdown in ``README.md`` and ``docs/``; every source and text file of
    the package (compiled caches skipped)."""
    out: list[Path] = []
    for top in tops:
        p = ROOT / top
        if p.is_file():
            out.append(p)
            continue
        suffixes = {".md"} if top == "docs" else {".py", ".md", ".txt", ".json", ".toml", ".cfg"}
        out.extend(f for f in sorted(p.rglob("*"))
                   if f.is_file() and f.suffix in suffixes and "__pycache__" not in f.parts)
    return out


def _report(files: list[Path]) -> list[str]:
    return [f"{f.relative_to(ROOT)}:{no}: {kind}: {text!r}"
            for f in files for no, kind, text in history_references(f.read_text(encoding="utf-8"))]


@pytest.mark.parametrize("planted", [
    "measured in session 14 on a quiet machine",
    "(docs/results.md \"Session 9\")",
    "sessions 3-5 changed it",
    "the front end before issue 12",
    "the issue-27 front end",
    "an estimator protocol (issue #15)",
    "Issues 10 and 11",
    "one layout for every estimator (#26)",
    "benchmarks/results/render_s12.json",
    "heldout_default_model_s6_noac.json",
    "conventions pinned in DESIGN.md §3",
    "metrics (DESIGN §9)",
    "twice as fast (FACTS.md)",
    "run /work/main/.venv/bin/python -m pytest",
    "see /root/notes.txt",
    "measured 2026-12-01",
])
def test_the_checker_flags_a_planted_history_reference(planted):
    text = f"A clean first line.\n{planted}\n"
    found = history_references(text)
    assert found and all(no == 2 for no, _, _ in found), found


def test_the_checker_passes_legitimate_text():
    clean = """\
The observation term (deena2010 eq. 5, Eq. (5)) and the dynamics term (eq. 7).
Smoothness across states (deena2010 §4.2.3); englebienne2008 §3 and App. A.
Zip members are stamped 1980-01-01; Rasmussen & Williams 2006 §2.7; Talts et al. 2018.
A phone "@#" or "a#2" of espeak; the entity &#38; a colour #fff; the issue's range.
Step 3 of 5; version 2 of the format; s1, s2 = 1.0, 2.0; ``s_2`` and ``s*_1..4``.
#: a comment
# 1. a numbered comment
benchmarks/results/quick/work/corpus and ~/work/x and ./work/y are relative paths.
benchmarks/results/render.json, heldout_dev.json, sbc_s.json.
The design_size constant DESIGN_SIZE; a session of the command line.
"""
    assert history_references(clean) == []


def test_the_package_has_no_development_history():
    files = checked_files("bayes_talk")
    assert len(files) > 100          # the package's modules were found
    problems = _report(files)
    assert not problems, f"{len(problems)} development-history references:\n" + "\n".join(problems)


def test_the_readme_and_the_docs_have_no_development_history():
    files = checked_files("README.md", "docs")
    assert ROOT / "README.md" in files and len(files) > 3
    problems = _report(files)
    assert not problems, f"{len(problems)} development-history references:\n" + "\n".join(problems)


#: a file of the repository cited by the package: a docs page, a benchmark, a test, a notebook
CITED_FILE = re.compile(r"\b(?:docs|benchmarks|tests|notebooks)/[\w/.-]+?\.(?:md|py|json|ipynb)\b")


def test_every_repository_file_the_package_cites_exists():
    """The package cites docs pages, benchmarks and tests instead of notes outside the
    repository: each must exist (a moved or deleted file leaves no dangling citation)."""
    cited: dict[str, list[str]] = {}
    for f in checked_files("bayes_talk"):
        for path in set(CITED_FILE.findall(f.read_text(encoding="utf-8"))):
            cited.setdefault(path, []).append(str(f.relative_to(ROOT)))
    assert len(cited) > 3        # the pattern finds the citations
    missing = {p: sorted(fs) for p, fs in sorted(cited.items()) if not (ROOT / p).is_file()}
    assert not missing, f"files cited by the package but absent: {missing}"
