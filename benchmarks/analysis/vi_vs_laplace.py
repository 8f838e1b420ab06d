"""VI against Laplace on held-out utterances: does the ELBO's Gaussian give better bands?
(docs/results.md, "VI: a Gaussian that fits better than Laplace, and still k̂ ≫ 0.7".)

For each held-out utterance, the whole-utterance posterior by ``laplace`` and by ``vi``
(library defaults, 64 draws, seed 0, the same joint MAP): raw bands (no band calibration:
it is fitted for Laplace), coverage of the central 50 / 90 % bands pooled over every
(frame, parameter) entry, AMSE of the posterior mean (no post-filter), PSIS k̂ and ESS, the
ELBO's rise from the Laplace start, and the seconds. Writes OUT (JSON).

Usage: python benchmarks/analysis/vi_vs_laplace.py MODEL_DIR TRAIN_CORPUS TEST_CORPUS OUT [N]
"""
import json
import sys
import time

import numpy as np

from bayes_talk.corpus import load_corpus
from bayes_talk.evaluation.metrics import amse, coverage
from bayes_talk.base.files import write_json
from bayes_talk.gp.threads import torch_threads
from bayes_talk.pipeline import load_trained
from bayes_talk.posterior.sampling import sample_synthesis

mdir, train_dir, test_dir, out_path = sys.argv[1:5]
n = int(sys.argv[5]) if len(sys.argv) > 5 else 8
model = load_trained(mdir).uncalibrated
test = list(load_corpus(test_dir, aam=load_corpus(train_dir).aam_path).sequences)[:n]
methods = ("laplace", "vi")
got = {m: {"mean": [], "lo50": [], "hi50": [], "lo90": [], "hi90": [], "khat": [], "psis_ess": [], "seconds": []}
       for m in methods}
rows = []
truth = []
t0 = time.time()
with torch_threads(1):
    for s in test:
        truth.append(s.aam)
        row = {"utt": s.name, "frames": s.n_frames}
        for m in methods:
            r = sample_synthesis(model, s.mfcc, s.labels, method=m, seed=0, log_warnings=False)
            g = got[m]
            g["mean"].append(r.mean)
            (lo50, hi50), (lo90, hi90) = r.interval(0.5), r.interval(0.9)
            g["lo50"].append(lo50), g["hi50"].append(hi50), g["lo90"].append(lo90), g["hi90"].append(hi90)
            d = r.diagnostics
            g["khat"].append(d["khat"]), g["psis_ess"].append(d["psis_ess"]), g["seconds"].append(r.seconds)
            row[m] = {"khat": d["khat"], "psis_ess": d["psis_ess"], "seconds": r.seconds,
                      "elbo_start": d.get("vi_elbo_start"), "elbo_end": d.get("vi_elbo_end")}
        rows.append(row)
        print(s.name, {m: round(row[m]["khat"], 2) for m in methods}, round(time.time() - t0), flush=True)
out = {"command": " ".join(sys.argv), "n": len(test), "frames": int(sum(s.n_frames for s in test)),
       "seconds": time.time() - t0, "utterances": rows}
for m in methods:
    g = got[m]
    out[m] = {"amse": amse(truth, g["mean"]), "cov50": coverage(truth, g["lo50"], g["hi50"]),
              "cov90": coverage(truth, g["lo90"], g["hi90"]), "khat_median": float(np.median(g["khat"])),
              "khat_max": float(np.max(g["khat"])), "psis_ess_median": float(np.median(g["psis_ess"])),
              "seconds_per_frame": float(np.sum(g["seconds"]) / out["frames"])}
out["vi_elbo_gain_median"] = float(np.median([r["vi"]["elbo_end"] - r["vi"]["elbo_start"] for r in rows]))
write_json(out_path, out)
print(json.dumps({k: out[k] for k in (*methods, "vi_elbo_gain_median", "n", "seconds")}, indent=1))
