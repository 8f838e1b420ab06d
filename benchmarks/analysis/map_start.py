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
    dynamics step x_t ← μ_x(x_{t−1}) in time order, block starts kept; ``along_dynamics``
    below), the rule measured as a library change in session 17 and not adopted
    (docs/experiments.md, "Where the joint MAP starts").

For each: log density at the start and at the end, converged, iterations, seconds.

    python benchmarks/analysis/map_start.py --json benchmarks/results/map_start_nb03_s17.json
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from bayes_talk.data.corpus import build_corpus
from bayes_talk.evaluation.harness import evaluate
from bayes_talk.files import write_json
from bayes_talk.gp.predictive_fused import Runs
from bayes_talk.synthesis import posterior
from bayes_talk.synthesis.joint_map import maximise_utterance


def along_dynamics(dens, X: np.ndarray) -> np.ndarray:
    """X with every dynamics step of the density replaced by the dynamics GP's mean given the
    frame before it, in time order; every other frame kept."""
    X = np.array(X, dtype=np.float64).reshape(dens.T, dens.d)
    tm = dens.terms
    row_gp = tm.d_runs.row_gp()
    for j in np.argsort(tm.d_dst, kind="stable"):
        t = tm.d_dst[j]
        mu, _ = tm.dyn_gps.mean_var(Runs(row_gp[j:j + 1], np.zeros(1), np.ones(1)), X[t - 1:t])
        X[t] = mu[0]
    return X


def capture(n_utterances: int, seed: int, work: Path) -> list:
    """(density, Algorithm 1's path, keyword arguments) of every joint MAP the protocol runs."""
    problems = []

    def recording(dens, X0, **kw):
        problems.append((dens, np.array(X0), kw))
        return maximise_utterance(dens, X0, **kw)

    posterior.maximise_utterance = recording
    try:
        corpus = build_corpus(work / "corpus", n_utterances=n_utterances, seed=seed)
        evaluate("deena2010", corpus, work / "quick.json", methods=["ssgpdm-vlmm-posterior"], quick=True,
                 seed=seed, min_utterances=n_utterances)
    finally:
        posterior.maximise_utterance = maximise_utterance
    return problems


def run(dens, start: np.ndarray, kw: dict) -> dict:
    t0 = time.perf_counter()
    r = maximise_utterance(dens, start, **kw)
    return {"start_log_density": float(dens(start)[0]), "log_density": r.log_density, "converged": r.converged,
            "iterations": r.n_iter, "grad_norm": r.grad_norm, "seconds": time.perf_counter() - t0}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n-utterances", type=int, default=14, help="notebook 03's corpus size")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", required=True)
    a = ap.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory(prefix="bt_map_start_") as tmp:
        for dens, X0, kw in capture(a.n_utterances, a.seed, Path(tmp)):
            Xr = along_dynamics(dens, X0)
            carried_start = Xr if dens(Xr)[0] > dens(X0)[0] else X0
            rows.append({"frames": dens.T, "latent_dim": dens.d,
                         "algorithm1": run(dens, X0, kw), "carried": run(dens, carried_start, kw)})
            r = rows[-1]
            print({k: (round(r[k]["log_density"], 2), r[k]["converged"], round(r[k]["seconds"], 1))
                   for k in ("algorithm1", "carried")}, flush=True)
    out = {"benchmark": "map_start", "n_utterances": a.n_utterances, "seed": a.seed, "problems": rows,
           "total_seconds": {k: sum(r[k]["seconds"] for r in rows) for k in ("algorithm1", "carried")},
           "converged": {k: sum(r[k]["converged"] for r in rows) for k in ("algorithm1", "carried")},
           "command": "python benchmarks/analysis/map_start.py " + " ".join(argv if argv is not None else sys.argv[1:])}
    write_json(a.json, out)
    print(out["total_seconds"], out["converged"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
