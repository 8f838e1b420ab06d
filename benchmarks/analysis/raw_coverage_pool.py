"""Pool the raw (uncalibrated) accuracy of several ``benchmarks/posterior.py --efficiency``
runs into one figure per sampler (issue 24: "the raw coverage of the converged posterior on
held-out sentences, reported beside the default's").

Each efficiency row holds ``raw_accuracy``: the coverage of the central 50/80/90/95 % bands,
the mean band widths, CRPS, NLPD and AMSE of the sampler's predictive on the run's one
utterance, every one of them a mean over that utterance's frames × AAM parameters. Pooling
weighs each run by its entries (frames × parameters), so the pooled figure is the mean over
every entry of every utterance, as ``benchmarks/posterior.py`` computes it over a corpus.
Runs must name different utterances of one test corpus, projected through one AAM, of one
model (a repeated utterance would count twice). Samplers missing from a run are pooled over
the runs that have them (``utterances`` lists which).

    PYTHONPATH=. .venv/bin/python benchmarks/analysis/raw_coverage_pool.py RUN1.json RUN2.json ... \\
        [--out benchmarks/results/raw_coverage_pooled.json]
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from bayes_talk.base.files import write_json

#: the per-entry means pooled besides the coverages and widths
SCALARS = ("crps", "nlpd", "amse")


def pool(runs: list[tuple[str, dict]], dims: int) -> dict:
    """The entry-weighted means of every sampler's ``raw_accuracy`` over ``runs`` (name, JSON)."""
    keys = {(r["model"], r["test_corpus"], r["aam"]) for _, r in runs}
    if len(keys) != 1:
        raise SystemExit(f"the runs differ in model / test corpus / AAM: {sorted(keys)}")
    names = [r["utterance"] for _, r in runs]
    if len(set(names)) != len(names):
        raise SystemExit(f"an utterance appears twice: {names}")
    out = {}
    for method in sorted({m for _, r in runs for m in r["samplers"]}):
        rows = [(r["utterance"], r["frames"] * dims, r["samplers"][method]["raw_accuracy"])
                for path, r in runs if "raw_accuracy" in r["samplers"].get(method, {})]
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path, help="JSON files written by benchmarks/posterior.py --efficiency")
    ap.add_argument("--dims", type=int, default=18, help="AAM parameters per frame (the model's)")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    runs = [(str(p), json.loads(p.read_text())) for p in args.runs]
    res = {"command": "benchmarks/analysis/raw_coverage_pool.py " + " ".join(sys.argv[1:]),
           "runs": [p for p, _ in runs], "samplers": pool(runs, args.dims)}
    print(json.dumps(res["samplers"], indent=1))
    if args.out:
        write_json(args.out, res)


if __name__ == "__main__":
    main()
