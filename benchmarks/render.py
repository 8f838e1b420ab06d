"""Per-frame cost of the synthetic face: landmarks, rendering, AAM fit and projection.

Budget (issue #3): the 300-utterance corpus (~25,000 frames) must be built and featurised
in < 3 min on 2 cores, i.e. ~3 ms/frame for rendering and ~2 ms/frame for projection.
Also times skimage.transform.warp + PiecewiseAffineTransform for comparison, and (issue
25, session 12) the renderer, the warp and the bilinear sampler against the vectorised
NumPy versions they replaced (tests/warp_reference.py) in the same run, on the same
frames: CPU seconds (process time) and wall seconds of each, their ratio, and whether the
outputs are identical.

Run: .venv/bin/python benchmarks/render.py [--out benchmarks/results/render.json]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from skimage.transform import PiecewiseAffineTransform, warp

from bayes_talk.data import face

from bayes_talk.corpus import render
from bayes_talk.data.face import random_phone_intervals
from bayes_talk.features import warp as _warp
from bayes_talk.features.aam import AAM

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
import warp_reference  # the NumPy implementations, before session 12

N_SEQ, N_FRAMES, N_FIT = 40, 75, 600
#: frames of the warp-only comparison (its (frames, 128, 128) float64 outputs are not
#: batched: 3000 frames would time page faults)
N_WARP = 300


def _timed(fn, *args, **kwargs):
    """(result, CPU seconds, wall seconds) of one call."""
    c0, w0 = time.process_time(), time.perf_counter()
    out = fn(*args, **kwargs)
    return out, time.process_time() - c0, time.perf_counter() - w0


def _side_by_side(name: str, new, old, *args, **kwargs) -> dict:
    """Old (NumPy) and new (compiled) implementation of one call, on the same input."""
    a, cpu_old, wall_old = _timed(old, *args, **kwargs)
    b, cpu_new, wall_new = _timed(new, *args, **kwargs)
    a, b = (a, b) if isinstance(a, tuple) else ((a,), (b,))
    identical = all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    diff = max(float(np.max(np.abs(np.asarray(x, np.float64) - np.asarray(y, np.float64)))) for x, y in zip(a, b, strict=True))
    return {"call": name, "numpy_cpu_s": cpu_old, "numba_cpu_s": cpu_new, "numpy_wall_s": wall_old,
            "numba_wall_s": wall_new, "cpu_ratio_numpy_over_numba": cpu_old / cpu_new,
            "identical": identical, "max_abs_difference": diff}


def compare(lm: np.ndarray) -> dict:
    """The renderer (default camera and point sampling), the 1x warp of the texture onto
    the first N_WARP landmark sets (AAM.render's call) and bilinear sampling (the AAM's
    projection), old NumPy vs compiled."""
    tex, ref, tri = render.face_texture(128), face.reference_shape(128), render.face_triangles(128)
    rng = np.random.default_rng(2)
    frames = rng.uniform(0.0, 255.0, (50, 128, 128))
    x, y = rng.uniform(-1.0, 129.0, 2_000_000), rng.uniform(-1.0, 129.0, 2_000_000)
    f = rng.integers(0, 50, 2_000_000)
    rows = [
        _side_by_side("render_frames", render.render_frames, warp_reference.render_frames, lm),
        _side_by_side("render_frames(supersample=1, psf_px=0)", render.render_frames, warp_reference.render_frames,
                      lm, supersample=1, psf_px=0.0),
        _side_by_side("warp_piecewise_affine(128x128)", _warp.warp_piecewise_affine,
                      warp_reference.warp_piecewise_affine, tex, ref, lm[:N_WARP], tri, (128, 128)),
        _side_by_side("bilinear_sample(2e6 points)", _warp.bilinear_sample, warp_reference.bilinear_sample,
                      frames, f, x, y),
    ]
    for r in rows:
        if r["call"].startswith(("render", "warp")):
            r["frames"] = N_WARP if r["call"].startswith("warp") else len(lm)
            r["ms_per_frame_numpy_cpu"] = 1e3 * r["numpy_cpu_s"] / r["frames"]
            r["ms_per_frame_numba_cpu"] = 1e3 * r["numba_cpu_s"] / r["frames"]
    return {"frames": len(lm), "rows": rows}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="benchmarks/results/render.json",
                        help="result JSON, relative to the repository (default: %(default)s)")
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    ivs = [random_phone_intervals(rng, N_FRAMES) for _ in range(N_SEQ)]
    # first call in this process: loads (or, in a fresh environment, compiles) the numba
    # kernels and paints the texture
    _, first_cpu, first_wall = _timed(render.render_frames, face.reference_shape(128)[None])
    warp_reference.render_frames(face.reference_shape(128)[None])
    _warp.warp_piecewise_affine(np.zeros((4, 4)), np.zeros((3, 2)), np.zeros((3, 2)), np.array([[0, 1, 2]]), (4, 4))
    _warp.bilinear_sample(np.zeros((1, 4, 4)), None, np.zeros(1), np.zeros(1))

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
        "first_render_call_cpu_s": first_cpu,
        "first_render_call_wall_s": first_wall,
        "numpy_vs_numba": compare(lm),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "cpu_count": os.cpu_count(),
    }
    out = ROOT / args.out
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=out.parent, suffix=".tmp")
    with os.fdopen(fd, "w") as fh:
        json.dump(result, fh, indent=1)
        fh.write("\n")
    os.replace(tmp, out)
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
