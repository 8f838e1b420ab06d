"""Per-frame cost of the synthetic face: landmarks, rendering, AAM fit and projection.

Budget (issue #3): the 300-utterance corpus (~25,000 frames) must be built and featurised
in < 3 min on 2 cores, i.e. ~3 ms/frame for rendering and ~2 ms/frame for projection.
Also times skimage.transform.warp + PiecewiseAffineTransform for comparison.

Run: .venv/bin/python benchmarks/render.py   -> benchmarks/results/render.json
"""
from __future__ import annotations

import json
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
from skimage.transform import PiecewiseAffineTransform, warp

from bayes_talk.data import face, render
from bayes_talk.data.face import random_phone_intervals
from bayes_talk.features.aam import AAM

ROOT = Path(__file__).resolve().parents[1]

N_SEQ, N_FRAMES, N_FIT = 40, 75, 600


def main() -> None:
    rng = np.random.default_rng(0)
    ivs = [random_phone_intervals(rng, N_FRAMES) for _ in range(N_SEQ)]
    render.render_frames(face.reference_shape(128)[None])  # warm the texture cache

    t0 = time.perf_counter()
    lm = np.concatenate([face.face_landmarks(iv, N_FRAMES, rng=rng) for iv in ivs])
    t_lm = time.perf_counter() - t0
    n = len(lm)

    t0 = time.perf_counter()
    frames = render.render_frames(lm)
    t_render = time.perf_counter() - t0

    idx = np.sort(np.random.default_rng(1).choice(n, N_FIT, replace=False))
    t0 = time.perf_counter()
    model = AAM.fit(frames[idx], lm[idx])
    t_fit = time.perf_counter() - t0

    t0 = time.perf_counter()
    params = model.project(frames, lm)
    t_proj = time.perf_counter() - t0

    tex = face.reference_shape(128)
    texture = render.face_texture(128)
    k = 20
    t0 = time.perf_counter()
    for i in range(k):
        tf = PiecewiseAffineTransform.from_estimate(lm[i], tex)
        warp(texture, tf, output_shape=(128, 128), order=1, preserve_range=True)
    t_sk = time.perf_counter() - t0

    result = {
        "frames": n,
        "image_size": 128,
        "landmarks_ms_per_frame": 1e3 * t_lm / n,
        "render_ms_per_frame": 1e3 * t_render / n,
        "aam_fit_s": t_fit,
        "aam_fit_frames": N_FIT,
        "aam_project_ms_per_frame": 1e3 * t_proj / n,
        "skimage_pwa_warp_ms_per_frame": 1e3 * t_sk / k,
        "aam_n_params": model.n_params,
        "aam_modes_shape_texture_combined": [model.n_shape_modes, model.n_texture_modes, model.n_combined],
        "aam_texture_pixels": model.n_pixels,
        "params_finite": bool(np.all(np.isfinite(params))),
        "estimated_25000_frames_s": 25000 * (t_lm + t_render + t_proj) / n,
        "python": platform.python_version(),
        "numpy": np.__version__,
        "cpu_count": os.cpu_count(),
    }
    out = ROOT / "benchmarks" / "results" / "render.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=out.parent, suffix=".tmp")
    with os.fdopen(fd, "w") as fh:
        json.dump(result, fh, indent=1)
        fh.write("\n")
    os.replace(tmp, out)
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
