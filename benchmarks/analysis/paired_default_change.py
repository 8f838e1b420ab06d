"""Paired per-utterance comparison of two runs of heldout_default_model.py (docs/results.md
"Audio context in the default model"): AMSE and ACC of ``ssgpdm-phone-rc-posterior`` per held-out
utterance in A_PREFIX.npz and B_PREFIX.npz (same truth), the mean difference B - A with its
standard error, and on how many utterances B is better.

Usage: python benchmarks/analysis/paired_default_change.py A_PREFIX B_PREFIX"""
import sys

import numpy as np

from bayes_talk.evaluation.metrics import acc, amse

a, b = np.load(sys.argv[1] + ".npz"), np.load(sys.argv[2] + ".npz")
m = "ssgpdm-phone-rc-posterior"
utts = sorted({k.split("|")[1] for k in a if k.startswith(m)})
da, db, ca, cb = [], [], [], []
for u in utts:
    t = a[f"{m}|{u}|truth"]; assert np.array_equal(t, b[f"{m}|{u}|truth"])
    pa, pb = a[f"{m}|{u}|mean"], b[f"{m}|{u}|mean"]
    da.append(amse([t], [pa])); db.append(amse([t], [pb]))
    ca.append(acc([t], [pa])); cb.append(acc([t], [pb]))
da, db, ca, cb = map(np.array, (da, db, ca, cb))
d, c = db - da, cb - ca
n = len(utts)
print(f"n {n} AMSE A {da.mean():.3f} B {db.mean():.3f}")
print(f"paired AMSE diff mean {d.mean():.3f} se {d.std(ddof=1) / np.sqrt(n):.3f}, B better on {np.sum(d < 0)}/{n}")
print(f"paired ACC diff mean {c.mean():.4f} se {c.std(ddof=1) / np.sqrt(n):.4f}, B better on {np.sum(c > 0)}/{n}")
