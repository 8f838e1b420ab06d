"""Experiment (issue #9, part 5): the switching SGPDM on the residual of a label-context ridge.

A GP with explicit basis functions (Rasmussen & Williams 2006, §2.7): the visual mean is
the context ridge (labels t−8..t+8 + MFCCs t−4..t+4, picked by grouped CV), and the
switching SGPDM models what is left (trained on 5-fold cross-fitted residuals of the
training utterances). Scored on our 40 held-out sentences against the ridge alone.
Result (docs/results.md): the SGPDM residual makes every metric worse.

    .venv/bin/python benchmarks/analysis/context_residual.py TRAIN_CORPUS HELDOUT_CORPUS
"""
import dataclasses
import sys
import time

import numpy as np
from sklearn.model_selection import GroupKFold

from bayes_talk.estimators.baselines.context import ContextRidge
from bayes_talk.corpus import load_corpus
from bayes_talk.estimators.switching import SwitchingSGPDM
from bayes_talk.evaluation import metrics as M
from bayes_talk.gp.threads import torch_threads
from bayes_talk.posterior.sampling import sample_synthesis

tr = load_corpus(sys.argv[1]); te = load_corpus(sys.argv[2], aam=tr.aam_path)
train = tr.sequences
t0 = time.time()
cr = ContextRidge().fit(train)
L, Mw = cr.windows_
print('ridge windows', cr.windows_, time.time()-t0, flush=True)
res = [None]*len(train)
for a, b in GroupKFold(5).split(np.arange(len(train)), groups=np.arange(len(train))):
    f = ContextRidge(label_window=L, mfcc_window=Mw).fit([train[i] for i in a])
    for i in b: res[i] = dataclasses.replace(train[i], aam=train[i].aam - f.predict(train[i]))
print('cross-fitted', time.time()-t0, flush=True)
with torch_threads(1):
    m = SwitchingSGPDM(states='vlmm', seed=0).fit(res)
print('trained', time.time()-t0, flush=True)
truth = [s.aam for s in te]; var = np.vstack(truth).var(0)
def score(name, preds):
    print(f"{name:28s} AMSE {M.amse(truth, preds):.3f} ACC {M.acc(truth, preds):.3f} NMSE {np.mean(M.normalised_mse(truth, preds, var)):.3f}", flush=True)
ridge = [cr.predict(s) for s in te]
score('ridge', ridge)
with torch_threads(1):
    a1 = [m.synthesize(s.mfcc, s.labels).mean for s in te]
    score('ridge + A1 resid', [r + a for r, a in zip(ridge, a1)])
    lap = [sample_synthesis(m, s.mfcc, s.labels, method='laplace').mean for s in te]
    score('ridge + laplace resid', [r + a for r, a in zip(ridge, lap)])
print('done', time.time()-t0)
