"""Corpus layouts on disk: the built corpus's manifest entries and the user corpus
(``NAME.wav`` + ``NAME.lab``/``.TextGrid`` + frames, video or features; docs/data.md),
each read into :class:`CorpusItem` records and checked; frames, images and videos read."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bayes_talk.corpus.format import (
    FPS,
    IMAGE_EXT,
    MANIFEST,
    READABLE_VERSIONS,
    VIDEO_EXT,
    load_npz,
)
from bayes_talk.data.checks import check_audio_vs_labels
from bayes_talk.data.labels import read_labels
from bayes_talk.features.mfcc import frame_count, load_wav, samples_per_frame


@dataclass
class CorpusItem:
    """One utterance's inputs before featurisation."""

    name: str
    wav: Path
    labels: Path
    n_frames: int
    intervals: list
    visual: Path | None = None            # frames .npz, image folder or video
    landmarks: Path | None = None
    features: Path | None = None          # precomputed visual features (.npy)
    meta: dict = field(default_factory=dict)
    inputs: list[Path] = field(default_factory=list)


def check_item_audio(wav: Path, lab: Path, n_samples: int, sr: int, intervals) -> None:
    """The labels of ``lab`` end where the audio of ``wav`` ends (:func:`~bayes_talk.data.checks.check_audio_vs_labels`)."""
    check_audio_vs_labels(wav, lab, n_samples / sr, intervals[-1][1], detail=f"{n_samples} samples at {sr} Hz")


def built_items(root: Path, m: dict) -> tuple[list[CorpusItem], int]:
    """The utterances of a built corpus's manifest ``m`` (files checked) and its audio rate."""
    if m.get("format_version") not in READABLE_VERSIONS:
        raise ValueError(f"{root / MANIFEST}: format_version {m.get('format_version')!r}, "
                         f"expected one of {list(READABLE_VERSIONS)}")
    if float(m.get("fps", -1)) != FPS:
        raise ValueError(f"{root / MANIFEST}: fps {m.get('fps')!r}, expected {FPS}")
    rate = int(m["audio_rate"])
    items = []
    for sm in m["sequences"]:
        wav, lab = root / sm["wav"], root / sm["lab"]
        y, sr = load_wav(wav)
        if sr != rate:
            raise ValueError(f"{wav}: sample rate {sr} Hz, expected {rate} Hz (manifest audio_rate)")
        intervals = read_labels(lab)
        check_item_audio(wav, lab, y.size, sr, intervals)
        T = frame_count(y.size, sr, FPS)
        if T != int(sm["n_frames"]):
            raise ValueError(f"{wav}: {T} frames of audio, manifest says {sm['n_frames']}")
        item = CorpusItem(sm["name"], wav, lab, T, intervals, visual=root / sm["frames"],
                     landmarks=root / sm["landmarks"],
                     meta={k: sm[k] for k in ("text", "voice", "rate", "pitch") if k in sm})
        item.inputs = [wav, lab, item.visual, item.landmarks]
        items.append(item)
    return items, rate


def read_images(folder: Path) -> np.ndarray:
    """The image files of ``folder`` in name order, as grey frames (T, H, W) uint8."""
    import imageio.v3 as iio

    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXT)
    if not files:
        raise ValueError(f"{folder}: no image files ({', '.join(IMAGE_EXT)})")
    out = []
    for f in files:
        try:
            im = np.asarray(iio.imread(f))
        except Exception as exc:
            raise ValueError(f"{f}: cannot read image ({exc})") from exc
        out.append(_to_gray(im, f))
    shapes = {im.shape for im in out}
    if len(shapes) != 1:
        raise ValueError(f"{folder}: images differ in size {sorted(shapes)}")
    return np.stack(out)


def _to_gray(im: np.ndarray, where: Path) -> np.ndarray:
    if im.ndim == 3:
        from skimage.color import rgb2gray

        im = im[..., :3]
        im = np.rint(rgb2gray(im) * (255.0 if im.dtype == np.uint8 else 1.0))
    if im.ndim != 2:
        raise ValueError(f"{where}: expected a grayscale or RGB image, found shape {im.shape}")
    return np.clip(im, 0, 255).astype(np.uint8)


def read_video(path: Path) -> np.ndarray:
    """The frames of the video ``path`` as grey frames (T, H, W) uint8 (ValueError unless at :data:`FPS`)."""
    import imageio_ffmpeg

    try:
        gen = imageio_ffmpeg.read_frames(str(path), pix_fmt="gray", bpp=1)
        meta = next(gen)
        w, h = meta["size"]
        fps = float(meta.get("fps", FPS))
        frames = [np.frombuffer(b, dtype=np.uint8).reshape(h, w) for b in gen]
    except Exception as exc:
        raise ValueError(f"{path}: cannot read video ({exc})") from exc
    if abs(fps - FPS) > 1e-3:
        raise ValueError(f"{path}: video at {fps} fps, expected {FPS} fps")
    if not frames:
        raise ValueError(f"{path}: video has no frames")
    return np.stack(frames)


def label_file_for(root: Path, wav: Path) -> Path:
    """The label file beside a user corpus's ``NAME.wav``: ``NAME.lab`` or ``NAME.TextGrid``."""
    name = wav.stem
    labs = [p for p in (root / f"{name}.lab", root / f"{name}.TextGrid",
                        root / f"{name}.textgrid") if p.exists()]
    if not labs:
        raise ValueError(f"{wav}: no label file {name}.lab or {name}.TextGrid beside it")
    return labs[0]


def user_items(root: Path) -> tuple[list[CorpusItem], int]:
    """The utterances of a user corpus (``NAME.wav`` + labels + frames/video/features; docs/data.md) and its audio rate."""
    wavs = sorted(root.glob("*.wav"))
    if not wavs:
        raise ValueError(f"{root}: no manifest.json and no *.wav files; not a corpus directory "
                         "(see docs/data.md for the user-corpus layout)")
    items: list[CorpusItem] = []
    rate = None
    for wav in wavs:
        name = wav.stem
        lab = label_file_for(root, wav)
        y, sr = load_wav(wav)
        samples_per_frame(sr, FPS)
        if rate is None:
            rate = sr
        elif sr != rate:
            raise ValueError(f"{wav}: sample rate {sr} Hz, expected {rate} Hz like {wavs[0]}")
        intervals = read_labels(lab)
        check_item_audio(wav, lab, y.size, sr, intervals)
        T = frame_count(y.size, sr, FPS)
        item = CorpusItem(name, wav, lab, T, intervals, meta={})
        feat = root / f"{name}.visual.npy"
        lmk = root / f"{name}.landmarks.npy"
        vids = [root / f"{name}{e}" for e in VIDEO_EXT if (root / f"{name}{e}").exists()]
        if feat.exists():
            item.features = feat
        elif (root / name).is_dir() or vids:
            item.visual = root / name if (root / name).is_dir() else vids[0]
            if not lmk.exists():
                raise ValueError(f"{item.visual}: frames need per-frame landmarks in {lmk} "
                                 "(with only some frames annotated, run `bayes-talk corpus track`; "
                                 "docs/data.md)")
            item.landmarks = lmk
        else:
            raise ValueError(
                f"{wav}: no visual data; expected {feat.name} (features), a folder {name}/ of "
                f"images or a video {name}.mp4, with {lmk.name}"
            )
        item.inputs = [wav, lab] + [p for p in (item.features, item.landmarks) if p is not None]
        if item.visual is not None:
            item.inputs += (sorted(item.visual.iterdir()) if item.visual.is_dir() else [item.visual])
        items.append(item)
    return items, int(rate)


def load_visual(item: CorpusItem) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray | None]:
    """(frames, landmarks, features) of one item, checked for frame-count agreement.

    The sequence length is the audio frame count T; visual data may hold T or T+1 frames
    (a trailing partial frame), anything else is an error naming both files.
    """
    T = item.n_frames

    def fit_len(n: int, what: Path) -> None:
        if n not in (T, T + 1):
            raise ValueError(f"{what}: {n} frames, but {item.wav} holds {T} whole 40 ms frames "
                             f"(expected {T} or {T + 1})")

    if item.features is not None:
        try:
            f = np.load(item.features, allow_pickle=False)
        except Exception as exc:
            raise ValueError(f"{item.features}: cannot read ({exc})") from exc
        if f.ndim != 2 or not np.all(np.isfinite(f)):
            raise ValueError(f"{item.features}: expected finite (T, D) features, found shape {f.shape}")
        fit_len(f.shape[0], item.features)
        return None, None, np.asarray(f[:T], dtype=np.float64)
    if item.visual.suffix == ".npz":
        frames = load_npz(item.visual, ("frames",))["frames"]
        lm = load_npz(item.landmarks, ("landmarks",))["landmarks"]
    else:
        frames = read_images(item.visual) if item.visual.is_dir() else read_video(item.visual)
        try:
            lm = np.load(item.landmarks, allow_pickle=False)
        except Exception as exc:
            raise ValueError(f"{item.landmarks}: cannot read ({exc})") from exc
    if lm.ndim != 3 or lm.shape[2] != 2:
        raise ValueError(f"{item.landmarks}: expected (T, P, 2) landmarks, found shape {lm.shape}")
    if not np.all(np.isfinite(lm)):
        bad = np.flatnonzero(~np.isfinite(lm).reshape(lm.shape[0], -1).all(axis=1))
        raise ValueError(f"{item.landmarks}: landmarks contain NaN or inf (first at frame {bad[0]}); frames "
                         f"{bad[:10].tolist()} have no finite landmarks; for sparse annotations use "
                         "NAME.annotations.npy and `bayes-talk corpus track` (docs/data.md)")
    if lm.shape[0] != frames.shape[0]:
        raise ValueError(f"{item.landmarks}: {lm.shape[0]} landmark frames but {item.visual} "
                         f"has {frames.shape[0]} image frames")
    fit_len(frames.shape[0], item.visual)
    return frames[:T], np.asarray(lm[:T], dtype=np.float64), None

