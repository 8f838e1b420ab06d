"""Per-frame cost of the synthetic face: landmarks, rendering, AAM fit and projection.

Budget: the 300-utterance corpus (~25,000 frames) must be built and featurised in < 3 min on
2 cores, i.e. ~3 ms/frame for rendering and ~2 ms/frame for projection. Also times
skimage.transform.warp + PiecewiseAffineTransform for comparison, and the first call of the
renderer (in a fresh environment numba compiles its kernels then).

Run: .venv/bin/python benchmarks/render.py [--out benchmarks/results/render.json]
     .venv/bin/python benchmarks/render.py --quick     # 300 frames -> benchmarks/results/quick/render.json
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from skimage.transform import PiecewiseAffineTransform, warp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bayes_talk.corpus import render
from bayes_talk.data import face
from bayes_talk.data.face import random_phone_intervals
from bayes_talk.features import warp as _warp
from bayes_talk.features.aam import AAM
from benchmarks.common import result_path, write_result

N_SEQ, N_FRAMES, N_FIT = 40, 75, 600
QUICK_SEQ, QUICK_FIT = 4, 100


def _timed(fn, *args, **kwargs):
    """(result, CPU seconds, wall seconds) of one call."""
    c0, w0 = time.process_time(), time.perf_counter()
    out = fn(*args, **kwargs)
    return out, time.process_time() - c0, time.perf_counter() - w0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help=f"{QUICK_SEQ * N_FRAMES} frames")
    parser.add_argument("--out", default=None, help="default benchmarks/results/render.json (--quick: results/quick/)")
    args = parser.parse_args()
    out = result_path("render", args.quick, args.out)
    n_seq, n_fit = (QUICK_SEQ, QUICK_FIT) if args.quick else (N_SEQ, N_FIT)
    rng = np.random.default_rng(0)
    ivs = [random_phone_intervals(rng, N_FRAMES) for _ in range(n_seq)]
    # first call in this process: loads (or, in a fresh environment, compiles) the numba
    # kernels and paints the texture
    _, first_cpu, first_wall = _timed(render.render_frames, face.reference_shape(128)[None])
    _warp.warp_piecewise_affine(np.zeros((4, 4)), np.zeros((3, 2)), np.zeros((3, 2)), np.array([[0, 1, 2]]), (4, 4))
    _warp.bilinear_sample(np.zeros((1, 4, 4)), None, np.zeros(1), np.zeros(1))

    t0 = time.perf_counter()
    lm = np.concatenate([face.face_landmarks(iv, N_FRAMES, rng=rng) for iv in ivs])
    t_lm = time.perf_counter() - t0
    n = len(lm)

    t0 = time.perf_counter()
    frames = render.render_frames(lm)
    t_render = time.perf_counter() - t0

    idx = np.sort(np.random.default_rng(1).choice(n, n_fit, replace=False))
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
        "aam_fit_frames": n_fit,
        "aam_project_ms_per_frame": 1e3 * t_proj / n,
        "skimage_pwa_warp_ms_per_frame": 1e3 * t_sk / k,
        "aam_n_params": model.n_params,
        "aam_modes_shape_texture_combined": [model.n_shape_modes, model.n_texture_modes, model.n_combined],
        "aam_texture_pixels": model.n_pixels,
        "params_finite": bool(np.all(np.isfinite(params))),
        "estimated_25000_frames_s": 25000 * (t_lm + t_render + t_proj) / n,
        "first_render_call_cpu_s": first_cpu,
        "first_render_call_wall_s": first_wall,
    }
    write_result(out, result)
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
