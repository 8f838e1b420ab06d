"""Synthesis speed: frames per second of MAP and of the posterior summary, beside Voice Puppetry.

A switching model written by ``bayes-talk train`` (``--model``) and Brand's Voice Puppetry,
trained on the first ``--n-train`` utterances of the model's training corpus (0: all),
synthesise the same held-out utterances (``--test-corpus``, projected through the training
corpus's AAM as ``evaluate --test-corpus`` does) with, in one run and interleaved per
utterance (so every system sees the same machine load):

* ``algorithm1``: deena2010's Algorithm 1 (``model.synthesize``), the paper's MAP path;
* ``joint_map``: the whole-utterance MAP (``sample_synthesis(method="map")``: Algorithm 1's
  path, then the joint optimisation of :mod:`bayes_talk.posterior.sampling`);
* ``posterior``: the default posterior summary (``method="laplace"``: the MAP, the Hessian
  and the visual mixture) — what ``bayes-talk synth`` runs;
* ``voice_puppetry``: ``VoicePuppetry.predict`` (Viterbi + banded solve).

Goals: MAP (Algorithm 1) ≥ 250 frames/s, posterior summary ≥ 25 frames/s (real time at 25
fps). Writes JSON with frames/s per system from wall time and from CPU time
(``time.process_time``: the machine is shared, wall time counts other jobs' turns), the
ratio to Voice Puppetry, the load average and the fraction of joint MAPs that converged.
Every call runs with one torch thread (as the executors run tasks). Each system is called
once on the first test utterance before the timed loop (``warmup_call_seconds``): the
compiled GP loops are JIT-compiled on their first call in a fresh environment.

    .venv/bin/python benchmarks/synthesis.py --model MODEL_DIR --test-corpus data/test3 --n-train 0 --n-test 8
    .venv/bin/python benchmarks/synthesis.py --quick    # the quick model and held-out corpus, 1 utterance
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from bayes_talk.estimators.baselines import REGISTRY
from bayes_talk.gp.threads import torch_threads
from bayes_talk.posterior.sampling import sample_synthesis
from benchmarks.common import bench_corpus, bench_model, result_path, write_result

#: Voice Puppetry's settings in the quick mode
QUICK_VOICE_PUPPETRY = {"n_states": 8, "n_iter": 20}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", type=Path, default=None, help="a trained switching model directory")
    ap.add_argument("--test-corpus", type=Path, default=None, help="the test utterances")
    ap.add_argument("--n-train", type=int, default=0, help="Voice Puppetry's training utterances (0: all)")
    ap.add_argument("--n-test", type=int, default=8)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true", help="the quick model and held-out corpus, 1 utterance")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    args.out = result_path("synthesis", args.quick, args.out)
    vp_kw = {}
    if args.quick:
        args.n_test, vp_kw = 1, QUICK_VOICE_PUPPETRY   # the default 26 states overfit 12 utterances
    args.model = args.model or bench_model(args.quick)
    args.test_corpus = args.test_corpus or bench_corpus("test", args.quick)
    from bayes_talk.corpus import load_corpus
    from bayes_talk.pipeline import load_trained

    tm = load_trained(args.model)
    if tm.kind == "sgplvm":
        raise SystemExit(f"{args.model}: an sgplvm model; this benchmark times the switching SGPDM")
    model = tm.uncalibrated
    train_dir = tm.training_corpus()
    train_c = load_corpus(train_dir)
    train = list(train_c.sequences)[: args.n_train or None]
    test = list(load_corpus(args.test_corpus, aam=train_c.aam_path).sequences)[: args.n_test]
    root = HERE.parent
    source = {"model": os.path.relpath(Path(args.model).resolve(), root), "kind": tm.kind,
              "training_corpus": os.path.relpath(Path(train_dir).resolve(), root),
              "test_corpus": os.path.relpath(Path(args.test_corpus).resolve(), root)}
    with torch_threads(1):
        t_fit = time.perf_counter()
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
    res = {"data": source,
           "n_train": len(train), "n_test": len(test), "test_frames": frames,
           "n_state_models": len(model.models_), "voice_puppetry_settings": vp_kw or "defaults",
           "voice_puppetry_fit_seconds": t_fit, "warmup_call_seconds": warm,
           "frames_per_second": fps, "frames_per_cpu_second": fps_cpu,
           "ratio_to_voice_puppetry": {k: fps[k] / fps["voice_puppetry"] for k in fps},
           "cpu_ratio_to_voice_puppetry": {k: fps_cpu[k] / fps_cpu["voice_puppetry"] for k in fps_cpu},
           "goals_met_cpu": {"map (algorithm1)": fps_cpu["algorithm1"] >= 250, "posterior": fps_cpu["posterior"] >= 25},
           "goals_frames_per_second": {"map": 250, "posterior": 25},
           "joint_map_converged": f"{converged}/{len(test)}",
           "loadavg_start_end": [load0[0], os.getloadavg()[0]]}
    write_result(args.out, res)
    print(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
