"""The ``bayes-talk`` command line.

Sub-commands::

    bayes-talk corpus build OUT_DIR [--n-utterances N] [--seed S] [--sentences FILE]
                                    [--voice NAME] [--image-size PX] [--force]
    bayes-talk demo [--out DIR]
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


def _cmd_demo(args: argparse.Namespace) -> int:
    from bayes_talk.demo import run_demo

    return run_demo(Path(args.out))


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

    # --- demo ---------------------------------------------------------------------------
    d = sub.add_parser("demo", help="the main job on the built-in corpus")
    d.add_argument("--out", default="demo_out")
    d.set_defaults(func=_cmd_demo)
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
