"""Synthesis speed: frames per second of MAP and of the posterior summary, beside Voice Puppetry.

Trains a switching SGPDM (VLMM states) and Brand's Voice Puppetry on the same training
utterances, then synthesises the same held-out utterances with, in one run and
interleaved per utterance (so every system sees the same machine load):

* ``algorithm1``: deena2010's Algorithm 1 (``model.synthesize``), the paper's MAP path;
* ``joint_map``: the whole-utterance MAP (``sample_synthesis(method="map")``: Algorithm 1's
  path, then the joint optimisation of :mod:`bayes_talk.synthesis.posterior`);
* ``posterior``: the default posterior summary (``method="laplace"``, 64 draws: the MAP,
  the Hessian and the visual mixture) — what ``bayes-talk synth`` runs;
* ``voice_puppetry``: ``VoicePuppetry.predict`` (Viterbi + banded solve).

Goals (issue #9): MAP ≥ 250 frames/s, posterior summary ≥ 25 frames/s (real time at 25 fps).
Writes JSON with frames/s per system, the ratio to Voice Puppetry, the load average and
the fraction of joint MAPs that converged.

    .venv/bin/python benchmarks/synthesis.py                       # toy data (tests/toydata.py)
    .venv/bin/python benchmarks/synthesis.py --corpus DIR --n-train 60 --n-test 4
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE.parent / "tests"))

from bayes_talk.baselines import REGISTRY  # noqa: E402
from bayes_talk.estimators.switching import SwitchingSGPDM  # noqa: E402
from bayes_talk.gp.threads import torch_threads  # noqa: E402
from bayes_talk.synthesis.posterior import sample_synthesis  # noqa: E402

SMALL = dict(latent_dim=3, max_iter=40, min_count=4, max_frames_per_state=120, fallback_frames=150)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--corpus", type=Path, default=None)
    ap.add_argument("--n-train", type=int, default=60)
    ap.add_argument("--n-test", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=HERE / "results" / "synthesis.json")
    args = ap.parse_args()
    if args.corpus:
        from bayes_talk.data.corpus import load_corpus

        seqs = list(load_corpus(args.corpus).sequences)
        perm = np.random.default_rng(args.seed).permutation(len(seqs))
        test = [seqs[i] for i in perm[:args.n_test]]
        train = [seqs[i] for i in perm[args.n_test:args.n_test + args.n_train]]
        cfg, source, vp_kw = {}, str(args.corpus), {}
    else:
        from toydata import make_utterances

        train, test = make_utterances(24, seed=0), make_utterances(args.n_test, seed=1, mean_len=40)
        cfg, source, vp_kw = SMALL, "tests/toydata.py", {"n_states": 6}  # 26 states overfit the toy
    with torch_threads(1):
        model = SwitchingSGPDM(states="vlmm", seed=args.seed, **cfg).fit(train)
        vp = REGISTRY["voice-puppetry"](random_state=args.seed, **vp_kw).fit(train)
    systems = {
        "algorithm1": lambda s: model.synthesize(s.mfcc, s.labels),
        "joint_map": lambda s: sample_synthesis(model, s.mfcc, s.labels, method="map", seed=args.seed),
        "posterior": lambda s: sample_synthesis(model, s.mfcc, s.labels, method="laplace", seed=args.seed),
        "voice_puppetry": lambda s: vp.predict(s),
    }
    secs = {k: 0.0 for k in systems}
    converged = 0
    load0 = os.getloadavg()
    for s in test:
        for name, fn in systems.items():
            t0 = time.perf_counter()
            r = fn(s)
            secs[name] += time.perf_counter() - t0
            if name == "joint_map":
                converged += int(r.map.converged)
    frames = sum(s.n_frames for s in test)
    fps = {k: frames / v for k, v in secs.items()}
    res = {"command": "benchmarks/synthesis.py " + " ".join(sys.argv[1:]), "data": source,
           "n_train": len(train), "n_test": len(test), "test_frames": frames,
           "frames_per_second": fps,
           "ratio_to_voice_puppetry": {k: fps[k] / fps["voice_puppetry"] for k in fps},
           "goals_frames_per_second": {"map": 250, "posterior": 25},
           "joint_map_converged": f"{converged}/{len(test)}",
           "loadavg_start_end": [load0[0], os.getloadavg()[0]],
           "machine": {"python": platform.python_version(), "cpus": os.cpu_count()}}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_suffix(".tmp")
    tmp.write_text(json.dumps(res, indent=1))
    tmp.replace(args.out)
    print(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
