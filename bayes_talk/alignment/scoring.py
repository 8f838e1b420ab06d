"""Accuracy of a segmentation against the truth: phone error rate and boundary errors.

* Phone error rate (PER): Levenshtein distance (substitutions + deletions + insertions,
  unit costs) between the reference and hypothesis phone sequences, divided by the
  reference length, pooled over utterances (sum of distances / sum of lengths).
* Boundary error: the two sequences are matched by the same edit-distance alignment; for
  every reference phone matched to an identical hypothesis phone (a "hit"), except the
  first phone of the utterance (which starts at 0 in both), ``|start_ref - start_hyp|`` in
  seconds. With an aligner the sequences usually coincide and every boundary is scored;
  with a recogniser only the hits are.
* Frame agreement: fraction of 25 Hz video frames whose majority-vote label
  (:func:`bayes_talk.data.labels.frame_labels`) is the same under both -- what the
  switching model actually sees.
"""
from __future__ import annotations

import numpy as np

__all__ = ["edit_alignment", "score_segmentation", "summarise_scores"]


def edit_alignment(ref: list[str], hyp: list[str]) -> tuple[int, list[tuple[int, int]]]:
    """(edit distance, [(i_ref, i_hyp) of hits]) by dynamic programming with backtrace.

    Among the alignments with the fewest edits, one with the most hits is chosen (cost
    ``edits * L - hits`` with ``L = len(ref) + len(hyp) + 1``, so hits only break ties).
    """
    n, m = len(ref), len(hyp)
    L = n + m + 1
    D = np.zeros((n + 1, m + 1), dtype=np.int64)
    D[:, 0] = np.arange(n + 1) * L
    D[0, :] = np.arange(m + 1) * L
    for i in range(1, n + 1):
        for j in range(1, m + 1):
            diag = D[i - 1, j - 1] + (L if ref[i - 1] != hyp[j - 1] else -1)
            D[i, j] = min(D[i - 1, j] + L, D[i, j - 1] + L, diag)
    hits, edits = [], 0
    i, j = n, m
    while i > 0 or j > 0:
        if i > 0 and j > 0 and D[i, j] == D[i - 1, j - 1] + (L if ref[i - 1] != hyp[j - 1] else -1):
            if ref[i - 1] == hyp[j - 1]:
                hits.append((i - 1, j - 1))
            else:
                edits += 1
            i, j = i - 1, j - 1
        elif i > 0 and D[i, j] == D[i - 1, j] + L:
            i, edits = i - 1, edits + 1
        else:
            j, edits = j - 1, edits + 1
    hits.reverse()
    return edits, hits


def score_segmentation(ref: list[tuple[float, float, str]], hyp: list[tuple[float, float, str]],
                       n_frames: int | None = None, fps: float = 25.0) -> dict:
    """Edit distance, reference length, boundary errors (s) and frame agreement of one utterance."""
    from bayes_talk.data.labels import frame_labels

    rp, hp = [p for _, _, p in ref], [p for _, _, p in hyp]
    dist, hits = edit_alignment(rp, hp)
    errs = [abs(ref[i][0] - hyp[j][0]) for i, j in hits if i > 0 and j > 0]
    out = {"edits": dist, "n_ref": len(rp), "boundary_errors": errs}
    if n_frames:
        a, b = frame_labels(ref, n_frames, fps), frame_labels(hyp, n_frames, fps)
        out["frames_agree"] = int(sum(x == y for x, y in zip(a, b)))
        out["n_frames"] = int(n_frames)
    return out


def summarise_scores(rows: list[dict]) -> dict:
    """Pooled PER, boundary-error median / 90th percentile / mean (ms), frame agreement."""
    errs = np.array([e for r in rows for e in r["boundary_errors"]], dtype=np.float64) * 1e3
    out = {"n_utterances": len(rows),
           "phone_error_rate": float(sum(r["edits"] for r in rows) / max(1, sum(r["n_ref"] for r in rows))),
           "n_boundaries": int(errs.size),
           "boundary_error_ms_median": float(np.median(errs)) if errs.size else None,
           "boundary_error_ms_p90": float(np.percentile(errs, 90)) if errs.size else None,
           "boundary_error_ms_mean": float(errs.mean()) if errs.size else None,
           "within_20ms": float(np.mean(errs <= 20.0)) if errs.size else None}
    nf = sum(r.get("n_frames", 0) for r in rows)
    if nf:
        out["frame_label_agreement"] = float(sum(r.get("frames_agree", 0) for r in rows) / nf)
    return out
