"""The ``bayes-talk`` command line.

Sub-commands::

    bayes-talk corpus build OUT_DIR [--n-utterances N] [--seed S] [--sentences FILE]
                                    [--voice NAME] [--image-size PX] [--force]
    bayes-talk train CORPUS_DIR --model {ssgpdm-vlmm,ssgpdm-phone,sgplvm} --out MODEL_DIR
    bayes-talk synth MODEL_DIR --audio X.wav --labels X.lab --out OUT_DIR
                     [--algorithm {optimise,predict}] [--init {nn,hmm,back-constraint}]
    bayes-talk evaluate --protocol {deena2009,deena2010,englebienne2008} --corpus DIR ...
    bayes-talk demo [--out DIR]
    bayes-talk align WAV --model MODEL_DIR (--text "..." | --transcript FILE) --out X.lab|X.TextGrid
    bayes-talk recognise WAV --model MODEL_DIR --out X.lab|X.TextGrid
    bayes-talk align-train CORPUS_DIR --model-dir MODEL_DIR
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
        rate=args.rate,
        pitch=args.pitch,
    )
    return 0


def _cmd_train(args: argparse.Namespace) -> int:
    from bayes_talk.pipeline import train

    out = train(args.corpus_dir, args.model, args.out, workers=args.workers, force=args.force,
                alignment=not args.no_alignment)
    print(f"model written to {out}")
    return 0


def _cmd_synth(args: argparse.Namespace) -> int:
    from bayes_talk.pipeline import synth

    written = synth(args.model_dir, args.audio, args.labels, args.out, algorithm=args.algorithm,
                    init=args.init, force=args.force, video=not args.no_video, posterior=args.posterior,
                    n_draws=args.draws, seed=args.seed, text=args.text, transcript=args.transcript,
                    align_method=args.align_method)
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
                      lowpass_hz=args.lowpass_hz, labels=args.labels)
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
    e.add_argument("--labels", default="true",
                   help="test labels: comma-separated sources among true, aligned, recognised "
                        "(docs/alignment.md; models trained once, every method scored under each)")
    e.add_argument("--json", required=True, help="output JSON; OUT.md and OUT_trajectories.png go beside it")
    e.set_defaults(func=_cmd_evaluate)


# --- align / recognise / align-train (issue #13) --------------------------------------------
def _cmd_align(args: argparse.Namespace) -> int:
    from bayes_talk.alignment.commands import check_label_output, label_audio, write_segmentation

    if args.text is None and args.transcript is None:
        raise ValueError("align needs the transcript: --text \"...\" or --transcript FILE "
                         "(for audio alone use `bayes-talk recognise`)")
    out = check_label_output(args.out, args.force)
    res = label_audio(args.model, args.wav, text=args.text, transcript=args.transcript, method=args.method)
    write_segmentation(out, res.intervals)
    print(f"{len(res.intervals)} phones aligned ({res.method}, cost {res.cost:.2f}) -> {out}")
    return 0


def _cmd_recognise(args: argparse.Namespace) -> int:
    from bayes_talk.alignment.commands import check_label_output, write_segmentation
    from bayes_talk.alignment.model import AlignmentModel

    out = check_label_output(args.out, args.force)
    res = AlignmentModel.load(args.model).recognise(args.wav)
    write_segmentation(out, res.intervals)
    print(f"{len(res.intervals)} phones recognised -> {out}")
    return 0


def _cmd_align_train(args: argparse.Namespace) -> int:
    from bayes_talk.alignment.commands import align_train

    print(f"alignment models written to {align_train(args.corpus_dir, args.model_dir, args.force)}")
    return 0


def _add_alignment_parsers(sub) -> None:
    a = sub.add_parser("align", help="align a transcript to a WAV: phone labels (.lab / .TextGrid)")
    a.add_argument("wav")
    a.add_argument("--model", required=True, help="trained model directory (holds alignment.json)")
    a.add_argument("--text", default=None, help="the transcript")
    a.add_argument("--transcript", default=None, help="UTF-8 file holding the transcript")
    a.add_argument("--method", choices=("hmm", "dtw"), default="dtw", help="aligner (default dtw)")
    a.add_argument("--out", required=True, help="X.lab or X.TextGrid")
    a.add_argument("--force", action="store_true", help="overwrite --out")
    a.set_defaults(func=_cmd_align)
    r = sub.add_parser("recognise", help="phone labels of a WAV from the audio alone")
    r.add_argument("wav")
    r.add_argument("--model", required=True, help="trained model directory (holds alignment.json)")
    r.add_argument("--out", required=True, help="X.lab or X.TextGrid")
    r.add_argument("--force", action="store_true", help="overwrite --out")
    r.set_defaults(func=_cmd_recognise)
    t = sub.add_parser("align-train", help="fit the aligner/recogniser of an existing model directory")
    t.add_argument("corpus_dir")
    t.add_argument("--model-dir", required=True)
    t.add_argument("--force", action="store_true", help="replace existing alignment models")
    t.set_defaults(func=_cmd_align_train)


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
    b.add_argument("--rate", type=int, default=None,
                   help="speaking rate (words/min) the per-utterance jitter is centred on (default 175)")
    b.add_argument("--pitch", type=int, default=None,
                   help="espeak pitch (0-100) the per-utterance jitter is centred on (default 50)")
    b.set_defaults(func=_cmd_corpus_build)

    # --- train / synth -------------------------------------------------------------------
    from bayes_talk.pipeline import MODEL_KINDS

    t = sub.add_parser("train", help="train a model on a corpus directory")
    t.add_argument("corpus_dir")
    t.add_argument("--model", choices=MODEL_KINDS, default="ssgpdm-vlmm")
    t.add_argument("--out", required=True, help="model directory to write")
    t.add_argument("--workers", type=int, default=2, help="processes for the per-state models")
    t.add_argument("--force", action="store_true", help="allow writing into a non-empty directory")
    t.add_argument("--no-alignment", action="store_true",
                   help="skip the aligner/phone recogniser (synth then needs --labels; docs/alignment.md)")
    t.set_defaults(func=_cmd_train)

    s = sub.add_parser("synth", help="synthesise a talking face for a WAV and its phone labels")
    s.add_argument("model_dir")
    s.add_argument("--audio", required=True, help="WAV file")
    s.add_argument("--labels", default=None,
                   help="HTK .lab or Praat .TextGrid (without it: --text/--transcript, else the recogniser)")
    s.add_argument("--text", default=None, help="transcript of the audio (aligned to it; docs/alignment.md)")
    s.add_argument("--transcript", default=None, help="UTF-8 file holding the transcript")
    s.add_argument("--align-method", choices=("hmm", "dtw"), default=None,
                   help="aligner for --text/--transcript (default: dtw)")
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
    _add_alignment_parsers(sub)
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
