"""Where the joint MAP starts: Algorithm 1's path, or that path carried along the GP dynamics
(issues 27 and 29, session 17).

Notebook 03 (deena2010's protocol, quick, on 14 built utterances) spends most of its time in
the joint MAP of its four Laplace syntheses (``ssgpdm-vlmm-posterior``: two held-out
calibration utterances, two test utterances), and two of the four stop at the iteration cap
unconverged. Algorithm 1's path is 10⁵-10⁶ nats below the mode on the dynamics terms alone:
it is built block by block under each state model's own objective, and with the dynamics
noise at 10⁻⁶ any step off the dynamics GP's mean costs (Δ/10⁻³)²/2 nats.

This script runs that protocol, captures every joint-MAP problem (the density and Algorithm
1's path), and maximises each twice with the library's ``maximise_utterance``:

``algorithm1``
    from Algorithm 1's path (what the library does);
``carried``
    from the higher of that path and the path carried along the dynamics means (each
    dynamics step x_t ← μ_x(x_{t−1}) in time order, block starts kept; the library's
    ``joint_map.along_dynamics``), the rule measured as a library change in session 17 and not adopted
    (docs/experiments.md, "Where the joint MAP starts").

Since session 18 the library carries the start when Algorithm 1's path is off the dynamics
(RMS standardised residual > ``CARRY_RMS_Z``); ``algorithm1`` is then run with that rule
switched off, and each problem also records the start's RMS z and what the library does
(``library``).

For each: log density at the start and at the end, converged, iterations, seconds.

    python benchmarks/analysis/map_start.py --json benchmarks/results/map_start_nb03_s17.json

With ``--model-dir`` and ``--test-corpus`` the problems are those of ``bayes-talk synth``
(Laplace, the default) on the first ``--n`` utterances of a corpus instead of notebook 03's:

    python benchmarks/analysis/map_start.py --model-dir data/model_vlmm_nocal \
        --test-corpus data/dev40 --n 10 --json benchmarks/results/map_start_dev_vlmm_s18.json
"""
from __future__ import annotations

import argparse
import contextlib
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from bayes_talk.corpus import build_corpus
from bayes_talk.evaluation.harness import evaluate
from bayes_talk.base.files import write_json
from bayes_talk.synthesis import joint_map
from bayes_talk.posterior import sampling as posterior
from bayes_talk.synthesis.joint_map import along_dynamics, dynamics_rms_z, maximise_utterance


@contextlib.contextmanager
def recording_maps():
    """A list that collects (density, Algorithm 1's path, keyword arguments) of every joint MAP
    the posterior module runs inside the block (the library's function still runs)."""
    problems = []

    def recording(dens, X0, **kw):
        problems.append((dens, np.array(X0), kw))
        return maximise_utterance(dens, X0, **kw)

    posterior.maximise_utterance = recording
    try:
        yield problems
    finally:
        posterior.maximise_utterance = maximise_utterance


def capture(n_utterances: int, seed: int, work: Path) -> list:
    """The joint MAP problems of notebook 03's protocol run (:func:`recording_maps`)."""
    with recording_maps() as problems:
        corpus = build_corpus(work / "corpus", n_utterances=n_utterances, seed=seed)
        evaluate("deena2010", corpus, work / "quick.json", methods=["ssgpdm-vlmm-posterior"], quick=True,
                 seed=seed, min_utterances=n_utterances)
    return problems


def capture_synth(model_dir: Path, corpus: Path, n: int, work: Path) -> list:
    """The first joint MAP problem of ``bayes-talk synth`` on each of the first n utterances
    of a corpus (their own label files; restarts are not the start)."""
    from bayes_talk.app.cli import main as cli

    first = []
    for i, wav in enumerate(sorted((corpus / "utterances").glob("*.wav"))[:n]):
        with recording_maps() as problems:
            assert cli(["-q", "synth", str(model_dir), "--audio", str(wav), "--labels", str(wav.with_suffix(".lab")),
                        "--out", str(work / f"o{i}"), "--no-video"]) == 0
        first.append(problems[0])
    return first


def run(dens, start: np.ndarray, kw: dict, carry: bool = True) -> dict:
    t0 = time.perf_counter()
    saved = joint_map.CARRY_RMS_Z
    joint_map.CARRY_RMS_Z = saved if carry else np.inf
    try:
        r = maximise_utterance(dens, start, **kw)
    finally:
        joint_map.CARRY_RMS_Z = saved
    return {"start_log_density": float(dens(start)[0]), "log_density": r.log_density, "converged": r.converged,
            "iterations": r.n_iter, "grad_norm": r.grad_norm, "carried": r.carried,
            "seconds": time.perf_counter() - t0}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n-utterances", type=int, default=14, help="notebook 03's corpus size")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--model-dir", type=Path, help="a trained model: its synth problems instead of notebook 03's")
    ap.add_argument("--test-corpus", type=Path, help="with --model-dir: the utterances to synthesise")
    ap.add_argument("--n", type=int, default=10, help="with --model-dir: the first N utterances")
    ap.add_argument("--json", required=True)
    a = ap.parse_args(argv)
    if (a.model_dir is None) != (a.test_corpus is None):
        ap.error("--model-dir and --test-corpus go together")
    rows = []
    kinds = ("algorithm1", "carried", "library")
    with tempfile.TemporaryDirectory(prefix="bt_map_start_") as tmp:
        problems = (capture_synth(a.model_dir, a.test_corpus, a.n, Path(tmp)) if a.model_dir
                    else capture(a.n_utterances, a.seed, Path(tmp)))
        for dens, X0, kw in problems:
            Xr = along_dynamics(dens, X0)
            carried_start = Xr if dens(Xr)[0] > dens(X0)[0] else X0
            rows.append({"frames": dens.T, "latent_dim": dens.d, "start_rms_z": dynamics_rms_z(dens, X0),
                         "algorithm1": run(dens, X0, kw, carry=False), "carried": run(dens, carried_start, kw, carry=False),
                         "library": run(dens, X0, kw)})
            r = rows[-1]
            print(round(r["start_rms_z"], 2), {k: (round(r[k]["log_density"], 2), r[k]["converged"],
                                                   round(r[k]["seconds"], 1)) for k in kinds}, flush=True)
    out = {"benchmark": "map_start", "problems": rows,
           **({"model_dir": str(a.model_dir), "test_corpus": str(a.test_corpus), "n": a.n} if a.model_dir
              else {"n_utterances": a.n_utterances, "seed": a.seed}),
           "total_seconds": {k: sum(r[k]["seconds"] for r in rows) for k in kinds},
           "converged": {k: sum(r[k]["converged"] for r in rows) for k in kinds},
           "command": "python benchmarks/analysis/map_start.py " + " ".join(argv if argv is not None else sys.argv[1:])}
    write_json(a.json, out)
    print(out["total_seconds"], out["converged"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
