"""How well the synthesis samplers do on one held-out utterance of a trained model: convergence,
effective sample size per second, and the raw (uncalibrated) predictive's accuracy.

Each sampler with its library defaults (``--methods``, default ``laplace,pg-nuts``; also
``nuts``, ``emcee``, ``vi``), side by side in one run, on one utterance of a held-out corpus
(``--model DIR --test-corpus DIR --aam AAM --utterance NAME``, its first ``--frames`` frames;
the corpus is projected through the training corpus's AAM). Per sampler: wall time (MAP +
sampler), warm-up and sampling seconds, the smallest bulk and tail ESS over the T·d latent
coordinates, rank R-hat, ESS per second, and the wall time to bulk ESS 400 = warm-up seconds +
sampling seconds × 400 / (smallest bulk ESS) (measured, not extrapolated, when the run reached
400; a lower bound when R-hat is above 1.01, flagged ``seconds_to_ess_400_is_lower_bound``).
NUTS and pg-nuts rows also hold the AAM parameters' ``aam_rhat_max``, ``aam_ess_bulk_min`` and
``aam_ess_tail_min`` (what users consume). VI and Laplace draw iid from an approximation q:
their row holds PSIS k̂ and the PSIS effective sample size (``reliable`` only where k̂ ≤ 0.7).
Every row holds ``raw_accuracy``: the uncalibrated predictive's coverage of the utterance's own
AAM track at 50/80/90/95 %, band widths, CRPS, NLPD and AMSE. ``--nuts-chains``,
``--nuts-warmup``, ``--draws`` (pooled) and ``--emcee-warmup`` override the library defaults
(recorded under ``budget``); ``--workers`` runs the chains in that many processes;
``--save-draws STEM.npz`` keeps each sampler's draws (``STEM_METHOD.npz``).
Writes ``benchmarks/results/posterior_efficiency.json``:

    PYTHONPATH=. python benchmarks/posterior.py --model MODEL_DIR --test-corpus data/test3 \
        --aam data/train250/aam.npz --utterance utt0004 --workers 2 [--frames 75]

``--pool RUN.json ...`` pools the ``raw_accuracy`` of runs on different utterances (of one
model, test corpus and AAM) into one figure per sampler, weighting each run by its entries
(frames × AAM parameters) -> ``benchmarks/results/posterior_coverage.json``.

``--quick``: the same code path at toy size: the quick mode's model and held-out corpus
(``benchmarks/common.py``), 10 frames of its first utterance, Laplace and pg-nuts with 2 chains
of 8 draws after 10 warm-up, then ``--pool`` of that run.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
import warnings
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from bayes_talk.evaluation.metrics import (
    amse,
    coverage,
    crps_ensemble,
    crps_gaussian,
    nlpd_gaussian,
)
from bayes_talk.posterior.diagnostics import RHAT_MAX
from bayes_talk.posterior.sampling import sample_synthesis
from bayes_talk.synthesis.result import DEFAULT_LEVELS
from benchmarks.common import ROOT, bench_corpus, bench_model, result_path, write_result


def evaluate(truth, means, vars_, bands, samples) -> dict:
    out = {"coverage": {}, "width": {}}
    for q in DEFAULT_LEVELS:
        lo, hi = [b[q][0] for b in bands], [b[q][1] for b in bands]
        out["coverage"][str(q)] = coverage(truth, lo, hi)
        out["width"][str(q)] = float(np.mean(np.concatenate([(h - lo_).ravel() for lo_, h in zip(lo, hi)])))
    if samples is None:
        out["crps"] = crps_gaussian(truth, means, [np.sqrt(v) for v in vars_])
    else:
        out["crps"] = crps_ensemble(truth, samples)
    out["nlpd"] = nlpd_gaussian(truth, means, vars_)
    out["amse"] = amse(truth, means)
    return out


def _efficiency_budget(args, method: str) -> dict:
    """``sample_synthesis`` keywords overriding the library defaults (``--nuts-chains``,
    ``--nuts-warmup``, ``--draws`` (pooled over chains), ``--emcee-warmup``); {} = the defaults."""
    out = {}
    if method in ("nuts", "pg-nuts"):
        if args.nuts_chains is not None:
            out["chains"] = args.nuts_chains
        if args.nuts_warmup is not None:
            out["warmup"] = args.nuts_warmup
    if method == "emcee" and args.emcee_warmup is not None:
        out["warmup"] = args.emcee_warmup
    if args.draws is not None:
        out["n_draws"] = args.draws
    return out


def efficiency(args) -> None:
    """The samplers side by side on one utterance (see the module docstring)."""
    from bayes_talk.corpus import load_corpus
    from bayes_talk.pipeline import corpus_front_end, load_trained

    tm = load_trained(args.model)
    model = tm.uncalibrated
    seqs = {s.name: s for s in load_corpus(args.test_corpus, aam=args.aam, cache=False,
                                           **corpus_front_end(tm.audio)).sequences}
    s = seqs[args.utterance]
    T = min(args.frames, s.n_frames) if args.frames else s.n_frames
    res = {"model": _rel(args.model), "test_corpus": _rel(args.test_corpus), "aam": _rel(args.aam),
           "utterance": s.name, "frames": T, "aam_dims": int(s.aam.shape[1]), "seconds_of_speech": T / 25.0, "ess_target": 400, "samplers": {}}
    out_path = result_path("posterior_efficiency", args.quick, args.out)
    for method in args.methods.split(","):
        if method not in ("nuts", "pg-nuts", "emcee", "vi", "laplace"):
            raise SystemExit(f"--efficiency compares nuts, pg-nuts, emcee, vi and laplace, got {method!r}")
        print(f"{method} ...", flush=True)
        load0 = os.getloadavg()[0]
        t0 = time.perf_counter()
        skw = {"max_steps": args.emcee_max_steps} if method == "emcee" and args.emcee_max_steps else {}
        if method in ("nuts", "pg-nuts") and args.workers:
            skw["workers"] = args.workers
        budget = _efficiency_budget(args, method)
        p = sample_synthesis(model, s.mfcc[:T], s.labels[:T], method=method, seed=args.seed, log_warnings=False,
                             sampler_kw=skw or None, **budget)
        wall = time.perf_counter() - t0
        d = p.diagnostics
        # the raw (uncalibrated) predictive against the held-out utterance's own AAM track
        raw = evaluate([s.aam[:T]], [p.mean], [p.var], [p.quantiles(DEFAULT_LEVELS)],
                       [p.sample(1000)])
        # the predictive as synth ships it: with the model's observation term (every method alike)
        shipped = _shipped_accuracy(model, p, s.aam[:T], s.labels[:T])
        if args.save_draws and p.latent_draws is not None:
            path = args.save_draws.with_name(f"{args.save_draws.stem}_{method}.npz")
            np.savez(path, latents=p.latent_draws, aam_mean=p.draw_mean, truth=s.aam[:T])
        if method in ("vi", "laplace"):
            res["samplers"][method] = row = _iid_efficiency(p, wall, load0, budget)
            row["raw_accuracy"] = raw
            row.update(shipped)
            print(json.dumps({k: v for k, v in row.items() if k != "diagnostics"}, default=str), flush=True)
            _write_atomic(out_path, res)
            continue
        sampler_s = d["sampler_seconds"]
        if method in ("nuts", "pg-nuts"):
            # warmup_seconds sums the chains' (and nuts's pilot, run before them); with chains in
            # parallel processes the wall-clock warm-up is the pilot plus the rest of the sampler's
            # wall time times the warm-up's share of the chains' time
            pilot_s = float(d.get("pilot_seconds", 0.0))
            chain_s = float(np.sum(d.get("chain_seconds", [sampler_s - pilot_s])))
            share = min(1.0, (d["warmup_seconds"] - pilot_s) / chain_s) if chain_s > 0 else 0.0
            warm_s = pilot_s + (sampler_s - pilot_s) * share
        else:
            warm_s = sampler_s * d["warmup"] / d["steps"]
        draw_s = sampler_s - warm_s
        ess = d["ess_bulk_min"]
        to_400 = warm_s + draw_s * 400.0 / ess if ess > 0 else float("inf")
        converged = d["rhat_max"] <= RHAT_MAX
        row = {k: d[k] for k in ("rhat_max", "ess_bulk_min", "ess_tail_min", "mcse_mean_max", "n_chains", "n_draws")}
        # what users consume: the AAM parameters' means at the draws (per frame)
        row.update({k: d[k] for k in ("aam_rhat_max", "aam_ess_bulk_min", "aam_ess_tail_min") if k in d})
        row.update(wall_seconds=wall, setup_seconds=wall - sampler_s, sampler_seconds=sampler_s,
                   warmup_seconds=warm_s, sampling_seconds=draw_s, ess_bulk_per_second=ess / sampler_s,
                   ess_bulk_per_sampling_second=ess / draw_s if draw_s > 0 else None,
                   seconds_to_ess_400=to_400 + (wall - sampler_s), reached_ess_400=bool(ess >= 400),
                   # ESS grows linearly with the draws only once the chains agree: with R-hat above
                   # the threshold the extrapolated time is a lower bound, not an estimate
                   seconds_to_ess_400_is_lower_bound=bool(not converged and ess < 400),
                   rhat_ok=bool(converged), budget=budget or "library defaults", sampler_kw=skw,
                   warnings=p.warnings, loadavg_start_end=[load0, os.getloadavg()[0]],
                   diagnostics={k: v for k, v in d.items() if np.ndim(v) == 0 or isinstance(v, list)})
        row["raw_accuracy"] = raw
        row.update(shipped)
        res["samplers"][method] = row
        print(json.dumps({k: v for k, v in row.items() if k != "diagnostics"}, default=str), flush=True)
        _write_atomic(out_path, res)


def _shipped_accuracy(model, p, truth, labels) -> dict:
    """``accuracy`` (the predictive with the model's observation term, as ``synth`` ships it)
    and ``raw_mixture_accuracy`` (without it), each scored as ``evaluate`` scores: coverage of the
    exact bands, mixture NLPD, CRPS (bayes_talk.evaluation.calibration); empty for a model
    without the term."""
    from bayes_talk.evaluation.calibration import score_utterance, summarise_calibration

    if getattr(model, "face_noise_", None) is None:
        return {}

    def scored(r) -> dict:
        sm = summarise_calibration([score_utterance(r, truth)])
        return {"coverage": {str(q): sm["coverage"][f"{q:g}"]["pooled"] for q in DEFAULT_LEVELS},
                "width": {str(q): sm["width"][f"{q:g}"] for q in DEFAULT_LEVELS},
                "crps": sm["crps"]["mean"], "nlpd": sm["nlpd"]["mean"], "amse": sm["mse"]["mean"]}
    return {"accuracy": scored(model.observe(p, labels)), "raw_mixture_accuracy": scored(p)}


def _write_atomic(path: Path, res: dict) -> None:
    write_result(path, json.loads(json.dumps(res, default=str)))


def _rel(path) -> str:
    return os.path.relpath(Path(path).resolve(), ROOT)


#: the per-entry means pooled besides the coverages and widths
SCALARS = ("crps", "nlpd", "amse")


def pool(runs: list[tuple[str, dict]], dims: int, key: str = "raw_accuracy") -> dict:
    """The entry-weighted means of every sampler's ``key`` (``raw_accuracy``, or ``accuracy``:
    with the model's observation term) over ``runs`` (name, JSON)."""
    keys = {(r["model"], r["test_corpus"], r["aam"]) for _, r in runs}
    if len(keys) != 1:
        raise SystemExit(f"the runs differ in model / test corpus / AAM: {sorted(keys)}")
    names = [r["utterance"] for _, r in runs]
    if len(set(names)) != len(names):
        raise SystemExit(f"an utterance appears twice: {names}")
    out = {}
    for method in sorted({m for _, r in runs for m in r["samplers"]}):
        rows = [(r["utterance"], r["frames"] * dims, r["samplers"][method][key])
                for path, r in runs if key in r["samplers"].get(method, {})]
        if not rows:
            continue
        n = sum(w for _, w, _ in rows)
        acc = {"utterances": [u for u, _, _ in rows], "entries": n}
        for part in ("coverage", "width"):
            acc[part] = {q: sum(w * a[part][q] for _, w, a in rows) / n for q in rows[0][2][part]}
        for k in SCALARS:
            acc[k] = sum(w * a[k] for _, w, a in rows) / n
        acc["per_utterance"] = {u: {"coverage": a["coverage"], "amse": a["amse"], "nlpd": a["nlpd"]}
                                for u, _, a in rows}
        out[method] = acc
    return out


def pool_runs(paths: list[Path], dims: int | None, out: Path) -> dict:
    """``--pool``: the runs' raw accuracy pooled over their utterances, written to ``out``."""
    runs = [(str(p), json.loads(Path(p).read_text())) for p in paths]
    if dims is None:
        dims = _aam_dims(runs[0][1])
    res = {"runs": [_rel(p) for p, _ in runs], "dims": dims, "samplers": pool(runs, dims),
           "shipped": pool(runs, dims, "accuracy")}
    write_result(out, res)
    for m, acc in res["samplers"].items():
        print(f"{m}: {len(acc['utterances'])} utterances, coverage {acc['coverage']}", flush=True)
    return res


def _aam_dims(run: dict) -> int:
    """AAM parameters per frame of a run (recorded as ``aam_dims``)."""
    if "aam_dims" not in run:
        raise SystemExit("the runs do not record aam_dims: give --dims (the model's AAM parameters per frame)")
    return int(run["aam_dims"])


def _iid_efficiency(p, wall: float, load0: float, budget: dict) -> dict:
    """VI and Laplace give iid draws of an approximation q: their efficiency for p is that
    of importance sampling, the PSIS effective sample size of the k̂ draws, and it means
    something only where k̂ ≤ 0.7 (``reliable``)."""
    from bayes_talk.posterior.diagnostics import KHAT_MAX

    d = p.diagnostics
    ess = d["psis_ess"]
    # Laplace's time: everything after the MAP is the Hessian and the draws, counted in wall
    sampler_s = d.get("sampler_seconds", wall)
    reliable = bool(d["khat"] <= KHAT_MAX)
    return {"khat": d["khat"], "psis_ess": ess, "khat_draws": d["khat_draws"], "wall_seconds": wall,
            "sampler_seconds": sampler_s, "psis_ess_per_second": ess / sampler_s if sampler_s > 0 else None,
            "reliable": reliable, "reached_ess_400": bool(reliable and ess >= 400),
            "budget": budget or "library defaults", "warnings": p.warnings,
            "loadavg_start_end": [load0, os.getloadavg()[0]],
            "diagnostics": {k: v for k, v in d.items() if np.ndim(v) == 0 or isinstance(v, list)}}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", type=Path, default=None, help="directory written by `bayes-talk train` "
                    "(default: the suite's model)")
    ap.add_argument("--test-corpus", type=Path, default=None, help="held-out corpus (default: the suite's)")
    ap.add_argument("--aam", type=Path, default=None, help="the training corpus's AAM (aam.npz; default: the suite's)")
    ap.add_argument("--utterance", default=None, help="utterance name in --test-corpus (default: its first)")
    ap.add_argument("--frames", type=int, default=None, help="first frames (default all)")
    ap.add_argument("--methods", default="laplace,pg-nuts")
    ap.add_argument("--emcee-max-steps", type=int, default=None,
                    help="bound emcee's run-on for the autocorrelation rule (default: the library's)")
    ap.add_argument("--draws", type=int, default=None, help="draws kept, pooled over chains (default: the library's)")
    ap.add_argument("--nuts-warmup", type=int, default=None, help="default: the library's")
    ap.add_argument("--nuts-chains", type=int, default=None, help="default: the library's")
    ap.add_argument("--emcee-warmup", type=int, default=None, help="default: the library's")
    ap.add_argument("--workers", type=int, default=None,
                    help="NUTS/pg-nuts chains in this many processes (default: in-process)")
    ap.add_argument("--save-draws", type=Path, default=None,
                    help="write each sampler's draws to STEM_METHOD.npz (latents (C, S, T, d), "
                         "aam_mean (C, S, T, D), truth (T, D))")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--pool", type=Path, nargs="+", default=None, metavar="RUN",
                    help="pool the raw accuracy of these runs (this script's JSON) -> posterior_coverage.json")
    ap.add_argument("--dims", type=int, default=None, help="with --pool: AAM parameters per frame (default: the model's)")
    ap.add_argument("--quick", action="store_true", help="toy size (the quick model, 10 frames, short chains)")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    warnings.filterwarnings("ignore", category=FutureWarning)
    if args.pool:
        pool_runs(args.pool, args.dims, result_path("posterior_coverage", args.quick, args.out))
        return
    if args.quick:
        args.frames = args.frames or 10
        args.nuts_chains, args.nuts_warmup, args.draws = 2, 10, 16
    args.model = args.model or bench_model(args.quick)
    args.test_corpus = args.test_corpus or bench_corpus("test", args.quick)
    args.aam = args.aam or bench_corpus("train", args.quick) / "aam.npz"
    if args.utterance is None:
        from bayes_talk.corpus import load_corpus

        args.utterance = min(s.name for s in load_corpus(args.test_corpus, aam=args.aam).sequences)
    efficiency(args)
    if args.quick:
        pool_runs([result_path("posterior_efficiency", True, args.out)], args.dims,
                  result_path("posterior_coverage", True))


if __name__ == "__main__":
    from bayes_talk.base.executor import interruptible

    # `kill` stops the worker processes too, not only this one
    interruptible(main)
