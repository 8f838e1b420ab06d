"""Experiment (issue 9, part 5): right-context (anticipatory) switching states.

State of a run of phone p followed by phone q: (">q", p); its model is trained on the runs of p
followed by q, and a pair with too few frames backs off (SwitchingModel.model_for drops the first
element) to the phone's own model (p,), trained on every run of p. Synthesis is offline, so the
next phone is known. deena2010 settings, 4 Hz post-filter, no band calibration (time).

Usage: python benchmarks/analysis/right_context_states.py OUT.json [AUDIO_CONTEXT]
(reads data/v2/train250 and data/v2/heldout40; 24 min wall at load 3-6; the states
replace the phone states of the ``ssgpdm-phone`` family for this process only; results in
docs/results.md, "Experiment: right-context (anticipatory) switching states").
"""
import json
import sys
import time

from audio_context_patch import use_audio_context

import bayes_talk.models.switching as sw
from bayes_talk.corpus import load_corpus
from bayes_talk.evaluation.harness import run_protocol
from bayes_talk.evaluation.protocols import get_protocol
from bayes_talk.models.vlmm import Segment


class RightPhoneStates(sw.PhoneStates):
    def segment(self, labels, unknown="error"):
        runs = super().segment(labels, unknown)
        out = []
        for j, r in enumerate(runs):
            nxt = runs[j + 1].state[0] if j + 1 < len(runs) else "sil"
            out.append(Segment((">" + nxt, r.state[0]), r.start, r.stop))
        return out

    def training_subsequences(self, labels, unknown="error"):
        segs = self.segment(labels, unknown)
        return segs + [Segment(s.state[1:], s.start, s.stop) for s in segs]

    def to_dict(self):
        return {"kind": "phone-right", "alphabet": self.alphabet_}


sw.PhoneStates = RightPhoneStates
K = int(sys.argv[2]) if len(sys.argv) > 2 else 0   # audio context half-width (SwitchingConfig.audio_context)
use_audio_context(K)
if __name__ == "__main__":
    out = sys.argv[1]
    methods = ["ssgpdm-phone-posterior", "ssgpdm-phone-optimise"]
    t0 = time.time()
    tr = load_corpus("data/v2/train250", cmvn="mean")
    te = load_corpus("data/v2/heldout40", aam=tr.aam_path, cmvn="mean")
    proto = get_protocol("deena2010", lowpass_hz=4.0, band_calibration=None)
    res, _ = run_protocol(proto, list(tr.sequences), methods, test_sequences=list(te.sequences))
    res["experiment"] = {"states": "right-context phone pairs", "audio_context": K, "seconds": time.time() - t0}
    with open(out, "w") as f:
        json.dump(res, f, indent=1, default=str)
    for m in methods:
        r = res["methods"][m]
        print(m, {k: r[k]["mean"] for k in ("mse", "corr", "nmse", "coverage_50", "coverage_90")
                  if isinstance(r.get(k), dict)}, flush=True)
    print("done", time.time() - t0)
