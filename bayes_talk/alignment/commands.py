"""What the command line does with the alignment models: train them into a model
directory, label a WAV (transcript -> aligner, none -> recogniser), write the result."""
from __future__ import annotations

import logging
import os
from pathlib import Path

from bayes_talk.alignment.model import JSON_NAME, NPZ_NAME, AlignmentModel, AlignmentResult

__all__ = ["DEFAULT_ALIGN_METHOD", "align_train", "check_label_output", "fit_alignment", "label_audio",
           "write_segmentation"]

log = logging.getLogger(__name__)

#: the default aligner: measured better than the HMM forced aligner on both held-out
#: corpora (docs/alignment.md)
DEFAULT_ALIGN_METHOD = "dtw"
LABEL_SUFFIXES = (".lab", ".textgrid")


def fit_alignment(sequences, seed: int = 0) -> AlignmentModel:
    """An :class:`AlignmentModel` fitted on ``sequences`` (one BLAS thread)."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1):
        return AlignmentModel(seed=seed).fit(sequences)


def align_train(corpus_dir: str | os.PathLike, model_dir: str | os.PathLike, force: bool = False) -> Path:
    """Fit the alignment models on a corpus and save them into an existing model directory."""
    from bayes_talk.base.bundle import DESCRIPTOR
    from bayes_talk.corpus import load_corpus

    d = Path(model_dir)
    if not (d / DESCRIPTOR).exists():
        raise FileNotFoundError(f"{d} is not a bayes_talk model directory (no {DESCRIPTOR}); "
                                "train one with `bayes-talk train` first")
    existing = [n for n in (JSON_NAME, NPZ_NAME) if (d / n).exists()]
    if existing and not force:
        raise FileExistsError(f"{d} already holds alignment models {existing}; pass --force to replace them")
    corpus = load_corpus(corpus_dir)
    return fit_alignment(corpus.sequences).save(d)


def check_label_output(path: str | os.PathLike, force: bool = False) -> Path:
    """Validate an output label path before any work: .lab or .TextGrid, not overwritten unasked."""
    p = Path(path)
    if p.suffix.lower() not in LABEL_SUFFIXES:
        raise ValueError(f"{p}: unknown label format {p.suffix!r}; expected .lab or .TextGrid")
    if p.is_dir():
        raise ValueError(f"{p}: is a directory")
    if p.exists() and not force:
        raise FileExistsError(f"{p} exists; choose another path or pass --force")
    return p


def write_segmentation(path: str | os.PathLike, intervals) -> Path:
    """Write intervals as HTK .lab or Praat TextGrid by extension (atomically)."""
    from bayes_talk.data.labels import write_lab, write_textgrid

    p = Path(path)
    (write_lab if p.suffix.lower() == ".lab" else write_textgrid)(p, intervals)
    return p


def label_audio(model_dir: str | os.PathLike, wav: str | os.PathLike, text: str | None = None,
                transcript: str | os.PathLike | None = None,
                method: str = DEFAULT_ALIGN_METHOD) -> AlignmentResult:
    """Phone intervals of ``wav``: aligned to ``text`` / the ``transcript`` file if given,
    else recognised from the audio alone (logged as a warning)."""
    from bayes_talk.alignment.transcript import read_transcript

    if text is not None and transcript is not None:
        raise ValueError("give the transcript either as --text or as --transcript FILE, not both")
    model = AlignmentModel.load(model_dir)
    if transcript is not None:
        text = read_transcript(transcript)
    if text is not None:
        res = model.align(wav, text, method=method, where=str(wav))
        log.info("%s: %d phones aligned by %s in %.2f s (cost %.2f)", wav, len(res.intervals),
                 res.method, res.seconds, res.cost)
        return res
    log.warning("%s: no phone labels or transcript given; phone labels come from the phone recogniser "
                "(phone error rate in docs/alignment.md)", wav)
    return model.recognise(wav, where=str(wav))
