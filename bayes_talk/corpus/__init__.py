"""The built-in talking-head corpus and the user-corpus loader (docs/data.md).

Built corpus (:func:`build_corpus`), a self-describing directory::

    OUT_DIR/
      manifest.json                 format, version, fps, audio rate, phone set, image size,
                                    seed, voice, AAM files + prototype frames, sequences,
                                    and the list of every file the build wrote
      utterances/utt0000.wav        16-bit mono PCM, 22050 Hz, length = whole frames
      utterances/utt0000.lab        HTK phone segmentation (100 ns units), ARPAbet 39 + sil
      utterances/utt0000.landmarks.npz   "landmarks": (T, P, 2) float64 pixels (x, y)
      utterances/utt0000.frames.npz      "frames": (T, H, W) uint8 grayscale, deflated
      aam*                          the AAM learned from prototype frames (AAM.save)
      features.npz                  cache written by load_corpus (not part of the build)

Reproducibility: speech is synthesised one utterance per fresh process (see
:mod:`bayes_talk.data.speech`); every random draw comes from ``np.random.default_rng``
seeded with ``[seed, utterance_index, stream]``; ``.npz`` files are written by
:func:`save_npz`, which pins every zip member's timestamp to 1980-01-01 (verified: with
Python 3.11 and numpy 2.4, ``np.savez_compressed`` also writes that fixed stamp, because
``ZipFile.open(name, "w")`` uses the ``ZipInfo`` default; ``save_npz`` makes it explicit
rather than relying on that detail) -- so the same arguments give a byte-identical
directory, and utterance i does not depend on ``n_utterances``.

Random streams: utterance i's rate/pitch jitter ``[seed, i]``; its face ``[seed, i, 1]``;
the AAM prototype choice ``[seed, 2**31]``.

Speed: utterances are built end to end (speech, face, frames, files) and featurised
(MFCC, AAM projection) in worker processes with one BLAS thread each (see the section
bayes_talk.corpus.workers); nothing depends on which process did the work.

AAM prototypes (deena2010 §3.2: 4 random frames per phoneme + 1 silence frame): up to
``AAM_FRAMES_PER_PHONE`` frames drawn at random (without replacement) among the frames
whose majority-vote label is that phone, for every phone present, ``sil`` included.

See ``docs/data.md`` for the user-corpus layout read by :func:`load_corpus`.

Modules: :mod:`.format` (names, versions, deterministic files), :mod:`.layouts` (built and
user layouts on disk), :mod:`.build`, :mod:`.load`, :mod:`.workers` (per-utterance tasks and
the processes that run them).
"""
from bayes_talk.corpus.build import build_corpus, load_sentences
from bayes_talk.corpus.format import (
    AAM_FRAMES_PER_PHONE,
    AAM_TEXTURE_INSET,
    AAM_VARIANCE,
    FEATURE_VERSION,
    FORMAT_NAME,
    FORMAT_VERSION,
    FPS,
    load_npz,
    renderer_settings,
    save_npz,
)
from bayes_talk.corpus.load import Corpus, load_corpus

__all__ = [
    "AAM_FRAMES_PER_PHONE",
    "AAM_TEXTURE_INSET",
    "AAM_VARIANCE",
    "FEATURE_VERSION",
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "FPS",
    "Corpus",
    "build_corpus",
    "load_corpus",
    "load_npz",
    "load_sentences",
    "renderer_settings",
    "save_npz",
]
