"""What the band calibration's budget costs in training time and buys in calibration.

``bayes-talk train`` spends most of its time on the band calibration: a second fit of the
state models (``--calibrated-model refit``) and the posterior synthesis of the held-out
training utterances (``--calibrate-bands FRACTION``, 20 % by default). This script trains
the same family under several calibration budgets, one after another on the same machine,
and scores each model on a *test corpus* of sentences it never saw, the way a user's
recordings arrive:

* per configuration: ``bayes-talk train`` wall and CPU time (the train process and its
  workers, ``os.getloadavg()`` around it), then the calibrated posterior (``--posterior``,
  the calibrated method, Laplace by default) of every test utterance through
  ``TrainedModel.model.predict_dist`` in ``--workers`` spawned processes;
* scores over the test utterances (:func:`bayes_talk.evaluation.calibration.summarise_calibration`):
  pooled 50 % / 90 % coverage, NLPD and CRPS per entry, the fraction of AAM parameters
  whose 90 % coverage lies in 0.85-0.95, and AMSE of the mean (deena2010 §5);
* paired against the first configuration (the reference, the default budget): the
  difference of NLPD and CRPS per entry with its cluster-robust standard error over
  utterances (:func:`bayes_talk.evaluation.calibration.ratio_se`), since every model is
  scored on the same utterances.

    PYTHONPATH=. .venv/bin/python benchmarks/calibration_budget.py data/train250 --test data/dev40 \\
        --configs refit:0.2,holdout:0.1,holdout:0.05,refit:0.05 \\
        --out benchmarks/results/calibration_budget.json
    PYTHONPATH=. .venv/bin/python benchmarks/calibration_budget.py --quick   # the quick corpora -> results/quick/

A configuration is ``SCHEME:FRACTION`` (``train --calibrated-model SCHEME --calibrate-bands
FRACTION``). The test utterances' AAM parameters are projected on the trained model's AAM
(as ``evaluate --test-corpus`` does). Paths in the JSON are relative to the repository.
"""
from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import resource
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from bayes_talk.evaluation.calibration import ratio_se, score_utterance, summarise_calibration
from bayes_talk.evaluation.metrics import amse
from benchmarks.common import QUICK_MODEL, bench_corpus, result_path, write_result
from benchmarks.train_speed import run_train

_LOADED: dict = {}


def _score_one(job: tuple[str, str, str, str]) -> dict:
    """The calibrated posterior of one test utterance and its scores (runs in a worker)."""
    from bayes_talk.corpus import load_corpus
    from bayes_talk.pipeline import corpus_front_end, load_trained

    model_dir, test, name, posterior = job
    if (model_dir, test) not in _LOADED:
        _LOADED.clear()
        tm = load_trained(model_dir)
        _LOADED[(model_dir, test)] = (tm.model, {u.name: u for u in load_corpus(test, aam=Path(model_dir) / "aam.npz",
                                                                                **corpus_front_end(tm.audio))})
    model, utts = _LOADED[(model_dir, test)]
    u = utts[name]
    r = model.predict_dist(u, posterior=posterior)
    return {"name": name, "score": score_utterance(r, u.aam), "mean": r.mean, "truth": u.aam}


def score_model(model_dir: Path, test: str, names: list[str], posterior: str, workers: int) -> dict:
    """Scores of the calibrated posterior of ``model_dir`` on the utterances ``names`` of ``test``."""
    jobs = [(str(model_dir), test, n, posterior) for n in names]
    t0 = time.perf_counter()
    with ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn")) as ex:
        out = list(ex.map(_score_one, jobs))
    scores = [o["score"] for o in out]
    summary = summarise_calibration(scores)
    return {"summary": {"coverage_90": summary["coverage"]["0.9"]["pooled"],
                        "coverage_50": summary["coverage"]["0.5"]["pooled"],
                        "nlpd": summary["nlpd"], "crps": summary["crps"],
                        "params_in_range_90": summary["params_in_range_90"],
                        "amse": amse([o["truth"] for o in out], [o["mean"] for o in out])},
            "per_utterance": {"name": [o["name"] for o in out],
                              "entries": [int(s.n_frames * s.nlpd.size) for s in scores],
                              "nlpd": [float(s.nlpd.sum()) for s in scores],
                              "crps": [float(s.crps.sum()) for s in scores]},
            "score_wall_s": round(time.perf_counter() - t0, 1)}


def paired(a: dict, ref: dict) -> dict:
    """NLPD and CRPS per entry of ``a`` minus those of ``ref`` (same utterances), with SEs."""
    if a["per_utterance"]["name"] != ref["per_utterance"]["name"]:
        raise ValueError("paired: the two configurations were scored on different utterances")
    e = np.asarray(ref["per_utterance"]["entries"], np.float64)
    out = {}
    for key in ("nlpd", "crps"):
        d = np.asarray(a["per_utterance"][key]) - np.asarray(ref["per_utterance"][key])
        r, se = ratio_se(d, e)
        out[key] = {"diff": r, "se": se}
    return out


def parse_configs(text: str) -> list[tuple[str, float]]:
    """``refit:0.2,holdout:0.05`` → [("refit", 0.2), ("holdout", 0.05)], checked."""
    out = []
    for part in text.split(","):
        scheme, _, frac = part.strip().partition(":")
        if scheme not in ("refit", "holdout", "cv") or not frac:
            raise SystemExit(f"--configs: {part!r} is not SCHEME:FRACTION with SCHEME refit, holdout or cv")
        f = float(frac)
        if not 0.0 < f < 1.0:
            raise SystemExit(f"--configs: fraction {f} in {part!r} is not in (0, 1)")
        out.append((scheme, f))
    return out


def _train_quick(corpus: str, out: Path, scheme: str, frac: float, kind: str | None) -> dict:
    """Quick mode: ``pipeline.train`` in this process with the quick mode's small settings."""
    from bayes_talk import pipeline

    load0, c0, t0 = os.getloadavg(), resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
    pipeline.train(corpus, kind or pipeline.DEFAULT_MODEL, out, workers=1, calibrate_bands=frac,
                   calibrated_model=scheme, **QUICK_MODEL)
    c1 = resource.getrusage(resource.RUSAGE_SELF)
    return {"wall_s": round(time.perf_counter() - t0, 2),
            "cpu_s": round((c1.ru_utime + c1.ru_stime) - (c0.ru_utime + c0.ru_stime), 2),
            "loadavg_before": [round(x, 2) for x in load0], "loadavg_after": [round(x, 2) for x in os.getloadavg()]}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("corpus", nargs="?", default=None, help="training corpus")
    ap.add_argument("--test", default=None, help="test corpus (sentences not in the training corpus)")
    ap.add_argument("--configs", default="refit:0.2,holdout:0.05", help="SCHEME:FRACTION,...; the first is "
                    "the reference the others are paired against")
    ap.add_argument("--model", default=None, help="train --model (default: train's default family)")
    ap.add_argument("--posterior", default="laplace", help="the calibrated posterior method")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--quick", action="store_true", help="the quick corpora; small models trained in this process")
    ap.add_argument("--out", default=None, help="default benchmarks/results/calibration_budget.json (--quick: results/quick/)")
    args = ap.parse_args(argv)
    args.out = result_path("calibration_budget", args.quick, args.out)
    args.corpus = args.corpus or str(bench_corpus("train", args.quick))
    args.test = args.test or str(bench_corpus("test", args.quick))
    if args.quick:
        args.configs = "refit:0.2,holdout:0.2"
    configs = parse_configs(args.configs)
    from bayes_talk.corpus import load_corpus

    names = [u.name for u in load_corpus(args.test)]
    corpus = str(Path(args.corpus).resolve())
    extra = ["--model", args.model] if args.model else []
    runs = []
    with tempfile.TemporaryDirectory(prefix="calibration_budget_") as tmp:
        for i, (scheme, frac) in enumerate(configs):
            out = Path(tmp) / f"model_{i}"
            cfg = ["--calibrated-model", scheme, "--calibrate-bands", str(frac), "--workers", str(args.workers)]
            timing = (_train_quick(corpus, out, scheme, frac, args.model) if args.quick
                      else run_train(ROOT, corpus, out, extra + cfg, {}))
            scores = score_model(out, str(Path(args.test).resolve()), names, args.posterior, args.workers)
            run = {"scheme": scheme, "fraction": frac, "train": timing, **scores}
            if runs:
                run["vs_reference"] = paired(run, runs[0])
            runs.append(run)
            s = run["summary"]
            print(f"{scheme}:{frac} train {timing['wall_s']} s; cov90 {s['coverage_90']:.3f} nlpd "
                  f"{s['nlpd']['mean']:.4f} crps {s['crps']['mean']:.4f} amse {s['amse']:.3f}"
                  + (f"; vs reference nlpd {run['vs_reference']['nlpd']['diff']:+.4f}"
                     f"±{run['vs_reference']['nlpd']['se']:.4f}" if "vs_reference" in run else ""), flush=True)
    result = {"quick_model_settings": QUICK_MODEL if args.quick else None,
              "corpus": os.path.relpath(corpus, ROOT), "test": os.path.relpath(Path(args.test).resolve(), ROOT),
              "model": args.model or "default", "posterior": args.posterior, "workers": args.workers,
              "runs": runs}
    write_result(args.out, result)
    return result


if __name__ == "__main__":
    from bayes_talk.base.executor import interruptible

    # `kill` stops the worker processes too, not only this one
    interruptible(main)
