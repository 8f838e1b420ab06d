"""Simulation-based calibration of the synthesis samplers (Talts et al. 2018; DESIGN.md §6).

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
its spread 0.85×, i.e. covariance × 0.7225: the positive control of issue 24, which SBC must
reject). Besides the χ²-Holm verdict (``passed``), every sampler gets the combined verdict of
:func:`bayes_talk.evaluation.sbc_power.combined_verdict` (χ² Holm, the pooled dispersion test
and the bias test at α/3 each: ``verdict``), and ``ranked_draws_le_ess`` says whether the
``--rank-draws`` ranked draws were at most the smallest bulk ESS of every simulation (MCMC
draws are thinned evenly from the pooled chains; Talts et al. §4.1); ``sampler_options``
records the sampler's library options at the commit run (``INFERENCE[...].options``; the
controls: Laplace's), which ``benchmarks/sbc_pool.py`` requires to agree, and ``run_options``
what this run overrode of them (``--nuts-chains``, ``--nuts-warmup``, ``--nuts-draws`` for
``nuts`` and ``pg-nuts``; the 200 draws of Laplace and its controls; nothing for emcee). Power of these tests:
``benchmarks/sbc_power.py``.

    PYTHONPATH=. python benchmarks/sbc.py --model MODEL_DIR --corpus CORPUS [--utterance NAME]
        [--start 10] [--frames 4] [--sims 200] [--nuts-sims N] [--emcee-sims N] [--rank-draws 19]
        [--smoothness frame|off]
        [--methods nuts,laplace,laplace-halved,laplace-0.85sd,emcee] [--workers 2] [--out benchmarks/results/sbc.json]

Without ``--model``: a toy switching model (tests/toydata.py, the test configuration) and
the labels of a toy utterance. Writes JSON after each sampler (atomic replace).
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

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE.parent / "tests"))

from bayes_talk.evaluation.sbc import sampler_posterior, scaled_laplace, synthesis_sbc
from bayes_talk.base.executor import executor_for
from bayes_talk.posterior.methods import INFERENCE
from bayes_talk.posterior.nuts_chain import WARMUP_ADAPTATION

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
SMALL = {"latent_dim": 3, "max_iter": 40, "min_count": 4, "max_frames_per_state": 120, "fallback_frames": 150}


def load(args):
    if args.model:
        from bayes_talk.corpus import load_corpus
        from bayes_talk.pipeline import load_trained

        model = load_trained(args.model).uncalibrated
        seqs = {s.name: s for s in load_corpus(args.corpus, cache=False).sequences}
        name = args.utterance or min(seqs)
        return model, list(seqs[name].labels), {"model": str(args.model), "corpus": str(args.corpus),
                                                 "utterance": name}
    from toydata import make_utterances

    from bayes_talk.estimators.switching import SwitchingSGPDM

    model = SwitchingSGPDM(states="vlmm", **SMALL).fit(make_utterances(24, seed=0))
    return model, list(make_utterances(1, seed=1, mean_len=20)[0].labels), {
        "model": "toy: SwitchingSGPDM(vlmm, test configuration) on make_utterances(24, seed=0)",
        "utterance": "make_utterances(1, seed=1, mean_len=20)[0]"}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", type=Path, default=None, help="directory written by `bayes-talk train`")
    ap.add_argument("--corpus", type=Path, default=None, help="corpus holding --utterance (for its labels)")
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
    ap.add_argument("--out", type=Path, default=HERE / "results" / "sbc.json")
    args = ap.parse_args()
    if args.model and not args.corpus:
        ap.error("--model needs --corpus (the labels of --utterance)")
    warnings.filterwarnings("ignore", category=FutureWarning)

    model, labels, src = load(args)
    labels = labels[args.start:args.start + args.frames]
    if len(labels) != args.frames:
        raise SystemExit(f"the utterance has fewer than {args.start + args.frames} frames")
    res = {"command": "benchmarks/sbc.py " + " ".join(sys.argv[1:]), "source": src, "labels": labels,
           "machine": {"python": platform.python_version(), "cpus": os.cpu_count()},
           "settings": {k: v for k, v in vars(args).items() if k not in ("out", "model", "corpus")},
           "samplers": {}}

    def save():
        args.out.parent.mkdir(parents=True, exist_ok=True)
        tmp = args.out.with_suffix(".tmp")
        tmp.write_text(json.dumps(res, indent=1, default=str))
        tmp.replace(args.out)

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
        # the sampler's own defaults at this commit (runs pooled by sbc_pool.py must agree on them)
        out["sampler_options"] = json.loads(json.dumps({**INFERENCE[LIBRARY_METHOD[method]].options,
                                                        "warmup_adaptation": WARMUP_ADAPTATION}))
        # what this run used in place of those defaults (the budget --nuts-* set; Laplace's draws)
        out["run_options"] = RUN_OPTIONS[LIBRARY_METHOD[method]](args)
        res["samplers"][method] = out
        print(json.dumps({k: v for k, v in out.items() if k not in ("p_values", "ranks")}, default=str), flush=True)
        save()
    res["complete"] = True
    save()


if __name__ == "__main__":
    from bayes_talk.base.executor import interruptible

    # `kill` stops the worker processes too, not only this one
    interruptible(main)
