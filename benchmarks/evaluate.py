"""Benchmark: held-out accuracy of a protocol's methods, and the wall time of ``bayes-talk evaluate``.

Runs ``bayes-talk evaluate`` as a subprocess (the command a user types) on a built corpus
(``--corpus``; its feature cache is warmed first, outside the timing), trained on all of it
and tested on ``--test-corpus`` when given (sentences the models never saw), else on the
protocol's own splits. Writes ``benchmarks/results/evaluate.json``: the wall time of the
evaluate command, the load average at start and end (the machine is shared), the headline
numbers per method (AMSE, ACC, NMSE, training seconds, synthesis frames per second) and the
whole evaluate JSON (``evaluate``). ``--protocol-quick`` runs the protocol's quick variant
(its target: within 10 minutes on 2 cores, ``vs_target`` = wall / 600 s).

    .venv/bin/python benchmarks/evaluate.py --corpus data/train250 --test-corpus data/test3_40
    .venv/bin/python benchmarks/evaluate.py --corpus data/train120 --protocol-quick
    .venv/bin/python benchmarks/evaluate.py --quick    # the quick corpora, three methods -> results/quick/
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import ROOT, bench_corpus, result_path, write_result

QUICK_TARGET_S = 600.0
#: the methods of the quick mode (the default family's posterior, a baseline and the floor)
QUICK_METHODS = "ssgpdm-phone-ctx-mean-posterior,voice-puppetry,zero"


def _rel(path) -> str:
    return os.path.relpath(Path(path).resolve(), ROOT)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--corpus", default=None, help="a built corpus (training utterances; default: the suite's)")
    ap.add_argument("--test-corpus", default=None, help="held-out corpus (default: the protocol's splits)")
    ap.add_argument("--protocol", default="deena2010")
    ap.add_argument("--protocol-quick", action="store_true", help="the protocol's quick variant (evaluate --quick)")
    ap.add_argument("--methods", default=None, help="evaluate --methods (default: the protocol's)")
    ap.add_argument("--quick", action="store_true",
                    help=f"the quick corpora, the quick protocol, methods {QUICK_METHODS}")
    ap.add_argument("--out", default=None, help="default benchmarks/results/evaluate.json (--quick: results/quick/)")
    ap.add_argument("--eval-dir", default=None, help="where the evaluate outputs go (default: a temp dir)")
    args = ap.parse_args()
    out = result_path("evaluate", args.quick, args.out)
    if args.quick:
        args.corpus, args.test_corpus = bench_corpus("train", True), bench_corpus("test", True)
        args.protocol_quick, args.methods = True, args.methods or QUICK_METHODS
    args.corpus = args.corpus or bench_corpus("train")
    from bayes_talk.corpus import load_corpus

    t0 = time.perf_counter()
    n_utt = len(load_corpus(args.corpus))          # warms the feature cache (not timed below)
    if args.test_corpus:
        load_corpus(args.test_corpus, aam=Path(args.corpus) / "aam.npz")
    warm_s = time.perf_counter() - t0
    eval_dir = Path(args.eval_dir) if args.eval_dir else Path(tempfile.mkdtemp(prefix="bt_eval_"))
    eval_dir.mkdir(parents=True, exist_ok=True)
    out_json = eval_dir / "evaluate.json"
    cmd = [sys.executable, "-m", "bayes_talk.app.cli", "-q", "evaluate", "--protocol", args.protocol,
           "--corpus", _rel(args.corpus), "--json", str(out_json), "--no-figures"]
    cmd += ["--quick"] * args.protocol_quick + (["--test-corpus", _rel(args.test_corpus)] if args.test_corpus else [])
    cmd += ["--methods", args.methods] if args.methods else []
    load_start = [round(x, 2) for x in os.getloadavg()]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    load_end = [round(x, 2) for x in os.getloadavg()]
    if proc.returncode != 0:
        sys.stderr.write(proc.stderr[-4000:])
        raise SystemExit(f"evaluate failed with exit code {proc.returncode}")
    res = json.loads(out_json.read_text())
    result = {
        "evaluate_command": " ".join(["bayes-talk"] + cmd[4:]).replace(str(out_json), "OUT.json"),
        "corpus": _rel(args.corpus), "test_corpus": _rel(args.test_corpus) if args.test_corpus else None,
        "corpus_utterances": n_utt, "cache_warm_s": round(warm_s, 2), "wall_s": round(wall, 2),
        "protocol_quick": args.protocol_quick,
        "quick_target_s": QUICK_TARGET_S if args.protocol_quick else None,
        "vs_target": round(wall / QUICK_TARGET_S, 3) if args.protocol_quick else None,
        "evaluate_elapsed_s": round(res["elapsed_seconds"], 2), "n_train": res["n_train"], "n_test": res["n_test"],
        "methods": {k: {"AMSE": e["headline"].get("AMSE"), "ACC": e["headline"].get("ACC"),
                        "NMSE": e["nmse"]["mean"], "train_s": round(e["train_seconds"], 2),
                        "synth_frames_per_s": e["synth_frames_per_second"]}
                    for k, e in res["methods"].items()},
        "loadavg_start": load_start, "loadavg_end": load_end,
        "evaluate": res,
    }
    write_result(out, result)
    print(json.dumps({k: v for k, v in result.items() if k != "evaluate"}, indent=1))


if __name__ == "__main__":
    main()
