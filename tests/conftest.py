import sys
from pathlib import Path

import pytest

# tests import the shared synthetic-data helpers (tests/toydata.py) by module name
sys.path.insert(0, str(Path(__file__).parent))

#: the corpus shared by the test files that only read a small built corpus
SHARED_CORPUS_UTTERANCES = 10
SHARED_CORPUS_SEED = 3


@pytest.fixture(scope="session")
def shared_built_corpus(tmp_path_factory) -> Path:
    """A built corpus of 10 utterances (seed 3), built once per test session through the
    command line and shared by the files that read one (test_pipeline, test_bad_inputs):
    a corpus build is the largest set-up cost of the suite (issue 29). Treat it as
    read-only: a test that changes a corpus works on a copy (``shutil.copytree``); the
    feature cache that loading writes into it is the only change, and it is the same for
    every reader."""
    from bayes_talk.cli import main

    out = tmp_path_factory.mktemp("shared") / "corpus"
    assert main(["-q", "corpus", "build", str(out), "--n-utterances", str(SHARED_CORPUS_UTTERANCES),
                 "--seed", str(SHARED_CORPUS_SEED)]) == 0
    return out
