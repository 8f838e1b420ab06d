"""Experiment (issue 9), v2 corpora, through the deena2010 protocol: the switching SGPDM on the
residual of a label/MFCC context ridge (4 Hz post-filter, band calibration as in evaluate).

A GP with explicit basis functions (Rasmussen & Williams 2006, §2.7): z_t = h(x_t)ᵀβ + f(latent)
with h the context features of bayes_talk.estimators.baselines.context. The ridge is fitted on the training
utterances; the SGPDM is trained on out-of-fold residuals (5-fold, grouped by utterance, so the
residuals have the size they will have on new audio); synthesis = ridge(test) + SGPDM(test).

Usage: python benchmarks/analysis/context_residual_protocol.py OUT.json [methods]
(reads data/v2/train250 and data/v2/heldout40; 55 min wall at load 7-9; results in
docs/results.md, "Experiment: the switching SGPDM on the residual of a label-context mean").
"""
import dataclasses
import json
import sys
import time

import numpy as np
from sklearn.model_selection import GroupKFold

from bayes_talk.estimators.baselines.context import ContextRidge
from bayes_talk.corpus import load_corpus
from bayes_talk.evaluation import systems
from bayes_talk.evaluation.harness import run_protocol
from bayes_talk.evaluation.protocols import get_protocol

out = sys.argv[1]
methods = sys.argv[2].split(",") if len(sys.argv) > 2 else ["ssgpdm-vlmm-posterior", "ssgpdm-vlmm-optimise"]
if __name__ == "__main__":
    t0 = time.time()
    tr = load_corpus("data/v2/train250", cmvn="mean")
    te = load_corpus("data/v2/heldout40", aam=tr.aam_path, cmvn="mean")
    train, test = list(tr.sequences), list(te.sequences)
    ridge = ContextRidge().fit(train)
    L, M = ridge.windows_
    print("ridge windows", L, M, time.time() - t0, flush=True)
    oof = [None] * len(train)
    for fit_idx, hold_idx in GroupKFold(5).split(np.arange(len(train)), groups=np.arange(len(train))):
        r = ContextRidge(label_window=L, mfcc_window=M).fit([train[i] for i in fit_idx])
        for i in hold_idx:
            oof[i] = r.predict(train[i])
    res_train = [dataclasses.replace(s, aam=s.aam - o) for s, o in zip(train, oof)]
    print("oof done; residual var / aam var", float(np.mean([((s.aam) ** 2).mean() for s in res_train]) /
          np.mean([(s.aam ** 2).mean() for s in train])), time.time() - t0, flush=True)
    base_predict = systems._predict

    def _predict(m, model, seq, cfg):
        p = base_predict(m, model, seq, cfg)
        if not m.family.startswith("ssgpdm-"):
            return p
        h = ridge.predict(seq)
        return systems.Prediction(p.mean + h, p.var, result=None if p.result is None else p.result.shift(h),
                                  raw=None if p.raw is None else p.raw.shift(h))
    systems._predict = _predict
    proto = get_protocol("deena2010", lowpass_hz=4.0)
    # the band calibration scores residual predictions against residual truths (consistent)
    res, _ = run_protocol(proto, res_train, methods, test_sequences=test)
    res["experiment"] = {"residual_of": "context-ridge", "windows": [L, M], "seconds": time.time() - t0}
    with open(out, "w") as f:
        json.dump(res, f, indent=1, default=str)
    for m in methods:
        r = res["methods"][m]
        print(m, {kk: r[kk]["mean"] for kk in r if isinstance(r[kk], dict) and "mean" in r[kk]}, flush=True)
    print("done", time.time() - t0)
