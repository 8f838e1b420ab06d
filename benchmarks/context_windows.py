"""Benchmark: the context-window regressions of issue #15, window by window, side by side.

Trains on ``--corpus`` and scores on ``--test-corpus`` (its frames projected through the
training corpus's AAM, as ``evaluate --test-corpus`` does) with the project's metric
functions: AMSE (mean over utterances of the MSE), ACC (mean Pearson), NMSE (MSE over
the variance of the pooled test frames, mean over utterances) and the coverage of the
central 90 % Gaussian band. Rows (the issue's table):

* zero (each utterance's mean: the AAM features are mean-removed per utterance);
* hmm-mean (per-phone mean face), the peer the issue compares with;
* context-ridge with the windows its grouped CV picks (the default);
* context-ridge on labels t-4..t+4; on labels t-8..t+8 + MFCCs t-4..t+4; on MFCCs t-4..t+4;
* context-mlp (default: the ridge's CV windows).

Writes ``benchmarks/results/context_windows.json`` (or ``--out``): per row the metrics,
the windows, the fit wall and CPU time (one BLAS thread), and the load average at start
and end.

    .venv/bin/python benchmarks/context_windows.py --corpus data/v1/train250 \\
        --test-corpus data/v1/heldout40
"""
from __future__ import annotations

import argparse
import os
import time
import warnings
from pathlib import Path

import numpy as np
import scipy.stats

from bayes_talk.estimators.baselines import ContextMLP, ContextRidge, HMMMean
from bayes_talk.corpus import load_corpus
from bayes_talk.evaluation import metrics as M
from bayes_talk.base.files import write_json

ROWS = [
    ("context-ridge (CV windows)", ContextRidge, {}),
    ("context-ridge labels t-4..t+4", ContextRidge, {"label_window": 4, "mfcc_window": None}),
    ("context-ridge labels t-8..t+8 + MFCC t-4..t+4", ContextRidge, {"label_window": 8, "mfcc_window": 4}),
    ("context-ridge MFCC t-4..t+4", ContextRidge, {"label_window": None, "mfcc_window": 4}),
    ("context-mlp (CV windows)", ContextMLP, {"seed": 0}),
]


def score(truth: list[np.ndarray], pred: list[np.ndarray], var: list[np.ndarray] | None) -> dict:
    v = np.concatenate(truth).var(axis=0)
    with warnings.catch_warnings():   # the zero row has no usable dimension for ACC
        warnings.simplefilter("ignore", RuntimeWarning)
        corr = M.acc(truth, pred)
    out = {"amse": M.amse(truth, pred), "acc": corr if np.isfinite(corr) else None,
           "nmse": float(np.mean(M.normalised_mse(truth, pred, variance=v)))}
    if var is not None:
        z = scipy.stats.norm.ppf(0.95)
        sd = [np.sqrt(x) for x in var]
        out["coverage_90"] = M.coverage(truth, [p - z * s for p, s in zip(pred, sd, strict=True)],
                                        [p + z * s for p, s in zip(pred, sd, strict=True)])
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--corpus", required=True)
    ap.add_argument("--test-corpus", required=True)
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "context_windows.json"))
    args = ap.parse_args()
    load_start = [round(x, 2) for x in os.getloadavg()]
    train_c = load_corpus(args.corpus)
    test_c = load_corpus(args.test_corpus, aam=train_c.aam_path)
    train, test = list(train_c.sequences), list(test_c.sequences)
    truth = [s.aam for s in test]
    rows: dict[str, dict] = {"zero (each utterance's mean)": score(truth, [np.zeros_like(z) for z in truth], None)}
    t0 = time.perf_counter()
    hm = HMMMean().fit(train)
    rows["hmm-mean (per-phone mean)"] = {**score(truth, [hm.predict(s) for s in test], None),
                                         "fit_seconds": time.perf_counter() - t0}
    for label, cls, kw in ROWS:
        t0, c0 = time.perf_counter(), time.process_time()
        m = cls(**kw).fit(train)
        fit_s, fit_cpu = time.perf_counter() - t0, time.process_time() - c0
        r = score(truth, [m.predict(s) for s in test], [m.predict_var(s) for s in test])
        rows[label] = {**r, "windows": list(m.windows_), "fit_seconds": fit_s, "fit_cpu_seconds": fit_cpu}
        print(f"{label:<48} AMSE {r['amse']:.3f} ACC {r['acc']:.3f} NMSE {r['nmse']:.3f} "
              f"cov90 {r['coverage_90']:.3f} windows {m.windows_} fit {fit_s:.1f} s ({fit_cpu:.1f} s CPU)",
              flush=True)
    result = {"corpus": str(Path(args.corpus).resolve()), "test_corpus": str(Path(args.test_corpus).resolve()),
              "n_train": len(train), "n_test": len(test), "n_train_frames": int(sum(s.n_frames for s in train)),
              "rows": rows, "load_average_start": load_start,
              "load_average_end": [round(x, 2) for x in os.getloadavg()]}
    write_json(args.out, result)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
