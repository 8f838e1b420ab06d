"""Tracking a user corpus from a few annotated frames (deena2010 §3.2; docs/data.md).

deena2010 placed landmarks by hand on 184 prototype frames (4 random frames per phoneme,
1 silence frame), built the AAM from them, and ran the AAM search over the whole corpus.
This module does the same for a user corpus (docs/data.md, "Your own corpus") whose
frames are annotated only sparsely:

* :func:`propose_prototypes` picks the frames to annotate -- up to ``per_phone`` random
  frames of every phone present (25 Hz majority-vote labels), drawn exactly as the
  built corpus and :func:`~bayes_talk.corpus.load_corpus` draw their AAM prototypes
  (random stream ``[seed, 2**31]``) -- plus, optionally, ``per_video`` random frames of
  each video that got none -- and writes them as PNG images with a ``prototypes.json``.
* :func:`track_corpus` reads the annotations, builds the AAM from the annotated frames
  (99 % variance, 1 px texture inset, as the corpus AAM), fits every other frame with
  :class:`~bayes_talk.features.aam_fit.AAMFitter` and writes ``NAME.landmarks.npy`` (every
  frame), ``NAME.track.json`` (per-frame score and source, lost frames) and ``aam.npz``;
  :func:`~bayes_talk.corpus.load_corpus` then loads the corpus as a fully annotated
  one (and projects through that AAM).

Annotation layout (per video ``NAME``; one of the two)::

    NAME.annotations/FRAME.pts  or  FRAME.npy   one file per annotated frame; FRAME is the
                                                0-based frame index (any zero padding);
                                                .pts: the IBUG text format
                                                ("version: 1 / n_points: P / { x y ... }"),
                                                .npy: (P, 2) float
    NAME.annotations.npy                        (T, P, 2) float, NaN rows = not annotated

Coordinates as in ``NAME.landmarks.npy``: x = column, y = row, 0-based, pixel centres at
integer coordinates (IBUG tools write 1-based .pts: subtract 1).

Never overwritten unasked: ``NAME.landmarks.npy``, ``NAME.track.json`` and ``aam.npz``/
``aam.json`` are replaced only if the previous ``track.json`` lists them with the same
SHA-256 (i.e. we wrote them and nobody changed them since), or with ``force``.

This module stays above ~400 lines because :func:`track_corpus` is one procedure (scan,
annotate, build the AAM, track, interpolate lost frames, write a corpus that
:func:`~bayes_talk.corpus.load_corpus` reads) whose steps share its file-ownership
rules; the annotation readers and the prototype proposal are small.
"""
from __future__ import annotations

import hashlib
import json
import logging
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bayes_talk.base.files import write_bytes, write_json, write_npy
from bayes_talk.corpus.format import (
    AAM_FRAMES_PER_PHONE,
    AAM_TEXTURE_INSET,
    AAM_VARIANCE,
    FPS,
    VIDEO_EXT,
    prototype_frames,
)
from bayes_talk.corpus.layouts import (
    check_item_audio,
    label_file_for,
    read_images,
    read_video,
)
from bayes_talk.data.labels import frame_labels, read_labels
from bayes_talk.features.aam_fit import (
    LOST_THRESHOLD,
    AAMFitter,
    FrameSizeError,
    LandmarkCountError,
    TrackResult,
)
from bayes_talk.features.mfcc import frame_count, load_wav

__all__ = [
    "NoAnnotatedFrameError",
    "TrackSummary",
    "propose_prototypes",
    "read_annotations",
    "read_pts",
    "track_corpus",
]

log = logging.getLogger(__name__)

_SUMMARY = "track.json"
_FORMAT = "bayes_talk.track"


class NoAnnotatedFrameError(ValueError):
    """A video (or the whole corpus) has no annotated frame to start tracking from."""


# ----------------------------------------------------------------------------- reading
@dataclass
class _Video:
    name: str
    wav: Path
    labels_path: Path
    n_frames: int                  # audio frames T
    labels: list[str]
    visual: Path
    annotations: Path | None = None
    frames: np.ndarray | None = field(default=None, repr=False)

    def load_frames(self) -> np.ndarray:
        if self.frames is None:
            self.frames = (read_images(self.visual) if self.visual.is_dir()
                           else read_video(self.visual))
        return self.frames


def _scan(root: Path) -> list[_Video]:
    """The user corpus's videos (WAV + labels + a folder of images or a video)."""
    root = Path(root)
    if not root.is_dir():
        raise ValueError(f"{root}: corpus directory not found")
    if (root / "manifest.json").exists():
        raise ValueError(f"{root}: a built corpus (manifest.json) has landmarks for every frame; "
                         "tracking is for user corpora (docs/data.md)")
    wavs = sorted(root.glob("*.wav"))
    if not wavs:
        raise ValueError(f"{root}: no *.wav files; not a user corpus directory (docs/data.md)")
    out = []
    for wav in wavs:
        name = wav.stem
        lab = label_file_for(root, wav)
        y, sr = load_wav(wav)
        intervals = read_labels(lab)
        check_item_audio(wav, lab, y.size, sr, intervals)
        T = frame_count(y.size, sr, FPS)
        vids = [root / f"{name}{e}" for e in VIDEO_EXT if (root / f"{name}{e}").exists()]
        if (root / name).is_dir():
            visual = root / name
        elif vids:
            visual = vids[0]
        else:
            raise ValueError(f"{wav}: no frames to track; expected a folder {name}/ of images or "
                             f"a video {name}.mp4 (docs/data.md)")
        ann = [p for p in (root / f"{name}.annotations", root / f"{name}.annotations.npy")
               if p.exists()]
        if len(ann) > 1:
            raise ValueError(f"{root}: both {ann[0].name}/ and {ann[1].name} exist for {name}; "
                             "use one annotation layout per video")
        out.append(_Video(name, wav, lab, T, frame_labels(intervals, T, FPS), visual,
                          ann[0] if ann else None))
    return out


def read_pts(path: str | Path) -> np.ndarray:
    """Landmarks (P, 2) from an IBUG ``.pts`` file (``version``, ``n_points``, ``{ x y ... }``)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: cannot read landmarks ({exc})") from exc
    m = re.search(r"n_points\s*:\s*(\d+)", text)
    body = re.search(r"\{(.*)\}", text, re.DOTALL)
    if m is None or body is None:
        raise ValueError(f"{path}: not a .pts file (expected 'n_points: P' and '{{ x y ... }}')")
    try:
        pts = np.array([[float(v) for v in ln.split()] for ln in body.group(1).splitlines()
                        if ln.strip()], dtype=np.float64)
    except ValueError as exc:
        raise ValueError(f"{path}: unreadable coordinates ({exc})") from exc
    n = int(m.group(1))
    if pts.ndim != 2 or pts.shape[1] != 2 or pts.shape[0] != n:
        raise ValueError(f"{path}: n_points says {n}, found {pts.shape[0] if pts.ndim == 2 else 0} "
                         "lines of 'x y'")
    return pts


def read_annotations(path: str | Path, n_frames: int) -> dict[int, np.ndarray]:
    """Annotated frames of one video: ``{frame index: (P, 2) landmarks}`` from a
    ``NAME.annotations/`` folder or a sparse ``NAME.annotations.npy`` (NaN rows).

    Errors name the file: unreadable, a frame index outside ``0..n_frames-1``, a
    non-integer file name, partly-NaN rows, or a point count that differs between frames
    (:class:`~bayes_talk.features.aam_fit.LandmarkCountError`).
    """
    path = Path(path)
    ann: dict[int, np.ndarray] = {}
    where: dict[int, Path] = {}
    if path.is_dir():
        for f in sorted(path.iterdir()):
            if f.suffix.lower() not in (".pts", ".npy"):
                continue
            if not f.stem.isdigit():
                raise ValueError(f"{f}: annotation file names must be the 0-based frame index "
                                 "(e.g. 0012.pts)")
            t = int(f.stem)
            if t in ann:
                raise ValueError(f"{f}: frame {t} is annotated twice (also {where[t]})")
            if f.suffix.lower() == ".pts":
                lm = read_pts(f)
            else:
                try:
                    lm = np.asarray(np.load(f, allow_pickle=False), dtype=np.float64)
                except Exception as exc:
                    raise ValueError(f"{f}: cannot read ({exc})") from exc
            if lm.ndim != 2 or lm.shape[1] != 2 or not np.all(np.isfinite(lm)):
                raise ValueError(f"{f}: expected finite (P, 2) landmarks, found shape {lm.shape}")
            ann[t], where[t] = lm, f
    else:
        try:
            arr = np.asarray(np.load(path, allow_pickle=False), dtype=np.float64)
        except Exception as exc:
            raise ValueError(f"{path}: cannot read ({exc})") from exc
        if arr.ndim != 3 or arr.shape[2] != 2:
            raise ValueError(f"{path}: expected (T, P, 2) landmarks with NaN rows, found {arr.shape}")
        fin = np.isfinite(arr).reshape(arr.shape[0], -1)
        partial = np.flatnonzero(fin.any(axis=1) & ~fin.all(axis=1))
        if partial.size:
            raise ValueError(f"{path}: frame {partial[0]} is partly NaN; a frame is either fully "
                             "annotated or all NaN")
        for t in np.flatnonzero(fin.all(axis=1)):
            ann[int(t)], where[int(t)] = arr[t], path
    for t in ann:
        if not (0 <= t < n_frames):
            raise ValueError(f"{where[t]}: annotated frame {t} outside the video's frames "
                             f"0..{n_frames - 1}")
    counts = {t: lm.shape[0] for t, lm in ann.items()}
    if len(set(counts.values())) > 1:
        t0 = min(counts)
        t1 = next(t for t in sorted(counts) if counts[t] != counts[t0])
        raise LandmarkCountError(f"{where[t1]}: frame {t1} has {counts[t1]} landmarks, expected "
                                 f"{counts[t0]} like frame {t0} ({where[t0]})")
    return dict(sorted(ann.items()))


# ----------------------------------------------------------------------------- proposing
def _proposals(videos: list[_Video], per_phone: int, per_video: int,
               seed: int) -> list[tuple[int, int, str]]:
    """(video, frame, why) picks: deena2010's random frames per phone (the stream the
    built corpus uses), then ``per_video`` random frames of every video left without one."""
    if int(per_phone) < 1:
        raise ValueError(f"per_phone: expected >= 1, found {per_phone}")
    labels = [v.labels for v in videos]
    picks = [(s, t, labels[s][t]) for s, t in
             prototype_frames(labels, np.random.default_rng([int(seed), 2**31]), int(per_phone))]
    covered = {s for s, _, _ in picks}
    rng = np.random.default_rng([int(seed), 2**31, 1])
    for s, v in enumerate(videos):
        if s in covered or per_video < 1:
            continue
        for t in sorted(rng.choice(v.n_frames, size=min(int(per_video), v.n_frames), replace=False)):
            picks.append((s, int(t), "video"))
    return sorted(picks)


def propose_prototypes(root: str | Path, per_phone: int = AAM_FRAMES_PER_PHONE,
                       out: str | Path | None = None, *, per_video: int = 0, seed: int = 0,
                       force: bool = False) -> Path:
    """Write the frames to annotate as PNGs, ``OUT/NAME/FRAME.png``, and
    ``OUT/prototypes.json`` listing video, frame, phone, image and the annotation file to
    create (``NAME.annotations/FRAME.pts``). ``out`` defaults to ``ROOT/prototypes``; a
    non-empty ``out`` is refused unless ``force``. Returns the ``prototypes.json`` path."""
    import imageio.v3 as iio

    root = Path(root)
    videos = _scan(root)
    out = Path(out) if out is not None else root / "prototypes"
    if out.exists() and any(out.iterdir()) and not force:
        raise FileExistsError(f"{out}: not empty; refusing to write prototype images there "
                              "(pass --force / force=True)")
    picks = _proposals(videos, per_phone, per_video, seed)
    listing = []
    for s in sorted({s for s, _, _ in picks}):
        v = videos[s]
        frames = v.load_frames()
        width = max(4, len(str(frames.shape[0] - 1)))
        for ss, t, why in picks:
            if ss != s:
                continue
            if t >= frames.shape[0]:
                continue
            img = out / v.name / f"{t:0{width}d}.png"
            img.parent.mkdir(parents=True, exist_ok=True)
            data = iio.imwrite("<bytes>", frames[t], extension=".png")
            write_bytes(img, data)
            listing.append({"video": v.name, "frame": int(t), "phone": why if why != "video" else
                            v.labels[t], "reason": "per-video" if why == "video" else "per-phone",
                            "image": str(img.relative_to(out)),
                            "annotation": f"{v.name}.annotations/{t:0{width}d}.pts"})
        v.frames = None
    path = out / "prototypes.json"
    write_json(path, {"format": "bayes_talk.prototypes", "per_phone": int(per_phone),
                      "per_video": int(per_video), "seed": int(seed), "corpus": str(root),
                      "rule": "deena2010 §3.2: up to per_phone random frames of every phone "
                              "(25 Hz majority labels), random stream [seed, 2**31]",
                      "frames": listing})
    return path


# ----------------------------------------------------------------------------- tracking
@dataclass
class TrackSummary:
    """What :func:`track_corpus` did: per video the lost frame indices, whether its
    landmarks were written, and the files written."""

    lost: dict[str, list[int]]
    written: list[Path]
    not_written: list[str]
    n_annotated: int
    scores: dict[str, np.ndarray]
    thin_phones: dict[str, int]


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _owned(root: Path) -> dict[str, str]:
    p = root / _SUMMARY
    if not p.exists():
        return {}
    try:
        m = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return m.get("files", {}) if isinstance(m, dict) and m.get("format") == _FORMAT else {}


def _may_write(path: Path, owned: dict[str, str], root: Path, force: bool) -> None:
    if not path.exists() or force:
        return
    rel = str(path.relative_to(root))
    if owned.get(rel) != _sha(path):
        raise FileExistsError(f"{path}: exists and was not written by `corpus track` (or was "
                              "changed since); refusing to overwrite it (pass --force)")


def _interpolate_lost(lm: np.ndarray, lost: list[int]) -> np.ndarray:
    good = np.array([t for t in range(lm.shape[0]) if t not in set(lost)])
    out = lm.copy()
    flat = lm.reshape(lm.shape[0], -1)
    for j in range(flat.shape[1]):
        out.reshape(lm.shape[0], -1)[lost, j] = np.interp(lost, good, flat[good, j])
    return out


def track_corpus(root: str | Path, per_phone: int = AAM_FRAMES_PER_PHONE, *,
                 search_unannotated: bool = False, allow_lost: bool = False,
                 lost_threshold: float = LOST_THRESHOLD, n_levels: int = 2, seed: int = 0,
                 force: bool = False) -> TrackSummary:
    """Build the AAM from the annotated frames of a user corpus and track every frame.

    Errors (each a ``ValueError`` subclass naming the file): no annotated frame anywhere
    (:class:`NoAnnotatedFrameError`; the ``per_phone`` frames to annotate are proposed
    into ``ROOT/prototypes`` first, if that folder does not exist); a video without an
    annotated frame (:class:`NoAnnotatedFrameError`) unless ``search_unannotated`` (then
    its frames are searched from the AAM's mean shape at the prototypes' mean pose,
    :meth:`AAMFitter.track`); frames of another size than the annotated ones
    (:class:`FrameSizeError`); annotation files with different point counts
    (:class:`LandmarkCountError`); too few annotated frames for the 99 % variance target
    (:class:`TooFewPrototypesError`).

    A video with lost frames (score above ``lost_threshold``) gets its
    ``NAME.track.json`` (indices in ``"lost"``) but no ``NAME.landmarks.npy`` -- annotate
    those frames and rerun -- unless ``allow_lost``: then their landmarks are linearly
    interpolated between the nearest tracked frames and marked ``"interpolated"``.
    Phones with fewer than ``per_phone`` annotated frames are logged (``thin_phones``).
    """
    root = Path(root)
    videos = _scan(root)
    anns: list[dict[int, np.ndarray]] = []
    for v in videos:
        if v.annotations is None:
            anns.append({})
            continue
        frames = v.load_frames()
        anns.append(read_annotations(v.annotations, frames.shape[0]))
        v.frames = None
    n_ann = sum(len(a) for a in anns)
    if n_ann == 0:
        msg = f"{root}: no annotated frame in any video (expected NAME.annotations/FRAME.pts or " \
              "NAME.annotations.npy, docs/data.md)"
        if not (root / "prototypes").exists():
            p = propose_prototypes(root, per_phone, seed=seed)
            msg += f"; the frames to annotate ({per_phone} per phone) are listed in {p}"
        raise NoAnnotatedFrameError(msg)
    missing = [v.name for v, a in zip(videos, anns) if not a]
    if missing and not search_unannotated:
        raise NoAnnotatedFrameError(
            f"{root / missing[0]}: video has no annotated frame to start tracking from "
            f"({len(missing)} such videos: {', '.join(missing[:5])}{' ...' if len(missing) > 5 else ''}); "
            "annotate one frame each (propose-prototypes --per-video 1) or pass "
            "--search-unannotated")
    owned = _owned(root)
    if (root / _SUMMARY).exists() and not owned and not force:
        raise FileExistsError(f"{root / _SUMMARY}: exists and is not a `corpus track` summary; "
                              "refusing to overwrite it (pass --force)")
    files: dict[str, str] = {}
    written: list[Path] = []
    lost: dict[str, list[int]] = {}
    scores: dict[str, np.ndarray] = {}
    not_written: list[str] = []
    aam_base = root / "aam"
    for p in [root / "aam.npz", root / "aam.json"] + [
            root / f"{v.name}{ext}" for v in videos for ext in (".landmarks.npy", ".track.json")]:
        _may_write(p, owned, root, force)      # all refusals before any work is written
    # reference point count and frame size from the first annotated frame
    ref_v = next(i for i, a in enumerate(anns) if a)
    ref_t = next(iter(anns[ref_v]))
    ref_where = videos[ref_v].annotations
    P = anns[ref_v][ref_t].shape[0]
    imgs, lms = [], []
    ref_shape = None
    for v, a in zip(videos, anns):
        if not a:
            continue
        if next(iter(a.values())).shape[0] != P:
            raise LandmarkCountError(f"{v.annotations}: {next(iter(a.values())).shape[0]} landmarks "
                                     f"per frame, expected {P} like {ref_where}")
        frames = v.load_frames()
        if ref_shape is None:
            ref_shape, ref_name = frames.shape[1:], v.visual
        elif frames.shape[1:] != ref_shape:
            raise FrameSizeError(f"{v.visual}: frames are {frames.shape[1]}x{frames.shape[2]} pixels, "
                                 f"but the annotated frames of {ref_name} are "
                                 f"{ref_shape[0]}x{ref_shape[1]}")
        for t, lm in a.items():
            imgs.append(frames[t])
            lms.append(lm)
        v.frames = None
    fitter = AAMFitter.from_prototypes(np.stack(imgs), np.stack(lms), n_levels=n_levels,
                                       variance=AAM_VARIANCE, texture_inset=AAM_TEXTURE_INSET,
                                       lost_threshold=lost_threshold)
    counts: dict[str, int] = {}
    for v, a in zip(videos, anns):
        for t in a:
            if t < len(v.labels):
                counts[v.labels[t]] = counts.get(v.labels[t], 0) + 1
    present = {p for v in videos for p in v.labels}
    thin = {p: counts.get(p, 0) for p in sorted(present) if counts.get(p, 0) < per_phone}
    if thin:
        log.warning("phones with fewer than %d annotated frames: %s", per_phone,
                    ", ".join(f"{p} ({n})" for p, n in thin.items()))

    for v, a in zip(videos, anns):
        frames = v.load_frames()
        if frames.shape[1:] != tuple(fitter.image_shape):
            raise FrameSizeError(f"{v.visual}: frames are {frames.shape[1]}x{frames.shape[2]} pixels, "
                                 f"but the annotated frames are {fitter.image_shape[0]}x"
                                 f"{fitter.image_shape[1]}")
        res: TrackResult = fitter.track(frames, a, where=str(v.visual))
        v.frames = None
        lost[v.name] = res.lost
        scores[v.name] = res.scores
        lm_path = root / f"{v.name}.landmarks.npy"
        tj_path = root / f"{v.name}.track.json"
        source = list(res.source)
        landmarks = res.landmarks
        write_lm = not res.lost
        if res.lost and allow_lost and len(res.lost) < len(source):
            landmarks = _interpolate_lost(landmarks, res.lost)
            source = ["interpolated" if s == "lost" else s for s in source]
            write_lm = True
        if res.lost:
            log.warning("%s: %d lost frames: %s", v.visual, len(res.lost), res.lost)
        write_json(tj_path, {
            "format": "bayes_talk.track_video", "video": v.name, "n_frames": len(source),
            "lost_threshold": fitter.lost_threshold,
            "score": "projected-out texture residual RMS (units of texture std), finest level",
            "lost": res.lost, "landmarks_written": bool(write_lm),
            "scores": [None if not np.isfinite(s) else round(float(s), 6) for s in res.scores],
            "source": source})
        files[tj_path.name] = _sha(tj_path)
        written.append(tj_path)
        if write_lm:
            write_npy(lm_path, landmarks)
            files[lm_path.name] = _sha(lm_path)
            written.append(lm_path)
        else:
            not_written.append(v.name)
            if lm_path.exists():  # ours from an earlier run (checked above): now stale
                lm_path.unlink()
    for p in fitter.aam.save(aam_base):
        files[p.name] = _sha(p)
        written.append(p)
    write_json(root / _SUMMARY, {
        "format": _FORMAT, "n_annotated_frames": n_ann, "per_phone": int(per_phone),
        "lost_threshold": fitter.lost_threshold, "n_levels": int(n_levels),
        "aam": {"n_params": fitter.aam.n_params, "n_shape_modes": fitter.aam.n_shape_modes,
                "n_texture_modes": fitter.aam.n_texture_modes},
        "lost": {k: v for k, v in lost.items() if v}, "landmarks_not_written": not_written,
        "thin_phones": thin, "files": files})
    return TrackSummary(lost=lost, written=written, not_written=not_written, n_annotated=n_ann,
                        scores=scores, thin_phones=thin)


# ----------------------------------------------------------------------------- built -> sparse
def sparse_copy_of_built(built: str | Path, out: str | Path,
                         annotate: dict[str, list[int]] | None = None) -> Path:
    """Rewrite a built corpus as a sparsely annotated *user* corpus (for tests, the
    benchmark and the docs): ``NAME.wav``, ``NAME.lab``, ``NAME/FRAME.png`` and
    ``NAME.annotations.npy`` holding the true landmarks of the frames in ``annotate``
    (``{name: [frames]}``; default: the built AAM's prototype frames, 4 per phone) and
    NaN elsewhere (no file for a video without annotated frames; ``annotate={}``: none). ``out`` must not exist or be empty. Returns ``out``."""
    import shutil

    import imageio.v3 as iio

    from bayes_talk.corpus import load_npz

    built, out = Path(built), Path(out)
    m = json.loads((built / "manifest.json").read_text(encoding="utf-8"))
    if out.exists() and any(out.iterdir()):
        raise FileExistsError(f"{out}: not empty; refusing to write a corpus there")
    if annotate is None:
        annotate = {}
        for name, t in m["aam"]["prototypes"]:
            annotate.setdefault(name, []).append(int(t))
    out.mkdir(parents=True, exist_ok=True)
    for s in m["sequences"]:
        name = s["name"]
        shutil.copy(built / s["wav"], out / f"{name}.wav")
        shutil.copy(built / s["lab"], out / f"{name}.lab")
        frames = load_npz(built / s["frames"], ("frames",))["frames"]
        lm = load_npz(built / s["landmarks"], ("landmarks",))["landmarks"]
        (out / name).mkdir()
        for t, img in enumerate(frames):
            write_bytes(out / name / f"{t:04d}.png", iio.imwrite("<bytes>", img, extension=".png"))
        if annotate.get(name):                   # no annotation file for a video without
            sparse = np.full_like(lm, np.nan)
            for t in annotate[name]:
                sparse[t] = lm[t]
            write_npy(out / f"{name}.annotations.npy", sparse)
    return out
