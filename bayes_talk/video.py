"""Writing rendered faces to MP4 (with the speech) through imageio-ffmpeg's bundled ffmpeg."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from bayes_talk.files import atomic_write


def side_by_side(*videos: np.ndarray, gap: int = 2) -> np.ndarray:
    """Concatenate (T, H, W) uint8 videos left to right (shortest length), with a dark gap."""
    T = min(v.shape[0] for v in videos)
    H = max(v.shape[1] for v in videos)
    parts = []
    for i, v in enumerate(videos):
        pad = np.zeros((T, H, v.shape[2]), np.uint8)
        pad[:, : v.shape[1]] = v[:T]
        parts.append(pad)
        if i < len(videos) - 1 and gap:
            parts.append(np.zeros((T, H, gap), np.uint8))
    return np.concatenate(parts, axis=2)


def write_video(path: str | os.PathLike, frames: np.ndarray, fps: float = 25.0,
                audio_path: str | os.PathLike | None = None, overwrite: bool = False) -> Path:
    """Write grayscale frames (T, H, W) uint8 as H.264 MP4, muxing the WAV if given.

    Written to a temporary file beside ``path`` and moved into place, so a failure never
    leaves half a video; an existing ``path`` is refused unless ``overwrite``.
    """
    import imageio_ffmpeg

    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; refusing to overwrite it")
    frames = np.asarray(frames)
    if frames.ndim != 3 or frames.dtype != np.uint8:
        raise ValueError(f"frames must be a (T, H, W) uint8 array, got {frames.dtype} {frames.shape}")
    H, W = frames.shape[1:]
    if H % 2 or W % 2:  # yuv420p needs even sizes
        frames = np.pad(frames, ((0, 0), (0, H % 2), (0, W % 2)))
    H, W = frames.shape[1:]
    kw = {"fps": fps, "codec": "libx264", "pix_fmt_in": "gray", "pix_fmt_out": "yuv420p",
          "macro_block_size": 1, "quality": None, "output_params": ["-crf", "18"],
          "ffmpeg_log_level": "error"}  # no "Guessed Channel Layout" notices on stderr
    if audio_path is not None:
        kw.update(audio_path=str(audio_path), audio_codec="aac", output_params=["-crf", "18", "-shortest"])

    def encode(tmp: str) -> None:
        gen = imageio_ffmpeg.write_frames(tmp, (W, H), **kw)
        gen.send(None)
        for f in frames:
            gen.send(np.ascontiguousarray(f))
        gen.close()

    atomic_write(path, encode, suffix=".mp4")
    return path
