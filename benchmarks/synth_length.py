"""How `synth`'s time and memory grow with the length of the speech.

Held-out utterances of ``--test-corpus`` are joined in order (cycled when the corpus is
shorter) into WAV + label files of about ``--seconds`` each (whole utterances, the first total
at or above the target), and ``bayes-talk synth MODEL --audio X.wav --labels X.lab`` runs on
each in a fresh process with the defaults and ``-v`` (``--synth-args`` adds options, e.g. ``--no-video``).
Per length: the speech's seconds and frames, wall seconds, wall per second of speech and its
ratio to the shortest length's, the process's peak resident memory (from ``/usr/bin/time``'s
maximum RSS) per minute of speech, each stage's wall seconds (``-v``'s "done in" lines), and
the longest gap between two lines the run printed on its standard error (not a terminal), from
its start to its end: the progress a user sees in a log.

    PYTHONPATH=. python benchmarks/synth_length.py --model MODEL_DIR --test-corpus data/dev40 \\
        [--seconds 3,10,26,60,300] [--synth-args "--no-video"] [--out benchmarks/results/synth_length.json]
    PYTHONPATH=. python benchmarks/synth_length.py --quick    # 3 and 10 s on the quick model
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shlex
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from benchmarks.common import bench_corpus, bench_model, result_path, write_result


def join_utterances(corpus: Path, seconds: float, out: Path) -> dict:
    """WAV + .lab of the corpus's utterances joined in name order (cycled) until ``seconds``."""
    import soundfile as sf

    from bayes_talk.data.labels import read_lab, write_lab
    from bayes_talk.data.speech import write_wav

    wavs = sorted((corpus / "utterances").glob("*.wav"))
    if not wavs:
        raise SystemExit(f"{corpus}/utterances has no WAV files")
    pieces, labels, t, k, sr = [], [], 0.0, 0, None
    while t < seconds:
        wav = wavs[k % len(wavs)]
        x, sr_k = sf.read(wav, dtype="int16")
        if sr is not None and sr_k != sr:
            raise SystemExit(f"{wav}: sample rate {sr_k}, the others {sr}")
        sr = sr_k
        for start, stop, ph in read_lab(wav.with_suffix(".lab")):
            labels.append((start + t, min(stop, len(x) / sr) + t, ph))
        pieces.append(x)
        t += len(x) / sr
        k += 1
    write_wav(out.with_suffix(".wav"), np.concatenate(pieces), sr)
    write_lab(out.with_suffix(".lab"), labels)
    return {"seconds": t, "utterances": k, "sample_rate": sr}


def run_synth(cmd: list[str], timeout: float) -> dict:
    """Run ``cmd`` under /usr/bin/time; wall seconds, peak RSS, exit code and the longest gap
    between lines on its standard error (start and end included)."""
    t0 = time.monotonic()
    proc = subprocess.Popen(["/usr/bin/time", "-f", "MAXRSS_KB=%M", *cmd], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    stamps, lines = [t0], []

    def read():
        for line in proc.stderr:
            stamps.append(time.monotonic())
            lines.append(line.rstrip())
    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        rc = proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        rc = None
    reader.join(5)
    wall = time.monotonic() - t0
    rss = next((int(x.split("=")[1]) for x in lines if x.startswith("MAXRSS_KB=")), None)
    gaps = np.diff(stamps + [t0 + wall])
    before = ["(start)", *lines][int(np.argmax(gaps))]
    return {"wall_seconds": wall, "peak_rss_mb": None if rss is None else rss / 1024, "returncode": rc,
            "stderr_lines": len(lines), "longest_silence_seconds": float(gaps.max()),
            "longest_silence_after": before, "stderr_lines_all": lines,
            "stderr_tail": [x for x in lines if not x.startswith("MAXRSS_KB=")][-5:]}


def stage_seconds(lines: list[str]) -> dict[str, float]:
    """Each stage's wall seconds from synth's ``-v`` lines "NAME: done in 1 min 3.6 s (...)"."""
    out = {}
    for line in lines:
        m = re.search(r"INFO: (.+?): done in (?:(\d+) min )?([\d.]+) s", line)
        if m:
            out[m.group(1)] = 60 * float(m.group(2) or 0) + float(m.group(3))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", default=None)
    ap.add_argument("--test-corpus", default=None)
    ap.add_argument("--seconds", default="3,10,26,60,300")
    ap.add_argument("--synth-args", default="", help="extra synth options, one string")
    ap.add_argument("--timeout", type=float, default=3600.0, help="seconds per run before it is stopped")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    args.out = result_path("synth_length", args.quick, args.out)
    if args.quick:
        args.seconds = "3,10"
    model = Path(args.model or bench_model(args.quick))
    corpus = Path(args.test_corpus or bench_corpus("test", args.quick))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for target in [float(s) for s in args.seconds.split(",")]:
            base = Path(tmp) / f"joined_{target:g}s"
            row = {"target_seconds": target, **join_utterances(corpus, target, base)}
            out = Path(tmp) / f"out_{target:g}s"
            cmd = [sys.executable, "-m", "bayes_talk.app.cli", "-v", "synth", str(model), "--audio", str(base.with_suffix(".wav")),
                   "--labels", str(base.with_suffix(".lab")), "--out", str(out), *shlex.split(args.synth_args)]
            row.update(run_synth(cmd, args.timeout))
            row["stage_seconds"] = stage_seconds(row.pop("stderr_lines_all"))
            diag_path = out / "diagnostics.json"
            if diag_path.is_file():
                diag = json.loads(diag_path.read_text())
                inner = diag.get("diagnostics", {})
                row["map"] = {k: inner.get(k) for k in ("map_converged", "map_iter", "map_grad_norm",
                                                         "hessian_modified", "dim", "khat")}
            row["wall_per_speech_second"] = row["wall_seconds"] / row["seconds"]
            row["peak_rss_mb_per_speech_minute"] = (None if row["peak_rss_mb"] is None
                                                    else row["peak_rss_mb"] / (row["seconds"] / 60))
            print(json.dumps({k: v for k, v in row.items() if k != "stderr_tail"}), flush=True)
            rows.append(row)
    ok = [r for r in rows if r["returncode"] == 0]
    base_rate = ok[0]["wall_per_speech_second"] if ok else None
    for r in ok:
        r["per_second_ratio_to_shortest"] = r["wall_per_speech_second"] / base_rate
    summary = {"lengths": [r["seconds"] for r in rows],
               "wall_seconds": [r["wall_seconds"] for r in rows],
               "per_second_ratio_to_shortest": [r.get("per_second_ratio_to_shortest") for r in rows],
               "peak_rss_mb": [r["peak_rss_mb"] for r in rows],
               "longest_silence_seconds": [r["longest_silence_seconds"] for r in rows],
               "all_finished": len(ok) == len(rows)}
    write_result(args.out, {"model": os.path.relpath(model.resolve(), HERE.parent),
                            "test_corpus": os.path.relpath(corpus.resolve(), HERE.parent),
                            "synth_args": args.synth_args, "runs": rows, "summary": summary})
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
