"""The README's Python section runs as a plain script.

A user's ``python script.py`` has no ``if __name__ == "__main__":`` guard; a library call
that started spawn workers behind its back made every worker re-run the script and the
caller die with BrokenProcessPool. The corpus has 16 utterances, the size from which
``load_corpus`` used to start 2 worker processes by default, and no feature cache yet.
"""
from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def readme_python_section() -> str:
    """The ```python block of the README's "## Python" section that starts from a corpus
    (``load_corpus``); the section's other block starts from a trained model directory
    (tests/project/test_doc_commands.py runs it)."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    m = re.search(r"^## Python\n(.*?)(?=^## )", text, re.DOTALL | re.MULTILINE)
    assert m, "README.md: no '## Python' section"
    blocks = re.findall(r"^```python\n(.*?)^```", m.group(1), re.DOTALL | re.MULTILINE)
    block = next((b for b in blocks if "load_corpus(" in b), None)
    assert block, "README.md: no ```python block with load_corpus under '## Python'"
    return block


@pytest.mark.slow
def test_readme_python_section_runs_as_a_plain_script_on_a_fresh_corpus(tmp_path):
    from bayes_talk.corpus import build_corpus

    build_corpus(tmp_path / "CORPUS", n_utterances=16, seed=0, image_size=64)
    assert not (tmp_path / "CORPUS" / "features.npz").exists()
    code = readme_python_section()
    assert 'load_corpus("CORPUS")' in code
    (tmp_path / "script.py").write_text(code, encoding="utf-8")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run([sys.executable, "script.py"], cwd=tmp_path, env=env, capture_output=True, check=False,
                          text=True, timeout=1800)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr and "BrokenProcessPool" not in proc.stderr, proc.stderr[-3000:]
    last = proc.stdout.strip().splitlines()[-1]
    assert re.fullmatch(r"\(\d+, \d+\) MAP converged: (True|False)", last), proc.stdout[-500:]
    assert (tmp_path / "CORPUS" / "features.npz").exists()    # featurised (in this process) and cached


def test_workers_asked_for_without_the_main_guard_get_an_error_that_names_the_guard(tmp_path):
    script = tmp_path / "noguard.py"
    script.write_text("import operator\n"
                      "from bayes_talk.base.executor import ProcessExecutor\n"
                      "with ProcessExecutor(2) as ex:\n"
                      "    print(ex.map(operator.neg, [1, 2, 3]))\n", encoding="utf-8")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run([sys.executable, str(script)], cwd=tmp_path, env=env, capture_output=True, text=True,
                          check=False, timeout=600)
    assert proc.returncode != 0
    assert "RuntimeError: a worker process died" in proc.stderr
    # our message (double quotes; Python's own spawn text uses single ones) follows the error
    # line; the dying pool's resource tracker may print its own warning after it
    after = proc.stderr[proc.stderr.index("RuntimeError: a worker process died"):]
    assert 'if __name__ == "__main__":' in after
    guarded = tmp_path / "guard.py"
    guarded.write_text("import operator\n"
                       "from bayes_talk.base.executor import ProcessExecutor\n"
                       "if __name__ == '__main__':\n"
                       "    with ProcessExecutor(2) as ex:\n"
                       "        print(ex.map(operator.neg, [1, 2, 3]))\n", encoding="utf-8")
    ok = subprocess.run([sys.executable, str(guarded)], cwd=tmp_path, env=env, capture_output=True, text=True,
                        check=False, timeout=600)
    assert ok.returncode == 0 and ok.stdout.strip() == "[-1, -2, -3]", ok.stderr[-2000:]
