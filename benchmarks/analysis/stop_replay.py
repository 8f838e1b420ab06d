"""Where pg-nuts's stopping rule would have ended runs made with a fixed budget (session 36).

``sample_synthesis(method="pg-nuts")`` stops drawing once the latents' and the AAM parameters'
rank R-hat ≤ 1.01 and bulk and tail ESS ≥ 400
(:class:`bayes_talk.posterior.sampling.TargetCheck`), asked after ``min_draws_per_chain``
draws per chain and every ``check_every`` after (``PG_NUTS_BUDGET``). The chains draw in
batches between the checks, and batches draw exactly what one uninterrupted run draws
(``tests/test_warmup_pooling.py``), so on the draws a fixed-budget run saved
(``benchmarks/posterior.py --efficiency --save-draws``) the rule, asked on their prefixes, stops
where a run with the rule on, at the same seed and library, stops. This replays it: per run,
the checks (draws per chain, R-hat, ESS, failed checks), the draws per chain kept, and the
share of the run's draw-phase seconds (``sampling_seconds`` of its JSON) the stop would have
saved, assuming every draw iteration costs the same (an estimate; a live run measures it).

    PYTHONPATH=. .venv/bin/python benchmarks/analysis/stop_replay.py \\
        RUN.json:RUN_draws_pg-nuts.npz [...] --out benchmarks/results/stop_replay.json
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from bayes_talk.base.files import write_json
from bayes_talk.posterior.methods import PG_NUTS_BUDGET
from bayes_talk.posterior.sampling import TargetCheck


def replay(latents: np.ndarray, aam: np.ndarray, first: int, every: int) -> dict:
    """The rule on prefixes of (chains, S, T, d) latent draws and (chains, S, T, D_z) AAM means."""
    S = latents.shape[1]
    check, kept = TargetCheck(), S
    for n in range(min(first, S), S, every):
        if check.judge(latents[:, :n], aam[:, :n]):
            kept = n
            break
    return {"draws_per_chain_run": int(S), "draws_per_chain_kept": int(kept), "stopped_early": kept < S,
            "checks": check.history}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", help="RUN.json:DRAWS.npz pairs (the efficiency JSON and its saved pg-nuts draws)")
    ap.add_argument("--min-draws", type=int, default=PG_NUTS_BUDGET["min_draws_per_chain"])
    ap.add_argument("--check-every", type=int, default=PG_NUTS_BUDGET["check_every"])
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    out = {"command": "benchmarks/analysis/stop_replay.py " + " ".join(sys.argv[1:]),
           "min_draws_per_chain": args.min_draws, "check_every": args.check_every, "runs": {}}
    for pair in args.runs:
        js, _, npz = pair.partition(":")
        if not npz:
            raise SystemExit(f"{pair}: expected RUN.json:DRAWS.npz")
        run = json.loads(Path(js).read_text())
        with np.load(npz) as d:
            lat, aam = d["latents"], d["aam_mean"]
        pg = run["samplers"]["pg-nuts"]
        if lat.shape[:2] != (pg["n_chains"], pg["n_draws"]):
            raise SystemExit(f"{npz}: draws {lat.shape[:2]} do not match {js}'s pg-nuts run "
                             f"({pg['n_chains']}, {pg['n_draws']})")
        r = replay(lat, aam, args.min_draws, args.check_every)
        frac = 1 - r["draws_per_chain_kept"] / r["draws_per_chain_run"]
        r.update(run=Path(js).name, test_corpus=run["test_corpus"], utterance=run["utterance"],
                 frames=run["frames"], wall_seconds_run=pg["wall_seconds"], sampling_seconds_run=pg["sampling_seconds"],
                 sampling_seconds_saved_estimate=frac * pg["sampling_seconds"],
                 wall_seconds_estimate=pg["wall_seconds"] - frac * pg["sampling_seconds"])
        out["runs"][f"{run['test_corpus']}/{run['utterance']}"] = r
        print(json.dumps({k: v for k, v in r.items() if k != "checks"}), flush=True)
    write_json(args.out, out)


if __name__ == "__main__":
    main()
