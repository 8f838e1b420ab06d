"""Experiment (issue 9, part 5): give the switching SGPDM's audio view a context window of MFCCs.

Run before ``SwitchingConfig.audio_context`` existed: it splices the MFCCs itself and
trains with the library's k = 0 (the transform is the same as
:mod:`bayes_talk.features.audio_context`, which now does this inside the model).

    .venv/bin/python benchmarks/analysis/audio_context.py K OUT.json

Each frame's audio features become the MFCCs of frames t-k..t+k (edge-padded), projected by a
PCA fitted on the training frames to the original dimension (so only the information changes,
not the size of the audio view). Scored on the held-out sentences with deena2010 settings and
the 4 Hz post-filter, to compare with docs/results.md's row (posterior 8.343 / 0.351 / 0.881).
"""
import dataclasses
import json
import sys
import time

import numpy as np

from bayes_talk.corpus import load_corpus
from bayes_talk.evaluation.harness import run_protocol
from bayes_talk.evaluation.protocols import get_protocol

k = int(sys.argv[1]); out = sys.argv[2]
methods = sys.argv[3].split(",") if len(sys.argv) > 3 else ["ssgpdm-vlmm-posterior"]
tr = load_corpus("data/v2/train250", cmvn="mean")
te = load_corpus("data/v2/heldout40", aam=tr.aam_path, cmvn="mean")

def stack(m):
    T = len(m); idx = np.clip(np.arange(T)[:, None] + np.arange(-k, k + 1)[None, :], 0, T - 1)
    return m[idx].reshape(T, -1)

D = tr.sequences[0].mfcc.shape[1]
S = np.vstack([stack(s.mfcc) for s in tr.sequences]); mu = S.mean(0)
U, sv, Vt = np.linalg.svd(S - mu, full_matrices=False); P = Vt[:D].T
print("PCA kept variance", float((sv[:D] ** 2).sum() / (sv ** 2).sum()), flush=True)
def tf(s):
    return dataclasses.replace(s, mfcc=(stack(s.mfcc) - mu) @ P) if k > 0 else s
train = [tf(s) for s in tr.sequences]; test = [tf(s) for s in te.sequences]
proto = get_protocol("deena2010", lowpass_hz=4.0)
t0 = time.time()
res, _ = run_protocol(proto, train, methods, test_sequences=test)
res["experiment"] = {"audio_context": k, "seconds": time.time() - t0}
with open(out, "w") as f:
    json.dump(res, f, indent=1, default=str)
for m in methods:
    r = res["methods"][m]
    print(m, r["headline"], {kk: r[kk]["mean"] for kk in r if isinstance(r[kk], dict) and "mean" in r[kk]}, flush=True)
print("done", time.time() - t0)
