"""The context view's cross-validation: sklearn's ``cross_val_predict`` beside
``features.context_view.ridge_out_of_fold`` (issue 29).

On a built corpus, the context matrix of the default family (label window
``--label-window``, MFCC window 4) and the AAM parameters of every utterance; the
out-of-fold ridge predictions for the four penalties of ``context_view.ALPHAS`` over
the five utterance-grouped folds, (a) by four ``cross_val_predict(Ridge(alpha))`` calls
(what ``ContextView.fit`` ran before) and (b) by ``ridge_out_of_fold``; CPU seconds of
each on one BLAS thread, and the largest relative difference of the predictions.

Run:  PYTHONPATH=. .venv/bin/python benchmarks/context_view_fit.py data/s8/train250 \\
          [--out benchmarks/results/context_view_fit.json]
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"


def main(argv=None) -> int:
    from sklearn.linear_model import Ridge
    from sklearn.model_selection import GroupKFold, cross_val_predict
    from threadpoolctl import threadpool_limits

    from bayes_talk.corpus import load_corpus
    from bayes_talk.features import mfcc as _mf
    from bayes_talk.features.context_view import ALPHAS, ridge_out_of_fold
    from bayes_talk.features.context_window import ContextFeatures

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("corpus")
    ap.add_argument("--label-window", type=int, default=8, help="L (the default family's context_view)")
    ap.add_argument("--out", type=Path, default=RESULTS / "context_view_fit.json")
    args = ap.parse_args(argv)

    load0 = os.getloadavg()
    train = list(load_corpus(args.corpus, cmvn="mean", fmax=_mf.FMAX_HZ, floor_dbfs=_mf.FLOOR_DBFS).sequences)
    feats = ContextFeatures.fit(train, args.label_window, 4)
    X = np.vstack([feats.transform(s) for s in train])
    Z = np.vstack([s.aam for s in train])
    groups = np.concatenate([np.full(s.n_frames, i) for i, s in enumerate(train)])
    cv = GroupKFold(n_splits=5)
    with threadpool_limits(1):
        c = time.process_time()
        ref = [cross_val_predict(Ridge(alpha=a), X, Z, groups=groups, cv=cv) for a in ALPHAS]
        t_ref = time.process_time() - c
        c = time.process_time()
        new = ridge_out_of_fold(X, Z, [t for _, t in cv.split(X, Z, groups)], ALPHAS)
        t_new = time.process_time() - c
    out = {
        "benchmark": "context_view_fit", "issue": 29, "corpus": os.path.relpath(args.corpus, Path.cwd()),
        "X_shape": list(X.shape), "Z_shape": list(Z.shape), "alphas": list(ALPHAS), "folds": 5, "blas_threads": 1,
        "cpu_s": {"cross_val_predict": round(t_ref, 3), "ridge_out_of_fold": round(t_new, 3)},
        "ratio": round(t_new / t_ref, 3),
        "max_rel_diff": {str(a): float(np.abs(r - n).max() / np.abs(r).max()) for a, r, n in zip(ALPHAS, ref, new)},
        "loadavg_before": load0, "loadavg_after": os.getloadavg(),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_suffix(".tmp")
    tmp.write_text(json.dumps(out, indent=1))
    tmp.replace(args.out)
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
