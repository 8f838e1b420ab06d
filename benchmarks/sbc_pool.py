"""Pool the ranks of several ``benchmarks/sbc.py`` runs into one larger SBC (issue 24 item 6).

Runs of ``benchmarks/sbc.py`` that differ only in ``--seed`` simulate different latent
trajectories from the same model and stretch, so their simulations are independent draws
from the same prior and their rank arrays (kept in the JSON as ``ranks``) can be stacked:
N₁ + N₂ + … simulations, tested exactly as one run of that size would be
(:func:`bayes_talk.evaluation.sbc.uniformity_test` — χ² per coordinate, Holm — and the
combined verdict of :func:`bayes_talk.evaluation.sbc_power.combined_verdict`). The runs
must agree on everything but the seed and the number of simulations (model, corpus,
utterance, stretch, smoothness, ranked draws, sampler settings); they must not share a seed.
A sampler's runs must also record the same ``sampler_options`` (its library options when it
ran; older runs record none, and pool only with each other). Per sampler the worst
convergence figures over the runs are carried over (largest R-hat,
smallest bulk/tail ESS and E-BFMI, divergences summed), and ``ranked_draws_le_ess`` is true
only if it was in every run.

    PYTHONPATH=. .venv/bin/python benchmarks/sbc_pool.py RUN1.json RUN2.json ... \\
        --out benchmarks/results/sbc_pooled.json
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from bayes_talk.evaluation.sbc import SBCResult, uniformity_test
from bayes_talk.base.files import write_json

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


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="+", help="JSON files written by benchmarks/sbc.py (with ranks)")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    if len(args.runs) < 2:
        raise SystemExit("give at least two runs to pool")
    runs = [(p, json.loads(Path(p).read_text())) for p in args.runs]
    pooled = pool(runs)
    result = {"benchmark": "sbc_pool", "issue": 24,
              "runs": [os.path.relpath(Path(p).resolve(), ROOT) for p in args.runs],
              "source": runs[0][1].get("source"),
              "settings": {k: v for k, v in runs[0][1]["settings"].items() if k not in PER_RUN},
              "seeds": [r["settings"]["seed"] for _, r in runs], **pooled}
    write_json(args.out, result)
    for m, r in pooled["samplers"].items():
        v = r["verdict"]
        print(f"{m}: {r['n_sims']} sims, {'passed' if v['passed'] else 'rejected'}; chi2-Holm rejected "
              f"{r['n_rejected']}/{r['n_coordinates']}, dispersion t {v['dispersion_t']:+.2f} (p {v['dispersion_p']:.3g}), "
              f"bias t {v['bias_t']:+.2f}, outer fraction {r['extreme_fraction']:.3f}")
    return result


if __name__ == "__main__":
    main()
