"""The ``bayes-talk`` command line.

This module is above ~400 lines because it is the one place where every sub-command's
flags and defaults are declared (argparse), next to the small functions that call the
library; the work itself is in the modules those functions import.

Sub-commands::

    bayes-talk corpus build OUT_DIR [--n-utterances N] [--seed S] [--sentences FILE]
                                    [--voice NAME] [--image-size PX] [--force]
                                    [--speech {espeak,vtl}]
    bayes-talk corpus track DIR [--prototypes 4] [--search-unannotated] [--allow-lost]
    bayes-talk corpus propose-prototypes DIR [--prototypes 4] [--per-video K] [--out DIR]
    bayes-talk train CORPUS_DIR --model {ssgpdm-vlmm,ssgpdm-phone,ssgpdm-vlmm-rc,ssgpdm-phone-rc,sgplvm} --out MODEL_DIR
    bayes-talk synth MODEL_DIR --audio X.wav --labels X.lab --out OUT_DIR
                     [--algorithm {optimise,predict}] [--init {nn,hmm,back-constraint}]
    bayes-talk synth MODEL_DIR (--audio-dir DIR | --audio-list FILE) --out OUT_DIR [--file-workers N]
    bayes-talk evaluate --protocol {deena2009,deena2010,englebienne2008} --corpus DIR ...
    bayes-talk demo [--out DIR]
    bayes-talk align WAV --model MODEL_DIR (--text "..." | --transcript FILE) --out X.lab|X.TextGrid
    bayes-talk recognise WAV --model MODEL_DIR --out X.lab|X.TextGrid
    bayes-talk align-train CORPUS_DIR --model-dir MODEL_DIR
    bayes-talk evaluate --protocol {deena2009,deena2010,englebienne2008} --corpus DIR
                        [--test-corpus DIR] [--methods a,b,...] [--quick] [--seed S]
                        [--no-figures] --json OUT.json

-v/--verbose and -q/--quiet may be given anywhere on the line; ``COMMAND --help`` shows
every option with its default.
"""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path


def _cmd_corpus_build(args: argparse.Namespace) -> int:
    from bayes_talk.corpus import build_corpus
    from bayes_talk.corpus.workers import suggested_workers

    workers = args.workers if args.workers is not None else suggested_workers(args.n_utterances)
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
        n_workers=workers,
        executor=args.executor,
        scheduler=args.scheduler,
        speech=args.speech,
    )
    print(f"corpus written to {args.out_dir} (speech: {args.speech})")
    return 0


# --- corpus track / propose-prototypes -------------------------------------------------------
def _cmd_corpus_track(args: argparse.Namespace) -> int:
    from bayes_talk.corpus.tracking import track_corpus

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
    from bayes_talk.corpus.tracking import propose_prototypes

    p = propose_prototypes(Path(args.dir), args.prototypes, args.out, per_video=args.per_video,
                           seed=args.seed, force=args.force)
    print(f"frames to annotate listed in {p}")
    return 0


def _add_track_parsers(csub) -> None:
    from bayes_talk.features.aam_fit import LOST_THRESHOLD

    t = csub.add_parser("track", help="AAM-track a user corpus from a few annotated frames", **_SUB_KW)
    t.add_argument("dir", help="user corpus directory (docs/data.md)")
    t.add_argument("--prototypes", type=int, default=4,
                   help="frames per phone to annotate (proposed if none is annotated; fewer warn)")
    t.add_argument("--search-unannotated", action="store_true",
                   help="search videos without an annotated frame from the mean pose")
    t.add_argument("--allow-lost", action="store_true",
                   help="interpolate lost frames (flagged) instead of not writing the video's landmarks")
    t.add_argument("--lost-threshold", type=float, default=LOST_THRESHOLD,
                   help="texture residual RMS above which a frame is lost")
    t.add_argument("--seed", type=int, default=0, help="random seed of the prototype frames proposed")
    t.add_argument("--force", action="store_true", help="overwrite files track did not write")
    t.set_defaults(func=_cmd_corpus_track)
    q = csub.add_parser("propose-prototypes", help="write the frames to annotate as PNG images", **_SUB_KW)
    q.add_argument("dir", help="user corpus directory (docs/data.md)")
    q.add_argument("--prototypes", type=int, default=4, help="frames per phone (deena2010: 4)")
    q.add_argument("--per-video", type=int, default=0,
                   help="extra random frames for each video without one")
    q.add_argument("--out", default=None, help="output folder (default DIR/prototypes)")
    q.add_argument("--seed", type=int, default=0, help="random seed of the frames drawn")
    q.add_argument("--force", action="store_true", help="write into a non-empty --out")
    q.set_defaults(func=_cmd_corpus_propose)


def _cmd_train(args: argparse.Namespace) -> int:
    from bayes_talk.pipeline import DEFAULT_CALIBRATION, calibrates_bands, train

    if args.no_calibrate_bands and args.calibrate_bands is not None:
        raise ValueError("give --calibrate-bands or --no-calibrate-bands, not both")
    cal = args.calibrate_bands
    if cal is None and not args.no_calibrate_bands and calibrates_bands(args.model):
        cal = DEFAULT_CALIBRATION
    out = train(args.corpus_dir, args.model, args.out, workers=args.workers, force=args.force,
                holdout=args.holdout, holdout_list=args.holdout_list, cmvn=args.cmvn,
                alignment=not args.no_alignment, executor=args.executor, scheduler=args.scheduler,
                calibrate_bands=cal, calibrated_model=args.calibrated_model, calibration=args.calibration)
    print(f"model written to {out}")
    return 0


def _cmd_synth(args: argparse.Namespace) -> int:
    from bayes_talk.pipeline import synth

    common = {"algorithm": args.algorithm, "init": args.init, "video": not args.no_video, "posterior": args.posterior,
              "n_draws": args.draws, "seed": args.seed, "tier": args.tier, "calibrated": not args.raw_bands,
              "lowpass_hz": args.lowpass_hz or None, "export": args.export,
              "sampler_options": {"chains": args.chains, "warmup": args.warmup,
                                  "target_accept": args.target_accept, "max_tree_depth": args.max_tree_depth,
                                  "pg_particles": args.pg_particles, "workers": args.workers,
                                  "stop_at_targets": False if args.all_draws else None}}
    if args.audio is None:
        return _synth_batch(args, common)
    if args.file_workers != 1:
        raise ValueError("--file-workers runs the files of --audio-dir/--audio-list in parallel; with one --audio "
                         "use --workers (NUTS chains in parallel)")
    written = synth(args.model_dir, args.audio, args.labels, args.out, force=args.force, text=args.text,
                    transcript=args.transcript, align_method=args.align_method, truth=args.truth, **common)
    for k, p in written.items():
        print(f"{k:>10}: {p}")
    return 0


def _synth_batch(args: argparse.Namespace, options: dict) -> int:
    """``synth --audio-dir/--audio-list``: every file into OUT/<stem>/, a summary table; exit
    status 1 when a file failed."""
    from bayes_talk.pipeline.batch import (
        inputs_from_dir,
        inputs_from_list,
        summary_table,
        synth_many,
    )

    flag = "--audio-dir" if args.audio_dir is not None else "--audio-list"
    for name in ("labels", "text", "transcript", "align_method", "truth"):
        if getattr(args, name) is not None:
            raise ValueError(f"--{name.replace('_', '-')} belongs to one --audio: with {flag} each WAV's labels "
                             "are the .lab/.TextGrid beside it (or the list's second column), else the recogniser's")
    inputs = inputs_from_dir(args.audio_dir) if args.audio_dir is not None else inputs_from_list(args.audio_list)
    res = synth_many(args.model_dir, inputs, args.out, workers=args.file_workers, force=args.force, **options)
    print(summary_table(res.rows))
    print(f"{len(res.rows) - len(res.failed)} of {len(res.rows)} files synthesised; summary in {res.summary_json} "
          f"and {res.summary_csv}")
    return 1 if res.failed else 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from bayes_talk.app.demo import run_demo

    return run_demo(Path(args.out), workers=2)


# --- evaluate --------------------------------------------------------------------------------
def _cmd_evaluate(args: argparse.Namespace) -> int:
    from bayes_talk.evaluation.harness import evaluate

    result = evaluate(args.protocol, Path(args.corpus), Path(args.json),
                      test_corpus=Path(args.test_corpus) if args.test_corpus else None,
                      methods=args.methods, quick=args.quick, seed=args.seed, figures=not args.no_figures,
                      lowpass_hz=args.lowpass_hz, oracle_draws=args.oracle_draws,
                      sample_draws=args.sample_draws,
                      calibrated_model=args.calibrated_model, calibration=args.calibration,
                      min_utterances=args.min_utterances, cmvn=args.cmvn,
                      labels=args.labels, executor=args.executor, workers=args.workers,
                      scheduler=args.scheduler)
    for name, e in result["methods"].items():
        heads = ", ".join(f"{k} {v:.4g}" if v is not None else f"{k} -" for k, v in e["headline"].items())
        print(f"{name}: {heads}")
    print(f"wrote {args.json}")
    return 0


def _add_evaluate_parser(sub) -> None:
    from bayes_talk.calibration.bands import CALIBRATED_MODELS, CALIBRATIONS
    from bayes_talk.evaluation.protocols import PROTOCOLS
    from bayes_talk.evaluation.systems import METHODS
    from bayes_talk.features.audio import DEFAULT_CMVN

    e = sub.add_parser("evaluate", help="run a published evaluation protocol (JSON + Markdown + figure)",
                       **_SUB_KW)
    e.add_argument("--protocol", required=True, choices=sorted(PROTOCOLS), help="protocol (docs/evaluation.md)")
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
    e.add_argument("--calibrated-model", choices=CALIBRATED_MODELS, default=None,
                   help="the model the band calibration of the *-posterior methods is scored with, as "
                        "train --calibrated-model (default: the protocol's, refit)")
    e.add_argument("--calibration", choices=CALIBRATIONS, default=None,
                   help="what the *-posterior methods fit on held-out training utterances, as train "
                        "--calibration (default: the protocol's, noise)")
    e.add_argument("--oracle-draws", type=int, default=None,
                   help="generator draws per utterance of method oracle (default 32, >= 2)")
    e.add_argument("--sample-draws", type=int, default=None,
                   help="predictive draws per utterance behind the landmark diversity, mean-of-samples and "
                        "best-of-N lip errors of every method that samples its path (the *-posterior methods; "
                        "default 16, >= 2; docs/evaluation.md)")
    e.add_argument("--labels", default="true",
                   help="test labels: comma-separated sources among true, aligned, recognised "
                        "(docs/alignment.md; models trained once, every method scored under each)")
    e.add_argument("--json", required=True, help="output JSON; OUT.md and OUT_trajectories.png go beside it")
    e.add_argument("--min-utterances", type=_non_negative_int, default=None,
                   help="evaluate a corpus smaller than the protocol needs (but at least this many "
                        "utterances) with the protocol's split scaled to it; the report says so")
    e.add_argument("--cmvn", choices=("mean", "mean+var", "off"), default=DEFAULT_CMVN,
                   help="per-utterance cepstral normalisation of the MFCCs (as train --cmvn)")
    e.add_argument("--workers", type=_positive_int, default=2,
                   help="processes for --executor processes/dask (a LocalCluster's size)")
    _add_executor_args(e, "the protocol's splits (or one split's per-state models) and featurisation")
    e.set_defaults(func=_cmd_evaluate)


SYNTH_OUTPUTS = """\
outputs in --out (docs/outputs.md):
  trajectory.npy   (T, n_params) float64 AAM parameters per 25 Hz frame, MEAN-REMOVED: add the
                   model's AAM offset (bayes_talk_model.json "aam_offset") before using them
  variance.npy     (T, n_params) predictive variance of each parameter
  landmarks.npy    (T, P, 2) landmark (x, y) pixels = AAM shape of trajectory + offset
  segments.json    the state segmentation (switching models) and fps
  face.mp4         rendered frames with the audio (unless --no-video)
  bands.npz        central 50 % / 90 % bands (lower50, upper50, lower90, upper90), mean-removed
  posterior.nc     ArviZ InferenceData (az.from_netcdf; az.summary)
  bands.png        the first AAM parameters over time: mean, 50 %/90 % bands (+ --truth)
  uncertainty.mp4  mean face | per-pixel standard deviation of rendered draws (unless --no-video)
  diagnostics.json with --posterior laplace|nuts|pg-nuts|emcee|vi
  frames.json|csv  with --export: per frame time, parameter mean/sd/5-50-95 % quantiles,
                   landmarks and their sd (schema in docs/outputs.md)
  landmarks_track.json|csv  with --export: x, y of every landmark per frame (a 2-D tool's track)
with --audio-dir/--audio-list: the above in OUT/<WAV stem>/ for every WAV, and
  summary.json|csv every file's labels, output directory, frames, wall seconds, status, error
time and memory grow linearly with the length of the speech: about 2-2.5 s per second of
  speech on 2 cores with the defaults (a third of it the videos: --no-video), plus ~8 s of
  start-up; 5 minutes of speech: 12.5 minutes, 1.9 GB (docs/benchmarks.md)
frames in Python:
  from bayes_talk.pipeline import load_trained; import numpy as np
  tm = load_trained(MODEL_DIR); p = np.load("OUT/trajectory.npy") + tm.offset
  landmarks, _ = tm.aam.reconstruct(p); frames = tm.aam.render(p)   # (T, H, W) uint8
"""


DESCRIPTION = """\
Speech in, talking face out, with the model's own account of how sure it is: a switching
shared Gaussian-process dynamical model (Deena, Hou & Galata 2010) maps MFCCs of speech to
the Active Appearance Model parameters of a face, and synthesis returns the trajectory with
its posterior uncertainty bands."""

EPILOG = """\
a first run (docs in the repository's README.md and docs/):
  bayes-talk corpus build CORPUS --n-utterances 300      # the built-in corpus
  bayes-talk train CORPUS --out MODEL
  bayes-talk synth MODEL --audio X.wav --labels X.lab --out OUT
  bayes-talk evaluate --protocol deena2010 --corpus CORPUS --quick --json results.json
  bayes-talk demo --out demo_out                          # all of it on a small corpus
COMMAND --help shows each command's options and their defaults."""


class _HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Defaults in every option's help (not for required options, flags, or a None default,
    whose help says what happens); epilogs kept as written."""

    def _get_help_string(self, action: argparse.Action) -> str:
        # identity, not ==: a default of 0 (== False) is shown like any other
        if action.required or any(action.default is x for x in (None, False, argparse.SUPPRESS)):
            return action.help or ""
        return super()._get_help_string(action)


def _verbosity_parser(suppress: bool) -> argparse.ArgumentParser:
    """-v/-q, accepted before or after the sub-command (sub-parsers must not reset them)."""
    kw = {"default": argparse.SUPPRESS} if suppress else {"default": False}
    v = argparse.ArgumentParser(add_help=False)
    v.add_argument("-v", "--verbose", action="store_true", help="log details (INFO level): every stage's start and end "
                   "with its wall time", **kw)
    v.add_argument("-q", "--quiet", action="store_true", help="errors only; no progress (bars on a terminal, "
                   "a line every few seconds elsewhere)", **kw)
    return v


_SUB_KW = {"formatter_class": _HelpFormatter, "parents": [_verbosity_parser(True)]}


def _add_executor_args(p: argparse.ArgumentParser, what: str) -> None:
    """--executor and --scheduler (docs/scaling.md)."""
    from bayes_talk.base.executor import EXECUTORS

    p.add_argument("--executor", choices=EXECUTORS, default=None,
                   help=f"what runs {what}: local (this process), processes (--workers of them) "
                        "or dask (a LocalCluster of --workers processes, or --scheduler); the results "
                        "do not depend on it")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="address of a running dask scheduler, e.g. tcp://10.0.0.5:8786 (implies "
                        "--executor dask; docs/scaling.md)")


def _non_negative_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, found {text!r}") from None
    if v < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, found {v}")
    return v


def _positive_int(text: str) -> int:
    v = _non_negative_int(text)
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, found {v}")
    return v
# --- align / recognise / align-train ---------------------------------------------------------
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
    a = sub.add_parser("align", help="align a transcript to a WAV: phone labels (.lab / .TextGrid)", **_SUB_KW)
    a.add_argument("wav", help="the recording (WAV, any sample rate)")
    a.add_argument("--model", required=True, help="trained model directory (holds alignment.json)")
    a.add_argument("--text", default=None, help="the transcript")
    a.add_argument("--transcript", default=None, help="UTF-8 file holding the transcript")
    a.add_argument("--method", choices=("hmm", "dtw"), default="dtw", help="aligner (docs/alignment.md)")
    a.add_argument("--out", required=True, help="X.lab or X.TextGrid")
    a.add_argument("--force", action="store_true", help="overwrite --out")
    a.set_defaults(func=_cmd_align)
    r = sub.add_parser("recognise", help="phone labels of a WAV from the audio alone", **_SUB_KW)
    r.add_argument("wav", help="the recording (WAV, any sample rate)")
    r.add_argument("--model", required=True, help="trained model directory (holds alignment.json)")
    r.add_argument("--out", required=True, help="X.lab or X.TextGrid")
    r.add_argument("--force", action="store_true", help="overwrite --out")
    r.set_defaults(func=_cmd_recognise)
    t = sub.add_parser("align-train", help="fit the aligner/recogniser of an existing model directory",
                       **_SUB_KW)
    t.add_argument("corpus_dir", help="the corpus the model was trained on (built or user corpus)")
    t.add_argument("--model-dir", required=True, help="model directory written by train, to add the models to")
    t.add_argument("--force", action="store_true", help="replace existing alignment models")
    t.set_defaults(func=_cmd_align_train)


def build_parser() -> argparse.ArgumentParser:
    """The ``bayes-talk`` argument parser with every sub-command."""
    from bayes_talk import __version__
    from bayes_talk.posterior.methods import (
        DEFAULT_METHOD,
        EMCEE_WARMUP,
        INFERENCE,
        NUTS_DEFAULTS,
        PG_NUTS_BUDGET,
        PG_NUTS_DEFAULTS,
        draws_help,
    )

    p = argparse.ArgumentParser(prog="bayes-talk", description=DESCRIPTION, epilog=EPILOG,
                                parents=[_verbosity_parser(False)], formatter_class=_HelpFormatter)
    p.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND", title="commands")

    # --- corpus -------------------------------------------------------------------------
    corpus = sub.add_parser("corpus", help="build the built-in corpus; track or annotate a user corpus",
                            **_SUB_KW)
    csub = corpus.add_subparsers(dest="corpus_command", required=True)
    b = csub.add_parser("build", help="synthesise speech, faces and frames into OUT_DIR", **_SUB_KW)
    b.add_argument("out_dir", help="directory to create (or an empty one)")
    b.add_argument("--n-utterances", type=_positive_int, default=300, help="utterances to synthesise")
    b.add_argument("--seed", type=_non_negative_int, default=0, help="random seed (>= 0)")
    b.add_argument("--sentences", default=None,
                   help="text file, one sentence a line (default: the built-in English sentences)")
    from bayes_talk.data.text_check import english_voices

    b.add_argument("--voice", default="en",
                   help=f"English espeak-ng voice: {', '.join(english_voices())}; +VARIANT picks one of "
                        "espeak-ng's variants (en+f3)")
    b.add_argument("--image-size", type=_positive_int, default=128, help="frame width and height, pixels")
    b.add_argument("--force", action="store_true", help="allow building into a non-empty dir")
    b.add_argument("--rate", type=int, default=None,
                   help="speaking rate (words/min) the per-utterance jitter is centred on (default 175)")
    b.add_argument("--pitch", type=int, default=None,
                   help="espeak pitch (0-100) the per-utterance jitter is centred on (default 50)")
    b.add_argument("--workers", type=_positive_int, default=None,
                   help="processes (default: 2 from 16 utterances on, else 1)")
    b.add_argument("--speech", choices=("espeak", "vtl"), default="espeak",
                   help="audio generator: espeak-ng, or vtl = VocalTractLab driven by espeak-ng's "
                        "phones, one vocal tract for the voice and the face (needs "
                        "pip install 'bayes_talk[articulatory]')")
    _add_executor_args(b, "the utterances (speech, face, frames) and their featurisation")
    b.set_defaults(func=_cmd_corpus_build)
    _add_track_parsers(csub)

    # --- train / synth -------------------------------------------------------------------
    from bayes_talk.calibration.bands import CALIBRATED_MODELS, CALIBRATIONS
    from bayes_talk.features.audio import DEFAULT_CMVN
    from bayes_talk.pipeline import (
        DEFAULT_CALIBRATED_MODEL,
        DEFAULT_CALIBRATION,
        DEFAULT_MODEL,
        MODEL_KINDS,
    )
    from bayes_talk.synthesis.sequential import POST_FILTER_HZ

    t = sub.add_parser("train", help="train a model on a corpus directory", **_SUB_KW)
    t.add_argument("corpus_dir", help="built or user corpus directory")
    t.add_argument("--model", choices=MODEL_KINDS, default=DEFAULT_MODEL,
                   help=f"model kind (docs/model.md; {DEFAULT_MODEL}: right-context phone states; "
                        "ssgpdm-vlmm: deena2010's)")
    t.add_argument("--out", required=True, help="model directory to write")
    t.add_argument("--workers", type=int, default=2, help="processes for the per-state models")
    t.add_argument("--force", action="store_true", help="allow writing into a non-empty directory")
    th = t.add_mutually_exclusive_group()
    th.add_argument("--holdout", type=int, default=None, metavar="N",
                    help="hold the corpus's last N utterances out of training (recorded in the model)")
    th.add_argument("--holdout-list", default=None, metavar="FILE",
                    help="hold out the utterances named in FILE (one name a line, e.g. utt0249)")
    t.add_argument("--cmvn", choices=("mean", "mean+var", "off"), default=DEFAULT_CMVN,
                   help="per-utterance cepstral mean (and variance) normalisation of the MFCCs, "
                        "recorded in the model and applied the same way by synth")
    t.add_argument("--no-alignment", action="store_true",
                   help="skip the aligner/phone recogniser (synth then needs --labels; docs/alignment.md)")
    _add_executor_args(t, "the per-state models and the featurisation")
    t.add_argument("--calibrate-bands", type=float, nargs="?", const=DEFAULT_CALIBRATION, default=None,
                   metavar="FRACTION",
                   help=f"hold out FRACTION (default {DEFAULT_CALIBRATION:g}) of the training utterances, train once "
                        "more on the rest, synthesise them and fit --calibration on them (saved in the model, "
                        f"applied by synth to every --posterior; docs/uncertainty.md). On by default "
                        f"({DEFAULT_CALIBRATION:g}) for switching models")
    t.add_argument("--no-calibrate-bands", action="store_true",
                   help="skip the calibration (half the training time; synth then gives the GP predictive alone)")
    t.add_argument("--calibration", choices=CALIBRATIONS, default="noise",
                   help="what is fitted on the held-out utterances: noise = the face's observation term of the "
                        "model (per AAM parameter a mean shrinkage and a Student-t scale per phone class, fitted by "
                        "held-out log score); bands = the post-hoc four-stage band calibration")
    t.add_argument("--calibrated-model", choices=CALIBRATED_MODELS, default=DEFAULT_CALIBRATED_MODEL,
                   help="the model saved with the calibration: holdout = the one trained on the other "
                        "utterances, which the calibration was fitted for (one fit); refit = one more fit on "
                        "all utterances, the calibration carried over to it; cv = the fit on all utterances, the "
                        "calibration fitted on out-of-fold syntheses of every utterance (1/FRACTION folds)")
    t.set_defaults(func=_cmd_train)

    s = sub.add_parser("synth", help="synthesise a talking face for a WAV (or many) and its phone labels",
                       epilog=SYNTH_OUTPUTS, **_SUB_KW)
    s.add_argument("model_dir", help="directory written by train")
    a = s.add_mutually_exclusive_group(required=True)
    a.add_argument("--audio", help="WAV file (any rate: resampled to the model's; stereo downmixed)")
    a.add_argument("--audio-dir", metavar="DIR",
                   help="every *.wav of DIR, each into OUT/<its stem>/ with the model loaded once, labels from the "
                        ".lab (or .TextGrid) beside it, else the recogniser; a file that fails is reported and "
                        "skipped, OUT/summary.json and .csv list every file, exit status 1 if one failed")
    a.add_argument("--audio-list", metavar="FILE",
                   help="as --audio-dir for the WAVs FILE lists, one a line, each optionally followed by its "
                        "labels file (relative paths: from FILE's directory)")
    s.add_argument("--file-workers", type=_positive_int, default=1, metavar="N",
                   help="--audio-dir/--audio-list: processes synthesising files at once, each loading the model "
                        "once")
    s.add_argument("--labels", default=None,
                   help="HTK .lab or Praat .TextGrid (without it: --text/--transcript, else the recogniser)")
    s.add_argument("--tier", default=None,
                   help="TextGrid tier with the phones (default: 'phones'/'phone' if present, else "
                        "the first tier of known phones)")
    s.add_argument("--text", default=None, help="transcript of the audio (aligned to it; docs/alignment.md)")
    s.add_argument("--transcript", default=None, help="UTF-8 file holding the transcript")
    s.add_argument("--align-method", choices=("hmm", "dtw"), default=None,
                   help="aligner for --text/--transcript (default: dtw)")
    s.add_argument("--out", required=True,
                   help="output directory (--audio-dir/--audio-list: one sub-directory per WAV and the summary)")
    s.add_argument("--algorithm", choices=("optimise", "predict"), default="optimise",
                   help="with --posterior map: deena2010 Algorithm 1 (optimise) or 2 (predict)")
    s.add_argument("--init", choices=("nn", "hmm", "back-constraint"), default=None,
                   help="initialiser (sgplvm: back-constraint = SGPLVM A, hmm = SGPLVM B)")
    s.add_argument("--posterior", choices=tuple(INFERENCE), default=None,
                   help=f"{'/'.join(m for m in INFERENCE if m != 'map')} (default for switching models: "
                        f"{DEFAULT_METHOD}): the whole-utterance synthesis posterior; map: the paper's sequential path (Algorithm 1/2; sgplvm's only choice); "
                        "write the posterior mean, variance and diagnostics.json (every method writes bands.npz, "
                        "posterior.nc, bands.png)")
    s.add_argument("--draws", type=_positive_int, default=None,
                   help=f"posterior draws pooled over chains ({draws_help()})")
    s.add_argument("--chains", type=_positive_int, default=None, help=f"NUTS chains (default {NUTS_DEFAULTS['chains']})")
    s.add_argument("--warmup", type=_non_negative_int, default=None,
                   help=f"NUTS warm-up iterations per chain (default {NUTS_DEFAULTS['warmup']}; pg-nuts "
                        f"{PG_NUTS_BUDGET['warmup']}) / emcee burn-in steps "
                        f"(default {EMCEE_WARMUP})")
    s.add_argument("--target-accept", type=float, default=None,
                   help=f"NUTS target acceptance statistic of the step-size adaptation "
                        f"(default {NUTS_DEFAULTS['target_accept']})")
    s.add_argument("--max-tree-depth", type=_positive_int, default=None, help=f"NUTS max tree depth (default {NUTS_DEFAULTS['max_tree_depth']})")
    s.add_argument("--pg-particles", type=_positive_int, default=None,
                   help=f"pg-nuts: particles of each particle Gibbs sweep (default {PG_NUTS_DEFAULTS['pg_particles']})")
    s.add_argument("--all-draws", action="store_true",
                   help=f"pg-nuts: keep drawing to --draws; by default the chains stop once R-hat <= 1.01 and bulk "
                        f"and tail ESS >= 400 on the latents and AAM parameters, checked after "
                        f"{PG_NUTS_BUDGET['min_draws_per_chain']} draws per chain and every "
                        f"{PG_NUTS_BUDGET['check_every']} after")
    s.add_argument("--workers", type=_positive_int, default=None,
                   help="nuts/pg-nuts: processes running one file's chains in parallel (default 1); the draws "
                        "depend on --seed only, not on this. Files in parallel: --file-workers")
    s.add_argument("--seed", type=_non_negative_int, default=0, help="sampler seed (>= 0)")
    s.add_argument("--truth", default=None,
                   help="ground-truth AAM parameters, a .npy (T, n_params) in the space of trajectory.npy: "
                        "drawn in bands.png and stored as observed_data in posterior.nc")
    s.add_argument("--no-video", action="store_true", help="skip the MP4s")
    s.add_argument("--lowpass-hz", type=float, default=0.0, metavar="HZ",
                   help=f"zero-phase low-pass (Hz) of a switching model's mean, bands moving with it "
                        f"(deena2010 §4.2.3 uses {POST_FILTER_HZ:g}; 0: off, as evaluate scores it: on "
                        "sentences nobody tuned on the filter made AMSE, NLPD and CRPS worse, docs/results.md)")
    s.add_argument("--raw-bands", action="store_true",
                   help="the GP predictive alone: without the model's observation term or band calibration "
                        "(train --calibrate-bands)")
    s.add_argument("--export", choices=("json", "csv"), default=None,
                   help="also write frames.json|csv (per frame: time, the AAM parameters' mean, sd and 5/50/95 %% "
                        "quantiles, the landmarks and their sd over seeded predictive draws) and "
                        "landmarks_track.json|csv (x, y of every landmark per frame, for a 2-D tool); "
                        "docs/outputs.md")
    s.add_argument("--force", action="store_true",
                   help="replace an earlier run's outputs in --out (its files this run does not write "
                        "are removed)")
    s.set_defaults(func=_cmd_synth)

    # --- demo ---------------------------------------------------------------------------
    d = sub.add_parser("demo", help="the main job on the built-in corpus", **_SUB_KW)
    d.add_argument("--out", default="demo_out", help="output directory")
    d.set_defaults(func=_cmd_demo)

    # --- evaluate -----------------------------------------------------------------------
    _add_evaluate_parser(sub)
    _add_alignment_parsers(sub)
    return p


_HANDLER: logging.Handler | None = None


class _CurrentStderrHandler(logging.StreamHandler):
    """A StreamHandler on whatever ``sys.stderr`` is when a record is written, not the one
    of its creation: ``main`` called in-process (tests, notebooks) under a replaced stderr
    that is later closed must not leave the root logger writing to a closed file (every
    later record -- e.g. dask's at a cluster's shutdown -- printed "--- Logging error ---
    ... ValueError: I/O operation on closed file")."""

    @property
    def stream(self):  # type: ignore[override]
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:  # StreamHandler.__init__ assigns it: ignored
        pass


def _log_to_stderr(level: int, fmt: str) -> None:
    """One stderr handler on the root logger (replacing the one an earlier ``main`` added,
    leaving any other handler alone)."""
    global _HANDLER
    root = logging.getLogger()
    if _HANDLER is not None:
        root.removeHandler(_HANDLER)
    _HANDLER = _CurrentStderrHandler()
    _HANDLER.setFormatter(logging.Formatter(fmt))
    root.addHandler(_HANDLER)
    root.setLevel(level)


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the process exit status (143 on SIGTERM, 130 on Ctrl-C)."""
    from bayes_talk.base.executor import sigterm_as_interrupt

    with sigterm_as_interrupt():
        return _main(argv)


def _main(argv: list[str] | None) -> int:
    args = build_parser().parse_args(argv)
    verbose, quiet = getattr(args, "verbose", False), getattr(args, "quiet", False)
    level = logging.INFO if verbose else logging.ERROR if quiet else logging.WARNING
    _log_to_stderr(level, "%(asctime)s %(name)s %(levelname)s: %(message)s" if verbose
                   else "bayes-talk: %(levelname)s: %(message)s")
    from bayes_talk.base import logs

    # hmmlearn's "Model is not converging" (noise to a user) kept for -v; worker processes
    # log the same way (bayes_talk.base.logs)
    logs.quiet_third_party(verbose)
    logging.captureWarnings(True)  # library warnings (e.g. unseen phones) go through logging, one line each
    import warnings

    warnings.formatwarning = logs.brief_warning
    from bayes_talk.base.progress import HEARTBEAT_LOGGER, set_enabled

    set_enabled(not quiet)
    # progress off a terminal (a heartbeat line every few seconds of a long stage) is shown
    # by default, not only with -v; -q switches it off (set_enabled)
    logging.getLogger(HEARTBEAT_LOGGER).setLevel(logging.INFO)
    from bayes_talk.base.memory import release_large_blocks

    release_large_blocks()  # freed N×N matrices go back to the system (bayes_talk.base.memory)
    from bayes_talk.base.executor import Terminated

    try:
        return int(args.func(args) or 0)
    except Terminated:  # before KeyboardInterrupt, its base class
        print("bayes-talk: error: terminated (SIGTERM)", file=sys.stderr)
        return 143
    except KeyboardInterrupt:
        print("bayes-talk: error: interrupted", file=sys.stderr)
        return 130
    except (ValueError, OSError, RuntimeError) as exc:
        print(f"bayes-talk: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
