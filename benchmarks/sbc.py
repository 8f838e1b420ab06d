"""Simulation-based calibration of the synthesis samplers (Talts et al. 2018).

For a trained switching model and a short stretch of frame labels (``--frames`` frames
from ``--start`` of one utterance's labels), ``bayes_talk.evaluation.sbc.synthesis_sbc``
simulates ``--sims`` latent trajectories and audio from the synthesis model
(``pyro.infer.Predictive``; with ``--smoothness frame``, the default, also the smoothness
factors' pseudo-observations u, on which the samplers then condition:
bayes_talk/synthesis/joint.py, (S)), runs each sampler on every simulated audio, ranks the true latents among ``--rank-draws`` thinned posterior draws, and tests
rank uniformity per latent coordinate (χ², Holm-corrected, family-wise α = 0.05).

Samplers: ``nuts`` and ``pg-nuts`` (``--nuts-chains`` chains, ``--nuts-warmup`` warm-up,
``--nuts-draws`` draws per chain; ``pg-nuts`` with ``PG_NUTS_DEFAULTS``), ``laplace`` (200 draws), ``emcee`` (library defaults), and the controls
``laplace-halved`` (Laplace with its covariance halved) and ``laplace-0.85sd`` (Laplace with
its spread 0.85×, i.e. covariance × 0.7225: the positive control, which SBC must
reject). Besides the χ²-Holm verdict (``passed``), every sampler gets the combined verdict of
:func:`bayes_talk.evaluation.sbc_power.combined_verdict` (χ² Holm, the pooled dispersion test
and the bias test at α/3 each: ``verdict``), and ``ranked_draws_le_ess`` says whether the
``--rank-draws`` ranked draws were at most the smallest bulk ESS of every simulation (MCMC
draws are thinned evenly from the pooled chains; Talts et al. §4.1); ``sampler_options``
records the sampler's library options at the commit run (``INFERENCE[...].options``; the
controls: Laplace's), which ``--pool`` requires to agree, and ``run_options``
what this run overrode of them (``--nuts-chains``, ``--nuts-warmup``, ``--nuts-draws`` for
``nuts`` and ``pg-nuts``; the 200 draws of Laplace and its controls; nothing for emcee). Power of these tests:
``benchmarks/sbc_power.py``.

    PYTHONPATH=. python benchmarks/sbc.py --model MODEL_DIR --corpus CORPUS [--utterance NAME]
        [--start 10] [--frames 4] [--sims 200] [--nuts-sims N] [--emcee-sims N] [--rank-draws 19]
        [--smoothness frame|off]
        [--methods nuts,laplace,laplace-halved,laplace-0.85sd,emcee] [--workers 2] [--out RUN.json]
    PYTHONPATH=. python benchmarks/sbc.py --pool RUN1.json RUN2.json ... --out benchmarks/results/sbc.json
    PYTHONPATH=. python benchmarks/sbc.py --quick                            # toy size -> results/quick/sbc.json

Runs that differ only in ``--seed`` (and the number of simulations) are independent draws from
the same prior: ``--pool`` stacks their ranks (kept in each run's JSON as ``ranks``) into one
SBC of the summed simulations, tested exactly as one run of that size would be
(:func:`bayes_talk.evaluation.sbc.uniformity_test` and the combined verdict), and refuses runs
whose settings or sampler options differ (another commit's sampler). The committed
``results/sbc.json`` is such a pool: pg-nuts and the controls, 200 simulations of 20 frames of
a development utterance under the default model.

``--quick``: the same code path at toy size: the quick mode's small model and held-out corpus
(``benchmarks/common.py``), 4 frames, 15 simulations of Laplace, its 0.85-sd control and pg-nuts
(2 chains of 8 draws after 10 warm-up), a second run of Laplace at another seed, and the pool
of the two runs.

Without ``--model`` and ``--corpus``: the suite's model and held-out corpus
(``benchmarks/common.py``). Writes JSON after each sampler (atomic replace).
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

from bayes_talk.base.executor import executor_for
from bayes_talk.evaluation.sbc import (
    SBCResult,
    sampler_posterior,
    scaled_laplace,
    synthesis_sbc,
    uniformity_test,
)
from bayes_talk.posterior.methods import INFERENCE
from bayes_talk.posterior.nuts_chain import WARMUP_ADAPTATION
from benchmarks.common import ROOT, bench_corpus, bench_model, result_path, scratch, write_result

#: the library method behind each sampler of --methods (the controls scale Laplace's draws)
LIBRARY_METHOD = {"nuts": "nuts", "pg-nuts": "pg-nuts", "laplace": "laplace", "laplace-halved": "laplace",
                  "laplace-0.85sd": "laplace", "emcee": "emcee"}
#: draws of Laplace and its controls (i.i.d. from the Gaussian), thinned to --rank-draws for the ranks
LAPLACE_DRAWS = 200


def _mcmc_budget(a) -> dict:
    """The chains, warm-up and draws per chain of nuts and pg-nuts here (``--nuts-*``)."""
    return {"chains": a.nuts_chains, "warmup": a.nuts_warmup, "draws_per_chain": a.nuts_draws}


#: the options each library method's runs here override (``run_options`` in the JSON)
RUN_OPTIONS = {"nuts": _mcmc_budget, "pg-nuts": _mcmc_budget, "laplace": lambda a: {"n_draws": LAPLACE_DRAWS},
               "emcee": lambda a: {}}


def load(args):
    from bayes_talk.corpus import load_corpus
    from bayes_talk.pipeline import load_trained

    model = load_trained(args.model).uncalibrated
    seqs = {s.name: s for s in load_corpus(args.corpus, cache=False).sequences}
    name = args.utterance or min(seqs)
    return model, list(seqs[name].labels), {"model": os.path.relpath(Path(args.model).resolve(), ROOT),
                                             "corpus": os.path.relpath(Path(args.corpus).resolve(), ROOT),
                                             "utterance": name}


#: settings that may differ between pooled runs
PER_RUN = ("sims", "seed", "workers", "nuts_sims", "emcee_sims", "methods")


def _check_compatible(runs: list[tuple[str, dict]]) -> None:
    first_path, first = runs[0]
    base = {k: v for k, v in first["settings"].items() if k not in PER_RUN}
    seeds = {}
    for path, run in runs:
        s = run["settings"]
        other = {k: v for k, v in s.items() if k not in PER_RUN}
        if other != base:
            diff = sorted(k for k in set(base) | set(other) if base.get(k) != other.get(k))
            raise SystemExit(f"{path}: settings {diff} differ from {first_path}'s; only "
                             f"{', '.join(PER_RUN)} may differ between pooled runs")
        if run.get("source") != first.get("source"):
            raise SystemExit(f"{path}: model/corpus/utterance {run.get('source')} differ from {first_path}'s "
                             f"{first.get('source')}")
        if s["seed"] in seeds:
            raise SystemExit(f"{path} and {seeds[s['seed']]} share --seed {s['seed']}: their simulations are "
                             "the same, not independent")
        seeds[s["seed"]] = path


def pool(runs: list[tuple[str, dict]]) -> dict:
    """The pooled SBC of every sampler present (with ranks) in all ``runs``."""
    _check_compatible(runs)
    names = [m for m in runs[0][1]["samplers"]
             if all("ranks" in r["samplers"].get(m, {}) for _, r in runs)]
    missing = sorted({m for _, r in runs for m in r["samplers"]} - set(names))
    out: dict = {}
    for m in names:
        parts = [r["samplers"][m] for _, r in runs]
        n_draws = {p["n_draws"] for p in parts}
        if len(n_draws) != 1:
            raise SystemExit(f"sampler {m}: the runs ranked among different numbers of draws {sorted(n_draws)}")
        L = n_draws.pop()
        options = [json.dumps(p.get("sampler_options"), sort_keys=True) for p in parts]
        if len(set(options)) != 1:
            raise SystemExit(f"sampler {m}: the runs' sampler options differ ({sorted(set(options))}): they ran "
                             "different samplers (another commit's defaults) and cannot be pooled")
        ranks = np.concatenate([np.asarray(p["ranks"], dtype=np.int64) for p in parts])
        p, p_adj, bins = uniformity_test(ranks, L)
        res = SBCResult(ranks, L, p, p_adj, bins).to_dict()
        res.pop("p_values")
        conv: dict = {"sims_per_run": [p["n_sims"] for p in parts]}
        for key, worst in (("worst_rhat_max", max), ("worst_ess_bulk_min", min), ("worst_ess_tail_min", min),
                           ("worst_ebfmi_min", min), ("worst_khat", max)):
            vals = [p[key] for p in parts if p.get(key) is not None]
            if vals:
                conv[key] = worst(vals)
        if any("divergences" in p for p in parts):
            conv["divergences"] = int(sum(p.get("divergences", 0) for p in parts))
        if any("ranked_draws_le_ess" in p for p in parts):
            conv["ranked_draws_le_ess"] = all(bool(p.get("ranked_draws_le_ess")) for p in parts)
        out[m] = {**res, **conv, "sampler_options": parts[0].get("sampler_options")}
        if parts[0].get("run_options") is not None:   # the budget (equal in every run: the settings agree)
            out[m]["run_options"] = parts[0]["run_options"]
    return {"samplers": out, "not_pooled": missing}


def pool_runs(paths: list[Path], out: Path) -> dict:
    """``--pool``: one SBC of the runs' summed simulations, written to ``out``."""
    if len(paths) < 2:
        raise SystemExit("give at least two runs to pool")
    runs = [(str(p), json.loads(Path(p).read_text())) for p in paths]
    pooled = pool(runs)
    result = {"runs": [os.path.relpath(Path(p).resolve(), ROOT) for p in paths],
              "source": runs[0][1].get("source"), "labels": runs[0][1].get("labels"),
              "settings": {k: v for k, v in runs[0][1]["settings"].items() if k not in PER_RUN},
              "seeds": [r["settings"]["seed"] for _, r in runs], **pooled}
    write_result(out, result)
    for m, r in pooled["samplers"].items():
        v = r["verdict"]
        print(f"{m}: {r['n_sims']} sims, {'passed' if v['passed'] else 'rejected'}; chi2-Holm rejected "
              f"{r['n_rejected']}/{r['n_coordinates']}, dispersion t {v['dispersion_t']:+.2f} (p {v['dispersion_p']:.3g}), "
              f"bias t {v['bias_t']:+.2f}, outer fraction {r['extreme_fraction']:.3f}")
    return result


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", type=Path, default=None, help="directory written by `bayes-talk train` "
                    "(default: the suite's model)")
    ap.add_argument("--corpus", type=Path, default=None, help="corpus holding --utterance, for its labels "
                    "(default: the suite's held-out corpus)")
    ap.add_argument("--utterance", default=None)
    ap.add_argument("--start", type=int, default=10)
    ap.add_argument("--frames", type=int, default=4)
    ap.add_argument("--sims", type=int, default=200)
    ap.add_argument("--nuts-sims", type=int, default=None, help="simulations for NUTS and pg-nuts (default --sims)")
    ap.add_argument("--smoothness", choices=("frame", "off"), default="frame",
                    help="smoothness factors on (simulated as pseudo-observations) or off")
    ap.add_argument("--emcee-sims", type=int, default=None, help="simulations for emcee (default --sims)")
    ap.add_argument("--rank-draws", type=int, default=19)
    ap.add_argument("--nuts-chains", type=int, default=2)
    ap.add_argument("--nuts-warmup", type=int, default=200)
    ap.add_argument("--nuts-draws", type=int, default=100, help="NUTS draws per chain")
    ap.add_argument("--methods", default="nuts,laplace,laplace-halved,laplace-0.85sd,emcee")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=1,
                    help="worker processes for the simulations' posterior runs (same ranks; default: this process)")
    ap.add_argument("--pool", type=Path, nargs="+", default=None, metavar="RUN",
                    help="pool these runs (JSON of this script, differing only in --seed) into --out")
    ap.add_argument("--quick", action="store_true", help="toy size: the quick model, 4 frames, 15 simulations")
    ap.add_argument("--out", type=Path, default=None,
                    help="default results/sbc.json (one run, or the pool; give runs to be pooled their own --out)")
    args = ap.parse_args(argv)
    if args.pool:
        pool_runs(args.pool, result_path("sbc", args.quick, args.out))
        return
    if args.quick:
        return quick(args)
    args.model = args.model or bench_model()
    args.corpus = args.corpus or bench_corpus("test")
    args.out = args.out or result_path("sbc")
    run(args)


def quick(args) -> None:
    """The code path of the full SBC at toy size: a run of Laplace, its 0.85-sd control and
    pg-nuts (short chains), a run of Laplace at another seed, then the pool of the two
    (the control and pg-nuts, in one run only, are listed as not pooled)."""
    model, corpus = bench_model(True), bench_corpus("test", True)
    runs = []
    for seed, methods in ((0, "laplace,laplace-0.85sd,pg-nuts"), (1, "laplace")):
        out = scratch("sbc") / f"run_seed{seed}.json"
        main(["--model", str(model), "--corpus", str(corpus), "--start", "2", "--frames", "4", "--sims", "15",
              "--methods", methods, "--nuts-chains", "2", "--nuts-warmup", "10", "--nuts-draws", "8",
              "--rank-draws", "14", "--seed", str(seed), "--workers", str(args.workers), "--out", str(out)])
        runs.append(out)
    pool_runs(runs, result_path("sbc", True, args.out))


def run(args) -> None:
    warnings.filterwarnings("ignore", category=FutureWarning)

    model, labels, src = load(args)
    labels = labels[args.start:args.start + args.frames]
    if len(labels) != args.frames:
        raise SystemExit(f"the utterance has fewer than {args.start + args.frames} frames")
    res = {"source": src, "labels": labels,
           "settings": {k: v for k, v in vars(args).items() if k not in ("out", "model", "corpus", "pool", "quick")},
           "samplers": {}}
    argv = [sys.argv[0], *_argv(args)]

    def save():
        write_result(args.out, json.loads(json.dumps(res, default=str)), argv)

    posteriors = {
        "nuts": lambda: sampler_posterior("nuts", n_draws=args.nuts_chains * args.nuts_draws, chains=args.nuts_chains,
                                          warmup=args.nuts_warmup),
        "pg-nuts": lambda: sampler_posterior("pg-nuts", n_draws=args.nuts_chains * args.nuts_draws,
                                             chains=args.nuts_chains, warmup=args.nuts_warmup),
        "laplace": lambda: sampler_posterior("laplace", n_draws=LAPLACE_DRAWS),
        "laplace-halved": lambda: scaled_laplace(0.5, n_draws=LAPLACE_DRAWS),
        "laplace-0.85sd": lambda: scaled_laplace(0.85 ** 2, n_draws=LAPLACE_DRAWS),
        "emcee": lambda: sampler_posterior("emcee"),
    }
    for method in args.methods.split(","):
        if method not in posteriors:
            raise SystemExit(f"unknown method {method!r}; choose from {sorted(posteriors)}")
        n = {"nuts": args.nuts_sims, "pg-nuts": args.nuts_sims, "emcee": args.emcee_sims}.get(method) or args.sims
        print(f"{method}: {n} simulations ...", flush=True)
        t0 = time.perf_counter()
        load0 = os.getloadavg()[0]
        with executor_for(None, args.workers) as ex:
            r = synthesis_sbc(model, labels, posteriors[method](), n_sims=n, n_draws=args.rank_draws, seed=args.seed,
                              smoothness=args.smoothness, executor=ex)
        out = r.to_dict()   # its "verdict": the combined verdict (sbc_power.combined_verdict)
        # the ranks themselves (n_sims, coordinates): runs with other --seed values simulate
        # other trajectories, so their ranks can be pooled into one larger SBC
        out["ranks"] = r.ranks.tolist()
        if "worst_ess_bulk_min" in r.info and method in ("nuts", "pg-nuts", "emcee"):
            out["ranked_draws_le_ess"] = bool(r.info["worst_ess_bulk_min"] >= r.n_draws)
        out.update(method=method, wall_seconds=time.perf_counter() - t0, loadavg_start_end=[load0, os.getloadavg()[0]])
        # the sampler's own defaults at this commit (runs pooled by --pool must agree on them)
        out["sampler_options"] = json.loads(json.dumps({**INFERENCE[LIBRARY_METHOD[method]].options,
                                                        "warmup_adaptation": WARMUP_ADAPTATION}))
        # what this run used in place of those defaults (the budget --nuts-* set; Laplace's draws)
        out["run_options"] = RUN_OPTIONS[LIBRARY_METHOD[method]](args)
        res["samplers"][method] = out
        print(json.dumps({k: v for k, v in out.items() if k not in ("p_values", "ranks")}, default=str), flush=True)
        save()
    res["complete"] = True
    save()


def _argv(args) -> list[str]:
    """The command line of one run (also when ``--quick`` called it)."""
    skip = {"pool", "quick"}
    out = []
    for k, v in vars(args).items():
        if k in skip or v is None:
            continue
        out += [f"--{k.replace('_', '-')}", str(v)]
    return out


if __name__ == "__main__":
    from bayes_talk.base.executor import interruptible

    # `kill` stops the worker processes too, not only this one
    interruptible(main)
