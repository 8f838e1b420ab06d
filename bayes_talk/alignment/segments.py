"""Frame-index segmentations <-> interval lists (seconds)."""
from __future__ import annotations

from bayes_talk.alignment.features import FeatureConfig

__all__ = ["segments_to_intervals"]


def segments_to_intervals(segs: list[tuple[str, int, int]], n_frames: int, duration: float,
                          cfg: FeatureConfig) -> list[tuple[float, float, str]]:
    """``[(phone, first frame, end frame), ...]`` (contiguous, covering 0..n_frames) ->
    intervals covering ``[0, duration]`` s; a boundary before frame j is at ``(j - 1/2) hop /
    sr`` (features.py). Adjacent ``sil`` segments are merged."""
    out: list[list] = []
    for i, (p, a, b) in enumerate(segs):
        s = 0.0 if i == 0 else max(0.0, (a - 0.5) * cfg.frame_s)
        e = duration if i == len(segs) - 1 else min(duration, (b - 0.5) * cfg.frame_s)
        if e <= s:
            continue
        if out and out[-1][2] == p == "sil":
            out[-1][1] = e
        else:
            if out:
                s = out[-1][1]
            out.append([s, e, p])
    if out:
        out[-1][1] = duration
    return [(float(s), float(e), str(p)) for s, e, p in out if e > s]
