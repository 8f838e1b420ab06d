"""Benchmark: alignment and phone recognition -- speed (seconds of audio per second of
wall time; goal >= 10x real time) and accuracy, side by side, in one run.

For every test corpus (built corpora; the sentence text of each utterance is in its
manifest), three labellers run on every utterance: the HMM forced aligner, the DTW
aligner (both from the sentence text) and the phone recogniser (audio only). Each is
timed per call from the WAV path to the interval list (espeak-ng G2P/synthesis, features,
decoding), after one untimed warm-up call (librosa's numba JIT). Accuracy against the
corpus's espeak-ng boundaries: phone error rate, boundary error median / p90 / mean
(ms), share within 20 ms, 25 Hz frame-label agreement (bayes_talk.alignment.scoring).

The alignment models come from ``--model-dir`` (a trained model directory, or any
directory with alignment.json/.npz) or are fitted on ``--train-corpus`` (timed, saved to
``--save-model`` if given). Writes benchmarks/results/align.json.

    .venv/bin/python benchmarks/align.py --train-corpus data/train250 \\
        --test-corpus data/heldout40 data/heldout40_f3
    .venv/bin/python benchmarks/align.py --quick    # the quick corpora -> benchmarks/results/quick/align.json
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import ROOT, bench_corpus, result_path, write_result

TARGET_REALTIME = 10.0


def main() -> None:
    from bayes_talk.alignment.commands import fit_alignment
    from bayes_talk.alignment.model import AlignmentModel
    from bayes_talk.alignment.scoring import score_segmentation, summarise_scores
    from bayes_talk.corpus import load_corpus

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    g = ap.add_mutually_exclusive_group()
    g.add_argument("--model-dir", default=None)
    g.add_argument("--train-corpus", default=None)
    ap.add_argument("--save-model", default=None, help="save the fitted models here")
    ap.add_argument("--test-corpus", nargs="+", default=None)
    ap.add_argument("--quick", action="store_true", help="the quick corpora (benchmarks/common.py)")
    ap.add_argument("--out", default=None, help="default benchmarks/results/align.json (--quick: results/quick/)")
    args = ap.parse_args()
    args.out = result_path("align", args.quick, args.out)
    if not args.model_dir:
        args.train_corpus = args.train_corpus or str(bench_corpus("train", args.quick))
    args.test_corpus = args.test_corpus or [str(bench_corpus("test", args.quick))]

    result: dict = {"load_average_start": os.getloadavg(), "target_realtime": TARGET_REALTIME}
    if args.model_dir:
        model = AlignmentModel.load(args.model_dir)
        result["model"] = os.path.relpath(Path(args.model_dir).resolve(), ROOT)
    else:
        t0 = time.perf_counter()
        model = fit_alignment(load_corpus(args.train_corpus).sequences)
        result["fit_seconds"] = time.perf_counter() - t0
        result["train_corpus"] = os.path.relpath(Path(args.train_corpus).resolve(), ROOT)
        if args.save_model:
            model.save(args.save_model)
    result["recogniser"] = {"lm_weight": model.lm_weight, "insertion": model.insertion,
                            "training_phone_error_rate": model.info.get("tune_phone_error_rate")}
    labellers = {"aligned-hmm": lambda s: model.align(s.audio_path, s.meta["text"], method="hmm"),
                 "aligned-dtw": lambda s: model.align(s.audio_path, s.meta["text"], method="dtw"),
                 "recognised": lambda s: model.recognise(s.audio_path)}
    result["corpora"] = {}
    for path in args.test_corpus:
        corpus = load_corpus(path)
        seqs = corpus.sequences
        entry = {"n_utterances": len(seqs), "voice": corpus.manifest.get("voice"),
                 "rate_pitch": sorted({(s.meta.get("rate"), s.meta.get("pitch")) for s in seqs})[:3]}
        for name, run in labellers.items():
            run(seqs[0])                                          # warm-up, untimed
            rows, wall, audio = [], 0.0, 0.0
            for s in seqs:
                t0 = time.perf_counter()
                r = run(s)
                wall += time.perf_counter() - t0
                audio += s.meta["intervals"][-1][1]
                rows.append(score_segmentation(s.meta["intervals"], r.intervals, s.n_frames))
            entry[name] = {"audio_seconds": audio, "wall_seconds": wall, "realtime_factor": audio / wall,
                           "meets_target": audio / wall >= TARGET_REALTIME, **summarise_scores(rows)}
            print(f"{Path(path).name} {name}: {audio / wall:.1f}x real time, PER "
                  f"{entry[name]['phone_error_rate']:.3f}, boundary median "
                  f"{entry[name]['boundary_error_ms_median']:.1f} ms, p90 {entry[name]['boundary_error_ms_p90']:.1f} ms")
        result["corpora"][os.path.relpath(Path(path).resolve(), ROOT)] = entry
    result["load_average_end"] = os.getloadavg()
    write_result(args.out, result)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
