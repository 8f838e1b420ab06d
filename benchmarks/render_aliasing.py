"""How much of each AAM mode's held-out variance is a rendering artefact of head motion.

A still face moved only by the generator's head pose (the same draws as the full face:
pose track from :func:`~bayes_talk.data.face.face_trajectories`; articulators fixed at the
utterance's mean, no blinks, brows at rest) changes nothing a perfect AAM models: its
combined (shape-free appearance) parameters should be constant, because Procrustes
alignment removes the similarity transform and the texture is sampled in the mean-shape
frame. Any variance they show is resampling artefact (aliasing). For each renderer
(``--supersample`` factors of :func:`~bayes_talk.corpus.render.render_frames`, measured side
by side in one run) this script

1. draws faces for ``--n-train`` training utterances the way ``corpus build`` does
   (rng ``[seed, i, 1]``), picks the corpus's AAM prototype frames (4 per phone, rng
   ``[seed, 2**31]``), renders them and fits an AAM exactly as the corpus does
   (``variance`` 0.99, texture inset 1 px);
2. for ``--n-heldout`` held-out utterances renders the full face and the pose-only face,
   projects both through that AAM, removes each utterance's mean, and reports per combined
   mode ``share_d = var(pose-only)_d / var(full)_d`` (pooled over held-out frames), with
   summaries: mode 5 and modes 10-32 (1-based), all modes
   (variance-weighted and the plain mean of the per-mode shares).

Phone timings come from the ``.lab`` files of built corpora (``--train-corpus``,
``--heldout-corpus``; their manifest seeds drive the face draws, so at ``supersample 1``
the frames are the corpus's own) or, without them, from
:func:`~bayes_talk.data.face.random_phone_intervals` (no speech synthesis needed).

    .venv/bin/python benchmarks/render_aliasing.py \
        --train-corpus data/train250 --heldout-corpus data/heldout40
    .venv/bin/python benchmarks/render_aliasing.py --quick      # random timings, small

Writes benchmarks/results/render_aliasing.json (``--out``; ``--quick``: results/quick/).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bayes_talk.corpus import render
from bayes_talk.corpus.format import (
    AAM_FRAMES_PER_PHONE,
    AAM_TEXTURE_INSET,
    AAM_VARIANCE,
    FPS,
    prototype_frames,
)
from bayes_talk.data import face
from bayes_talk.data.labels import frame_labels, read_labels
from bayes_talk.features.aam import AAM
from benchmarks.common import result_path, write_result


def corpus_timings(root: Path, n: int) -> tuple[list[tuple[list, int]], int]:
    """(intervals, n_frames) of the first ``n`` utterances of a built corpus, and its seed."""
    m = json.loads((root / "manifest.json").read_text(encoding="utf-8"))
    seqs = m["sequences"][:n]
    return [(read_labels(root / s["lab"]), int(s["n_frames"])) for s in seqs], int(m["seed"])


def random_timings(seed: int, n: int, n_frames: int = 75) -> list[tuple[list, int]]:
    rng = np.random.default_rng([seed, 2**30])
    return [(face.random_phone_intervals(rng, n_frames), n_frames) for _ in range(n)]


def tracks(timings: list[tuple[list, int]], seed: int) -> list[face.FaceTrack]:
    """The corpus's face draws: utterance i from ``default_rng([seed, i, 1])``."""
    return [face.face_trajectories(iv, T, fps=FPS, rng=np.random.default_rng([seed, i, 1]))
            for i, (iv, T) in enumerate(timings)]


def full_landmarks(tr: face.FaceTrack, size: int) -> np.ndarray:
    return face.shape_from_articulators(tr.articulators, tr.blink, tr.pose, tr.brow, image_size=size)


def pose_only_landmarks(tr: face.FaceTrack, size: int) -> np.ndarray:
    """The still face (articulators at the utterance mean, eyes open, brows at rest)
    moved by the same head-pose track."""
    T = tr.pose.shape[0]
    art = np.repeat(tr.articulators.mean(axis=0, keepdims=True), T, axis=0)
    return face.shape_from_articulators(art, None, tr.pose, None, image_size=size)


def fit_corpus_aam(timings, trs, seed: int, size: int, supersample: tuple[int, float]) -> AAM:
    """An AAM fitted the way ``build_corpus`` fits it, rendering only the prototype frames."""
    labels = [frame_labels(iv, T, FPS) for iv, T in timings]
    protos = prototype_frames(labels, np.random.default_rng([int(seed), 2**31]), AAM_FRAMES_PER_PHONE)
    lms = np.stack([full_landmarks(trs[s], size)[t] for s, t in protos])
    frames = render.render_frames(lms, image_size=size, supersample=supersample[0], psf_px=supersample[1])
    return AAM.fit(frames, lms, variance=AAM_VARIANCE, texture_inset=AAM_TEXTURE_INSET)


def pooled_variance(aam: AAM, lms: list[np.ndarray], size: int, supersample: tuple[int, float]) -> np.ndarray:
    """Per-parameter variance of the projected frames after per-utterance mean removal."""
    resid = []
    for lm in lms:
        p = aam.project(render.render_frames(lm, image_size=size, supersample=supersample[0],
                                             psf_px=supersample[1]), lm)
        resid.append(p - p.mean(axis=0))
    return np.concatenate(resid).var(axis=0)


def share_summary(var_full: np.ndarray, var_pose: np.ndarray) -> dict:
    share = var_pose / np.maximum(var_full, 1e-300)
    n = share.size
    out = {"n_modes": int(n), "share_per_mode": [round(float(x), 4) for x in share],
           "share_all_variance_weighted": float(var_pose.sum() / var_full.sum()),
           "share_all_mean": float(share.mean())}
    if n >= 5:
        out["share_mode_5"] = float(share[4])
    if n >= 10:
        sl = slice(9, min(n, 32))
        out["share_modes_10_32"] = float(var_pose[sl].sum() / var_full[sl].sum())
        out["share_modes_10_32_mean"] = float(share[sl].mean())
    return out


def measure(supersample: tuple[int, float], tr_timings, tr_tracks, tr_seed, ho_tracks, size: int) -> dict:
    t0 = time.perf_counter()
    aam = fit_corpus_aam(tr_timings, tr_tracks, tr_seed, size, supersample)
    t_fit = time.perf_counter() - t0
    sl = aam.param_slices["combined"]
    t0 = time.perf_counter()
    v_full = pooled_variance(aam, [full_landmarks(t, size) for t in ho_tracks], size, supersample)
    v_pose = pooled_variance(aam, [pose_only_landmarks(t, size) for t in ho_tracks], size, supersample)
    t_proj = time.perf_counter() - t0
    n_frames = sum(t.pose.shape[0] for t in ho_tracks)
    return {
        "supersample": supersample[0], "psf_px": supersample[1],
        "aam_n_params": aam.n_params,
        "aam_modes_shape_texture_combined": [aam.n_shape_modes, aam.n_texture_modes, aam.n_combined],
        "combined": share_summary(v_full[sl], v_pose[sl]),
        "var_full_combined": [round(float(x), 6) for x in v_full[sl]],
        "var_pose_only_combined": [round(float(x), 6) for x in v_pose[sl]],
        "aam_fit_s": round(t_fit, 2),
        "render_project_ms_per_frame": round(1e3 * t_proj / (2 * n_frames), 3),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--supersample", default="1:0,2:0.7",
                    help="comma-separated renderers FACTOR:PSF_PX (1:0 = point sampling, format 1)")
    ap.add_argument("--train-corpus", type=Path, help="built corpus whose .lab timings and seed drive the AAM fit")
    ap.add_argument("--heldout-corpus", type=Path, help="built corpus of held-out timings and seed")
    ap.add_argument("--n-train", type=int, default=250)
    ap.add_argument("--n-heldout", type=int, default=20)
    ap.add_argument("--image-size", type=int, default=128)
    ap.add_argument("--quick", action="store_true", help="random timings, 60 train / 8 held-out")
    ap.add_argument("--out", type=Path, default=None, help="default benchmarks/results/render_aliasing.json "
                    "(--quick: results/quick/)")
    a = ap.parse_args()
    a.out = result_path("render_aliasing", a.quick, a.out)
    factors = [(int(x.split(":")[0]), float(x.split(":")[1]) if ":" in x else 0.0)
               for x in a.supersample.split(",") if x.strip()]
    if a.quick:
        a.n_train, a.n_heldout = 60, 8
    if a.train_corpus is not None:
        tr_timings, tr_seed = corpus_timings(a.train_corpus, a.n_train)
    else:
        tr_seed = 0
        tr_timings = random_timings(tr_seed, a.n_train)
    if a.heldout_corpus is not None:
        ho_timings, ho_seed = corpus_timings(a.heldout_corpus, a.n_heldout)
    else:
        ho_seed = 1
        ho_timings = random_timings(ho_seed, a.n_heldout)
    tr_tracks = tracks(tr_timings, tr_seed)
    ho_tracks = tracks(ho_timings, ho_seed)
    load0 = [round(x, 2) for x in os.getloadavg()]
    runs = [measure(s, tr_timings, tr_tracks, tr_seed, ho_tracks, a.image_size) for s in factors]
    result = {
        "what": "share of each AAM combined mode's held-out variance produced by pose-only motion "
                "of a still face (per-utterance mean removed); 0 = no aliasing",
        "train_timings": str(a.train_corpus) if a.train_corpus else "random_phone_intervals",
        "heldout_timings": str(a.heldout_corpus) if a.heldout_corpus else "random_phone_intervals",
        "n_train": len(tr_timings), "n_heldout": len(ho_timings),
        "heldout_frames": int(sum(t.pose.shape[0] for t in ho_tracks)),
        "image_size": a.image_size,
        "runs": runs,
        "loadavg_start": load0, "loadavg_end": [round(x, 2) for x in os.getloadavg()],
    }
    write_result(a.out, result)
    for r in runs:
        c = r["combined"]
        print(f"supersample {r['supersample']} psf {r['psf_px']}: modes {r['aam_modes_shape_texture_combined']}, "
              f"share mode 5 {c.get('share_mode_5', float('nan')):.3f}, "
              f"modes 10-32 {c.get('share_modes_10_32', float('nan')):.3f}, "
              f"all (var-weighted) {c['share_all_variance_weighted']:.3f}, "
              f"mean {c['share_all_mean']:.3f}, {r['render_project_ms_per_frame']} ms/frame")
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
