"""How long ``bayes-talk train`` takes, and where the time goes; optionally beside a previous
commit's code, the two models compared.

Each run is the command line itself, ``python -m bayes_talk.app.cli train CORPUS --out DIR``
with its defaults (the default family, ``--workers 2``, the band calibration, the
aligner), started as a fresh process on a built corpus whose features are cached:

* ``new``: this source tree;
* ``previous`` (with ``--baseline COMMIT``): the source tree of that commit, exported with
  ``git archive`` into a temporary directory (or ``--baseline-src``, a directory holding such a tree).

The runs alternate (previous, new, previous, new, ... for ``--repeats``) so that both see
the same machine load; ``os.getloadavg()`` is recorded around each, and the CPU time of
the train process and its worker processes (``RUSAGE_CHILDREN``), which other processes
on a shared machine disturb less than the wall time. Then the two saved
models are compared array by array (state models' hyperparameters, latents, entry
distributions; the band calibration's factors): the largest absolute and relative
differences, and whether they are equal bit for bit.

Then where the time goes (unless ``--no-profile``): one more ``pipeline.train`` with the same defaults, in
this process under cProfile, and the cumulative seconds of the library functions that make up
its phases (:data:`PHASES`: feature loading, the state models' fits and their L-BFGS, the band
calibration and its syntheses, the aligner, saving), read from the profile (the library is not
changed; cProfile slows Python-heavy code, so read the shares, not the seconds).

Run:  PYTHONPATH=. .venv/bin/python benchmarks/train_speed.py data/train250 \
          [--repeats 1] [--baseline COMMIT | --baseline none] [--new-extra ARGS] [--no-profile]
          [--out benchmarks/results/train_speed.json]
      PYTHONPATH=. .venv/bin/python benchmarks/train_speed.py --quick   # the quick corpus
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import QUICK_MODEL, ROOT, bench_corpus, result_path, write_result

#: phase -> the library functions whose cumulative time in the profile is that phase's
PHASES = {
    "features_load": ("bayes_talk/corpus/load.py", "load_corpus"),
    "state_fits": ("bayes_talk/models/switching.py", "fit_state"),
    "state_lbfgs": ("bayes_talk/models/sgpdm.py", "_optimise"),
    "band_calibration": ("bayes_talk/calibration/bands.py", "calibrated_fit"),
    "calibration_synthesis": ("bayes_talk/posterior/sampling.py", "sample_synthesis"),
    "alignment": ("bayes_talk/alignment/commands.py", "fit_alignment"),
    "bundle_manifest": ("bayes_talk/base/bundle.py", "write_bundle_manifest"),
}


def profile_train(corpus: str, model: str | None, workers: int, overrides: dict | None = None) -> dict:
    """``pipeline.train`` with its defaults (and the model settings ``overrides``) in this process
    under cProfile: wall time and the cumulative seconds and calls of each phase's function
    (:data:`PHASES`)."""
    import cProfile
    import pstats

    from bayes_talk import pipeline

    prof = cProfile.Profile()
    with tempfile.TemporaryDirectory(prefix="train_profile_") as tmp:
        t0 = time.perf_counter()
        prof.enable()
        pipeline.train(corpus, model or pipeline.DEFAULT_MODEL, Path(tmp) / "model", workers=workers,
                       calibrate_bands=pipeline.DEFAULT_CALIBRATION, **(overrides or {}))
        prof.disable()
        wall = time.perf_counter() - t0
    stats = pstats.Stats(prof).stats
    phases = {}
    for name, (path, fn) in PHASES.items():
        rows = [(nc, ct) for (f, _, func), (_, nc, _, ct, _) in stats.items() if func == fn and f.endswith(path)]
        phases[name] = {"cumulative_s": round(sum(ct for _, ct in rows), 2), "calls": int(sum(nc for nc, _ in rows)),
                        "share": round(sum(ct for _, ct in rows) / wall, 3) if wall > 0 else None}
    top = sorted(({"function": f"{os.path.relpath(f, ROOT) if f.startswith(str(ROOT)) else os.path.basename(f)}"
                                f":{line}({func})", "calls": nc, "tottime_s": round(tt, 3), "cumtime_s": round(ct, 3)}
                  for (f, line, func), (_, nc, tt, ct, _) in stats.items()), key=lambda r: -r["tottime_s"])[:30]
    return {"workers": workers, "model_settings": overrides or "defaults", "wall_s_under_cprofile": round(wall, 2), "phases": phases, "top_by_own_time": top,
            "note": "state_lbfgs runs inside state_fits, and the calibration's syntheses inside "
                    "band_calibration; with workers > 1 the per-state fits run in worker processes "
                    "and are not seen by the profile"}


def export_tree(commit: str, dest: Path) -> Path:
    """The source tree of ``commit`` (``git archive``) unpacked into ``dest``."""
    dest.mkdir(parents=True, exist_ok=True)
    tar = dest / "src.tar"
    subprocess.run(["git", "-C", str(ROOT), "archive", "--format=tar", "-o", str(tar), commit], check=True)
    with tarfile.open(tar) as t:
        t.extractall(dest, filter="data")
    tar.unlink()
    return dest


def run_train(src: Path, corpus: str, out: Path, extra: list[str], env_extra: dict[str, str]) -> dict:
    """One ``bayes-talk train`` from the tree ``src``: wall time and load around it."""
    env = dict(os.environ, PYTHONPATH=str(src), **env_extra)
    cmd = [sys.executable, "-m", "bayes_talk.app.cli", "-q", "train", corpus, "--out", str(out), *extra]
    load0 = os.getloadavg()
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, cwd=str(src), capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    load1 = os.getloadavg()
    if proc.returncode != 0:
        raise RuntimeError(f"train from {src} failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    cpu = (r1.ru_utime + r1.ru_stime) - (r0.ru_utime + r0.ru_stime)  # the train process and its workers
    return {"wall_s": round(wall, 2), "cpu_s": round(cpu, 2), "loadavg_before": [round(x, 2) for x in load0],
            "loadavg_after": [round(x, 2) for x in load1]}


def compare_models(a: Path, b: Path) -> dict:
    """Array-by-array differences between two trained switching-model directories (and their
    calibrations), read by ``load_trained`` whatever layout each was saved in."""
    from bayes_talk.pipeline import load_trained

    ta, tb = load_trained(a), load_trained(b)
    (ma, za), (mb, zb) = ta.uncalibrated.state(), tb.uncalibrated.state()
    out: dict = {"same_keys": sorted(za) == sorted(zb)}
    groups: dict[str, dict] = {}
    for k in sorted(set(za) & set(zb)):
        x, y = np.asarray(za[k], dtype=np.float64), np.asarray(zb[k], dtype=np.float64)
        name = k.split("/", 1)[1] if "/" in k else k
        g = groups.setdefault(name, {"n": 0, "equal": 0, "max_abs": 0.0, "max_rel": 0.0})
        g["n"] += 1
        if x.shape != y.shape:
            g["max_abs"] = float("inf")
            continue
        g["equal"] += int(np.array_equal(x, y))
        d = np.abs(x - y)
        g["max_abs"] = max(g["max_abs"], float(d.max(initial=0.0)))
        g["max_rel"] = max(g["max_rel"], float((d / np.maximum(np.abs(y), 1e-300)).max(initial=0.0)))
    out["arrays"] = groups
    out["same_states"] = [e["state"] for e in ma["models"]] == [e["state"] for e in mb["models"]]
    if ta.calibration is not None and tb.calibration is not None:
        ja, jb = ta.calibration.to_dict(), tb.calibration.to_dict()
        sa, sb = np.asarray(ja["scale"]), np.asarray(jb["scale"])
        out["band_calibration"] = {
            "scale_equal": bool(np.array_equal(sa, sb)),
            "scale_max_rel": float((np.abs(sa - sb) / sb).max()),
            "coverage_calibrated": {"new": ja["coverage_calibrated"], "previous": jb["coverage_calibrated"]},
            "coverage_raw": {"new": ja["coverage_raw"], "previous": jb["coverage_raw"]}}
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("corpus", nargs="?", default=None, help="a built corpus (default: the suite's training corpus)")
    ap.add_argument("--baseline", default="none", help="commit of the previous code to time beside this tree "
                    "('none': this tree only)")
    ap.add_argument("--baseline-src", default=None, help="a directory holding the previous source tree")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--model", default=None, help="--model for train (default: train's default family)")
    ap.add_argument("--extra", default="", help="further train arguments, e.g. '--no-alignment'")
    ap.add_argument("--new-extra", default="", help="train arguments for the new tree only, e.g. "
                    "'--calibrated-model holdout' (the previous code may not know them)")
    ap.add_argument("--no-profile", action="store_true", help="skip the profiled in-process train (the phases)")
    ap.add_argument("--profile-workers", type=int, default=1, help="workers of the profiled train (1: all seen)")
    ap.add_argument("--quick", action="store_true", help="the quick corpus; the profiled train with the "
                    "quick mode's small model settings")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    args.corpus = args.corpus or str(bench_corpus("train", args.quick))
    args.profile = not args.no_profile
    args.out = result_path("train_speed", args.quick, args.out)
    corpus = str(Path(args.corpus).resolve())
    with_baseline = args.baseline != "none" or args.baseline_src is not None
    extra = args.extra.split() + (["--model", args.model] if args.model else [])
    new_extra = args.new_extra.split()
    runs: dict[str, list[dict]] = {"previous": [], "new": []}
    with tempfile.TemporaryDirectory(prefix="train_speed_") as tmp:
        tmp = Path(tmp)
        trees = {"new": ROOT}
        if with_baseline:
            trees["previous"] = (Path(args.baseline_src) if args.baseline_src
                                 else export_tree(args.baseline, tmp / "previous_src"))
        else:
            del runs["previous"]
        for r in range(args.repeats):
            for name in [n for n in ("previous", "new") if n in trees]:
                out = tmp / f"{name}_{r}"
                res = run_train(trees[name], corpus, out, extra + (new_extra if name == "new" else []), {})
                runs[name].append(res)
                print(name, r, res, flush=True)
        comparison = compare_models(tmp / "new_0", tmp / "previous_0") if with_baseline else None
    med = {k: float(np.median([x["wall_s"] for x in v])) for k, v in runs.items()}
    med_cpu = {k: float(np.median([x["cpu_s"] for x in v])) for k, v in runs.items()}
    result = {
        "corpus": os.path.relpath(corpus, ROOT), "train_command": "bayes-talk train CORPUS --out DIR " + " ".join(extra),
        "new_extra": " ".join(new_extra),
        "baseline": (None if not with_baseline else args.baseline if not args.baseline_src
                     else os.path.relpath(args.baseline_src, ROOT)),
        "runs": runs, "median_wall_s": med, "median_cpu_s": med_cpu,
    }
    if with_baseline:
        result.update(ratio_new_over_previous=round(med["new"] / med["previous"], 3),
                      speedup=round(med["previous"] / med["new"], 3),
                      cpu_ratio_new_over_previous=round(med_cpu["new"] / med_cpu["previous"], 3),
                      models_compared=comparison)
    write_result(args.out, result)
    if args.profile:
        print("profiling one in-process train ...", flush=True)
        result["profile"] = profile_train(corpus, args.model, args.profile_workers,
                                          QUICK_MODEL if args.quick else None)
        write_result(args.out, result)
    print(json.dumps({k: result.get(k) for k in ("median_wall_s", "ratio_new_over_previous", "speedup")}, indent=1))
    if args.profile:
        print(json.dumps(result["profile"]["phases"], indent=1))
    return result


if __name__ == "__main__":
    from bayes_talk.base.executor import interruptible

    # `kill` stops the worker processes too, not only this one
    sys.exit(0 if interruptible(main) else 1)
