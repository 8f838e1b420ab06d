"""Per-frame error of Algorithms 1 and 2 split by position in the segment (first frame vs
the rest), VLMM vs phone states, on the deena2010 split of a built corpus (>= 278
utterances, e.g. from ``benchmarks/switching.py --keep-corpus DIR``). Prints a table; it
explains why phone states win under sequential prediction (docs/results.md).

    .venv/bin/python benchmarks/analysis/prediction_by_position.py CORPUS_DIR
"""
import sys

import numpy as np

from bayes_talk.corpus import load_corpus
from bayes_talk.estimators.switching import SwitchingSGPDM
from bayes_talk.evaluation.protocols import PROTOCOLS
from bayes_talk.evaluation.splits import make_splits
from bayes_talk.pipeline import fit_model

seqs = list(load_corpus(sys.argv[1]).sequences)
split = make_splits(PROTOCOLS["deena2010"], len(seqs))[0]
tr = [seqs[i] for i in split.train]; te = [seqs[i] for i in split.test]
for states in ["vlmm", "phone"]:
    m = fit_model(SwitchingSGPDM(states=states), tr, workers=2)
    for alg in ["predict", "optimise"]:
        first, rest, seglen = [], [], []
        for s in te:
            r = m.synthesize(s.mfcc, s.labels, algorithm=alg)
            err = ((r.mean - s.aam) ** 2).mean(1)
            for seg in r.segments:
                first.append(err[seg.start]); rest += list(err[seg.start + 1:seg.stop]); seglen.append(seg.stop - seg.start)
        allf = np.concatenate([first, rest])
        print(f"{states} {alg}: mean seg len {np.mean(seglen):.2f}, frames first/rest {len(first)}/{len(rest)}, "
              f"MSE first {np.mean(first):.3f} rest {np.mean(rest):.3f} all {allf.mean():.3f}", flush=True)
