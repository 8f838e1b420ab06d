"""Benchmark of the switching SGPDM: training time and synthesis speed.

Measured in one run on a built-in corpus (``--corpus DIR`` reuses an existing built corpus,
else ``build_corpus(tmpdir, n_utterances=278, seed=0)`` is built first, ~90 s). The utterances
are split as the deena2010 protocol splits them (``evaluation.splits.make_splits``, seed 0):
250 train / 28 held out. ``--quick``: the quick corpus of ``benchmarks/common.py`` (12
utterances: 10 train / 2 held out) and the quick mode's small model settings.

(a) training: ``fit_model(SwitchingSGPDM(states="vlmm"), train, workers=2)`` (a process
    pool of 2, default settings: ≤ 300 frames per state, 100 L-BFGS iterations, d = 6),
    then the same with ``states="phone"``. Reported: wall and CPU time, number of state
    models (with the global fallback counted separately), frames per state model
    (min / median / max), L-BFGS outer steps per model. Target (VLMM): ≤ 600 s on 2 cores.
(b) synthesis on the held-out utterances for both state kinds × algorithm
    ("optimise", "predict") × smoothness ("frame", "off"), in this process (one torch
    thread, as ``synthesize`` sets): frames per second (all test frames / wall time), the
    real-time factor at 25 fps, and AMSE / ACC of the mean against ``seq.aam``
    (``evaluation.metrics``) so speed and quality are read together. Target: ≥ 100 frames/s
    (4× real time) for sequential optimisation; one warm-up synthesis per model first.
(c) ``vs_target``: train_s / 600 (≤ 1 meets it) and frames_per_s / 100 (≥ 1 meets it).

Every timed phase records wall time, CPU time (user + system of this process and of its
waited-for children: the pool workers, the corpus workers) and ``os.getloadavg()`` at its
start and end: the machine is shared, so read timings against the load. When the VLMM
training misses its target (or with ``--profile always``) one state fit (the state model
with the most frames, refitted in this process from its stored data) runs under cProfile
and the top functions go into the JSON. The JSON is rewritten (atomically) after every
phase with ``"complete": false`` until the end.

    .venv/bin/python benchmarks/switching.py [--corpus DIR | --keep-corpus DIR] [--quick]
        [--out PATH] [--workers 2] [--profile {auto,always,never}]
    -> benchmarks/results/switching.json (--quick: results/quick/switching.json)
"""
from __future__ import annotations

import argparse
import cProfile
import io
import logging
import os
import platform
import pstats
import resource
import statistics
import sys
import tempfile
import time
import warnings
from dataclasses import asdict, replace
from pathlib import Path
from typing import Self

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from benchmarks.common import (
    QUICK_MODEL,
    QUICK_TRAIN_UTTERANCES,
    bench_corpus,
    result_path,
    write_result,
)

TRAIN_TARGET_S = 600.0
FPS_TARGET = 100.0
VIDEO_FPS = 25.0
FULL = {"n_utterances": 278, "n_train": 250, "n_test": 28}
QUICK = {"n_utterances": QUICK_TRAIN_UTTERANCES, "n_train": QUICK_TRAIN_UTTERANCES - 2, "n_test": 2}


# ---------------------------------------------------------------------------- bookkeeping
def _cpu() -> dict[str, float]:
    me = resource.getrusage(resource.RUSAGE_SELF)
    ch = resource.getrusage(resource.RUSAGE_CHILDREN)
    return {"self_user": me.ru_utime, "self_system": me.ru_stime,
            "children_user": ch.ru_utime, "children_system": ch.ru_stime}


class Phase:
    """Wall time, CPU time and load average of a block: ``with Phase() as ph: ...; ph.record``."""

    def __enter__(self) -> Self:
        self.load0 = [round(x, 2) for x in os.getloadavg()]
        self.cpu0 = _cpu()
        self.t0 = time.perf_counter()
        return self

    def __exit__(self, *exc) -> None:
        self.wall = time.perf_counter() - self.t0
        cpu1 = _cpu()
        cpu = {k: round(cpu1[k] - self.cpu0[k], 2) for k in cpu1}
        cpu["total"] = round(sum(cpu.values()), 2)
        self.record = {"wall_s": round(self.wall, 2), "cpu_s": cpu,
                       "cpu_per_wall": round(cpu["total"] / self.wall, 2) if self.wall > 0 else None,
                       "loadavg_start": self.load0, "loadavg_end": [round(x, 2) for x in os.getloadavg()]}


def _stats(xs) -> dict:
    xs = list(xs)
    return {"min": min(xs), "median": statistics.median(xs), "max": max(xs), "n": len(xs)} if xs else {}


def machine_info() -> dict:
    import torch

    info = {"nproc": os.cpu_count(),
            "sched_affinity": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
            "python": platform.python_version(), "platform": platform.platform(),
            "torch": torch.__version__, "numpy": np.__version__,
            "torch_threads_main": torch.get_num_threads()}
    try:
        from threadpoolctl import threadpool_info

        info["blas"] = [{k: d.get(k) for k in ("internal_api", "num_threads", "version")}
                        for d in threadpool_info()]
    except ImportError:
        pass
    return info


# ---------------------------------------------------------------------------- training
def train_stats(model) -> dict:
    from bayes_talk.models.switching import FALLBACK

    own = {k: m for k, m in model.models_.items() if k != FALLBACK}
    frames = [int(sum(m.seq_lengths_)) for m in own.values()]
    steps = [len(m.history.log_joint) - 1 for m in model.models_.values()]
    sm = model.states_model_
    n_states = sm.n_states if hasattr(sm, "n_states") else len(sm.alphabet_)
    return {
        "n_state_models": len(own),
        "n_models_with_fallback": len(model.models_),
        "n_states_in_state_model": int(n_states() if callable(n_states) else n_states),
        "frames_per_state": _stats(frames),
        "frames_per_state_hist": {"<50": sum(f < 50 for f in frames),
                                  "50-149": sum(50 <= f < 150 for f in frames),
                                  "150-299": sum(150 <= f < 300 for f in frames),
                                  ">=300": sum(f >= 300 for f in frames)},
        "fallback_frames": int(sum(model.models_[FALLBACK].seq_lengths_)),
        "total_model_frames": int(sum(frames) + sum(model.models_[FALLBACK].seq_lengths_)),
        "lbfgs_outer_steps_per_model": _stats(steps),
        "config": asdict(model.config),
    }


def train(kind: str, train_seqs, workers: int, settings: dict):
    from bayes_talk.estimators.switching import SwitchingSGPDM
    from bayes_talk.pipeline import fit_model

    with Phase() as ph:
        model = fit_model(SwitchingSGPDM(states=kind, **settings), train_seqs, workers=workers)
    return model, ph


# ---------------------------------------------------------------------------- synthesis
def synth(model, test_seqs, algorithm: str, smoothness: str) -> dict:
    from bayes_talk.evaluation.metrics import acc, amse

    preds, per_utt = [], []
    n_frames = sum(s.n_frames for s in test_seqs)
    with warnings.catch_warnings(record=True) as caught, Phase() as ph:
        warnings.simplefilter("always")
        for s in test_seqs:
            t0 = time.perf_counter()
            preds.append(model.synthesize(s.mfcc, s.labels, algorithm=algorithm, smoothness=smoothness).mean)
            per_utt.append(s.n_frames / (time.perf_counter() - t0))
    fps = n_frames / ph.wall
    truth = [s.aam for s in test_seqs]
    return {"algorithm": algorithm, "smoothness": smoothness, "n_utterances": len(test_seqs),
            "n_frames": n_frames, **ph.record, "frames_per_s": round(fps, 1),
            "real_time_factor": round(fps / VIDEO_FPS, 2),
            "frames_per_s_per_utterance": {k: round(v, 1) for k, v in _stats(per_utt).items()},
            "AMSE": amse(truth, preds), "ACC": acc(truth, preds),
            "warnings": sorted({str(w.message) for w in caught})}


# ---------------------------------------------------------------------------- profile
def profile_state_fit(model, top: int = 30) -> dict:
    """Refit the state model with the most frames in this process under cProfile."""
    from bayes_talk.models.switching import FALLBACK, fit_state

    key, m = max(((k, m) for k, m in model.models_.items() if k != FALLBACK),
                 key=lambda km: sum(km[1].seq_lengths_))
    _, arrays = m.state()
    job = tuple(arrays[f"Y/{v}"] + arrays[f"mean/{v}"] for v in ("audio", "visual")) + (
        list(m.seq_lengths_), model._state_cfg())
    prof = cProfile.Profile()
    with Phase() as ph:
        prof.enable()
        fit_state(job)
        prof.disable()
    st = pstats.Stats(prof)
    total = st.total_tt

    def rows(sort: str) -> list[dict]:
        st.sort_stats(sort)
        out = []
        for func in st.fcn_list[:top]:
            _, nc, tt, ct, _ = st.stats[func]
            out.append({"function": f"{Path(func[0]).name}:{func[1]}({func[2]})", "ncalls": nc,
                        "tottime_s": round(tt, 3), "cumtime_s": round(ct, 3),
                        "tottime_frac": round(tt / total, 3)})
        return out

    buf = io.StringIO()
    pstats.Stats(prof, stream=buf).sort_stats("tottime").print_stats(top)
    calls = {f"{Path(f[0]).name}:{f[2]}": v[1] for f, v in st.stats.items()
             if f[2] in ("log_joint", "closure", "observation_loglik", "dynamics_loglik", "cholesky",
                         "_optimise", "_init_params", "_init_latents", "_finalise")}
    return {"state": " ".join(key), "n_frames": int(sum(m.seq_lengths_)), "n_subsequences": len(m.seq_lengths_),
            "lbfgs_outer_steps_in_training": len(m.history.log_joint) - 1, **ph.record,
            "profiled_total_s": round(total, 3), "call_counts": calls,
            "top_by_tottime": rows("tottime"), "top_by_cumtime": rows("cumulative"),
            "pstats_text": buf.getvalue()}


# ---------------------------------------------------------------------------- main
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--corpus", type=Path, default=None, help="an existing built corpus to reuse")
    ap.add_argument("--keep-corpus", type=Path, default=None,
                    help="build the corpus into this (new) directory instead of a temporary one")
    ap.add_argument("--quick", action="store_true", help="the quick corpus (10 train / 2 test), small models")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--workers", type=int, default=2, help="process pool size for training (2)")
    ap.add_argument("--seed", type=int, default=0, help="corpus build seed and split seed")
    ap.add_argument("--profile", choices=("auto", "always", "never"), default="auto",
                    help="cProfile one state fit: auto = when the training target is missed")
    args = ap.parse_args(argv)
    args.out = result_path("switching", args.quick, args.out)
    if args.quick and args.corpus is None:
        args.corpus = bench_corpus("train", True)
    settings = QUICK_MODEL if args.quick else {}
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(name)s %(message)s")
    from bayes_talk.corpus import build_corpus, load_corpus
    from bayes_talk.evaluation.protocols import PROTOCOLS
    from bayes_talk.evaluation.splits import make_splits
    from bayes_talk.synthesis.sequential import ALGORITHMS, SMOOTHNESS

    sizes = QUICK if args.quick else FULL
    t_start = time.perf_counter()
    res: dict = {"benchmark": "switching", "complete": False,
                 "quick": args.quick, "model_settings": settings or "defaults", "machine": machine_info(),
                 "loadavg_at_start": [round(x, 2) for x in os.getloadavg()],
                 "targets": {"train_vlmm_s_max": TRAIN_TARGET_S, "synth_optimise_frames_per_s_min": FPS_TARGET}}

    def save() -> None:
        res["wall_so_far_s"] = round(time.perf_counter() - t_start, 1)
        write_result(args.out, res)

    tmp = None
    try:
        if args.corpus is not None:
            root = args.corpus
            res["corpus"] = {"path": os.path.relpath(Path(root).resolve(), HERE.parent), "built_here": False}
        else:
            if args.keep_corpus is not None:
                root = args.keep_corpus
            else:
                tmp = tempfile.TemporaryDirectory(prefix="bt_switching_")
                root = Path(tmp.name) / "corpus"
            print(f"building {sizes['n_utterances']} utterances into {root} ...", flush=True)
            with Phase() as ph:
                build_corpus(root, n_utterances=sizes["n_utterances"], seed=args.seed)
            res["corpus"] = {"path": str(root), "built_here": True, "kept": tmp is None,
                             "n_utterances": sizes["n_utterances"], "seed": args.seed, "build": ph.record}
        with Phase() as ph:
            corpus = load_corpus(root)
        seqs = list(corpus.sequences)
        res["corpus"]["load"] = ph.record
        res["corpus"]["n_sequences"] = len(seqs)
        proto = replace(PROTOCOLS["deena2010"], n_train=sizes["n_train"], n_test=sizes["n_test"], seed=args.seed)
        split = make_splits(proto, len(seqs))[0]
        train_seqs = [seqs[i] for i in split.train]
        test_seqs = [seqs[i] for i in split.test]
        res["split"] = {"rule": "evaluation.splits.make_splits(deena2010, seed)",
                        "n_train": len(train_seqs), "n_test": len(test_seqs),
                        "train_frames": sum(s.n_frames for s in train_seqs),
                        "test_frames": sum(s.n_frames for s in test_seqs),
                        "test_utterances": [s.name for s in test_seqs]}
        save()

        # (a) training
        models = {}
        res["train"] = {}
        for kind in ("vlmm", "phone"):
            print(f"training states={kind} on {len(train_seqs)} utterances ({args.workers} workers) ...",
                  flush=True)
            model, ph = train(kind, train_seqs, args.workers, settings)
            models[kind] = model
            res["train"][kind] = {"call": f'fit_model(SwitchingSGPDM(states="{kind}"), train, '
                                          f"workers={args.workers})", **ph.record, **train_stats(model)}
            r = res["train"][kind]
            print(f"  {r['wall_s']:.1f} s wall, {r['cpu_s']['total']:.1f} s CPU, {r['n_state_models']} state "
                  f"models, frames/state {r['frames_per_state']}, load {r['loadavg_start']} -> "
                  f"{r['loadavg_end']}", flush=True)
            save()
        tv = res["train"]["vlmm"]["wall_s"]
        res["vs_target"] = {"train_vlmm": round(tv / TRAIN_TARGET_S, 3),
                            "train_vlmm_meets_target": tv <= TRAIN_TARGET_S,
                            "train_phone": round(res["train"]["phone"]["wall_s"] / TRAIN_TARGET_S, 3)}

        # (b) synthesis
        res["synth"] = []
        for kind, model in models.items():
            s0 = test_seqs[0]
            with Phase() as ph, warnings.catch_warnings():
                warnings.simplefilter("ignore")
                model.synthesize(s0.mfcc, s0.labels)                # warm-up, not counted
            res.setdefault("synth_warmup", {})[kind] = ph.record
            for algorithm in ALGORITHMS:
                for smoothness in SMOOTHNESS:
                    r = {"states": kind, **synth(model, test_seqs, algorithm, smoothness)}
                    r["vs_target"] = round(r["frames_per_s"] / FPS_TARGET, 3)
                    r["target_applies"] = algorithm == "optimise"
                    res["synth"].append(r)
                    print(f"  synth {kind:5s} {algorithm:8s} {smoothness:5s}: {r['frames_per_s']:8.1f} frames/s "
                          f"({r['real_time_factor']:.1f}x real time), AMSE {r['AMSE']:.4g}, ACC {r['ACC']:.3f}, "
                          f"load {r['loadavg_start']} -> {r['loadavg_end']}", flush=True)
                    save()
        res["vs_target"]["synth_frames_per_s"] = {
            f"{r['states']}/{r['algorithm']}/{r['smoothness']}": r["vs_target"] for r in res["synth"]}
        res["vs_target"]["synth_optimise_meets_target"] = all(
            r["frames_per_s"] >= FPS_TARGET for r in res["synth"] if r["target_applies"])

        # profile one state fit when the training target is missed
        if args.profile == "always" or (args.profile == "auto" and tv > TRAIN_TARGET_S):
            print("profiling one state fit ...", flush=True)
            res["profile_state_fit"] = profile_state_fit(models["vlmm"])
            p = res["profile_state_fit"]
            print(f"  state {p['state']!r}: {p['n_frames']} frames, {p['wall_s']} s wall", flush=True)
        res["complete"] = True
        res["loadavg_at_end"] = [round(x, 2) for x in os.getloadavg()]
        save()
    finally:
        if tmp is not None:
            tmp.cleanup()
    print(f"wrote {args.out} ({time.perf_counter() - t_start:.0f} s)")
    return 0


if __name__ == "__main__":
    from bayes_talk.base.executor import interruptible

    # `kill` stops the worker processes too, not only this one
    raise SystemExit(interruptible(main))
