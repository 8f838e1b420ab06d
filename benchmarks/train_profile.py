"""Where ``bayes-talk train`` spends its time, phase by phase (issue 29 item 1).

Runs :func:`bayes_talk.pipeline.train` -- what ``bayes-talk train CORPUS --out MODEL`` runs:
the default family (``pipeline.DEFAULT_MODEL``) with its band calibration
(``pipeline.DEFAULT_CALIBRATION``) and the aligner -- in this process on a built corpus
whose features are cached, with explicit timers wrapped around the library's own
functions (no change to the library):

============================  =============================================================
phase                          what is timed
============================  =============================================================
features_load                  ``data.corpus.load_corpus`` (the cached features)
state_model                    ``SwitchingModel.fit`` minus its per-state SGPDM fits: audio
                               context, phonetic context, VLMM / phone states, the
                               subsequences, the entry distributions
state_init                     per state: ``SGPDM._check_views``, ``_init_latents`` and
                               ``_init_params`` (PCA, median distance, tensors)
state_lbfgs                    per state: ``SGPDM._optimise`` (torch L-BFGS on the log joint)
state_finalise                 per state: ``SGPDM._finalise`` (the predictors' Cholesky factors)
calibration_synthesis          the held-out syntheses of the band calibration
                               (``synthesis.posterior.sample_synthesis``)
calibration_other              ``fit_band_calibration`` minus its model fit and syntheses
alignment                      ``alignment.commands.fit_alignment`` (the aligner)
saving                         model, AAM, calibration, descriptor, bundle manifest
============================  =============================================================

Every phase is split by where it runs: the main model's fit (``main``) or the band
calibration's second model (``calibration``). The per-state fits run in this process
(``--workers 1``, the default here) so that they can be timed; with ``--workers 2`` they
run in worker processes and only their wall time inside ``SwitchingModel.fit`` is seen
(``state_fits_wall``). Per state the number of frames N, the L-BFGS time and the number
of objective evaluations are recorded, so the cost can be read against N.

The machine is shared: ``os.getloadavg()`` is recorded before and after the run, and the
process's own CPU time beside the wall time. ``--cprofile`` adds the top functions by
cumulative and by own time (cProfile slows Python-heavy code, so its wall time is not the
one to quote).

Run:  PYTHONPATH=. .venv/bin/python benchmarks/train_profile.py data/s8/train250 \
          [--workers 1] [--out benchmarks/results/train_profile.json] [--cprofile]
"""
from __future__ import annotations

import argparse
import contextlib
import functools
import json
import os
import platform
import resource
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"


class PhaseTimer:
    """Exclusive wall time per phase: time spent inside a nested phase counts for the
    inner one only. ``section`` is "main" or "calibration" (set by the wrappers)."""

    def __init__(self) -> None:
        self.stack: list[list] = []       # [name, start, child_time]
        self.totals: dict[str, float] = defaultdict(float)
        self.counts: dict[str, int] = defaultdict(int)
        self.section = "main"

    @contextlib.contextmanager
    def phase(self, name: str):
        key = f"{self.section}/{name}"
        frame = [key, time.perf_counter(), 0.0]
        self.stack.append(frame)
        try:
            yield
        finally:
            self.stack.pop()
            total = time.perf_counter() - frame[1]
            self.totals[key] += total - frame[2]
            self.counts[key] += 1
            if self.stack:
                self.stack[-1][2] += total


def _wrap(owner, attr: str, timer: PhaseTimer, name: str, after=None) -> None:
    """Replace ``owner.attr`` by a version timed as phase ``name``."""
    fn = getattr(owner, attr)

    @functools.wraps(fn)
    def timed(*a, **k):
        with timer.phase(name):
            out = fn(*a, **k)
        if after is not None:
            after(a, k, out)
        return out

    setattr(owner, attr, timed)


def instrument(timer: PhaseTimer, per_state: list[dict]) -> None:
    """Wrap the library functions of the table in the module docstring."""
    import bayes_talk.alignment.commands as align_mod
    import bayes_talk.base.bundle as bundle_mod
    import bayes_talk.corpus as corpus_mod
    import bayes_talk.calibration.bands as bc_mod
    import bayes_talk.posterior.sampling as post_mod
    from bayes_talk.estimators.switching import SwitchingSGPDM
    from bayes_talk.models.sgpdm import SGPDM
    from bayes_talk.models.switching import SwitchingModel

    _wrap(corpus_mod, "load_corpus", timer, "features_load")
    _wrap(SwitchingModel, "fit", timer, "state_model")
    for attr in ("_check_views", "_init_latents", "_init_params"):
        _wrap(SGPDM, attr, timer, "state_init")
    _wrap(SGPDM, "_finalise", timer, "state_finalise")

    from bayes_talk.models.sgpdm_objective import SGPDMObjective

    opt = SGPDM._optimise
    lj = SGPDM.log_joint
    direct = SGPDMObjective.__call__
    n_eval = [0]  # objective evaluations: torch log joints and direct (NumPy) evaluations alike

    def counted_log_joint(self):
        n_eval[0] += 1
        return lj(self)

    def counted_direct(self, x):
        n_eval[0] += 1
        return direct(self, x)

    SGPDM.log_joint = counted_log_joint
    SGPDMObjective.__call__ = counted_direct

    @functools.wraps(opt)
    def timed_opt(self, *a, **k):
        n0 = n_eval[0]
        t0 = time.perf_counter()
        with timer.phase("state_lbfgs"):
            out = opt(self, *a, **k)
        per_state.append({"section": timer.section, "N": int(sum(self.seq_lengths_)),
                          "n_seq": len(self.seq_lengths_), "lbfgs_s": time.perf_counter() - t0,
                          "n_eval": int(n_eval[0] - n0), "n_iter": int(self.history.n_iter)})
        return out

    SGPDM._optimise = timed_opt

    fbc = bc_mod.fit_band_calibration

    @functools.wraps(fbc)
    def timed_fbc(*a, **k):
        timer.section = "calibration"
        try:
            with timer.phase("calibration_other"):
                return fbc(*a, **k)
        finally:
            timer.section = "main"

    bc_mod.fit_band_calibration = timed_fbc
    _wrap(post_mod, "sample_synthesis", timer, "calibration_synthesis")
    _wrap(align_mod, "fit_alignment", timer, "alignment")
    for owner, attr in ((SwitchingSGPDM, "save"), (bundle_mod, "write_bundle_manifest"),
                        (bc_mod.BandCalibration, "save")):
        _wrap(owner, attr, timer, "saving")
    _wrap(bundle_mod, "write_descriptor", timer, "saving")


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("corpus", help="a built corpus with cached features (e.g. data/s8/train250)")
    ap.add_argument("--workers", type=int, default=1, help="processes for the per-state models (1: timed here)")
    ap.add_argument("--model", default=None, help="model family (default: pipeline.DEFAULT_MODEL)")
    ap.add_argument("--no-calibration", action="store_true", help="skip the band calibration")
    ap.add_argument("--cprofile", action="store_true", help="also profile with cProfile (slower)")
    ap.add_argument("--out", default=str(RESULTS / "train_profile.json"))
    args = ap.parse_args(argv)

    import torch

    from bayes_talk import pipeline

    timer = PhaseTimer()
    per_state: list[dict] = []
    instrument(timer, per_state)
    kind = args.model or pipeline.DEFAULT_MODEL
    cal = None if args.no_calibration else pipeline.DEFAULT_CALIBRATION
    load_before = os.getloadavg()
    prof = None
    if args.cprofile:
        import cProfile

        prof = cProfile.Profile()
    with tempfile.TemporaryDirectory() as tmp:
        c0 = time.process_time()
        ch0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        if prof is not None:
            prof.enable()
        pipeline.train(args.corpus, kind, Path(tmp) / "model", workers=args.workers, calibrate_bands=cal)
        if prof is not None:
            prof.disable()
        wall = time.perf_counter() - t0
        cpu = time.process_time() - c0
        ch1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    load_after = os.getloadavg()
    phases = {k: round(v, 3) for k, v in sorted(timer.totals.items())}
    by_phase: dict[str, float] = defaultdict(float)
    for k, v in timer.totals.items():
        by_phase[k.split("/", 1)[1]] += v
    lb = [s["lbfgs_s"] for s in per_state]
    Ns = np.array([s["N"] for s in per_state])
    bins = [(0, 50), (50, 100), (100, 200), (200, 300), (300, 10**9)]
    by_size = []
    for lo, hi in bins:
        sel = [s for s in per_state if lo <= s["N"] < hi]
        if sel:
            by_size.append({"N_range": [lo, hi if hi < 10**9 else None], "n_states": len(sel),
                            "lbfgs_s": round(sum(s["lbfgs_s"] for s in sel), 2),
                            "n_eval": int(sum(s["n_eval"] for s in sel)),
                            "ms_per_eval": round(1e3 * sum(s["lbfgs_s"] for s in sel)
                                                 / max(1, sum(s["n_eval"] for s in sel)), 2)})
    out = {
        "benchmark": "train_profile", "issue": 29,
        "corpus": os.path.relpath(args.corpus, Path(__file__).resolve().parent.parent),
        "model": kind, "calibration": cal, "workers": args.workers, "cprofile": bool(args.cprofile),
        "wall_s": round(wall, 2), "cpu_s_this_process": round(cpu, 2),
        "cpu_s_children": round((ch1.ru_utime + ch1.ru_stime) - (ch0.ru_utime + ch0.ru_stime), 2),
        "loadavg_before": [round(x, 2) for x in load_before], "loadavg_after": [round(x, 2) for x in load_after],
        "phases_s": phases,
        "by_phase_s": {k: round(v, 2) for k, v in sorted(by_phase.items(), key=lambda kv: -kv[1])},
        "untimed_s": round(wall - sum(timer.totals.values()), 2),
        "per_state_summary": {"n_fits": len(per_state), "N_median": float(np.median(Ns)) if len(Ns) else None,
                              "N_max": int(Ns.max()) if len(Ns) else None, "lbfgs_total_s": round(sum(lb), 2),
                              "n_eval_total": int(sum(s["n_eval"] for s in per_state)),
                              "by_size": by_size},
        "per_state": per_state,
        "machine": {"cpus": os.cpu_count(), "torch_threads": torch.get_num_threads(),
                    "python": platform.python_version(), "torch": torch.__version__},
    }
    if prof is not None:
        import pstats

        st = pstats.Stats(prof)
        rows = []
        for (f, line, fn), (cc, nc, tt, ct, _) in st.stats.items():
            rows.append({"function": f"{os.path.basename(f)}:{line}({fn})", "calls": nc,
                         "tottime_s": round(tt, 3), "cumtime_s": round(ct, 3)})
        out["cprofile_cumulative"] = sorted(rows, key=lambda r: -r["cumtime_s"])[:40]
        out["cprofile_tottime"] = sorted(rows, key=lambda r: -r["tottime_s"])[:40]
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    tmp_out = Path(args.out).with_suffix(".json.tmp")
    tmp_out.write_text(json.dumps(out, indent=1) + "\n", encoding="utf-8")
    os.replace(tmp_out, args.out)
    summary = {k: out[k] for k in ("wall_s", "cpu_s_this_process", "cpu_s_children", "loadavg_before",
                                   "loadavg_after", "by_phase_s", "untimed_s")}
    summary["per_state"] = {k: v for k, v in out["per_state_summary"].items()}
    print(json.dumps(summary, indent=1))
    return out


if __name__ == "__main__":
    from bayes_talk.base.executor import interruptible

    # `kill` stops the worker processes too, not only this one
    sys.exit(0 if interruptible(main) else 1)
