"""CPU cost of rendering inside a corpus build (issue 25, session 12).

Builds ``--n`` utterances with ``build_corpus(..., n_workers=1)`` in this process, with
``render_frames`` wrapped by a timer, and records under ``--label`` in the result JSON
(other labels kept): build CPU / wall seconds (this process; espeak's child processes
separately), render CPU / wall seconds, frames, per-utterance CPU, and a SHA-256 over
every file of the built corpus (two builds with equal digests are byte-identical).
``--speech vtl`` with a synthesis cache that holds the utterances (``BAYES_TALK_CACHE``)
times a cached rebuild, issue 25's 2-minute case. Before/after a change: run it once with
``PYTHONPATH`` at each checkout, same ``--out``, different ``--label``.

    PYTHONPATH=. .venv/bin/python benchmarks/render_build.py --label numba \
        [--n 12] [--speech espeak|vtl] [--out benchmarks/results/render_build_s12.json]
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import resource
import subprocess
import tempfile
import time
from pathlib import Path

from bayes_talk.corpus import render
from bayes_talk.corpus.build import build_corpus
from bayes_talk.base.files import write_json

ROOT = Path(__file__).resolve().parents[1]


def corpus_digest(root: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(q for q in root.rglob("*") if q.is_file()):
        h.update(str(p.relative_to(root)).encode())
        h.update(p.read_bytes())
    return h.hexdigest()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--label", required=True, help="key of this run in the JSON (e.g. numpy, numba)")
    ap.add_argument("--n", type=int, default=12)
    ap.add_argument("--speech", choices=("espeak", "vtl"), default="espeak")
    ap.add_argument("--out", default="benchmarks/results/render_build_s12.json",
                    help="relative to the repository (default: %(default)s)")
    args = ap.parse_args()
    acc = {"cpu": 0.0, "wall": 0.0, "frames": 0}
    inner = render.render_frames

    def timed(landmarks, *a, **k):
        c, w = time.process_time(), time.perf_counter()
        frames = inner(landmarks, *a, **k)
        acc["cpu"] += time.process_time() - c
        acc["wall"] += time.perf_counter() - w
        acc["frames"] += len(frames)
        return frames

    render.render_frames = timed          # corpus workers import it at call time
    with tempfile.TemporaryDirectory() as tmp:
        c0, w0, l0 = time.process_time(), time.perf_counter(), os.getloadavg()
        build_corpus(Path(tmp) / "corpus", n_utterances=args.n, seed=0, n_workers=1, speech=args.speech)
        cpu, wall = time.process_time() - c0, time.perf_counter() - w0
        digest = corpus_digest(Path(tmp) / "corpus")
    ch = resource.getrusage(resource.RUSAGE_CHILDREN)
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=Path(render.__file__).parent,
                                capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        commit = None
    n = args.n
    record = {"speech": args.speech, "utterances": n, "frames": acc["frames"], "code_commit": commit,
              "build_cpu_s": cpu, "build_wall_s": wall, "children_cpu_s": ch.ru_utime + ch.ru_stime,
              "render_cpu_s": acc["cpu"], "render_wall_s": acc["wall"],
              "build_cpu_s_per_utterance": cpu / n, "render_cpu_s_per_utterance": acc["cpu"] / n,
              "render_cpu_ms_per_frame": 1e3 * acc["cpu"] / max(1, acc["frames"]),
              "corpus_sha256": digest, "loadavg_start": l0, "loadavg_end": os.getloadavg()}
    out = ROOT / args.out
    result = json.loads(out.read_text()) if out.exists() else {}
    result[f"{args.speech}/{args.label}"] = record
    write_json(out, result)
    print(json.dumps(record, indent=1))


if __name__ == "__main__":
    main()
