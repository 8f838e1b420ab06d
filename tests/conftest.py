import os
import shutil
import sys
from pathlib import Path

import pytest

# tests import the shared synthetic-data helpers (tests/toydata.py) by module name
sys.path.insert(0, str(Path(__file__).parent))

#: the corpus shared by the test files that only read a small built corpus
SHARED_CORPUS_UTTERANCES = 10
SHARED_CORPUS_SEED = 3


@pytest.fixture(scope="session")
def built_once(tmp_path_factory):
    """``built_once(name, build, leaf="out") -> Path``: the directory ``build(path)`` makes
    (``path`` named ``leaf``), made once per
    test run and shared (issue 29). Under pytest-xdist (``make test`` runs ``pytest -n 2``)
    every worker process has its own session; the first to ask builds ``name`` in the
    directory the workers share (the parent of their base temporary directories), under a
    file lock, and the others wait for it and read it, so it is built once per run, not once
    per worker (the pattern of pytest-xdist's documentation). Without xdist it is built in
    this session's temporary directory. ``name`` must say everything ``build`` depends on;
    the result is read-only (a test that changes it works on a copy, ``shutil.copytree``)."""
    from filelock import FileLock

    def get(name: str, build, leaf: str = "out") -> Path:
        if os.environ.get("PYTEST_XDIST_WORKER") is None:
            out = tmp_path_factory.mktemp(name) / leaf
            build(out)
            return out
        shared = tmp_path_factory.getbasetemp().parent / name
        out, done = shared / leaf, shared / "built"
        shared.mkdir(exist_ok=True)
        with FileLock(str(shared / "lock")):
            if not done.is_file():
                if out.exists():   # a build that failed half-way in another worker
                    shutil.rmtree(out)
                build(out)
                done.write_text("ok\n")
        return out

    return get


@pytest.fixture(scope="session")
def shared_built_corpus(built_once) -> Path:
    """A built corpus of 10 utterances (seed 3), built once per test run through the
    command line (:func:`built_once`) and shared by the files that read one (test_pipeline,
    test_bad_inputs, test_registry): a corpus build is the largest set-up cost of the suite
    (issue 29). Treat it as read-only: a test that changes a corpus works on a copy
    (``shutil.copytree``); the feature cache that loading writes into it is the only change,
    and it is the same for every reader (written atomically)."""
    from bayes_talk.app.cli import main

    def build(out: Path) -> None:
        assert main(["-q", "corpus", "build", str(out), "--n-utterances", str(SHARED_CORPUS_UTTERANCES),
                     "--seed", str(SHARED_CORPUS_SEED)]) == 0

    return built_once(f"corpus_cli_n{SHARED_CORPUS_UTTERANCES}_seed{SHARED_CORPUS_SEED}", build, leaf="corpus")


#: settings of the toy switching model the synthesis-posterior test files share
TOY_SMALL = {"latent_dim": 3, "max_iter": 40, "min_count": 4, "max_frames_per_state": 120, "fallback_frames": 150}


@pytest.fixture(scope="session")
def toy_vlmm():
    """``SwitchingSGPDM(states="vlmm", **TOY_SMALL)`` fitted on ``make_utterances(24,
    seed=0)``: the toy model of the synthesis-posterior test files (test_posterior,
    test_noncentred, test_parallel_chains, test_particle_gibbs, test_sampler_diagnostics,
    test_sbc, test_smoothness_simulation, test_switching), fitted once per test process instead of once per
    file (issue 29; 2.5–4 s a fit). Read-only: a test that changes a model fits its own."""
    from toydata import make_utterances

    from bayes_talk.estimators.switching import SwitchingSGPDM

    return SwitchingSGPDM(states="vlmm", **TOY_SMALL).fit(make_utterances(24, seed=0))


@pytest.fixture(scope="session")
def toy_vlmm_private():
    """:func:`toy_vlmm` with one of its 3 latent dimensions private to the face (the audio
    GPs read the first 2: SwitchingConfig.private_dims)."""
    from toydata import make_utterances

    from bayes_talk.estimators.switching import SwitchingSGPDM

    return SwitchingSGPDM(states="vlmm", private_dims=1, **TOY_SMALL).fit(make_utterances(24, seed=0))
