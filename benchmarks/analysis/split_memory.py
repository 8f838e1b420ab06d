"""Profile (issue 14, memory): the resident memory of one deena2009 split, phase by phase.

The first split of the deena2009 protocol on CORPUS (50 training utterances, the SGPLVM
with the 1,500-frame cap and d = 8, then N_TEST of the split's test utterances through
SGPLVM A and B, then Voice Puppetry), with this process's RSS sampled every 20 ms by a
thread and attributed to the phase running; prints each phase's peak and ``ru_maxrss``
(the SGPLVM is freed before Voice Puppetry's fit).
MAX_ITER and SYNTH_ITER cap the SGPLVM's training and synthesis iterations (the peak
depends on N, not on the iteration count). Large freed blocks go back to the system
(:mod:`bayes_talk.base.memory`) unless ``BAYES_TALK_MALLOC=0``: run both to see its share.

    PYTHONPATH=. python benchmarks/analysis/split_memory.py MAX_ITER SYNTH_ITER N_TEST [CORPUS]
"""
from __future__ import annotations

import json
import resource
import sys
import threading
import time


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096 / 2**20


def main() -> None:
    max_iter, synth_iter, n_test = (int(a) for a in sys.argv[1:4])
    corpus_dir = sys.argv[4] if len(sys.argv) > 4 else "data/v2/train250"
    phase, peaks = ["start"], {}

    def sample() -> None:
        while True:
            peaks[phase[0]] = max(peaks.get(phase[0], 0.0), _rss_mb())
            time.sleep(0.02)

    threading.Thread(target=sample, daemon=True).start()
    t0 = time.perf_counter()

    def enter(name: str) -> None:
        phase[0] = name
        print(f"{time.perf_counter() - t0:7.1f} s  {name}: RSS {_rss_mb():.0f} MB", flush=True)

    enter("import")
    from bayes_talk.corpus import load_corpus
    from bayes_talk.evaluation import systems
    from bayes_talk.evaluation.protocols import get_protocol
    from bayes_talk.evaluation.splits import make_splits
    from bayes_talk.base.memory import release_large_blocks

    release_large_blocks()
    enter("load corpus")
    seqs = load_corpus(corpus_dir).sequences
    proto = get_protocol("deena2009", sgplvm_max_iter=max_iter, sgplvm_synth_max_iter=synth_iter)
    split = make_splits(proto, len(seqs))[0]
    train, test = [seqs[i] for i in split.train], [seqs[i] for i in split.test][:n_test]
    enter("SGPLVM fit")
    model = systems.fit_family("sgplvm", train, proto.system)
    for name in ("sgplvm-a", "sgplvm-b"):
        enter(f"{name} synthesis")
        for s in test:
            systems.predict(name, model, s, proto.system)
    del model
    enter("Voice Puppetry fit")
    vp = systems.fit_family("voice-puppetry", train, proto.system)
    enter("Voice Puppetry synthesis")
    for s in test:
        systems.predict("voice-puppetry", vp, s, proto.system)
    enter("end")
    time.sleep(0.1)
    print(json.dumps({"peak_mb_by_phase": {k: round(v) for k, v in peaks.items()},
                      "ru_maxrss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)},
                     indent=1))


if __name__ == "__main__":
    main()
