"""Benchmark: the executors (bayes_talk.base.executor) and the peak memory of the full protocols.

Writes benchmarks/results/scaling.json (``--quick``: results/quick/scaling.json) with sections:

- ``executors``: per-state training of the switching SGPDM (VLMM states, default
  settings; ``--quick``: the quick mode's small settings) on the first ``--n-train``
  utterances of ``--corpus``, side by side in one run: the local serial executor, the local
  process pool (``ProcessExecutor``, 2 processes) and dask ``LocalCluster``s of 1 and 2
  worker processes on 127.0.0.1. Wall time of the training only (the cluster's start-up is
  recorded apart), speed-up over the serial run and over the process pool, and
  ``identical``: every array of every state model equal, bit for bit, to the serial model's.
- ``peak_rss``: each protocol of ``--protocols`` (default deena2009; ``--quick``: its
  quick variant) run by ``evaluate`` in a child process of this script; ``ru_maxrss`` of that
  process (``self_mb``) and of its largest child (``children_mb``: the worker processes of
  ``--executor``), their sum (an upper bound of the job's peak), and the wall time. The goal
  for the full deena2009 protocol is <= 2 GB (it was 4.6 GB, 23 min).

Every section records the load average at its start and end (the machine is shared).

    python benchmarks/scaling.py [--corpus data/train250] [--n-train 100]
        [--sections executors,peak_rss] [--protocols deena2009,deena2010,englebienne2008]
        [--executor local|processes|dask] [--repeats K] [--out PATH]
    python benchmarks/scaling.py --quick    # the quick corpus (benchmarks/common.py), small settings

A run of some ``--sections`` replaces those sections of an existing result file and keeps the
others. The sparse SGPDM's time and memory against N: ``benchmarks/sparse.py``.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import QUICK_MODEL, ROOT, bench_corpus, result_path, write_result


def _load() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


def _same_model(a, b) -> bool:
    """Every array of every state model equal bit for bit (and the same states)."""
    if a.models_.keys() != b.models_.keys():
        return False
    for k in a.models_:
        for da, db in zip(a.models_[k].state(), b.models_[k].state(), strict=True):
            for name, va in da.items():
                vb = db.get(name)
                if isinstance(va, np.ndarray):
                    if not (isinstance(vb, np.ndarray) and np.array_equal(va, vb)):
                        return False
                elif va != vb:
                    return False
    return True


# ------------------------------------------------------------------------------- executors
def executors_section(args: argparse.Namespace) -> dict:
    from bayes_talk.base.executor import DaskExecutor, LocalExecutor, ProcessExecutor
    from bayes_talk.corpus import load_corpus
    from bayes_talk.estimators.switching import SwitchingSGPDM

    settings = dict(QUICK_MODEL) if args.quick else {}
    train = load_corpus(args.corpus).sequences[: args.n_train]
    out: dict = {"corpus": args.corpus, "n_train": len(train), "n_frames": int(sum(s.n_frames for s in train)),
                 "model": "SwitchingSGPDM(states='vlmm')", "settings": settings or "defaults",
                 "loadavg_start": _load(), "runs": {}}

    def fit(ex):
        t0 = time.perf_counter()
        m = SwitchingSGPDM(states="vlmm", **settings).fit(train, executor=ex)
        return m, time.perf_counter() - t0

    engines = [("local", lambda: LocalExecutor()), ("processes-2", lambda: ProcessExecutor(2)),
               ("dask-1", lambda: DaskExecutor(n_workers=1)), ("dask-2", lambda: DaskExecutor(n_workers=2))]
    models = {}
    for name, make in engines:
        print(f"[scaling] training on {name} ...", flush=True)
        t0 = time.perf_counter()
        with make() as ex:
            start_s = time.perf_counter() - t0
            if name.startswith("processes"):  # start the pool's processes outside the timing too
                ex.map(abs, [1, 2])
                start_s = time.perf_counter() - t0
            models[name], wall = fit(ex)
        out["runs"][name] = {"train_s": round(wall, 2), "startup_s": round(start_s, 2),
                             "n_state_models": len(models[name].models_)}
    ref_s = out["runs"]["local"]["train_s"]
    pool_s = out["runs"]["processes-2"]["train_s"]
    for name, r in out["runs"].items():
        r["speedup_vs_local"] = round(ref_s / r["train_s"], 3)
        r["speedup_vs_process_pool"] = round(pool_s / r["train_s"], 3)
        r["identical_to_local"] = _same_model(models["local"], models[name])
    out["all_identical"] = all(r["identical_to_local"] for r in out["runs"].values())
    out["loadavg_end"] = _load()
    return out


# ------------------------------------------------------------------------------- peak RSS
def _rss_child(args: argparse.Namespace) -> None:
    """Child mode: run one protocol as ``evaluate`` does (load, run; ``--repeats`` caps its
    repeats/folds) and print its peak RSS as JSON."""
    import dataclasses

    from bayes_talk.base.executor import make_executor
    from bayes_talk.corpus import load_corpus
    from bayes_talk.evaluation.harness import run_protocol
    from bayes_talk.evaluation.protocols import get_protocol

    t0 = time.perf_counter()
    proto = get_protocol(args.rss_child, quick=args.quick)
    if args.repeats:
        proto = dataclasses.replace(proto, **({"n_folds": args.repeats} if proto.scheme == "kfold"
                                              else {"n_repeats": args.repeats}))
    if args.quick and proto.n_train is not None:   # the quick corpus holds 12 utterances
        proto = dataclasses.replace(proto, n_train=min(proto.n_train, 8), n_test=min(proto.n_test, 4))
    if args.quick and proto.n_use is not None:
        proto = dataclasses.replace(proto, n_use=min(proto.n_use, 12))
    with make_executor(args.executor, args.workers) as ex:
        corpus = load_corpus(args.corpus, executor=ex if ex.parallel else None)
        res, _ = run_protocol(proto, corpus.sequences, executor=ex)
    me = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    ch = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0
    print(json.dumps({"self_mb": round(me, 1), "children_mb": round(ch, 1), "wall_s": round(time.perf_counter() - t0, 1),
                      "description": res["description"], "n_splits": res["n_splits"], "quick": res["quick"],
                      "headline": {n: e["headline"] for n, e in res["methods"].items()},
                      "train_seconds": {n: e["train_seconds"] for n, e in res["methods"].items()}}))


def _run_sampling_rss(cmd: list[str], every_s: float = 0.5) -> tuple[subprocess.CompletedProcess, float, float]:
    """Run ``cmd`` to completion; meanwhile sum the RSS, and the PSS, of its whole process
    tree every ``every_s`` seconds (psutil). Returns the completed process and the largest
    sums (MB). RSS counts a page shared by a forked child and its parent twice; PSS
    (proportional set size) splits it between them, so the PSS sum is the tree's real
    footprint at the sample. Both are lower bounds of the true peak (a spike between
    samples is missed)."""
    import threading

    import psutil

    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    peak = [0.0, 0.0]
    done = threading.Event()

    def sample() -> None:
        try:
            root = psutil.Process(proc.pid)
        except psutil.NoSuchProcess:
            return
        while not done.is_set():
            total, pss = 0, 0
            try:
                procs = [root, *root.children(recursive=True)]
            except psutil.NoSuchProcess:
                break
            for q in procs:
                try:
                    total += q.memory_info().rss
                    pss += getattr(q.memory_full_info(), "pss", 0)
                except (psutil.NoSuchProcess, psutil.AccessDenied):
                    pass
            peak[0] = max(peak[0], total / 2**20)
            peak[1] = max(peak[1], pss / 2**20)
            done.wait(every_s)

    t = threading.Thread(target=sample, daemon=True)
    t.start()
    stdout, stderr = proc.communicate()
    done.set()
    t.join()
    return subprocess.CompletedProcess(cmd, proc.returncode, stdout, stderr), round(peak[0], 1), round(peak[1], 1)


def peak_rss_section(args: argparse.Namespace) -> dict:
    out: dict = {"corpus": args.corpus, "executor": args.executor, "quick": args.quick,
                 "repeats": args.repeats or "all (the protocol's)",
                 "how": ("evaluate in a child process; ru_maxrss of it (self_mb) and of its largest child "
                         "(children_mb); peak_upper_bound_mb = self + workers x largest child (at most "
                         "`workers` children run at once); peak_tree_sampled_mb = the largest sum of the "
                         "RSS of the child and all its descendants, sampled every 0.5 s (psutil): a lower "
                         "bound of the true peak; peak_tree_pss_sampled_mb = the same with PSS (a page "
                         "shared by a forked child and its parent counted once). With --executor local "
                         "the largest child is a fork whose ru_maxrss starts at the parent's high-water "
                         "mark, so the upper bound double-counts: read self_mb and the PSS figure"),
                 "goal_deena2009_mb": 2048, "before": {"deena2009": {"peak_mb": 4600, "wall_s": 23 * 60}},
                 "protocols": {}}
    for proto in args.protocols.split(","):
        print(f"[scaling] peak RSS of {proto}{' (quick)' if args.quick else ''} ...", flush=True)
        load0 = _load()
        cmd = [sys.executable, str(Path(__file__).resolve()), "--rss-child", proto, "--corpus", args.corpus,
               "--executor", args.executor, "--workers", str(args.workers),
               "--repeats", str(args.repeats or 0)] + (["--quick"] if args.quick else [])
        r, tree_mb, tree_pss_mb = _run_sampling_rss(cmd)
        if r.returncode != 0:
            raise SystemExit(f"{proto}: evaluate failed:\n{r.stderr[-3000:]}")
        got = json.loads(r.stdout.strip().splitlines()[-1])
        # at most ``workers`` worker processes run at once, none larger than the largest one
        n_at_once = 1 if args.executor == "local" else args.workers
        got["workers"] = n_at_once
        got["peak_upper_bound_mb"] = round(got["self_mb"] + n_at_once * got["children_mb"], 1)
        got["peak_tree_sampled_mb"] = tree_mb
        got["peak_tree_pss_sampled_mb"] = tree_pss_mb
        got["loadavg_start"], got["loadavg_end"] = load0, _load()
        if proto == "deena2009" and not args.quick and not args.repeats:  # the goal is the full protocol's
            got["within_goal"] = got["peak_upper_bound_mb"] <= out["goal_deena2009_mb"]
        out["protocols"][proto] = got
    return out


# ------------------------------------------------------------------------------- main
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small settings; the quick protocols")
    ap.add_argument("--corpus", default=None, help="a built corpus (default: the suite's training corpus)")
    ap.add_argument("--n-train", type=int, default=None, help="utterances for the executors section "
                    "(default 100; --quick 12)")
    ap.add_argument("--sections", default="executors,peak_rss")
    ap.add_argument("--protocols", default="deena2009")
    ap.add_argument("--executor", default="local", choices=("local", "processes", "dask"),
                    help="executor of the peak-RSS protocol runs")
    ap.add_argument("--workers", type=int, default=2,
                    help="processes of --executor processes/dask in the peak-RSS runs (evaluate's default: 2)")
    ap.add_argument("--repeats", type=int, default=0,
                    help="peak_rss: run only this many of each protocol's repeats/folds (0: all); the peak "
                         "of one split does not grow with their number (each split's models are freed)")
    ap.add_argument("--out", default=None)
    ap.add_argument("--rss-child", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.rss_child:
        return _rss_child(args)
    args.corpus = args.corpus or str(bench_corpus("train", args.quick))
    args.n_train = args.n_train or (12 if args.quick else 100)
    if args.quick and args.repeats == 0:
        args.repeats = 1
    out_path = result_path("scaling", args.quick, args.out)
    result = json.loads(out_path.read_text()) if out_path.exists() else {}
    for k in ("command", "machine", "commit"):
        result.pop(k, None)
    result["quick"] = args.quick
    sections = {"executors": executors_section, "peak_rss": peak_rss_section}
    for name in args.sections.split(","):
        if name not in sections:
            raise SystemExit(f"--sections: unknown section {name!r}; choose among {', '.join(sections)}")
        t0 = time.perf_counter()
        result[name] = sections[name](args)
        result[name]["section_wall_s"] = round(time.perf_counter() - t0, 1)
        write_result(out_path, result)  # atomically, each section as soon as it is done
    print(json.dumps({k: result[k] for k in args.sections.split(",")}, indent=1))
    print(f"wrote {out_path}")


if __name__ == "__main__":
    from bayes_talk.base.executor import interruptible

    # `kill` stops the worker processes too, not only this one
    interruptible(main)
