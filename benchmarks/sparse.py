"""Training time and peak memory of the sparse SGPDM against N, beside the exact SGPDM
where it fits.

Each fit runs in a fresh child process (``multiprocessing`` spawn) so that its peak
resident memory (``resource.getrusage(RUSAGE_SELF).ru_maxrss`` of the child) is its own.
The data are the first N frames (whole utterances, the last one cut) of a built corpus
(``--corpus``: audio = MFCCs, visual = AAM parameters, one sequence per utterance) or, without
a corpus, a synthetic smooth 6-d latent trajectory pushed through random nonlinear maps
(D = 20 + 40). Both models get the same views, sequence lengths, d = 6, fixed dynamics
and the same L-BFGS iteration budget (``--iters``); reported: wall and CPU seconds of
``fit``, seconds per L-BFGS iteration, final objective, peak RSS.

``measure(n_frames, ...) -> dict`` is the entry point for other scripts (e.g.
``benchmarks/scaling.py``); ``main`` runs a list of sizes and writes
``results/sparse.json`` atomically.

Run:  PYTHONPATH=. .venv/bin/python benchmarks/sparse.py [--corpus DIR] [--sizes 1000,2000,4000,8000,15000]
      [--exact-max 2000] [--iters 20] [--inducing 150] [--out PATH]
      PYTHONPATH=. .venv/bin/python benchmarks/sparse.py --quick     # synthetic data, N = 300, 600
"""
from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import result_path, write_result

SIZES = (1000, 2000, 4000, 8000, 15000)
QUICK_SIZES = (300, 600)


def synthetic_views(n_frames: int, seed: int = 0) -> tuple[dict[str, np.ndarray], list[int]]:
    """Audio (20-d) and visual (40-d) views of a smooth 6-d trajectory; 60-frame sequences."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, n_frames / 25.0, n_frames)[:, None]
    Xt = np.sin(t * rng.uniform(0.2, 1.5, 6) + rng.uniform(0, 2 * np.pi, 6))
    views = {"audio": np.tanh(Xt @ rng.normal(size=(6, 20))) + 0.1 * rng.normal(size=(n_frames, 20)),
             "visual": np.tanh(Xt @ rng.normal(size=(6, 40))) + 0.1 * rng.normal(size=(n_frames, 40))}
    lens = [60] * (n_frames // 60)
    if n_frames % 60:
        lens.append(n_frames % 60)
    return views, lens


def corpus_views(corpus: str | os.PathLike, n_frames: int) -> tuple[dict[str, np.ndarray], list[int]]:
    """The first ``n_frames`` frames of a corpus, whole utterances in corpus order."""
    from bayes_talk.corpus import load_corpus

    seqs = list(load_corpus(corpus))
    audio, visual, lens, n = [], [], [], 0
    for s in seqs:
        rest = n_frames - n
        if rest <= 0:
            break
        take = min(s.n_frames, rest)
        if rest - take == 1 and take > 2:  # a 1-frame remainder is no sequence: leave 2 for the next
            take -= 1
        if take <= 1:
            break
        audio.append(s.mfcc[:take])
        visual.append(s.aam[:take])
        lens.append(take)
        n += take
    if n < n_frames:
        raise ValueError(f"corpus {corpus} has only {n} frames, {n_frames} requested")
    return {"audio": np.vstack(audio), "visual": np.vstack(visual)}, lens


def _child(kind: str, views, lens, settings: dict, queue) -> None:
    import torch

    from bayes_talk.models.sgpdm import SGPDM
    from bayes_talk.models.sparse_sgpdm import SparseSGPDM

    torch.set_num_threads(settings.pop("threads"))
    calls = [0]

    class Counted(SparseSGPDM if kind == "sparse" else SGPDM):
        """The model, counting the evaluations of its objective (the fit's L-BFGS closure
        calls ``log_joint``)."""

        def log_joint(self):
            calls[0] += 1
            return super().log_joint()

    model = Counted(**settings)
    w0, c0 = time.perf_counter(), time.process_time()
    model.fit(views, seq_lengths=lens)
    wall, cpu = time.perf_counter() - w0, time.process_time() - c0
    steps = len(model.history.log_joint) - 1
    # fit evaluates the objective once before and once after each outer L-BFGS step, besides the closure
    n_evals = calls[0] - 1 - steps
    queue.put({"wall_s": wall, "cpu_s": cpu, "lbfgs_outer_steps": steps, "objective_evaluations": n_evals,
               "cpu_s_per_evaluation": cpu / max(n_evals, 1),
               "objective_start": model.history.log_joint[0], "objective_end": model.history.log_joint[-1],
               "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0})


def _run(kind: str, views, lens, settings: dict) -> dict:
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    p = ctx.Process(target=_child, args=(kind, views, lens, dict(settings), q))
    p.start()
    try:
        out = q.get()
    finally:
        p.join()
    if p.exitcode != 0:
        raise RuntimeError(f"{kind} fit failed in its child process (exit code {p.exitcode})")
    return out


def measure(n_frames: int, corpus: str | os.PathLike | None = None, n_inducing: int = 150, iters: int = 20,
            exact: bool | None = None, exact_max: int = 2000, latent_dim: int = 6, threads: int = 1,
            seed: int = 0) -> dict:
    """Fit the sparse SGPDM (and the exact one when ``exact``, default N ≤ ``exact_max``)
    on ``n_frames`` frames with ``iters`` L-BFGS iterations; each fit in its own process.

    Returns {"N", "sequences", "sparse": {...}, "exact": {...} or None} with wall/CPU
    seconds, seconds per iteration, objective before/after and peak RSS (MB) per fit.
    """
    views, lens = corpus_views(corpus, n_frames) if corpus else synthetic_views(n_frames, seed)
    base = {"latent_dim": latent_dim, "max_iter": iters, "seed": seed, "threads": threads}
    out: dict = {"N": n_frames, "sequences": len(lens), "data": str(corpus) if corpus else "synthetic"}
    sp = _run("sparse", views, lens, {**base, "n_inducing": n_inducing})
    sp["s_per_iter"] = sp["wall_s"] / iters
    sp["n_inducing"] = min(n_inducing, n_frames)
    out["sparse"] = sp
    if exact is None:
        exact = n_frames <= exact_max
    out["exact"] = None
    if exact:
        ex = _run("exact", views, lens, base)
        ex["s_per_iter"] = ex["wall_s"] / iters
        out["exact"] = ex
    return out



def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--corpus", default=None, help="built corpus (default: synthetic data)")
    p.add_argument("--sizes", default=",".join(map(str, SIZES)), help="comma-separated frame counts")
    p.add_argument("--exact-max", type=int, default=2000, help="fit the exact SGPDM up to this N")
    p.add_argument("--iters", type=int, default=20, help="L-BFGS iterations per fit")
    p.add_argument("--inducing", type=int, default=150, help="inducing inputs M")
    p.add_argument("--threads", type=int, default=1, help="torch threads in each fit")
    p.add_argument("--quick", action="store_true", help=f"synthetic data, N = {QUICK_SIZES}")
    p.add_argument("--out", type=Path, default=None, help="default results/sparse.json (--quick: results/quick/)")
    args = p.parse_args(argv)
    args.out = result_path("sparse", args.quick, args.out)
    if args.quick:
        args.corpus, args.sizes, args.exact_max = None, ",".join(map(str, QUICK_SIZES)), max(QUICK_SIZES)
    sizes = [int(s) for s in args.sizes.split(",") if s.strip()]
    res = {"benchmark": "sparse", "machine": {"loadavg_at_start": os.getloadavg()},
           "settings": vars(args) | {"out": str(args.out)}, "sizes": []}
    print(f"{'N':>6} {'sparse s':>9} {'s/iter':>7} {'RSS MB':>7} | {'exact s':>8} {'s/iter':>7} {'RSS MB':>7}")
    for n in sizes:
        r = measure(n, args.corpus, args.inducing, args.iters, exact_max=args.exact_max, threads=args.threads)
        res["sizes"].append(r)
        s, e = r["sparse"], r["exact"]
        ex = f"{e['wall_s']:>8.1f} {e['s_per_iter']:>7.2f} {e['peak_rss_mb']:>7.0f}" if e else f"{'-':>8} {'-':>7} {'-':>7}"
        print(f"{n:>6} {s['wall_s']:>9.1f} {s['s_per_iter']:>7.2f} {s['peak_rss_mb']:>7.0f} | {ex}", flush=True)
        write_result(args.out, res)
    res["machine"]["loadavg_at_end"] = os.getloadavg()
    write_result(args.out, res)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
