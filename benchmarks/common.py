"""What every benchmark shares: where its result goes, what the result records about the run,
and the tiny corpora and model of the quick mode.

Every script under ``benchmarks/`` answers one question and writes one result file,
``benchmarks/results/NAME.json`` (``--quick``: ``benchmarks/results/quick/NAME.json``, ignored by
git, so a quick run never overwrites a committed result). :func:`write_result` adds to it

* ``command``: the command line that produced it (relative to the repository);
* ``machine``: platform, CPU count, load average, Python and the versions of the key packages;
* ``commit``: the git commit of the source tree, and whether the tree had uncommitted changes.

A script given no corpus or model uses the suite's: :func:`bench_corpus` (a built corpus,
``bayes_talk.corpus.build.build_corpus``) and :func:`bench_model` (a model trained on it by
``bayes_talk.pipeline.train``), built once and reused; in quick mode tiny ones under the
scratch directory, else the full-size ones under ``data/`` (hours to build).
Scripts import only the public library API; they never patch it.
"""
from __future__ import annotations

import importlib.metadata
import os
import platform
import shlex
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
QUICK = RESULTS / "quick"

#: the packages whose versions a result records
PACKAGES = ("bayes_talk", "numpy", "scipy", "torch", "pyro-ppl", "numba", "scikit-learn", "arviz", "GPy")

#: settings of the small switching models of the quick mode (the test suite's toy settings)
QUICK_MODEL = {"latent_dim": 3, "max_iter": 20, "min_count": 3, "max_frames_per_state": 80, "fallback_frames": 100}
QUICK_TRAIN_UTTERANCES = 12
QUICK_TEST_UTTERANCES = 3


def result_path(name: str, quick: bool = False, out: str | os.PathLike | None = None) -> Path:
    """``out`` if given, else ``results/NAME.json`` (``results/quick/NAME.json`` in quick mode)."""
    if out is not None:
        return Path(out)
    return (QUICK if quick else RESULTS) / f"{name}.json"


def scratch(name: str) -> Path:
    """A directory under the quick scratch directory (created), for what a quick run builds."""
    d = QUICK / "data" / name
    d.mkdir(parents=True, exist_ok=True)
    return d


def machine() -> dict:
    """Platform, CPU count, load average, Python and package versions of this machine."""
    versions = {}
    for p in PACKAGES:
        try:
            versions[p] = importlib.metadata.version(p)
        except importlib.metadata.PackageNotFoundError:
            versions[p] = None
    return {"platform": platform.platform(), "machine": platform.machine(), "cpu_count": os.cpu_count(),
            "load_average": list(os.getloadavg()), "python": platform.python_version(), "packages": versions}


def commit() -> dict:
    """The git commit of the source tree and whether it had uncommitted changes (None outside git)."""
    def git(*args: str) -> str | None:
        try:
            return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True,
                                  check=True).stdout.strip()
        except (OSError, subprocess.CalledProcessError):
            return None
    sha = git("rev-parse", "HEAD")
    status = git("status", "--porcelain", "--untracked-files=no", "--", "bayes_talk", "benchmarks")
    return {"sha": sha, "dirty": bool(status) if status is not None else None}


def command(argv: list[str] | None = None) -> str:
    """The command line of this run, the script's path relative to the repository."""
    argv = list(sys.argv if argv is None else argv)
    script = Path(argv[0]).resolve()
    try:
        argv[0] = str(script.relative_to(ROOT))
    except ValueError:
        pass
    return " ".join(shlex.quote(a) for a in ["python", *argv])


def write_result(path: str | os.PathLike, result: dict, argv: list[str] | None = None) -> Path:
    """Write ``result`` as JSON (atomically) with its ``command``, ``machine`` (merged with the
    result's own ``machine`` entries, if any) and ``commit``."""
    from bayes_talk.base.files import write_json

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    record = {"command": command(argv), "machine": {**machine(), **result.get("machine", {})}, "commit": commit()}
    record.update({k: v for k, v in result.items() if k not in record})
    write_json(path, record)
    return path


#: the corpora of the full runs, under data/ (not committed): name -> (directory, utterances,
#: seed, sentences file or None for the built-in sentences); built on first use when missing,
#: with the commands of docs/benchmarks.md
FULL_CORPORA = {"train": ("data/train250", 250, 0, None),
                "test": ("data/dev40", 40, 1, "benchmarks/data/heldout_sentences.txt")}
#: the model of the full runs: ``bayes-talk train data/train250 --out data/model_default``
FULL_MODEL = "data/model_default"


def bench_corpus(name: str = "train", quick: bool = False) -> Path:
    """The training (``train``) or held-out (``test``) corpus of a benchmark: in quick mode a
    tiny one built once under the scratch directory (``QUICK_TRAIN_UTTERANCES`` built-in
    sentences, seed 0; ``QUICK_TEST_UTTERANCES`` held-out sentences of
    ``benchmarks/data/heldout_sentences.txt``, seed 1), else :data:`FULL_CORPORA`'s, built
    when missing (``bayes_talk.corpus.build.build_corpus``)."""
    from bayes_talk.corpus.build import build_corpus

    where, n, seed, sentences = FULL_CORPORA[name]
    if quick:
        n = QUICK_TEST_UTTERANCES if name == "test" else QUICK_TRAIN_UTTERANCES
        out = QUICK / "data" / f"corpus_{name}_n{n}_seed{seed}"
    else:
        out = ROOT / where
    if not (out / "manifest.json").is_file():
        build_corpus(out, n_utterances=n, seed=seed, force=True, n_workers=min(2, n),
                     sentences=ROOT / sentences if sentences else None)
    return out


def bench_model(quick: bool = False) -> Path:
    """The trained model of a benchmark (``bayes_talk.pipeline.train``, the default family with
    its band calibration, on ``bench_corpus("train", quick)``), trained once when missing: in
    quick mode with the small ``QUICK_MODEL`` settings under the scratch directory, else
    :data:`FULL_MODEL` with the library defaults."""
    from bayes_talk import pipeline

    out = QUICK / "data" / "model" if quick else ROOT / FULL_MODEL
    if not (out / "DONE" if quick else out / "bayes_talk_model.json").is_file():
        pipeline.train(bench_corpus("train", quick), pipeline.DEFAULT_MODEL, out, workers=1 if quick else 2,
                       force=True, calibrate_bands=pipeline.DEFAULT_CALIBRATION, **(QUICK_MODEL if quick else {}))
        if quick:
            (out / "DONE").write_text("ok\n")
    return out
