"""The ``bayes-talk`` command line.

Sub-commands::

    bayes-talk corpus build OUT_DIR [--n-utterances N] [--seed S] [--sentences FILE]
                                    [--voice NAME] [--image-size PX] [--force]
    bayes-talk corpus track DIR [--prototypes 4] [--search-unannotated] [--allow-lost]
    bayes-talk corpus propose-prototypes DIR [--prototypes 4] [--per-video K] [--out DIR]
    bayes-talk train CORPUS_DIR --model {ssgpdm-vlmm,ssgpdm-phone,sgplvm} --out MODEL_DIR
    bayes-talk synth MODEL_DIR --audio X.wav --labels X.lab --out OUT_DIR
                     [--algorithm {optimise,predict}] [--init {nn,hmm,back-constraint}]
    bayes-talk evaluate --protocol {deena2009,deena2010,englebienne2008} --corpus DIR ...
    bayes-talk demo [--out DIR]
    bayes-talk evaluate --protocol {deena2009,deena2010,englebienne2008} --corpus DIR
                        [--test-corpus DIR] [--methods a,b,...] [--quick] [--seed S]
                        [--no-figures] --json OUT.json
"""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path


def _cmd_corpus_build(args: argparse.Namespace) -> int:
    from bayes_talk.data.corpus import build_corpus

    build_corpus(
        Path(args.out_dir),
        n_utterances=args.n_utterances,
        seed=args.seed,
        sentences=Path(args.sentences) if args.sentences else None,
        voice=args.voice,
        image_size=args.image_size,
        force=args.force,
    )
    return 0


# --- corpus track / propose-prototypes (issue #16) -----------------------------------------
def _cmd_corpus_track(args: argparse.Namespace) -> int:
    from bayes_talk.data.tracking import track_corpus

    s = track_corpus(Path(args.dir), args.prototypes, search_unannotated=args.search_unannotated,
                     allow_lost=args.allow_lost, lost_threshold=args.lost_threshold,
                     seed=args.seed, force=args.force)
    n = sum(len(v) for v in s.scores.values())
    print(f"tracked {n} frames of {len(s.scores)} videos from {s.n_annotated} annotated frames")
    for name, idx in s.lost.items():
        if idx:
            print(f"{name}: {len(idx)} lost frames: {idx}")
    if s.not_written:
        print("landmarks NOT written (lost frames; annotate them or pass --allow-lost): "
              + ", ".join(s.not_written))
        return 1
    return 0


def _cmd_corpus_propose(args: argparse.Namespace) -> int:
    from bayes_talk.data.tracking import propose_prototypes

    p = propose_prototypes(Path(args.dir), args.prototypes, args.out, per_video=args.per_video,
                           seed=args.seed, force=args.force)
    print(f"frames to annotate listed in {p}")
    return 0


def _add_track_parsers(csub) -> None:
    from bayes_talk.features.aam_fit import LOST_THRESHOLD

    t = csub.add_parser("track", help="AAM-track a user corpus from a few annotated frames")
    t.add_argument("dir", help="user corpus directory (docs/data.md)")
    t.add_argument("--prototypes", type=int, default=4,
                   help="frames per phone to annotate (proposed if none is annotated; fewer warn)")
    t.add_argument("--search-unannotated", action="store_true",
                   help="search videos without an annotated frame from the mean pose")
    t.add_argument("--allow-lost", action="store_true",
                   help="interpolate lost frames (flagged) instead of not writing the video's landmarks")
    t.add_argument("--lost-threshold", type=float, default=LOST_THRESHOLD,
                   help="texture residual RMS above which a frame is lost")
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--force", action="store_true", help="overwrite files track did not write")
    t.set_defaults(func=_cmd_corpus_track)
    q = csub.add_parser("propose-prototypes", help="write the frames to annotate as PNG images")
    q.add_argument("dir", help="user corpus directory (docs/data.md)")
    q.add_argument("--prototypes", type=int, default=4, help="frames per phone (deena2010: 4)")
    q.add_argument("--per-video", type=int, default=0,
                   help="extra random frames for each video without one")
    q.add_argument("--out", default=None, help="output folder (default DIR/prototypes)")
    q.add_argument("--seed", type=int, default=0)
    q.add_argument("--force", action="store_true", help="write into a non-empty --out")
    q.set_defaults(func=_cmd_corpus_propose)


def _cmd_train(args: argparse.Namespace) -> int:
    from bayes_talk.pipeline import train

    out = train(args.corpus_dir, args.model, args.out, workers=args.workers, force=args.force)
    print(f"model written to {out}")
    return 0


def _cmd_synth(args: argparse.Namespace) -> int:
    from bayes_talk.pipeline import synth

    written = synth(args.model_dir, args.audio, args.labels, args.out, algorithm=args.algorithm,
                    init=args.init, force=args.force, video=not args.no_video, posterior=args.posterior,
                    n_draws=args.draws, seed=args.seed)
    for k, p in written.items():
        print(f"{k:>10}: {p}")
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from bayes_talk.demo import run_demo

    return run_demo(Path(args.out))


# --- evaluate (issue #5) -------------------------------------------------------------------
def _cmd_evaluate(args: argparse.Namespace) -> int:
    from bayes_talk.evaluation.protocols import evaluate

    result = evaluate(args.protocol, Path(args.corpus), Path(args.json),
                      test_corpus=Path(args.test_corpus) if args.test_corpus else None,
                      methods=args.methods, quick=args.quick, seed=args.seed, figures=not args.no_figures,
                      lowpass_hz=args.lowpass_hz)
    for name, e in result["methods"].items():
        heads = ", ".join(f"{k} {v:.4g}" if v is not None else f"{k} -" for k, v in e["headline"].items())
        print(f"{name}: {heads}")
    print(f"wrote {args.json}")
    return 0


def _add_evaluate_parser(sub) -> None:
    from bayes_talk.evaluation.protocols import PROTOCOLS
    from bayes_talk.evaluation.systems import METHODS

    e = sub.add_parser("evaluate", help="run a published evaluation protocol (JSON + Markdown + figure)")
    e.add_argument("--protocol", required=True, choices=sorted(PROTOCOLS))
    e.add_argument("--corpus", required=True, help="corpus directory (built or user)")
    e.add_argument("--test-corpus", default=None,
                   help="train on all of --corpus, test on all of this corpus")
    e.add_argument("--methods", default=None,
                   help="comma-separated methods (default: the protocol's); valid: " + ", ".join(METHODS))
    e.add_argument("--quick", action="store_true", help="the quick (smaller, labelled) variant")
    e.add_argument("--seed", type=int, default=None, help="replace the protocol's fixed seed (0)")
    e.add_argument("--no-figures", action="store_true", help="skip the trajectory figure")
    e.add_argument("--lowpass-hz", type=float, default=None,
                   help="zero-phase low-pass (Hz, e.g. 4) on every method's predicted mean, "
                        "deena2010's post-filter (default: off)")
    e.add_argument("--json", required=True, help="output JSON; OUT.md and OUT_trajectories.png go beside it")
    e.set_defaults(func=_cmd_evaluate)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="bayes-talk", description=__doc__.splitlines()[0])
    p.add_argument("-v", "--verbose", action="store_true", help="log progress (INFO level)")
    sub = p.add_subparsers(dest="command", required=True)

    # --- corpus -------------------------------------------------------------------------
    corpus = sub.add_parser("corpus", help="build the built-in talking-head corpus")
    csub = corpus.add_subparsers(dest="corpus_command", required=True)
    b = csub.add_parser("build", help="synthesise speech, faces and frames into OUT_DIR")
    b.add_argument("out_dir")
    b.add_argument("--n-utterances", type=int, default=300)
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--sentences", default=None, help="text file, one sentence a line")
    b.add_argument("--voice", default="en")
    b.add_argument("--image-size", type=int, default=128)
    b.add_argument("--force", action="store_true", help="allow building into a non-empty dir")
    b.set_defaults(func=_cmd_corpus_build)
    _add_track_parsers(csub)

    # --- train / synth -------------------------------------------------------------------
    from bayes_talk.pipeline import MODEL_KINDS

    t = sub.add_parser("train", help="train a model on a corpus directory")
    t.add_argument("corpus_dir")
    t.add_argument("--model", choices=MODEL_KINDS, default="ssgpdm-vlmm")
    t.add_argument("--out", required=True, help="model directory to write")
    t.add_argument("--workers", type=int, default=2, help="processes for the per-state models")
    t.add_argument("--force", action="store_true", help="allow writing into a non-empty directory")
    t.set_defaults(func=_cmd_train)

    s = sub.add_parser("synth", help="synthesise a talking face for a WAV and its phone labels")
    s.add_argument("model_dir")
    s.add_argument("--audio", required=True, help="WAV file")
    s.add_argument("--labels", required=True, help="HTK .lab or Praat .TextGrid")
    s.add_argument("--out", required=True, help="output directory")
    s.add_argument("--algorithm", choices=("optimise", "predict"), default="optimise")
    s.add_argument("--init", choices=("nn", "hmm", "back-constraint"), default=None,
                   help="initialiser (sgplvm: back-constraint = SGPLVM A, hmm = SGPLVM B)")
    s.add_argument("--posterior", choices=("map", "laplace", "nuts", "emcee"), default="map",
                   help="map: the MAP path; laplace/nuts/emcee: sample the synthesis posterior and "
                        "write its mean, variance, bands.npz and diagnostics.json (switching models)")
    s.add_argument("--draws", type=int, default=64, help="posterior draws per segment")
    s.add_argument("--seed", type=int, default=0, help="sampler seed")
    s.add_argument("--no-video", action="store_true", help="skip the MP4")
    s.add_argument("--force", action="store_true", help="overwrite earlier outputs in --out")
    s.set_defaults(func=_cmd_synth)

    # --- demo ---------------------------------------------------------------------------
    d = sub.add_parser("demo", help="the main job on the built-in corpus")
    d.add_argument("--out", default="demo_out")
    d.set_defaults(func=_cmd_demo)

    # --- evaluate -----------------------------------------------------------------------
    _add_evaluate_parser(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="%(asctime)s %(name)s %(levelname)s: %(message)s",
    )
    try:
        return int(args.func(args) or 0)
    except (ValueError, FileNotFoundError, FileExistsError, RuntimeError) as exc:
        print(f"bayes-talk: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
