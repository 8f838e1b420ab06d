"""Writing rendered faces to MP4 (with the speech) through imageio-ffmpeg's bundled ffmpeg."""
from __future__ import annotations

import itertools
import os
from pathlib import Path

import numpy as np

from bayes_talk.base.files import atomic_write


def side_by_side(*videos: np.ndarray, gap: int = 2, labels: tuple[str, ...] | list[str] | None = None) -> np.ndarray:
    """Concatenate (T, H, W) uint8 videos left to right (shortest length), with a dark gap.

    ``labels``: one caption per video (e.g. "ground truth", "synthesis"), drawn in a black
    strip above its panel (:func:`caption_strip`), so the video says which side is which.
    """
    if labels is not None and len(labels) != len(videos):
        raise ValueError(f"labels: expected one per video ({len(videos)}), found {len(labels)}")
    T = min(v.shape[0] for v in videos)
    H = max(v.shape[1] for v in videos)
    parts = []
    for i, v in enumerate(videos):
        pad = np.zeros((T, H, v.shape[2]), np.uint8)
        pad[:, : v.shape[1]] = v[:T]
        if labels is not None:
            strip = caption_strip(labels[i], v.shape[2])
            pad = np.concatenate([np.broadcast_to(strip, (T, *strip.shape)), pad], axis=1)
        parts.append(pad)
        if i < len(videos) - 1 and gap:
            parts.append(np.zeros((T, parts[-1].shape[1], gap), np.uint8))
    return np.concatenate(parts, axis=2)


def caption_strip(text: str, width: int, height: int = 16) -> np.ndarray:
    """(height, width) uint8: ``text`` in white, centred, on black (Pillow's built-in font,
    so no font file is needed; a caption wider than the panel is cut at its edges)."""
    from PIL import Image, ImageDraw, ImageFont

    img = Image.new("L", (width, height), 0)
    draw = ImageDraw.Draw(img)
    font = ImageFont.load_default(size=height - 5)
    left, top, right, bottom = draw.textbbox((0, 0), text, font=font)
    draw.text(((width - (right - left)) / 2 - left, (height - (bottom - top)) / 2 - top), text, fill=255, font=font)
    return np.asarray(img, dtype=np.uint8)


def write_video(path: str | os.PathLike, frames, fps: float = 25.0,
                audio_path: str | os.PathLike | None = None, overwrite: bool = False) -> Path:
    """Write grayscale frames as H.264 MP4, muxing the WAV if given. ``frames``: a (T, H, W)
    uint8 array, or an iterable of such arrays (chunks of frames, all of one H × W), which is
    encoded as it comes, so a long video never has to be held in memory.

    Written to a temporary file beside ``path`` and moved into place, so a failure never
    leaves half a video; an existing ``path`` is refused unless ``overwrite``.
    """
    import imageio_ffmpeg

    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; refusing to overwrite it")
    chunks = iter([frames] if isinstance(frames, np.ndarray) else frames)
    first = next(chunks, None)
    if first is None:
        raise ValueError("frames: no frames to write")

    def checked(chunk) -> np.ndarray:
        chunk = np.asarray(chunk)
        if chunk.ndim != 3 or chunk.dtype != np.uint8 or chunk.shape[1:] != first.shape[1:]:
            raise ValueError(f"frames must be (T, H, W) uint8 arrays of one H x W {first.shape[1:]}, "
                             f"got {chunk.dtype} {chunk.shape}")
        H, W = chunk.shape[1:]
        if H % 2 or W % 2:  # yuv420p needs even sizes
            chunk = np.pad(chunk, ((0, 0), (0, H % 2), (0, W % 2)))
        return chunk

    first = np.asarray(first)
    if first.ndim != 3 or first.dtype != np.uint8:
        raise ValueError(f"frames must be a (T, H, W) uint8 array, got {first.dtype} {first.shape}")
    H, W = checked(first).shape[1:]
    kw = {"fps": fps, "codec": "libx264", "pix_fmt_in": "gray", "pix_fmt_out": "yuv420p",
          "macro_block_size": 1, "quality": None, "output_params": ["-crf", "18"],
          "ffmpeg_log_level": "error"}  # no "Guessed Channel Layout" notices on stderr
    if audio_path is not None:
        kw.update(audio_path=str(audio_path), audio_codec="aac", output_params=["-crf", "18", "-shortest"])

    def encode(tmp: str) -> None:
        gen = imageio_ffmpeg.write_frames(tmp, (W, H), **kw)
        gen.send(None)
        for chunk in itertools.chain([first], chunks):
            for f in checked(chunk):
                gen.send(np.ascontiguousarray(f))
        gen.close()

    atomic_write(path, encode, suffix=".mp4")
    return path
