"""Does the highest mode of the whole-utterance posterior predict better than the first one
found (the mode in the basin of deena2010's Algorithm 1 path)? (docs/results.md, "The highest
posterior mode does not predict better".)

For each held-out utterance: the Laplace posterior summary (64 draws, seed 0) at the first
joint MAP (``map_restarts=0``, the default) and at the best of the restarts from Laplace draws
(``map_restarts=6``, up to 3 rounds, as NUTS and emcee use); means post-filtered at 4 Hz; AMSE,
ACC and NMSE (variance of the pooled test frames) of each against the truth in the training
AAM. No band calibration (it is the same map for both). Writes OUT (JSON).

Usage: python benchmarks/analysis/posterior_modes.py MODEL_DIR TRAIN_CORPUS TEST_CORPUS OUT [N]
e.g. ... /tmp/m250 data/v2/train250 data/v2/heldout40 benchmarks/results/posterior_modes.json
(33 min wall for 40 utterances at load 4-5)."""
import json
import sys
import time

import numpy as np

from bayes_talk.corpus import load_corpus
from bayes_talk.evaluation.metrics import acc, amse, normalised_mse
from bayes_talk.base.files import write_json
from bayes_talk.gp.threads import torch_threads
from bayes_talk.pipeline import load_trained
from bayes_talk.posterior.sampling import sample_synthesis
from bayes_talk.synthesis.sequential import lowpass

mdir, train_dir, test_dir, out_path = sys.argv[1:5]
n = int(sys.argv[5]) if len(sys.argv) > 5 else 40
model = load_trained(mdir).uncalibrated
test = list(load_corpus(test_dir, aam=load_corpus(train_dir).aam_path).sequences)[:n]
preds: dict[str, list[np.ndarray]] = {"first": [], "best": []}
truth, info = [], []
t0 = time.time()
with torch_threads(1):
    for s in test:
        r0 = sample_synthesis(model, s.mfcc, s.labels, method="laplace", seed=0, log_warnings=False)
        r1 = sample_synthesis(model, s.mfcc, s.labels, method="laplace", seed=0, map_restarts=6, log_warnings=False)
        preds["first"].append(lowpass(r0.mean, 4.0))
        preds["best"].append(lowpass(r1.mean, 4.0))
        truth.append(s.aam)
        info.append({"utt": s.name, "lp_first": r0.diagnostics["map_log_density"],
                     "lp_best": r1.diagnostics["map_log_density"]})
        print(s.name, round(info[-1]["lp_best"] - info[-1]["lp_first"], 2), round(time.time() - t0), flush=True)
var = np.var(np.vstack(truth), axis=0)
out = {"command": " ".join(sys.argv), "n": len(test), "seconds": time.time() - t0, "utterances": info,
       "n_higher_mode": sum(i["lp_best"] > i["lp_first"] + 1e-6 for i in info)}
for k, p in preds.items():
    out[k] = {"amse": amse(truth, p), "acc": acc(truth, p), "nmse": float(np.mean(normalised_mse(truth, p, var)))}
write_json(out_path, out)
print(json.dumps({k: out[k] for k in ("first", "best", "n", "n_higher_mode", "seconds")}, indent=1))
