"""The benchmark suite's conventions (docs/benchmarks.md): one script per question with a quick
mode, one current result file per question named for it, every one of them in the index, and
each result recording its command, machine and commit."""
from __future__ import annotations

import json
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
BENCH = ROOT / "benchmarks"
SCRIPTS = sorted(p for p in BENCH.glob("*.py") if p.stem not in ("__init__", "common"))
RESULTS = sorted((BENCH / "results").glob("*.json"))
#: a name that dates a result or tags it with a stage of work
HISTORY_TAG = re.compile(r"_s\d+(_|\.|$)|session|\d{4}-?\d{2}-?\d{2}")


def _common():
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    from benchmarks import common
    return common


def test_every_script_has_a_quick_mode_and_writes_through_the_shared_record():
    assert len(SCRIPTS) >= 10
    bad = [p.name for p in SCRIPTS
           if '"--quick"' not in p.read_text() or "write_result(" not in p.read_text()]
    assert bad == []


def test_no_script_reaches_into_the_tests_or_patches_the_library():
    bad = []
    for p in SCRIPTS:
        text = p.read_text()
        if '/ "tests"' in text or "toydata" in text or "warp_reference" in text:
            bad.append((p.name, "imports from tests/"))
        if re.search(r"^\s*(?:bayes_talk\.\S+|[a-z_]+_mod)\.\w+ = ", text, re.MULTILINE) or "setattr(" in text:
            bad.append((p.name, "assigns into a library module"))
    assert bad == []


def test_committed_results_are_few_named_for_their_question_and_indexed():
    index = (ROOT / "docs" / "benchmarks.md").read_text()
    assert 0 < len(RESULTS) <= 40
    assert [p.name for p in RESULTS if HISTORY_TAG.search(p.stem)] == []
    scripts = {p.stem for p in SCRIPTS}
    orphans = [p.name for p in RESULTS if p.stem not in scripts and p.stem.split("_")[0] not in scripts]
    assert orphans == []
    assert [p.name for p in RESULTS if f"`{p.name}`" not in index] == []
    assert [p.name for p in SCRIPTS if f"benchmarks/{p.name}" not in index] == []


def test_a_result_records_its_command_machine_and_commit(tmp_path):
    common = _common()
    out = common.write_result(tmp_path / "x.json", {"figure": 1.5, "machine": {"threads": 2}},
                              argv=[str(BENCH / "sbc.py"), "--quick"])
    saved = json.loads(out.read_text())
    assert saved["command"] == "python benchmarks/sbc.py --quick" and saved["figure"] == 1.5
    assert saved["machine"]["threads"] == 2 and saved["machine"]["cpu_count"] >= 1
    assert {"python", "platform", "packages", "load_average"} <= set(saved["machine"])
    assert saved["machine"]["packages"]["numpy"]
    assert "sha" in saved["commit"] and "dirty" in saved["commit"]


def test_quick_results_go_to_the_ignored_scratch_directory():
    common = _common()
    assert common.result_path("sbc") == BENCH / "results" / "sbc.json"
    assert common.result_path("sbc", quick=True) == BENCH / "results" / "quick" / "sbc.json"
    ignore = (BENCH / "results" / "quick" / ".gitignore").read_text().splitlines()
    assert "*" in ignore
