"""Benchmark: build and featurise the default 300-utterance corpus.

Writes benchmarks/results/corpus.json: wall time of build_corpus and of load_corpus
(featurisation: MFCC, AAM projection, frame labels; cold cache) and of a warm load,
CPU time (this process and its worker/espeak processes, user + system), the 1/5/15-min
load average at start and end (the machine is shared: compare timings with the load),
size on disk, the AAM size, and phone coverage (which of the 40 phones occur, frame
counts). Targets: build + featurise <= 180 s on 2 cores (``total_vs_target`` = total /
180), size <= 200 MB.

``--speech vtl`` (issue 25: VocalTractLab audio and face; needs
``pip install 'bayes_talk[articulatory]'``) writes benchmarks/results/corpus_vtl.json: the
build with an empty synthesis cache (target <= 15 min = 900 s on 2 cores), then a rebuild
into a second directory from the cache (target <= 2 min), and whether the two are
byte-identical (``rebuild_identical``, every file compared).

    .venv/bin/python benchmarks/corpus.py [--n 300] [--seed 0] [--speech espeak|vtl]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import tempfile
import time
from collections import Counter
from pathlib import Path

from bayes_talk.data.corpus import build_corpus, load_corpus
from bayes_talk.data.phones import PHONES


def _size(d: Path, exclude: tuple[str, ...] = ()) -> int:
    return sum(p.stat().st_size for p in d.rglob("*") if p.is_file() and p.name not in exclude)


def _files(d: Path) -> dict[str, str]:
    """Relative path -> SHA-256 of every file under ``d``."""
    import hashlib

    return {str(p.relative_to(d)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(d.rglob("*")) if p.is_file()}


def _cpu_s() -> dict[str, float]:
    me = resource.getrusage(resource.RUSAGE_SELF)
    ch = resource.getrusage(resource.RUSAGE_CHILDREN)   # waited-for workers and espeak
    return {"user": me.ru_utime + ch.ru_utime, "system": me.ru_stime + ch.ru_stime}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=300)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--speech", choices=("espeak", "vtl"), default="espeak")
    ap.add_argument("--out", default=None,
                    help="default benchmarks/results/corpus.json (corpus_vtl.json with --speech vtl)")
    args = ap.parse_args()
    if args.out is None:
        name = "corpus.json" if args.speech == "espeak" else "corpus_vtl.json"
        args.out = str(Path(__file__).parent / "results" / name)
    vtl_extra: dict = {}
    load_start = [round(x, 2) for x in os.getloadavg()]
    cpu0 = _cpu_s()
    with tempfile.TemporaryDirectory() as td:
        root = Path(td) / "corpus"
        if args.speech == "vtl":  # a cold synthesis cache, then a cached rebuild
            os.environ["BAYES_TALK_CACHE"] = str(Path(td) / "synthesis-cache")
        t0 = time.perf_counter()
        build_corpus(root, n_utterances=args.n, seed=args.seed, speech=args.speech)
        t_build = time.perf_counter() - t0
        if args.speech == "vtl":
            c0 = _cpu_s()
            t0 = time.perf_counter()
            again = build_corpus(Path(td) / "again", n_utterances=args.n, seed=args.seed, speech="vtl")
            t_cached = time.perf_counter() - t0
            c1 = _cpu_s()
            a, b = _files(root), _files(again)
            vtl_extra = {"speech": "vtl", "target_build_s": 900, "cached_rebuild_s": round(t_cached, 2),
                         "target_cached_rebuild_s": 120,
                         "cpu_cached_rebuild_s": {k: round(c1[k] - c0[k], 2) for k in c0},
                         "rebuild_identical": a == b,
                         "rebuild_differing": sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))}
            cpu0 = {k: cpu0[k] + (c1[k] - c0[k]) for k in cpu0}   # keep the cached rebuild out
        cpu1 = _cpu_s()
        size_build = _size(root)
        t0 = time.perf_counter()
        c = load_corpus(root)
        t_feat = time.perf_counter() - t0
        cpu2 = _cpu_s()
        load_end = [round(x, 2) for x in os.getloadavg()]
        t0 = time.perf_counter()
        load_corpus(root)
        t_warm = time.perf_counter() - t0
        size_total = _size(root)
        frames = Counter(lab for s in c for lab in s.labels)
        segs = Counter(p for s in c for _, _, p in s.meta["intervals"])
        n_frames = sum(s.n_frames for s in c)
        result = {
            "n_utterances": args.n,
            "seed": args.seed,
            "build_s": round(t_build, 2),
            "featurise_s": round(t_feat, 2),
            "total_s": round(t_build + t_feat, 2),
            "warm_load_s": round(t_warm, 2),
            "target_total_s": 180,
            "total_vs_target": round((t_build + t_feat) / 180, 3),
            "cpu_build_s": {k: round(cpu1[k] - cpu0[k], 2) for k in cpu0},
            "cpu_featurise_s": {k: round(cpu2[k] - cpu1[k], 2) for k in cpu0},
            "loadavg_start": load_start,
            "loadavg_end": load_end,
            "size_build_mb": round(size_build / 1e6, 2),
            "size_with_cache_mb": round(size_total / 1e6, 2),
            "target_size_mb": 200,
            "n_frames": n_frames,
            "audio_s": round(n_frames / 25.0, 1),
            "aam_n_params": int(c.aam.n_params),
            "aam_modes_shape_texture_combined": [c.aam.n_shape_modes, c.aam.n_texture_modes,
                                                 c.aam.n_combined],
            "phones_present": [p for p in PHONES if segs[p] > 0],
            "phones_missing": [p for p in PHONES if segs[p] == 0],
            "phone_segments": {p: segs[p] for p in PHONES},
            "phone_frames": {p: frames[p] for p in PHONES},
            "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
            **vtl_extra,
        }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp")
    tmp.write_text(json.dumps(result, indent=1) + "\n")
    os.replace(tmp, out)
    print(json.dumps({k: v for k, v in result.items() if not k.startswith("phone_")}, indent=1))


if __name__ == "__main__":
    main()
