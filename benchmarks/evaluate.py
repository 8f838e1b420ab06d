"""Benchmark: wall time of the quick deena2010 evaluation against its 10-minute target.

Runs ``bayes-talk evaluate --protocol deena2010 --quick`` as a subprocess (the command a
user types) on a built-in corpus: the one given with ``--corpus`` (reused as is; its
feature cache is warmed first, outside the timing), or one it builds once into
``--build-dir`` (default /tmp/bt_bench_corpus, reused if it already holds a corpus built
with the same ``--n`` and ``--seed``). Writes benchmarks/results/evaluate.json: the wall
time of the evaluate command, ``vs_target`` = wall / 600 s, the load average at start and
end (the machine is shared), the headline numbers per method and where the evaluate
outputs went.

    .venv/bin/python benchmarks/evaluate.py [--corpus DIR | --build-dir DIR --n 120 --seed 0]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

TARGET_S = 600.0
ROOT = Path(__file__).resolve().parents[1]


def _atomic_json(path: Path, obj: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    with os.fdopen(fd, "w") as f:
        f.write(json.dumps(obj, indent=1) + "\n")
    os.replace(tmp, path)


def _ensure_corpus(build_dir: Path, n: int, seed: int) -> Path:
    man = build_dir / "manifest.json"
    if man.exists():
        m = json.loads(man.read_text())
        if len(m.get("sequences", [])) == n and m.get("seed") == seed:
            return build_dir
        raise SystemExit(f"{build_dir} holds a different corpus (n={len(m.get('sequences', []))}, "
                         f"seed={m.get('seed')}); choose another --build-dir")
    subprocess.run([sys.executable, "-m", "bayes_talk.app.cli", "corpus", "build", str(build_dir),
                    "--n-utterances", str(n), "--seed", str(seed)], check=True, cwd=ROOT)
    return build_dir


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--corpus", default=None, help="an existing built corpus to reuse")
    ap.add_argument("--build-dir", default="/tmp/bt_bench_corpus")
    ap.add_argument("--n", type=int, default=120, help="utterances of the corpus to build")
    ap.add_argument("--seed", type=int, default=0, help="corpus build seed")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "evaluate.json"))
    ap.add_argument("--eval-dir", default=None, help="where the evaluate outputs go (default: a temp dir)")
    args = ap.parse_args()

    corpus = Path(args.corpus) if args.corpus else _ensure_corpus(Path(args.build_dir), args.n, args.seed)
    from bayes_talk.corpus import load_corpus

    t0 = time.perf_counter()
    n_utt = len(load_corpus(corpus))          # warms the feature cache (not timed below)
    warm_s = time.perf_counter() - t0
    eval_dir = Path(args.eval_dir) if args.eval_dir else Path(tempfile.mkdtemp(prefix="bt_eval_"))
    eval_dir.mkdir(parents=True, exist_ok=True)
    out_json = eval_dir / "deena2010_quick.json"
    cmd = [sys.executable, "-m", "bayes_talk.app.cli", "evaluate", "--protocol", "deena2010", "--quick",
           "--corpus", str(corpus), "--json", str(out_json)]
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
        "command": " ".join(["bayes-talk"] + cmd[3:]),
        "corpus": str(corpus),
        "corpus_utterances": n_utt,
        "cache_warm_s": round(warm_s, 2),
        "wall_s": round(wall, 2),
        "target_s": TARGET_S,
        "vs_target": round(wall / TARGET_S, 3),
        "within_target": wall <= TARGET_S,
        "evaluate_elapsed_s": round(res["elapsed_seconds"], 2),
        "quick": res["quick"],
        "n_train": res["n_train"],
        "n_test": res["n_test"],
        "methods": {k: {"AMSE": e["headline"].get("AMSE"), "ACC": e["headline"].get("ACC"),
                        "NMSE": e["nmse"]["mean"], "train_s": round(e["train_seconds"], 2),
                        "synth_frames_per_s": e["synth_frames_per_second"]}
                    for k, e in res["methods"].items()},
        "outputs": str(eval_dir),
        "loadavg_start": load_start,
        "loadavg_end": load_end,
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
    }
    _atomic_json(Path(args.out), result)
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
