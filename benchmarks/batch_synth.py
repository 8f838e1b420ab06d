"""How much `synth --audio-dir` saves against one `bayes-talk synth` process per file.

The first ``--n-files`` WAVs of ``--test-corpus`` (name order, with their ``.lab``) are
synthesised twice with the same options (``--synth-args``): by ``--n-files`` separate
``bayes-talk synth MODEL --audio X.wav --labels X.lab`` processes, one after another, and by
one ``bayes-talk synth MODEL --audio-dir DIR`` process (``--file-workers`` files at once).
Reported: each way's wall seconds in all and per file, the batch's per-file time as a ratio of
the separate processes' (below 1: the batch is faster), the seconds saved per file (the start-up
and model load the batch pays once), the per-file seconds the batch's ``summary.json`` records,
and the largest difference between the two ways' trajectories (0 with one file worker: the same
code on the same model).

    PYTHONPATH=. python benchmarks/batch_synth.py --model MODEL_DIR --test-corpus data/dev40 \\
        [--n-files 10] [--file-workers 1] [--synth-args "--no-video"] [--out benchmarks/results/batch_synth.json]
    PYTHONPATH=. python benchmarks/batch_synth.py --quick     # 3 files of the quick corpus, no video
"""
from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from benchmarks.common import bench_corpus, bench_model, result_path, write_result

CLI = [sys.executable, "-m", "bayes_talk.app.cli", "-q", "synth"]


def timed(cmd: list[str], timeout: float) -> dict:
    """Run ``cmd``; its wall seconds, exit code and the last lines of its standard error."""
    t0 = time.monotonic()
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, check=False)
        rc, err = proc.returncode, proc.stderr
    except subprocess.TimeoutExpired as exc:
        rc, err = None, (exc.stderr or b"").decode(errors="replace") if isinstance(exc.stderr, bytes) else ""
    return {"wall_seconds": time.monotonic() - t0, "returncode": rc, "stderr_tail": err.strip().splitlines()[-3:]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", default=None)
    ap.add_argument("--test-corpus", default=None)
    ap.add_argument("--n-files", type=int, default=10)
    ap.add_argument("--file-workers", type=int, default=1)
    ap.add_argument("--synth-args", default="", help="extra synth options for both ways, one string")
    ap.add_argument("--timeout", type=float, default=3600.0, help="seconds per process before it is stopped")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    args.out = result_path("batch_synth", args.quick, args.out)
    if args.quick:
        args.n_files, args.synth_args = 3, args.synth_args or "--no-video"
    model = Path(args.model or bench_model(args.quick))
    corpus = Path(args.test_corpus or bench_corpus("test", args.quick))
    wavs = sorted((corpus / "utterances").glob("*.wav"))[:args.n_files]
    if len(wavs) < args.n_files:
        raise SystemExit(f"{corpus}/utterances has {len(wavs)} WAV files, fewer than --n-files {args.n_files}")
    extra = shlex.split(args.synth_args)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        audio = tmp / "audio"
        audio.mkdir()
        for w in wavs:
            for p in (w, w.with_suffix(".lab")):
                (audio / p.name).symlink_to(p.resolve())
        separate = []
        for w in wavs:
            run = timed([*CLI, str(model), "--audio", str(audio / w.name), "--labels",
                         str(audio / f"{w.stem}.lab"), "--out", str(tmp / "separate" / w.stem), *extra], args.timeout)
            separate.append({"file": w.name, **run})
            print(json.dumps({"separate": w.name, "wall_seconds": round(run["wall_seconds"], 2),
                              "returncode": run["returncode"]}), flush=True)
        batch = timed([*CLI, str(model), "--audio-dir", str(audio), "--out", str(tmp / "batch"),
                       "--file-workers", str(args.file_workers), *extra], args.timeout)
        print(json.dumps({"batch": len(wavs), "wall_seconds": round(batch["wall_seconds"], 2),
                          "returncode": batch["returncode"]}), flush=True)
        summary_path = tmp / "batch" / "summary.json"
        rows = json.loads(summary_path.read_text())["files"] if summary_path.is_file() else []
        diffs = []
        for w in wavs:
            a, b = tmp / "separate" / w.stem / "trajectory.npy", tmp / "batch" / w.stem / "trajectory.npy"
            if a.is_file() and b.is_file():
                diffs.append(float(np.abs(np.load(a) - np.load(b)).max()))
    n = len(wavs)
    sep_total = sum(r["wall_seconds"] for r in separate)
    all_ok = batch["returncode"] == 0 and all(r["returncode"] == 0 for r in separate) and len(diffs) == n
    summary = {"n_files": n, "file_workers": args.file_workers,
               "separate_wall_seconds": sep_total, "separate_per_file": sep_total / n,
               "batch_wall_seconds": batch["wall_seconds"], "batch_per_file": batch["wall_seconds"] / n,
               "batch_to_separate_per_file": batch["wall_seconds"] / sep_total,
               "seconds_saved_per_file": (sep_total - batch["wall_seconds"]) / n,
               "batch_recorded_seconds": [r["seconds"] for r in rows],
               "largest_trajectory_difference": max(diffs) if diffs else None, "all_finished": all_ok}
    write_result(args.out, {"model": os.path.relpath(model.resolve(), HERE.parent),
                            "test_corpus": os.path.relpath(corpus.resolve(), HERE.parent),
                            "files": [w.name for w in wavs], "synth_args": args.synth_args,
                            "separate": separate, "batch": {**batch, "summary": rows}, "summary": summary})
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
