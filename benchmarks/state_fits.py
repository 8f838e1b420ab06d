"""Per-state SGPDM fits of a switching family by both fit paths (issue 29, item 1).

Builds the per-state training jobs exactly as ``SwitchingModel.fit`` does for the family
``--model`` on a built corpus (features cached; the jobs are taken from the executor's
``map`` before any fit runs), then fits a seeded sample of ``--states`` of them (0: all)
in this process on one thread, each twice: through torch autograd and
``torch.optim.LBFGS`` (switch ``direct_fit`` off: the path before issue 29's change) and
through the direct path (``models/sgpdm_objective.py`` + ``gp/lbfgs.py``, the default).
Per path it records CPU seconds of this process (``time.process_time``: the machine is
shared, so wall time is recorded but CPU time is the figure to read) and the number of
objective evaluations; per state the largest relative differences of the latents and
hyperparameters between the paths and of the final log joint.

Run:  PYTHONPATH=. .venv/bin/python benchmarks/state_fits.py data/s8/train250 \\
          --model ssgpdm-phone-ctx-mean --states 24 --out benchmarks/results/state_fits.json
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"


class _Jobs(Exception):
    def __init__(self, jobs):
        super().__init__("jobs captured")
        self.jobs = jobs


class _Capture:
    """An executor whose ``map`` hands back the jobs instead of running them."""

    def map(self, fn, iterable):
        raise _Jobs(list(iterable))


def state_jobs(corpus_dir: str, kind: str) -> list[tuple]:
    """The (audio, visual, lengths, config) job of every state model of ``kind``."""
    from bayes_talk.corpus import load_corpus
    from bayes_talk.features import mfcc as _mf
    from bayes_talk.pipeline import new_model

    corpus = load_corpus(corpus_dir, cmvn="mean", fmax=_mf.FMAX_HZ, floor_dbfs=_mf.FLOOR_DBFS)
    try:
        new_model(kind).fit(list(corpus.sequences), executor=_Capture())
    except _Jobs as got:
        return got.jobs
    raise RuntimeError(f"{kind}: the model did not fit its states through the executor")


def _fit(job, direct: bool):
    from bayes_talk.base import settings
    from bayes_talk.gp.threads import torch_threads
    from bayes_talk.models import sgpdm_objective
    from bayes_talk.models.sgpdm import SGPDM

    audio, visual, lengths, cfg = job
    calls = [0]
    orig = sgpdm_objective.SGPDMObjective.__call__

    def counted(self, x):
        calls[0] += 1
        return orig(self, x)

    import bayes_talk.models.sgpdm as sgpdm_mod
    orig_lj = sgpdm_mod.program_log_joint

    def counted_lj(*a, **k):
        calls[0] += 1
        return orig_lj(*a, **k)

    sgpdm_objective.SGPDMObjective.__call__ = counted
    sgpdm_mod.program_log_joint = counted_lj
    try:
        with settings.override(direct_fit=direct), torch_threads(1):
            w, c = time.perf_counter(), time.process_time()
            m = SGPDM(**cfg).fit({"audio": audio, "visual": visual}, seq_lengths=lengths)
            w, c = time.perf_counter() - w, time.process_time() - c
    finally:
        sgpdm_objective.SGPDMObjective.__call__ = orig
        sgpdm_mod.program_log_joint = orig_lj
    return m, w, c, calls[0]


def _rel(a, b) -> float:
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    return float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-300))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("corpus")
    ap.add_argument("--model", default="ssgpdm-phone-ctx-mean")
    ap.add_argument("--states", type=int, default=24, help="seeded sample of states (0: all)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=RESULTS / "state_fits.json")
    args = ap.parse_args(argv)

    load0 = os.getloadavg()
    jobs = state_jobs(args.corpus, args.model)
    idx = np.arange(len(jobs))
    if 0 < args.states < len(jobs):
        idx = np.sort(np.random.default_rng(args.seed).choice(len(jobs), args.states, replace=False))
    _fit(jobs[idx[0]], True)      # compile the numba passes, warm the caches
    _fit(jobs[idx[0]], False)
    rows = []
    for j in idx:
        ref, w0, c0, e0 = _fit(jobs[j], False)
        new, w1, c1, e1 = _fit(jobs[j], True)
        rows.append({
            "state": int(j), "N": len(jobs[j][0]), "n_seq": len(jobs[j][2]),
            "torch": {"cpu_s": c0, "wall_s": w0, "evals": e0, "n_iter": ref.history.n_iter},
            "direct": {"cpu_s": c1, "wall_s": w1, "evals": e1, "n_iter": new.history.n_iter},
            "rel_diff_X": _rel(new.X_, ref.X_),
            "rel_diff_hyper": max(_rel(new.hyper_[k], v) for k, v in ref.hyper_.items()),
            "log_joint": {"torch": ref.history.log_joint[-1], "direct": new.history.log_joint[-1]},
        })
        print(f"state {j} N={rows[-1]['N']}: torch {c0:.2f} CPU-s, direct {c1:.2f} CPU-s, "
              f"rel diff X {rows[-1]['rel_diff_X']:.1e}", file=sys.stderr)
    tot = {p: sum(r[p]["cpu_s"] for r in rows) for p in ("torch", "direct")}
    bins = []
    for lo, hi in ((0, 50), (50, 100), (100, 200), (200, 300), (300, None)):
        sel = [r for r in rows if r["N"] >= lo and (hi is None or r["N"] < hi)]
        if sel:
            t = {p: sum(r[p]["cpu_s"] for r in sel) for p in ("torch", "direct")}
            ev = {p: sum(r[p]["evals"] for r in sel) for p in ("torch", "direct")}
            bins.append({"N_range": [lo, hi], "n_states": len(sel), "cpu_s": t,
                         "ms_per_eval": {p: 1000 * t[p] / max(ev[p], 1) for p in t},
                         "ratio_direct_over_torch": t["direct"] / t["torch"]})
    out = {
        "benchmark": "state_fits", "issue": 29, "corpus": os.path.relpath(args.corpus, Path.cwd()),
        "model": args.model, "n_state_jobs": len(jobs), "states_fitted": len(rows), "seed": args.seed,
        "threads": 1, "command": "PYTHONPATH=. python benchmarks/state_fits.py " + " ".join(
            a if not os.path.isabs(a) else os.path.relpath(a, Path.cwd()) for a in (argv or sys.argv[1:])),
        "loadavg_before": load0, "loadavg_after": os.getloadavg(), "cpus": os.cpu_count(),
        "cpu_s": tot, "ratio_direct_over_torch": tot["direct"] / tot["torch"],
        "max_rel_diff_X": max(r["rel_diff_X"] for r in rows),
        "max_rel_diff_hyper": max(r["rel_diff_hyper"] for r in rows),
        "by_size": bins, "per_state": rows,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_suffix(".tmp")
    tmp.write_text(json.dumps(out, indent=1))
    tmp.replace(args.out)
    print(json.dumps({k: out[k] for k in ("model", "states_fitted", "cpu_s", "ratio_direct_over_torch",
                                           "max_rel_diff_X", "max_rel_diff_hyper")}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
