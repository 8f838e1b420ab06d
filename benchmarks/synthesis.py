"""Synthesis speed: frames per second of MAP and of the posterior summary, beside Voice Puppetry.

Trains a switching SGPDM (VLMM states) and Brand's Voice Puppetry on the same training
utterances, then synthesises the same held-out utterances with, in one run and
interleaved per utterance (so every system sees the same machine load):

* ``algorithm1``: deena2010's Algorithm 1 (``model.synthesize``), the paper's MAP path;
* ``joint_map``: the whole-utterance MAP (``sample_synthesis(method="map")``: Algorithm 1's
  path, then the joint optimisation of :mod:`bayes_talk.posterior.sampling`);
* ``posterior``: the default posterior summary (``method="laplace"``, 64 draws: the MAP,
  the Hessian and the visual mixture) — what ``bayes-talk synth`` runs;
* ``voice_puppetry``: ``VoicePuppetry.predict`` (Viterbi + banded solve).

Goals (issue #9): MAP (Algorithm 1) ≥ 250 frames/s, posterior summary ≥ 25 frames/s (real
time at 25 fps). Writes JSON with frames/s per system from wall time and from CPU time
(``time.process_time``: the machine is shared, wall time counts other jobs' turns), the
ratio to Voice Puppetry, the load average and the fraction of joint MAPs that converged.
Every call runs with one torch thread (as the executors run tasks). Each system is called
once on the first test utterance before the timed loop (``warmup_call_seconds``): the
compiled GP loops are JIT-compiled on their first call in a fresh environment.

    .venv/bin/python benchmarks/synthesis.py                       # toy data (tests/toydata.py)
    .venv/bin/python benchmarks/synthesis.py --corpus DIR --n-train 60 --n-test 4
    .venv/bin/python benchmarks/synthesis.py --model MODEL_DIR --test-corpus data/v2/heldout40 --n-test 8

``--model``: a model directory written by ``bayes-talk train`` (a switching SGPDM) is
loaded instead of training one; Voice Puppetry is trained on the first ``--n-train``
utterances of the model's training corpus (its ``bayes_talk_model.json`` ``corpus``; 0: all)
and the test utterances come from ``--test-corpus``, projected through that corpus's
AAM as ``evaluate --test-corpus`` does.
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

from bayes_talk.estimators.baselines import REGISTRY
from bayes_talk.estimators.switching import SwitchingSGPDM
from bayes_talk.base.files import write_json
from bayes_talk.gp.threads import torch_threads
from bayes_talk.posterior.sampling import sample_synthesis

SMALL = {"latent_dim": 3, "max_iter": 40, "min_count": 4, "max_frames_per_state": 120, "fallback_frames": 150}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--corpus", type=Path, default=None)
    ap.add_argument("--model", type=Path, default=None, help="a trained switching model directory")
    ap.add_argument("--test-corpus", type=Path, default=None, help="with --model: the test utterances")
    ap.add_argument("--n-train", type=int, default=60)
    ap.add_argument("--n-test", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=HERE / "results" / "synthesis.json")
    args = ap.parse_args()
    model = None
    if args.model:
        from bayes_talk.corpus import load_corpus
        from bayes_talk.pipeline import load_trained

        if args.test_corpus is None:
            raise SystemExit("--model needs --test-corpus (utterances the model was not trained on)")
        tm = load_trained(args.model)
        if tm.kind == "sgplvm":
            raise SystemExit(f"{args.model}: an sgplvm model; this benchmark times the switching SGPDM")
        model = tm.model
        train_dir = tm.training_corpus()
        train_c = load_corpus(train_dir)
        train = list(train_c.sequences)[: args.n_train or None]
        test = list(load_corpus(args.test_corpus, aam=train_c.aam_path).sequences)[: args.n_test]
        cfg, vp_kw = {}, {}
        source = f"model {args.model} (trained on {train_dir}); test {args.test_corpus}"
    elif args.corpus:
        from bayes_talk.corpus import load_corpus

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
        t_fit = time.perf_counter()
        if model is None:
            model = SwitchingSGPDM(states="vlmm", seed=args.seed, **cfg).fit(train)
        vp = REGISTRY["voice-puppetry"](random_state=args.seed, **vp_kw).fit(train)
        t_fit = time.perf_counter() - t_fit
    systems = {
        "algorithm1": lambda s: model.synthesize(s.mfcc, s.labels),
        "joint_map": lambda s: sample_synthesis(model, s.mfcc, s.labels, method="map", seed=args.seed),
        "posterior": lambda s: sample_synthesis(model, s.mfcc, s.labels, method="laplace", seed=args.seed),
        "voice_puppetry": lambda s: vp.predict(s),
    }
    secs = {k: 0.0 for k in systems}
    cpu = {k: 0.0 for k in systems}
    converged = 0
    # one untimed call of every system first: numba compiles the GP loops on their first call
    # in a fresh environment (seconds, then cached on disk), which is not synthesis time
    warm = {}
    with torch_threads(1):
        for name, fn in systems.items():
            t0 = time.perf_counter()
            fn(test[0])
            warm[name] = time.perf_counter() - t0
    load0 = os.getloadavg()
    with torch_threads(1):
        for s in test:
            for name, fn in systems.items():
                t0, c0 = time.perf_counter(), time.process_time()
                r = fn(s)
                secs[name] += time.perf_counter() - t0
                cpu[name] += time.process_time() - c0
                if name == "joint_map":
                    converged += int(r.map.converged)
    frames = sum(s.n_frames for s in test)
    fps = {k: frames / v for k, v in secs.items()}
    fps_cpu = {k: frames / v for k, v in cpu.items()}
    res = {"command": "benchmarks/synthesis.py " + " ".join(sys.argv[1:]), "data": source,
           "n_train": len(train), "n_test": len(test), "test_frames": frames,
           "n_state_models": len(model.models_), "fit_seconds": t_fit, "warmup_call_seconds": warm,
           "frames_per_second": fps, "frames_per_cpu_second": fps_cpu,
           "ratio_to_voice_puppetry": {k: fps[k] / fps["voice_puppetry"] for k in fps},
           "cpu_ratio_to_voice_puppetry": {k: fps_cpu[k] / fps_cpu["voice_puppetry"] for k in fps_cpu},
           "goals_met_cpu": {"map (algorithm1)": fps_cpu["algorithm1"] >= 250, "posterior": fps_cpu["posterior"] >= 25},
           "goals_frames_per_second": {"map": 250, "posterior": 25},
           "joint_map_converged": f"{converged}/{len(test)}",
           "loadavg_start_end": [load0[0], os.getloadavg()[0]],
           "machine": {"python": platform.python_version(), "cpus": os.cpu_count()}}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_json(args.out, res)
    print(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
