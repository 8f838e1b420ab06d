"""What R-hat and ESS perfectly mixed chains reach over many coordinates.

The convergence targets ask a sampler for rank R-hat ≤ 1.01 and bulk ESS ≥ 400 *for every
coordinate* of a whole utterance (T·d = 450 latents for 3 s). This script draws iid
N(0, 1) "chains" of the given shape — a sampler that mixes perfectly — and reports, over
``--seeds`` repetitions, the largest rank R-hat and the smallest bulk/tail ESS over the
coordinates (``bayes_talk.posterior.diagnostics.chain_diagnostics``, ArviZ), and how often
the largest R-hat is within 1.01. That is the best any sampler of that many draws can do.

    PYTHONPATH=. python benchmarks/rhat_iid.py [--chains 4] [--dim 450] \
        [--draws-per-chain 100,250,500,1000] [--seeds 10] [--out benchmarks/results/rhat_iid.json]
    PYTHONPATH=. python benchmarks/rhat_iid.py --quick    # -> benchmarks/results/quick/rhat_iid.json
"""
from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from bayes_talk.posterior.diagnostics import ESS_MIN, RHAT_MAX, chain_diagnostics
from benchmarks.common import result_path, write_result


def iid_reference(chains: int, draws: int, dim: int, seeds: int = 10) -> dict:
    """Largest R-hat / smallest ESS over ``dim`` coordinates of iid chains (chains, draws)."""
    rows = []
    for seed in range(seeds):
        d = chain_diagnostics(np.random.default_rng(seed).standard_normal((chains, draws, dim)))
        rows.append((d["rhat_max"], d["ess_bulk_min"], d["ess_tail_min"]))
    r = np.array(rows)
    return {"chains": chains, "draws_per_chain": draws, "dim": dim, "seeds": seeds,
            "rhat_max_median": float(np.median(r[:, 0])), "rhat_max_range": [float(r[:, 0].min()), float(r[:, 0].max())],
            "fraction_rhat_max_le_1_01": float(np.mean(r[:, 0] <= RHAT_MAX)),
            "ess_bulk_min_median": float(np.median(r[:, 1])), "ess_tail_min_median": float(np.median(r[:, 2])),
            "fraction_ess_min_ge_400": float(np.mean(np.minimum(r[:, 1], r[:, 2]) >= ESS_MIN))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--chains", type=int, default=4)
    ap.add_argument("--dim", type=int, default=450)
    ap.add_argument("--draws-per-chain", default="100,250,500,1000")
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--quick", action="store_true", help="60 coordinates, 100 and 250 draws per chain, 3 seeds")
    ap.add_argument("--out", type=Path, default=None, help="default results/rhat_iid.json (--quick: results/quick/)")
    args = ap.parse_args()
    if args.quick:
        args.dim, args.draws_per_chain, args.seeds = 60, "100,250", 3
    args.out = result_path("rhat_iid", args.quick, args.out)
    warnings.filterwarnings("ignore", category=FutureWarning)
    res = {"settings": {k: v for k, v in vars(args).items() if k != "out"},
           "thresholds": {"rhat": RHAT_MAX, "ess": ESS_MIN}, "rows": []}
    for n in (int(v) for v in args.draws_per_chain.split(",")):
        row = iid_reference(args.chains, n, args.dim, args.seeds)
        print(json.dumps(row), flush=True)
        res["rows"].append(row)
    write_result(args.out, res)


if __name__ == "__main__":
    main()
