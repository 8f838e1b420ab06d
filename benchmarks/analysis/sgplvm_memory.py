"""Profile (issue 14, memory): where the deena2009 protocol's peak RSS goes.

One deena2009 split's SGPLVM at the protocol's size (50 random training utterances of the
corpus, the 1500-frame cap, d = 8), then SGPLVM B (HMM/Viterbi initialiser) on 3 test
utterances, repeated ``REPEATS`` times on fresh random splits; prints this process's
current RSS and its peak (``ru_maxrss``) after each fit and each synthesis. ``MAX_ITER``
caps the training iterations (the peak depends on N, not on the iteration count).

Found with it: the HMM initialiser's transition table evaluated the dynamics predictive
at all M² = 90,000 (source, target) pairs of its M = 300 states, i.e. a 90,000 x 1,500
cross-kernel and its solves: the peak went from ~1.2 GB (the fit) to 4.0 GB at the first
synthesis. Now it evaluates the predictive at the M states once (docs/scaling.md).

    PYTHONPATH=. python benchmarks/analysis/sgplvm_memory.py MAX_ITER REPEATS [CORPUS]
"""
from __future__ import annotations

import os
import resource
import sys
import time

import numpy as np

from bayes_talk.corpus import load_corpus
from bayes_talk.evaluation.systems import SystemConfig, fit_family, predict


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def main() -> None:
    max_iter, repeats = int(sys.argv[1]), int(sys.argv[2])
    corpus = sys.argv[3] if len(sys.argv) > 3 else "data/v2/train250"
    seqs = load_corpus(corpus).sequences
    cfg = SystemConfig(latent_dim=8, sgplvm_max_iter=max_iter, sgplvm_synth_max_iter=20)
    t0 = time.time()
    print(f"corpus loaded: rss {_rss_mb():.0f} MB, peak {_peak_mb():.0f} MB", flush=True)
    for r in range(repeats):
        idx = np.random.default_rng([0, r]).permutation(len(seqs))
        train, test = [seqs[i] for i in idx[:50]], [seqs[i] for i in idx[50:53]]
        model = fit_family("sgplvm", train, cfg)
        print(f"{time.time() - t0:6.1f}s repeat {r} fit: rss {_rss_mb():.0f} MB, peak {_peak_mb():.0f} MB",
              flush=True)
        for s in test:
            predict("sgplvm-b", model, s, cfg)
        print(f"{time.time() - t0:6.1f}s repeat {r} synthesis (SGPLVM B): rss {_rss_mb():.0f} MB, "
              f"peak {_peak_mb():.0f} MB", flush=True)
        del model


if __name__ == "__main__":
    main()
