"""AAM search: tracking speed and landmark error on a held-out built corpus.

A built corpus knows the true landmarks of every frame. The fitter is built from the
landmarks of the corpus's AAM prototype frames only (4 random frames per phone,
deena2010 §3.2, listed in its manifest), every other frame is tracked
(:meth:`AAMFitter.track`: each video from its annotated frames; a video without one is
searched from the mean pose), and the tracked landmarks are compared with the truth.

Reported: frames per second of tracking (goal >= 25) from CPU time of this process with
one BLAS thread (the machine is shared; wall time is reported too), landmark error
(Euclidean, pixels at 128x128) pooled over all points of all tracked frames (median, p95,
p99, max) and per frame, the error floor (true landmarks projected onto the shape model
and similarity: what a perfect fit of this AAM could reach), lost frames and the score
distribution. Side by side: ``AAM.project`` with the true landmarks (features of frames
whose landmarks are known, no search) as the per-frame cost floor.

Run: .venv/bin/python benchmarks/aam_fit.py [--corpus DIR] [--max-videos N]
     -> benchmarks/results/aam_fit.json
     .venv/bin/python benchmarks/aam_fit.py --quick    # the quick held-out corpus -> results/quick/
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bayes_talk.corpus import load_npz
from bayes_talk.features.aam_fit import AAMFitter
from benchmarks.common import bench_corpus, result_path, write_result


def _stats(x: np.ndarray) -> dict[str, float]:
    return {"median": float(np.median(x)), "p95": float(np.percentile(x, 95)),
            "p99": float(np.percentile(x, 99)), "max": float(np.max(x)), "mean": float(np.mean(x))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--corpus", type=Path, default=None, help="a built corpus (default: the suite's held-out corpus)")
    ap.add_argument("--quick", action="store_true", help="the quick held-out corpus")
    ap.add_argument("--max-videos", type=int, default=None)
    ap.add_argument("--out", type=Path, default=None, help="default benchmarks/results/aam_fit.json (--quick: results/quick/)")
    args = ap.parse_args()
    args.out = result_path("aam_fit", args.quick, args.out)
    args.corpus = args.corpus or bench_corpus("test", args.quick)
    root = args.corpus
    m = json.loads((root / "manifest.json").read_text())
    seqs = m["sequences"][: args.max_videos]
    protos: dict[str, list[int]] = {}
    for name, t in m["aam"]["prototypes"]:
        protos.setdefault(name, []).append(int(t))
    data = []
    for s in m["sequences"]:
        fr = load_npz(root / s["frames"], ("frames",))["frames"]
        lm = load_npz(root / s["landmarks"], ("landmarks",))["landmarks"]
        data.append((s["name"], fr, lm))
    imgs = np.stack([fr[t] for n, fr, _ in data for t in protos.get(n, [])])
    lms = np.stack([lm[t] for n, _, lm in data for t in protos.get(n, [])])

    with threadpool_limits(limits=1):
        t0, c0 = time.perf_counter(), time.process_time()
        fitter = AAMFitter.from_prototypes(imgs, lms, n_levels=2)
        build = {"wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0}
        data = data[: len(seqs)]
        errs, frame_err, scores, floor = [], [], [], []
        n_frames = n_tracked = 0
        lost, searched = {}, []
        load0 = os.getloadavg()
        t0, c0 = time.perf_counter(), time.process_time()
        results = []
        for name, fr, lm in data:
            ann = {t: lm[t] for t in protos.get(name, [])}
            if not ann:
                searched.append(name)
            results.append(fitter.track(fr, ann, where=name))
        track = {"wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0}
        load1 = os.getloadavg()
        t0, c0 = time.perf_counter(), time.process_time()
        for _, fr, lm in data:
            fitter.aam.project(fr, lm)
        proj = {"wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0}
    lv = fitter.levels[0]
    for (name, fr, lm), r in zip(data, results):
        n_frames += len(fr)
        tracked = np.array([s == "tracked" for s in r.source])
        n_tracked += int(tracked.sum())
        if r.lost:
            lost[name] = r.lost
        e = np.linalg.norm(r.landmarks[tracked] - lm[tracked], axis=2)
        errs.append(e.ravel())
        frame_err.append(e.mean(axis=1))
        scores.append(r.scores[tracked])
        floor.append(np.concatenate([np.linalg.norm(lv.project_shape(x) - x, axis=1) for x in lm[tracked]]))
    e, fe, sc, fl = (np.concatenate(x) for x in (errs, frame_err, scores, floor))
    out = {
        "what": "AAM search (project-out inverse compositional, 2-level pyramid) tracking a held-out "
                "built corpus from the landmarks of its AAM prototype frames (4 per phone) only",
        "corpus": str(root), "n_videos": len(data), "n_frames": n_frames,
        "n_annotated_frames": int(sum(len(protos.get(n, [])) for n, _, _ in data)),
        "n_tracked_frames": n_tracked, "videos_searched_without_annotation": searched,
        "lost_threshold": fitter.lost_threshold, "lost_frames": lost,
        "aam": {"n_shape_modes": fitter.aam.n_shape_modes, "n_texture_modes": fitter.aam.n_texture_modes,
                "n_combined": fitter.aam.n_combined, "n_pixels": fitter.aam.n_pixels,
                "levels": [{"n_pixels": lv.aam.n_pixels, "n_texture_modes": lv.aam.n_texture_modes}
                           for lv in fitter.levels]},
        "build_fitter": build,
        "track": dict(track, fps_cpu=n_frames / track["cpu_s"], fps_wall=n_frames / track["wall_s"]),
        "peer_project_known_landmarks": dict(proj, fps_cpu=n_frames / proj["cpu_s"],
                                             fps_wall=n_frames / proj["wall_s"]),
        "goal_fps": 25.0,
        "landmark_error_px_all_points_of_tracked_frames": _stats(e),
        "landmark_error_px_per_frame_mean": _stats(fe),
        "error_floor_px_shape_model_projection": _stats(fl),
        "acceptance": {"median_le_0.5": bool(np.median(e) <= 0.5),
                       "p95_le_1.5": bool(np.percentile(e, 95) <= 1.5)},
        "score_of_tracked_frames": _stats(sc),
        "machine": {"loadavg_start": load0, "loadavg_end": load1, "blas_threads": 1},
    }
    write_result(args.out, out)
    print(json.dumps({k: out[k] for k in ("n_frames", "track", "landmark_error_px_all_points_of_tracked_frames",
                                          "acceptance", "lost_frames")}, indent=1))


if __name__ == "__main__":
    main()
