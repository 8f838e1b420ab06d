"""``bayes-talk train`` wall time: this code beside the previous code, and their models compared
(issue 29 item 3).

Each run is the command line itself, ``python -m bayes_talk.app.cli train CORPUS --out DIR``
with its defaults (the default family, ``--workers 2``, the band calibration, the
aligner), started as a fresh process on a built corpus whose features are cached:

* ``new``: this source tree;
* ``previous``: the source tree of commit ``--baseline`` (default 16dc4a6, the branch point
  of issue 29), exported with ``git archive`` into a temporary directory (or ``--baseline-src``,
  a directory holding such a tree).

The runs alternate (previous, new, previous, new, ... for ``--repeats``) so that both see
the same machine load; ``os.getloadavg()`` is recorded around each, and the CPU time of
the train process and its worker processes (``RUSAGE_CHILDREN``), which other processes
on a shared machine disturb less than the wall time. Then the two saved
models are compared array by array (state models' hyperparameters, latents, entry
distributions; the band calibration's factors): the largest absolute and relative
differences, and whether they are equal bit for bit.

Run:  PYTHONPATH=. .venv/bin/python benchmarks/train_speed.py data/s8/train250 \
          [--repeats 1] [--baseline 16dc4a6] [--new-extra ARGS] [--out benchmarks/results/train_speed.json]
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

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"


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
    ap.add_argument("corpus")
    ap.add_argument("--baseline", default="16dc4a6", help="commit of the previous code")
    ap.add_argument("--baseline-src", default=None, help="a directory holding the previous source tree")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--model", default=None, help="--model for train (default: train's default family)")
    ap.add_argument("--extra", default="", help="further train arguments, e.g. '--no-alignment'")
    ap.add_argument("--new-extra", default="", help="train arguments for the new tree only, e.g. "
                    "'--calibrated-model holdout' (the previous code may not know them)")
    ap.add_argument("--out", default=str(RESULTS / "train_speed.json"))
    args = ap.parse_args(argv)
    corpus = str(Path(args.corpus).resolve())
    extra = args.extra.split() + (["--model", args.model] if args.model else [])
    new_extra = args.new_extra.split()
    runs: dict[str, list[dict]] = {"previous": [], "new": []}
    with tempfile.TemporaryDirectory(prefix="train_speed_") as tmp:
        tmp = Path(tmp)
        base = Path(args.baseline_src) if args.baseline_src else export_tree(args.baseline, tmp / "previous_src")
        trees = {"previous": base, "new": ROOT}
        for r in range(args.repeats):
            for name in ("previous", "new"):
                out = tmp / f"{name}_{r}"
                res = run_train(trees[name], corpus, out, extra + (new_extra if name == "new" else []), {})
                runs[name].append(res)
                print(name, r, res, flush=True)
        comparison = compare_models(tmp / "new_0", tmp / "previous_0")
    med = {k: float(np.median([x["wall_s"] for x in v])) for k, v in runs.items()}
    med_cpu = {k: float(np.median([x["cpu_s"] for x in v])) for k, v in runs.items()}
    result = {
        "benchmark": "train_speed", "issue": 29,
        "corpus": os.path.relpath(corpus, ROOT), "command": "bayes-talk train CORPUS --out DIR " + " ".join(extra),
        "new_extra": " ".join(new_extra),
        "baseline": args.baseline if not args.baseline_src else os.path.relpath(args.baseline_src, ROOT),
        "new_commit": subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                                     text=True, check=False).stdout.strip(),
        "runs": runs, "median_wall_s": med,
        "ratio_new_over_previous": round(med["new"] / med["previous"], 3),
        "speedup": round(med["previous"] / med["new"], 3),
        "median_cpu_s": med_cpu, "cpu_ratio_new_over_previous": round(med_cpu["new"] / med_cpu["previous"], 3),
        "models_compared": comparison,
        "machine": {"cpus": os.cpu_count()},
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    tmp_out = Path(args.out).with_suffix(".json.tmp")
    tmp_out.write_text(json.dumps(result, indent=1) + "\n", encoding="utf-8")
    os.replace(tmp_out, args.out)
    print(json.dumps({k: result[k] for k in ("median_wall_s", "ratio_new_over_previous", "speedup")}, indent=1))
    return result


if __name__ == "__main__":
    from bayes_talk.base.executor import interruptible

    # `kill` stops the worker processes too, not only this one
    sys.exit(0 if interruptible(main) else 1)
