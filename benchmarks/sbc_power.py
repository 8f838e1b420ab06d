"""Power of simulation-based calibration: the rejection rate of a positive control (a sampler
whose spread is 0.85× the truth) and the false-rejection rate of an exact sampler.

Conjugate Gaussian, K coordinates: θ ~ N(0, I), y = θ + N(0, s² I), posterior N(y/(1+s²), s²/(1+s²) I).
Each "sampler" is MCMC-like: ``--chains`` AR(1) chains of ``--chain-draws`` draws with
autocorrelation ``--rho`` whose stationary law is the posterior with its standard deviation
multiplied by ``scale`` (1: exact; 0.85: the control). Variants:

* ``exact`` and ``control-0.85`` - thinned to ``--rank-draws`` (L) evenly spaced draws of the
  pooled chains (:func:`bayes_talk.evaluation.sbc_power.thin_to_ess`), whose smallest bulk ESS is
  recorded for every ``--ess-every``-th simulation (ESS via ArviZ costs ~50 ms) to check L ≤ ESS;
* ``exact-consecutive`` - the last L consecutive draws of chain 1 (L > ESS: Talts et al. §4.1).

Each repeat runs :func:`bayes_talk.evaluation.sbc.run_sbc` (the loop ``synthesis_sbc`` uses) with
``--sims`` simulations and counts three verdicts: the χ² test with Holm at α = 0.05 (the
criterion of ``SBCResult.passed``), the dispersion test alone at α = 0.05, and the combined
verdict (:func:`bayes_talk.evaluation.sbc_power.combined_verdict`, α/3 each).

    PYTHONPATH=. python benchmarks/sbc_power.py [--sims 200] [--repeats 20] [--coords 24]
        [--rank-draws 19] [--out benchmarks/results/sbc_power.json]
    PYTHONPATH=. python benchmarks/sbc_power.py --quick   # 60 simulations, 3 repeats -> results/quick/
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from bayes_talk.evaluation.sbc import ALPHA, run_sbc
from bayes_talk.evaluation.sbc_power import combined_verdict, dispersion_test, thin_to_ess
from benchmarks.common import result_path, write_result

S2 = 0.5


def ar1_chains(rng, mean, sd, chains, n, rho):
    """(chains, n, K) AR(1) draws started in, and stationary at, N(mean, sd²)."""
    K = mean.size
    x = np.empty((chains, n, K))
    x[:, 0] = mean + sd * rng.standard_normal((chains, K))
    e = sd * np.sqrt(1 - rho**2) * rng.standard_normal((chains, n, K))
    for t in range(1, n):
        x[:, t] = mean + rho * (x[:, t - 1] - mean) + e[:, t]
    return x


def one_repeat(args, variant, seed):
    scale = 0.85 if variant == "control-0.85" else 1.0
    K, L = args.coords, args.rank_draws
    ess = []
    count = [0]

    def simulate(rng):
        theta = rng.standard_normal(K)
        return theta, theta + np.sqrt(S2) * rng.standard_normal(K)

    def posterior(y, s):
        rng = np.random.default_rng(s)
        m, sd = y / (1 + S2), np.sqrt(S2 / (1 + S2)) * scale
        x = ar1_chains(rng, m, sd, args.chains, args.chain_draws, args.rho)
        count[0] += 1
        if variant == "exact-consecutive":
            return x[0, -L:]
        if (count[0] - 1) % args.ess_every:
            return x.reshape(-1, K)[np.linspace(0, args.chains * args.chain_draws - 1, L).round().astype(int)]
        d, e = thin_to_ess(x, L)
        ess.append(e)
        return d

    res = run_sbc(simulate, posterior, args.sims, L, seed=seed)
    v = combined_verdict(res.ranks, L, res.p_adjusted)
    return {"chi2_holm_rejects": not res.passed, "dispersion_rejects": dispersion_test(res.ranks, L)[1] < ALPHA,
            "combined_rejects": not v["passed"], "dispersion_t": v["dispersion_t"], "ess_bulk_min": ess}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sims", type=int, default=200)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--coords", type=int, default=24)
    ap.add_argument("--rank-draws", type=int, default=19)
    ap.add_argument("--chains", type=int, default=2)
    ap.add_argument("--chain-draws", type=int, default=500)
    ap.add_argument("--rho", type=float, default=0.7)
    ap.add_argument("--ess-every", type=int, default=10)
    ap.add_argument("--variants", default="exact,control-0.85,exact-consecutive")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true", help="60 simulations, 3 repeats")
    ap.add_argument("--out", type=Path, default=None, help="default results/sbc_power.json (--quick: results/quick/)")
    args = ap.parse_args()
    if args.quick:
        args.sims, args.repeats = 60, 3
    args.out = result_path("sbc_power", args.quick, args.out)
    res = {"settings": {k: v for k, v in vars(args).items() if k != "out"}, "variants": {}}
    for variant in args.variants.split(","):
        if variant not in ("exact", "control-0.85", "exact-consecutive"):
            raise SystemExit(f"unknown variant {variant!r}")
        t0 = time.perf_counter()
        runs = [one_repeat(args, variant, args.seed + 1000 * i) for i in range(args.repeats)]
        ess = np.concatenate([r["ess_bulk_min"] for r in runs]) if variant != "exact-consecutive" else np.array([])
        out = {k: float(np.mean([r[k] for r in runs])) for k in ("chi2_holm_rejects", "dispersion_rejects",
                                                                  "combined_rejects")}
        out = {k.replace("_rejects", "_rejection_rate"): v for k, v in out.items()}
        out.update(repeats=args.repeats, dispersion_t_mean=float(np.mean([r["dispersion_t"] for r in runs])),
                   seconds=time.perf_counter() - t0)
        if ess.size:
            out.update(ess_bulk_min_checked=int(ess.size), ess_bulk_min_min=float(ess.min()),
                       ess_bulk_min_median=float(np.median(ess)),
                       ranked_draws_le_ess_fraction=float(np.mean(ess >= args.rank_draws)))
        res["variants"][variant] = out
        print(variant, json.dumps(out), flush=True)
    write_result(args.out, res)


if __name__ == "__main__":
    main()
