"""Calibration of the synthesis posterior (DESIGN.md §6): MAP vs Laplace vs NUTS vs emcee.

Data: ``--corpus DIR`` loads a built corpus (``bayes_talk.corpus.load_corpus``) and
holds out ``--n-test`` utterances (seeded permutation; ``--n-train`` are trained on);
without it, toy data from tests/toydata.py (``make_utterances(24, seed=0)`` to train,
``make_utterances(n_test, seed=1, mean_len=30)`` held out). Model: ``SwitchingSGPDM``
(VLMM states) with the small test configuration on toy data, defaults on a corpus.

Systems, each on every held-out utterance (smoothness "frame"):
* ``map``: ``model.synthesize`` - Algorithm 1's latents, Gaussian N(μ_Z, σ²_Z/w²) (GP variance only);
* ``laplace`` / ``nuts`` / ``emcee``: ``sample_synthesis(method=...)``, the whole-utterance
  posterior's visual mixture.

Metrics pooled over every (frame, dimension) entry of the held-out utterances:
coverage of the central 50/80/90/95 % bands (MAP: Gaussian quantiles; samplers:
``SynthesisResult.quantiles``, exact mixture quantiles), mean band width, CRPS
(MAP: closed form; samplers: ``crps_ensemble`` on 1000 mixture samples), NLPD of a
Gaussian with the predictive mean and variance (moment-matched mixture for samplers),
AMSE of the mean, seconds per frame (wall, 1 torch thread), and the worst-case
diagnostics over utterances (max split R-hat, min bulk/tail ESS, divergences, acceptance,
utterances whose joint MAP converged).

    .venv/bin/python benchmarks/posterior.py [--corpus DIR] [--n-test 3] [--draws 200]
        [--nuts-warmup 150] [--emcee-warmup 500] [--methods map,laplace,nuts,emcee]
        [--out benchmarks/results/posterior.json]

Sampler efficiency (``--efficiency``, issue 10): NUTS, pg-nuts, emcee and VI (and Laplace) with their
library defaults, side by side in one run, on one held-out utterance of a trained model
(``--model DIR --test-corpus DIR --utterance NAME``, its first ``--frames`` frames; the
corpus is projected through the training AAM given by ``--aam``). Per sampler: wall
time (MAP + sampler), warm-up and sampling seconds, the smallest bulk and tail ESS over the
T·d latent coordinates, rank R-hat, ESS per second, and the wall time to bulk ESS 400
= warm-up seconds + sampling seconds × 400 / (smallest bulk ESS) (ESS grows linearly
with the draws of a converged chain; measured, not extrapolated, when the run reached
400; when R-hat is above 1.01 the chains have not met and that time is only a lower
bound, flagged ``seconds_to_ess_400_is_lower_bound``). VI and Laplace draw iid from an
approximation q: their row holds PSIS k̂ and the PSIS effective sample size of the k̂
draws (and ESS per second), ``reliable`` only where k̂ ≤ 0.7. ``--nuts-chains``, ``--nuts-warmup``,
``--draws`` (pooled) and ``--emcee-warmup`` override the library defaults (recorded under
``budget``); ``--workers`` runs NUTS/pg-nuts chains in that many processes, ``--coords``
sets their coordinates and ``--pg-frame-tries K``, ``--pg-frame-modes on|off``, ``--pg-block-len L``, ``--pg-neighbours on|off``, ``--pg-pairs on|off``, ``--pg-adapt-weights on|off``, ``--pg-block-sweeps R``, ``--pg-adapt-moments on|off``, ``--pg-adapt-clusters on|off`` pg-nuts's
updates of the isolated frames and short dynamics blocks (``sampler_kw``; default: the library's). NUTS and pg-nuts rows also hold the AAM parameters'
``aam_rhat_max``, ``aam_ess_bulk_min`` and ``aam_ess_tail_min`` (what users consume). Every row
holds ``raw_accuracy``: the uncalibrated predictive's coverage of the utterance's own AAM track
at 50/80/90/95 %, band widths, CRPS, NLPD and AMSE (as above, on the one utterance);
``--save-draws STEM.npz`` keeps each sampler's draws (``STEM_METHOD.npz``). Writes ``benchmarks/results/posterior_efficiency.json``:

    PYTHONPATH=. python benchmarks/posterior.py --efficiency --model MODEL_DIR \
        --test-corpus data/v2/heldout40 --aam data/v2/train250/aam.npz \
        --utterance utt0001 [--frames 75] [--methods nuts,emcee] [--emcee-max-steps N]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import scipy.stats

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE.parent / "tests"))

from bayes_talk.estimators.switching import SwitchingSGPDM
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

SMALL = {"latent_dim": 3, "max_iter": 40, "min_count": 4, "max_frames_per_state": 120, "fallback_frames": 150}


def load_data(args):
    if args.corpus:
        from bayes_talk.corpus import load_corpus

        seqs = list(load_corpus(args.corpus).sequences)
        perm = np.random.default_rng(args.seed).permutation(len(seqs))
        test = [seqs[i] for i in perm[:args.n_test]]
        train = [seqs[i] for i in perm[args.n_test:args.n_test + args.n_train]]
        return train, test, {"source": str(args.corpus), "config": "SwitchingConfig defaults"}, {}
    from toydata import make_utterances

    return (make_utterances(24, seed=0), make_utterances(args.n_test, seed=1, mean_len=30),
            {"source": "tests/toydata.py make_utterances(24, seed=0) / (n_test, seed=1, mean_len=30)",
             "config": SMALL}, SMALL)


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
    """NUTS vs emcee: wall time to bulk ESS 400 and ESS per second (see the module docstring)."""
    from bayes_talk.corpus import load_corpus
    from bayes_talk.pipeline import load_trained

    model = load_trained(args.model).uncalibrated
    seqs = {s.name: s for s in load_corpus(args.test_corpus, aam=args.aam, cache=False).sequences}
    s = seqs[args.utterance]
    T = min(args.frames, s.n_frames) if args.frames else s.n_frames
    res = {"command": "benchmarks/posterior.py " + " ".join(sys.argv[1:]), "model": str(args.model),
           "test_corpus": str(args.test_corpus), "aam": str(args.aam), "utterance": s.name, "frames": T,
           "seconds_of_speech": T / 25.0, "machine": {"python": platform.python_version(), "cpus": os.cpu_count()},
           "ess_target": 400, "samplers": {}}
    out_path = args.out if args.out != HERE / "results" / "posterior.json" else HERE / "results" / "posterior_efficiency.json"
    for method in args.methods.split(","):
        if method not in ("nuts", "pg-nuts", "emcee", "vi", "laplace"):
            raise SystemExit(f"--efficiency compares nuts, pg-nuts, emcee, vi and laplace, got {method!r}")
        print(f"{method} ...", flush=True)
        load0 = os.getloadavg()[0]
        t0 = time.perf_counter()
        skw = {"max_steps": args.emcee_max_steps} if method == "emcee" and args.emcee_max_steps else {}
        if method in ("nuts", "pg-nuts") and args.workers:
            skw["workers"] = args.workers
        if method in ("nuts", "pg-nuts") and args.coords:
            skw["coords"] = args.coords
        if method == "pg-nuts" and args.pg_frame_tries is not None:
            skw["pg_frame_tries"] = args.pg_frame_tries
        if method == "pg-nuts" and args.pg_frame_modes is not None:
            skw["pg_frame_modes"] = args.pg_frame_modes == "on"
        if method == "pg-nuts" and args.pg_neighbours is not None:
            skw["pg_neighbours"] = args.pg_neighbours == "on"
        if method == "pg-nuts" and args.pg_pairs is not None:
            skw["pg_pairs"] = args.pg_pairs == "on"
        if method == "pg-nuts" and args.pg_adapt_weights is not None:
            skw["pg_adapt_weights"] = args.pg_adapt_weights == "on"
        if method == "pg-nuts" and args.pg_block_sweeps is not None:
            skw["pg_block_sweeps"] = args.pg_block_sweeps
        if method == "pg-nuts" and args.pg_adapt_moments is not None:
            skw["pg_adapt_moments"] = args.pg_adapt_moments == "on"
        if method == "pg-nuts" and args.pg_adapt_clusters is not None:
            skw["pg_adapt_clusters"] = args.pg_adapt_clusters == "on"
        if method == "pg-nuts" and args.pg_mode_scale is not None:
            skw["pg_mode_scale"] = tuple(float(c) for c in args.pg_mode_scale.split(","))
        if method == "pg-nuts" and args.pg_block_len is not None:
            skw["pg_block_len"] = args.pg_block_len
        budget = _efficiency_budget(args, method)
        p = sample_synthesis(model, s.mfcc[:T], s.labels[:T], method=method, seed=args.seed, log_warnings=False,
                             sampler_kw=skw or None, **budget)
        wall = time.perf_counter() - t0
        d = p.diagnostics
        # the raw (uncalibrated) predictive against the held-out utterance's own AAM track
        raw = evaluate([s.aam[:T]], [p.mean], [p.var], [p.quantiles(DEFAULT_LEVELS)],
                       [p.sample(1000)])
        if args.save_draws and p.latent_draws is not None:
            path = args.save_draws.with_name(f"{args.save_draws.stem}_{method}.npz")
            np.savez(path, latents=p.latent_draws, aam_mean=p.draw_mean, truth=s.aam[:T])
        if method in ("vi", "laplace"):
            res["samplers"][method] = row = _iid_efficiency(p, wall, load0, budget)
            row["raw_accuracy"] = raw
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
        res["samplers"][method] = row
        print(json.dumps({k: v for k, v in row.items() if k != "diagnostics"}, default=str), flush=True)
        _write_atomic(out_path, res)


def _write_atomic(path: Path, res: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(res, indent=1, default=str))
    tmp.replace(path)


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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--efficiency", action="store_true", help="NUTS vs emcee: time to bulk ESS 400, ESS/s")
    ap.add_argument("--model", type=Path, default=None, help="--efficiency: directory written by `train`")
    ap.add_argument("--test-corpus", type=Path, default=None, help="--efficiency: held-out corpus")
    ap.add_argument("--aam", type=Path, default=None, help="--efficiency: the training corpus's AAM")
    ap.add_argument("--utterance", default=None, help="--efficiency: utterance name in --test-corpus")
    ap.add_argument("--frames", type=int, default=None, help="--efficiency: first frames (default all)")
    ap.add_argument("--emcee-max-steps", type=int, default=None,
                    help="--efficiency: bound emcee's run-on for the autocorrelation rule (default: the library's)")
    ap.add_argument("--corpus", type=Path, default=None)
    ap.add_argument("--n-train", type=int, default=50)
    ap.add_argument("--n-test", type=int, default=3)
    ap.add_argument("--draws", type=int, default=None, help="draws kept (default 200; --efficiency: the library's)")
    ap.add_argument("--nuts-warmup", type=int, default=None, help="default 150; --efficiency: the library's")
    ap.add_argument("--nuts-chains", type=int, default=None, help="default 2; --efficiency: the library's")
    ap.add_argument("--emcee-warmup", type=int, default=None, help="default 500; --efficiency: the library's")
    ap.add_argument("--workers", type=int, default=None,
                    help="--efficiency: NUTS/pg-nuts chains in this many processes (default: in-process)")
    ap.add_argument("--pg-frame-tries", type=int, default=None,
                    help="--efficiency, pg-nuts: K-try updates of the isolated frames after each sweep")
    ap.add_argument("--pg-frame-modes", choices=("on", "off"), default=None,
                    help="--efficiency, pg-nuts: those tries from the frames' own modes (default: the library's)")
    ap.add_argument("--pg-block-len", type=int, default=None,
                    help="--efficiency, pg-nuts: also update dynamics runs of up to this many frames (default: the library's)")
    ap.add_argument("--pg-neighbours", choices=("on", "off"), default=None,
                    help="--efficiency, pg-nuts: the blocks' modes conditioned on their neighbours (default: the library's)")
    ap.add_argument("--pg-pairs", choices=("on", "off"), default=None,
                    help="--efficiency, pg-nuts: also update consecutive blocks in pairs (default: the library's)")
    ap.add_argument("--pg-adapt-weights", choices=("on", "off"), default=None,
                    help="--efficiency, pg-nuts: learn the modes' weights during warm-up (default: the library's)")
    ap.add_argument("--pg-block-sweeps", type=int, default=None,
                    help="--efficiency, pg-nuts: passes of the block and pair updates after each sweep (default: the library's)")
    ap.add_argument("--pg-adapt-moments", choices=("on", "off"), default=None,
                    help="--efficiency, pg-nuts: learn the modes' means and covariances under the full conditional "
                         "during warm-up too (default: the library's)")
    ap.add_argument("--pg-adapt-clusters", choices=("on", "off"), default=None,
                    help="--efficiency, pg-nuts: propose from a Gaussian mixture fitted to each block's warm-up "
                         "states too (default: the library's)")
    ap.add_argument("--pg-mode-scale", default=None,
                    help="--efficiency, pg-nuts: the own-mode proposal's scale factors, comma-separated (default: the library's)")
    ap.add_argument("--coords", default=None,
                    help="--efficiency: NUTS/pg-nuts coordinates (sampler_kw['coords']; default: the method's)")
    ap.add_argument("--save-draws", type=Path, default=None,
                    help="--efficiency: write each sampler's draws to STEM_METHOD.npz (latents (C, S, T, d), "
                         "aam_mean (C, S, T, D), truth (T, D)) for analysis")
    ap.add_argument("--methods", default="map,laplace,nuts,emcee")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=HERE / "results" / "posterior.json")
    args = ap.parse_args()
    warnings.filterwarnings("ignore", category=FutureWarning)
    if args.efficiency:
        if not (args.model and args.test_corpus and args.utterance):
            ap.error("--efficiency needs --model, --test-corpus and --utterance")
        if args.methods == "map,laplace,nuts,emcee":
            args.methods = "nuts,emcee"
        return efficiency(args)
    for name, default in (("draws", 200), ("nuts_warmup", 150), ("nuts_chains", 2), ("emcee_warmup", 500)):
        if getattr(args, name) is None:
            setattr(args, name, default)

    train, test, data_info, cfg = load_data(args)
    res = {"command": "benchmarks/posterior.py " + " ".join(sys.argv[1:]), "data": data_info,
           "n_train": len(train), "n_test": len(test), "test_frames": int(sum(s.n_frames for s in test)),
           "levels": list(DEFAULT_LEVELS), "machine": {"python": platform.python_version(),
                                                       "cpus": os.cpu_count()},
           "settings": {"draws": args.draws, "nuts_warmup": args.nuts_warmup, "nuts_chains": args.nuts_chains,
                        "emcee_warmup": args.emcee_warmup, "seed": args.seed}, "systems": {}}

    def save():
        args.out.parent.mkdir(parents=True, exist_ok=True)
        tmp = args.out.with_suffix(".tmp")
        tmp.write_text(json.dumps(res, indent=1))
        tmp.replace(args.out)

    t0 = time.perf_counter()
    model = SwitchingSGPDM(states="vlmm", **cfg).fit(train)
    res["train_s"] = time.perf_counter() - t0
    truth = [s.aam for s in test]
    n_frames = res["test_frames"]
    for method in args.methods.split(","):
        print(f"{method} ...", flush=True)
        means, vars_, bands, samples, summaries = [], [], [], [], []
        t0 = time.perf_counter()
        load0 = os.getloadavg()[0]
        for s in test:
            if method == "map":
                r = model.synthesize(s.mfcc, s.labels)
                means.append(r.mean)
                vars_.append(r.var)
                sd = np.sqrt(r.var)
                bands.append({q: (r.mean - scipy.stats.norm.ppf(0.5 + q / 2) * sd,
                                  r.mean + scipy.stats.norm.ppf(0.5 + q / 2) * sd) for q in DEFAULT_LEVELS})
                continue
            kw = {"nuts": {"warmup": args.nuts_warmup, "chains": args.nuts_chains},
                  "emcee": {"warmup": args.emcee_warmup}, "laplace": {}}[method]
            p = sample_synthesis(model, s.mfcc, s.labels, method=method, n_draws=args.draws, seed=args.seed, **kw)
            means.append(p.mean)
            vars_.append(p.var)
            bands.append(p.quantiles(DEFAULT_LEVELS))
            samples.append(p.sample(1000))
            summaries.append(p.summary)
        secs = time.perf_counter() - t0
        ev = evaluate(truth, means, vars_, bands, samples if method != "map" else None)
        ev["seconds"] = secs
        ev["seconds_per_frame"] = secs / n_frames
        ev["loadavg_start_end"] = [load0, os.getloadavg()[0]]
        if method != "map":
            ev["mean_var_ratio_mixture_over_gp"] = float(np.mean([np.mean(v) for v in vars_]))
            ev["diagnostics"] = {
                "rhat_max": max(d.get("rhat_max", np.nan) for d in summaries),
                "ess_bulk_min": min(d.get("ess_bulk_min", np.nan) for d in summaries),
                "ess_tail_min": min(d.get("ess_tail_min", np.nan) for d in summaries),
                "n_segments": int(sum(d["n_segments"] for d in summaries)),
            }
            if method == "nuts":
                ev["diagnostics"]["divergences"] = int(sum(d.get("divergences", 0) for d in summaries))
            if method == "emcee":
                ev["diagnostics"]["acceptance_fraction_mean"] = float(
                    np.mean([d["acceptance_fraction"] for d in summaries]))
            ev["diagnostics"]["map_converged"] = int(sum(d["map_converged"] for d in summaries))
            del ev["mean_var_ratio_mixture_over_gp"]
        ev["mean_predictive_var"] = float(np.mean(np.concatenate([v.ravel() for v in vars_])))
        res["systems"][method] = ev
        print(json.dumps(ev), flush=True)
        save()
    res["complete"] = True
    save()


if __name__ == "__main__":
    from bayes_talk.base.executor import interruptible

    # `kill` stops the worker processes too, not only this one
    interruptible(main)
