"""One audio-visual utterance as the models see it.

Every model in the package (the SGPDM family and the baselines) consumes a list of
:class:`Utterance` objects: frame-synchronous audio features, visual features and
phone labels at 25 Hz.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


@dataclass
class Utterance:
    """A frame-synchronous utterance.

    Attributes
    ----------
    name : utterance identifier (unique within a corpus).
    mfcc : (T, D_y) float64 audio features (20 MFCCs at 25 Hz).
    aam : (T, D_z) float64 visual features (AAM parameters at 25 fps), or None at synthesis.
    labels : T frame-level phone labels (ARPAbet 39 + ``sil``).
    landmarks : optional (T, P, 2) landmark coordinates in pixels.
    audio_path : optional path of the WAV the MFCCs came from.
    meta : free-form metadata (sentence text, voice, ...).
    """

    name: str
    mfcc: np.ndarray
    aam: np.ndarray | None
    labels: list[str]
    landmarks: np.ndarray | None = None
    audio_path: Path | None = None
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.mfcc = np.asarray(self.mfcc, dtype=np.float64)
        if self.mfcc.ndim != 2:
            raise ValueError(f"sequence {self.name!r}: mfcc must be 2-D (T, D), got shape {self.mfcc.shape}")
        T = self.mfcc.shape[0]
        if self.aam is not None:
            self.aam = np.asarray(self.aam, dtype=np.float64)
            if self.aam.ndim != 2 or self.aam.shape[0] != T:
                raise ValueError(
                    f"sequence {self.name!r}: aam has shape {self.aam.shape}, expected ({T}, D_z) "
                    f"to match the {T} audio frames"
                )
        if len(self.labels) != T:
            raise ValueError(
                f"sequence {self.name!r}: {len(self.labels)} frame labels for {T} audio frames"
            )
        for arr, what in ((self.mfcc, "mfcc"), (self.aam, "aam")):
            if arr is not None and not np.all(np.isfinite(arr)):
                raise ValueError(f"sequence {self.name!r}: {what} contains NaN or inf")

    @property
    def n_frames(self) -> int:
        """Number of frames T."""
        return int(self.mfcc.shape[0])


def check_test(seq: Utterance, *, n_audio: int | None = None, n_visual: int | None = None,
               need_aam: bool = False) -> None:
    """Validate a test sequence against the fitted dimensions (ValueError on mismatch)."""
    if not isinstance(seq, Utterance):
        raise ValueError(f"expected a Utterance, got {type(seq).__name__}")  # noqa: TRY004
    if seq.n_frames < 1:
        raise ValueError(f"sequence {seq.name!r} has no frames")
    if n_audio is not None and seq.mfcc.shape[1] != n_audio:
        raise ValueError(
            f"sequence {seq.name!r}: mfcc has shape {seq.mfcc.shape}, expected (T, {n_audio})")
    if need_aam:
        if seq.aam is None:
            raise ValueError(f"sequence {seq.name!r} has no ground-truth aam to score")
        if n_visual is not None and seq.aam.shape[1] != n_visual:
            raise ValueError(
                f"sequence {seq.name!r}: aam has shape {seq.aam.shape}, expected (T, {n_visual})")
