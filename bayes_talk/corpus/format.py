"""The built-corpus format: names, versions, constants, deterministic ``.npz``/JSON files,
the renderer settings of each format version and the AAM prototype draw (deena2010 §3.2).

See :mod:`bayes_talk.corpus` for the directory layout.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from bayes_talk.base.files import write_npz
from bayes_talk.data.phones import PHONES

FORMAT_NAME = "bayes_talk-corpus"
#: 2: frames rendered with camera area integration and optics (render.RENDER_SUPERSAMPLE,
#: render.CAMERA_PSF_PX, recorded in the manifest's "renderer"); 1: point-sampled
#: frames. The file layout is the same, so both are read.
FORMAT_VERSION = 2
READABLE_VERSIONS = (1, 2)
FPS = 25.0
AAM_FRAMES_PER_PHONE = 4
AAM_VARIANCE = 0.99
#: texture pixels of the corpus AAM lie at least this far (px) inside the mean-shape hull
#: (``AAM.fit(texture_inset=...)``): the outermost ring straddles the face outline and
#: samples the background, which alone doubled the number of modes (docs/data.md)
AAM_TEXTURE_INSET = 1.0
#: the command line's default (no ``--workers``): 2 worker processes from this many
#: utterances on, else none (a worker's start-up, ~1-3 s of imports, outweighs the gain
#: on small jobs); library calls default to none (``n_workers=None``)
MIN_ITEMS_FOR_WORKERS = 16
#: bump when the derived features (MFCC settings, label rule, AAM projection) change
FEATURE_VERSION = 1
CACHE_NAME = "features.npz"
MANIFEST = "manifest.json"
_ZIP_DATE = (1980, 1, 1, 0, 0, 0)
VIDEO_EXT = (".mp4", ".avi", ".mov", ".mkv", ".webm")
IMAGE_EXT = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


# ---------------------------------------------------------------------------------------
# deterministic .npz and JSON
# ---------------------------------------------------------------------------------------

def save_npz(path: str | Path, compress: bool = True, **arrays: np.ndarray) -> None:
    """Byte-deterministic ``.npz`` (see :func:`bayes_talk.base.files.write_npz`), compressed by default."""
    write_npz(path, arrays, compress=compress)


def load_npz(path: str | Path, keys: tuple[str, ...] = ()) -> dict[str, np.ndarray]:
    """Read an ``.npz`` (no pickle); error naming the file if unreadable or a key is missing."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            out = {k: z[k] for k in z.files}
    except Exception as exc:
        raise ValueError(f"{path}: cannot read .npz ({exc})") from exc
    for k in keys:
        if k not in out:
            raise ValueError(f"{path}: expected array {k!r}, found {sorted(out)}")
    return out


def renderer_settings(format_version: int) -> dict:
    """How the frames of a built corpus of ``format_version`` were rendered: keyword
    arguments of :func:`~bayes_talk.corpus.render.render_frames` (a version-1 manifest has
    no "renderer" entry: point sampling, ideal lens)."""
    from bayes_talk.corpus import render

    if int(format_version) < 2:
        return {"supersample": 1, "psf_px": 0.0}
    return {"supersample": int(render.RENDER_SUPERSAMPLE), "psf_px": float(render.CAMERA_PSF_PX)}



def prototype_frames(labels: list[list[str]], rng: np.random.Generator,
                      per_phone: int) -> list[tuple[int, int]]:
    """(sequence, frame) pairs: up to ``per_phone`` random frames of each phone present."""
    by_phone: dict[str, list[tuple[int, int]]] = {}
    for s, labs in enumerate(labels):
        for t, lab in enumerate(labs):
            by_phone.setdefault(lab, []).append((s, t))
    chosen: list[tuple[int, int]] = []
    for p in PHONES:  # fixed order -> fixed sequence of draws
        cands = by_phone.get(p)
        if not cands:
            continue
        k = min(per_phone, len(cands))
        idx = rng.choice(len(cands), size=k, replace=False)
        chosen.extend(cands[i] for i in sorted(idx))
    return sorted(chosen)

