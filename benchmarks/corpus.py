"""Benchmark: build and featurise the built-in corpus (espeak or VocalTractLab speech).

Writes benchmarks/results/corpus.json: wall time of build_corpus and of load_corpus
(featurisation: MFCC, AAM projection, frame labels; cold cache) and of a warm load,
CPU time (this process and its worker/espeak processes, user + system), the 1/5/15-min
load average at start and end and sampled every 15 s during the run (the machine is
shared: compare timings with the load), size on disk, the AAM size, and phone coverage
(which of the 40 phones occur, frame counts). Targets: build + featurise <= 180 s on 2
cores (``total_vs_target`` = total / 180), size <= 200 MB.

The build uses ``--workers`` processes (default 2, what ``bayes-talk corpus build`` uses
from 16 utterances on; the output does not depend on it).

``--speech vtl`` (VocalTractLab audio and face; needs ``pip install 'bayes_talk[articulatory]'``)
times the build with the synthesis cache ``--cache-dir`` (default: a fresh empty directory, i.e. a
truly cold build; the number of cache entries before and after is recorded, so a warm
start is visible), target <= 15 min = 900 s on 2 cores; then a rebuild into a second
directory from the (now full) cache, target <= 2 min; and whether the two are
byte-identical (``rebuild_identical``, every file compared). ``--peer-espeak`` also builds
the espeak corpus of the same sentences, seed and workers in the same run: the ratio of
the two builds' wall times is a peer measure that the shared machine's load affects
alike. ``cpu_bound_wall_s`` = CPU time / workers is the wall time the build would take
with ``--workers`` free cores (every utterance's work is single-threaded).

    .venv/bin/python benchmarks/corpus.py [--n 300] [--seed 0] [--speech espeak|vtl]
        [--workers 2] [--cache-dir DIR] [--peer-espeak]
    .venv/bin/python benchmarks/corpus.py --quick     # 6 espeak utterances -> results/quick/corpus.json
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Self

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bayes_talk.corpus import build_corpus, load_corpus
from bayes_talk.data.phones import PHONES
from benchmarks.common import result_path, write_result


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


def _load() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


class _LoadSampler:
    """The 1-min load average every ``every`` seconds, in a daemon thread."""

    def __init__(self, every: float = 15.0) -> None:
        self.samples: list[float] = []
        self._stop = threading.Event()
        self._every = every
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while True:
            self.samples.append(round(os.getloadavg()[0], 2))
            if self._stop.wait(self._every):
                return

    def __enter__(self) -> Self:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()

    def summary(self) -> dict:
        s = self.samples
        return {"n": len(s), "min": min(s), "mean": round(sum(s) / len(s), 2), "max": max(s)}


def _phase(fn) -> dict:
    """Run ``fn()``; its wall time, CPU time (user + system, with waited-for children),
    the load average before and after and the 1-min load sampled while it ran."""
    load0, c0 = _load(), _cpu_s()
    with _LoadSampler() as ls:
        t0 = time.perf_counter()
        fn()
        wall = time.perf_counter() - t0
    c1 = _cpu_s()
    cpu = {k: round(c1[k] - c0[k], 2) for k in c0}
    return {"wall_s": round(wall, 2), "cpu_s": cpu, "cpu_total_s": round(sum(cpu.values()), 2),
            "loadavg_start": load0, "loadavg_end": _load(), "load1_during": ls.summary()}


def _cache_entries(d: Path) -> int:
    return sum(1 for _ in (d / "vtl").glob("*.npz")) if (d / "vtl").is_dir() else 0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=300)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--speech", choices=("espeak", "vtl"), default="espeak")
    ap.add_argument("--workers", type=int, default=2,
                    help="worker processes of the build (default 2, as bayes-talk corpus build)")
    ap.add_argument("--cache-dir", default=None,
                    help="--speech vtl: the synthesis cache (BAYES_TALK_CACHE) of the first build "
                         "(default: a fresh empty directory, a truly cold build)")
    ap.add_argument("--peer-espeak", action="store_true",
                    help="--speech vtl: also build the espeak corpus of the same sentences and seed")
    ap.add_argument("--keep", default=None,
                    help="copy the built corpora (featurised) into this directory after measuring: "
                         "KEEP/<speech> and, with --peer-espeak, KEEP/espeak; refuses an existing target")
    ap.add_argument("--quick", action="store_true", help="6 espeak utterances")
    ap.add_argument("--out", default=None, help="default benchmarks/results/corpus.json (--quick: results/quick/)")
    args = ap.parse_args()
    args.out = result_path("corpus", args.quick, args.out)
    if args.quick:
        args.n, args.speech = 6, "espeak"
    if args.speech == "espeak" and (args.cache_dir or args.peer_espeak):
        ap.error("--cache-dir and --peer-espeak go with --speech vtl")
    if args.keep:
        targets = [Path(args.keep) / args.speech] + (
            [Path(args.keep) / "espeak"] if args.speech == "vtl" and args.peer_espeak else [])
        for t in targets:
            if t.exists():
                ap.error(f"--keep: {t} exists; choose an empty directory (nothing is overwritten)")
    kw = {"n_utterances": args.n, "seed": args.seed, "n_workers": args.workers}
    vtl_extra: dict = {}
    load_start = _load()
    with tempfile.TemporaryDirectory() as td:
        root = Path(td) / "corpus"
        if args.speech == "vtl":
            cache = Path(args.cache_dir) if args.cache_dir else Path(td) / "synthesis-cache"
            os.environ["BAYES_TALK_CACHE"] = str(cache)
            entries_before = _cache_entries(cache)
        build = _phase(lambda: build_corpus(root, speech=args.speech, **kw))
        if args.speech == "vtl":
            entries_after = _cache_entries(cache)
            cached = _phase(lambda: build_corpus(Path(td) / "again", speech="vtl", **kw))
            a, b = _files(root), _files(Path(td) / "again")
            vtl_extra = {
                "speech": "vtl", "target_build_s": 900, "target_cached_rebuild_s": 120,
                "cache": "fresh (cold build)" if args.cache_dir is None else "given by --cache-dir",
                "cache_entries_before": entries_before, "cache_entries_after": entries_after,
                "cold_utterances": entries_after - entries_before,
                "build_vs_target": round(build["wall_s"] / 900, 3),
                "cached_rebuild": cached,
                "cached_rebuild_s": cached["wall_s"],
                "cached_rebuild_vs_target": round(cached["wall_s"] / 120, 3),
                "cached_rebuild_cpu_bound_wall_s": round(cached["cpu_total_s"] / args.workers, 1),
                "rebuild_identical": a == b,
                "rebuild_n_files": len(a),
                "rebuild_differing": sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k)),
            }
            if args.peer_espeak:
                peer = _phase(lambda: build_corpus(Path(td) / "espeak", speech="espeak", **kw))
                vtl_extra["peer_espeak_build"] = peer
                vtl_extra["build_wall_ratio_vtl_to_espeak"] = round(build["wall_s"] / peer["wall_s"], 2)
                vtl_extra["build_cpu_ratio_vtl_to_espeak"] = round(
                    build["cpu_total_s"] / max(peer["cpu_total_s"], 1e-9), 2)
        size_build = _size(root)
        loaded: list = []
        feat = _phase(lambda: loaded.append(load_corpus(root)))
        c = loaded[0]
        t0 = time.perf_counter()
        load_corpus(root)
        t_warm = time.perf_counter() - t0
        size_total = _size(root)
        if args.keep:
            keep = Path(args.keep)
            shutil.copytree(root, keep / args.speech)
            if args.speech == "vtl" and args.peer_espeak:
                shutil.copytree(Path(td) / "espeak", keep / "espeak")
        frames = Counter(lab for s in c for lab in s.labels)
        segs = Counter(p for s in c for _, _, p in s.meta["intervals"])
        n_frames = sum(s.n_frames for s in c)
        result = {
            "n_utterances": args.n,
            "seed": args.seed,
            "workers": args.workers,
            "build_s": build["wall_s"],
            "featurise_s": feat["wall_s"],
            "total_s": round(build["wall_s"] + feat["wall_s"], 2),
            "warm_load_s": round(t_warm, 2),
            "target_total_s": 180,
            "total_vs_target": round((build["wall_s"] + feat["wall_s"]) / 180, 3),
            "cpu_build_s": build["cpu_s"],
            "cpu_build_per_utterance_s": round(build["cpu_total_s"] / args.n, 2),
            "cpu_bound_wall_s": round(build["cpu_total_s"] / args.workers, 1),
            "cpu_featurise_s": feat["cpu_s"],
            "build": build,
            "featurise": feat,
            "loadavg_start": load_start,
            "loadavg_end": _load(),
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
            "speech": args.speech,
            **vtl_extra,
        }
    write_result(args.out, result)
    print(json.dumps({k: v for k, v in result.items() if not k.startswith("phone_")}, indent=1))


if __name__ == "__main__":
    from bayes_talk.base.executor import interruptible

    # `kill` stops the worker processes too, not only this one
    interruptible(main)
