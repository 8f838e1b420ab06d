"""The held-out figures of the default model (docs/results.md, "Right-context states with
the mean shrinkage: the new default"): deena2010 settings, 4 Hz post-filter, band
calibration on 20 % of the training utterances (stages 0-2), trained on
data/v2/train250, scored on data/v2/heldout40 (our own sentences) in the
training AAM; writes OUT_PREFIX.json (the evaluate result) and OUT_PREFIX.npz (every
prediction with its truth).

Usage: python benchmarks/analysis/heldout_default_model.py OUT_PREFIX METHODS [AUDIO_CONTEXT]
(AUDIO_CONTEXT given: every ssgpdm-* family is trained with it; omitted: each family's own.)
e.g. ... /tmp/final ssgpdm-phone-rc-posterior,ssgpdm-phone-rc-optimise,hmm-mean,voice-puppetry,zero
(22 min wall at load 3-5)."""
import json
import sys
import time

import numpy as np
from audio_context_patch import use_audio_context

from bayes_talk.corpus import load_corpus
from bayes_talk.evaluation import harness
from bayes_talk.evaluation.harness import run_protocol
from bayes_talk.evaluation.protocols import get_protocol

REC = {}
_pred0 = harness.predict
def predict(name, model, seq, cfg):
    p = _pred0(name, model, seq, cfg)
    REC[(name, seq.name)] = (np.asarray(p.mean), seq.aam.copy(), None if p.raw is None else np.asarray(p.raw.mean))
    return p
harness.predict = predict
# AUDIO_CONTEXT: every ssgpdm-* family trained with this audio context (0: none); omitted,
# each family keeps its own (the default family ssgpdm-phone-rc: 2, registry.FAMILY_DEFAULTS)
K = int(sys.argv[3]) if len(sys.argv) > 3 else None
if K is not None:
    use_audio_context(K)
out = sys.argv[1]; methods = sys.argv[2].split(",")
t0 = time.time()
tr = load_corpus("data/v2/train250", cmvn="mean")
te = load_corpus("data/v2/heldout40", aam=tr.aam_path, cmvn="mean")
proto = get_protocol("deena2010", lowpass_hz=4.0)
res, _ = run_protocol(proto, list(tr.sequences), methods, test_sequences=list(te.sequences))
res["experiment"] = {"audio_context": K, "seconds": time.time() - t0}
with open(out + ".json", "w") as f:
    json.dump(res, f, indent=1, default=str)
arrs = {}
for (m, u), (mu, z, raw) in REC.items():
    arrs[f"{m}|{u}|mean"] = mu; arrs[f"{m}|{u}|truth"] = z
    if raw is not None: arrs[f"{m}|{u}|rawmean"] = raw
np.savez_compressed(out + ".npz", **arrs)
for m in methods:
    r = res["methods"][m]
    print(m, {k: r[k]["mean"] for k in ("mse", "corr", "nmse", "coverage_50", "coverage_90") if isinstance(r.get(k), dict)},
          {k: r.get(k) for k in ("gain_amse", "gain_nmse")}, flush=True)
    for bc in r.get("band_calibration", []):
        print("mean_scale", np.round(bc.get("mean_scale") or [], 2))
print("done", time.time() - t0)
