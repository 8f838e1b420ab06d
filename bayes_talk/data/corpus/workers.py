"""Worker processes of the corpus build (speech + face + frames per utterance) and load
(MFCC + AAM projection per utterance), and the per-utterance tasks they run."""
from __future__ import annotations

import contextlib
import json
import os
import queue
import subprocess
import sys
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Self

import numpy as np

from bayes_talk.data.corpus.format import (
    _MIN_ITEMS_FOR_WORKERS,
    FORMAT_VERSION,
    FPS,
    renderer_settings,
    save_npz,
)
from bayes_talk.data.corpus.layouts import _Item, _load_visual
from bayes_talk.data.labels import frame_labels, write_lab
from bayes_talk.features.mfcc import FMAX_HZ, frame_count, load_wav, mfcc

#
# Parallel work goes to persistent fresh interpreters started with ``subprocess`` (not
# ``multiprocessing``: ``spawn`` re-imports the caller's ``__main__``, which breaks
# scripts without an ``if __name__ == "__main__"`` guard, and ``fork`` copies the
# caller's threads). Each worker runs with one BLAS/OpenMP thread (environment set
# before it starts): with two processes on two cores, multi-threaded BLAS only adds
# contention (measured: a 70x5635 @ 5635x97 product took 0.28 s with 2 OpenBLAS threads
# under load, 0.002-0.01 s with 1). The parent runs its own numerical work with one BLAS
# thread too (threadpoolctl), so results do not depend on where a task ran.
# Protocol: a JSON header line, then the raw bytes of the arrays it lists.

_BLAS_ENV = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
             "NUMEXPR_NUM_THREADS": "1", "VECLIB_MAXIMUM_THREADS": "1"}
_WORKER_PROGRAM = "from bayes_talk.data.corpus.workers import _worker_main; _worker_main()"


@contextlib.contextmanager
def _single_thread_blas() -> Iterator[None]:
    """One BLAS/OpenMP thread inside the block (no-op without threadpoolctl)."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - threadpoolctl comes with scikit-learn/librosa
        yield
        return
    with threadpool_limits(limits=1):
        yield


def _send(stream, header: dict, arrays: dict[str, np.ndarray] | None = None) -> None:
    arrays = {k: np.ascontiguousarray(v) for k, v in (arrays or {}).items()}
    header = dict(header, arrays=[[k, v.dtype.str, list(v.shape)] for k, v in arrays.items()])
    stream.write(json.dumps(header).encode("utf-8") + b"\n")
    for v in arrays.values():
        stream.write(v.tobytes())
    stream.flush()


def _recv(stream) -> tuple[dict, dict[str, np.ndarray]] | None:
    line = stream.readline()
    if not line:
        return None
    header = json.loads(line.decode("utf-8"))
    arrays = {}
    for name, dt, shape in header.pop("arrays", []):
        dtype = np.dtype(dt)
        n = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
        buf = stream.read(n)
        if len(buf) != n:
            return None
        arrays[name] = np.frombuffer(buf, dtype=dtype).reshape(shape).copy()
    return header, arrays


_EXC_TYPES = {"ValueError": ValueError, "FileExistsError": FileExistsError,
              "KeyError": KeyError, "FileNotFoundError": FileNotFoundError}


class _Workers:
    """``n`` persistent worker processes; :meth:`map` runs tasks on them in order."""

    def __init__(self, n: int) -> None:
        import bayes_talk

        pkg_root = str(Path(bayes_talk.__file__).resolve().parent.parent)
        env = dict(os.environ, **_BLAS_ENV)
        env["PYTHONPATH"] = os.pathsep.join([pkg_root] + [p for p in
                                            env.get("PYTHONPATH", "").split(os.pathsep) if p])
        self._procs: list[subprocess.Popen] = []
        self._free: queue.SimpleQueue = queue.SimpleQueue()
        try:
            for _ in range(n):
                p = subprocess.Popen([sys.executable, "-c", _WORKER_PROGRAM], env=env,
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE)
                self._procs.append(p)
                self._free.put(p)
        except BaseException:
            self.close()
            raise

    def _call(self, op: str, args: dict) -> tuple[dict, dict[str, np.ndarray]]:
        p = self._free.get()
        try:
            _send(p.stdin, {"op": op, "args": args})
            got = _recv(p.stdout)
        except (BrokenPipeError, OSError):
            got = None
        if got is None:
            code = p.poll()
            raise RuntimeError(f"corpus worker process died during {op!r} (exit code {code}); "
                               "see its messages above")
        self._free.put(p)
        head, arrays = got
        if "error" in head:
            raise _EXC_TYPES.get(head.get("type"), RuntimeError)(head["error"])
        return head, arrays

    def map(self, op: str, tasks: list[dict]) -> list[tuple[dict, dict[str, np.ndarray]]]:
        from bayes_talk.progress import bar

        ex = ThreadPoolExecutor(max_workers=max(1, len(self._procs)))
        try:
            futures = [ex.submit(self._call, op, a) for a in tasks]
            return [f.result() for f in bar(futures, len(futures), _PROGRESS.get(op, op), "utt")]
        finally:  # on an error, do not start the remaining tasks
            ex.shutdown(wait=True, cancel_futures=True)

    def close(self) -> None:
        for p in self._procs:
            with contextlib.suppress(OSError):
                p.stdin.close()
        for p in self._procs:
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:  # pragma: no cover
                p.kill()
                p.wait()
            with contextlib.suppress(OSError):
                p.stdout.close()
        self._procs = []

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _n_workers(n_workers: int | None, n_tasks: int) -> int:
    if n_workers is None:
        return 2 if n_tasks >= _MIN_ITEMS_FOR_WORKERS else 1
    if int(n_workers) < 1:
        raise ValueError(f"n_workers: expected >= 1 or None, found {n_workers}")
    return int(n_workers)


def _run_tasks(fn: Callable[[dict], tuple[dict, dict]], op: str, tasks: list[dict],
               n_workers: int) -> list[tuple[dict, dict[str, np.ndarray]]]:
    """``[fn(t) for t in tasks]``, in ``n_workers`` worker processes when > 1 (with a
    progress bar on a terminal, bayes_talk.progress)."""
    from bayes_talk.progress import bar

    if n_workers > 1 and len(tasks) > 1:
        with _Workers(min(n_workers, len(tasks))) as w:
            return w.map(op, tasks)
    with _single_thread_blas():
        return [fn(t) for t in bar(tasks, len(tasks), _PROGRESS.get(op, op), "utt")]


_PROGRESS = {"utterance": "building utterances", "features": "featurising"}


def _worker_main() -> None:
    """Serve tasks on stdin/stdout until stdin closes (see :class:`_Workers`).

    Ctrl-C is the parent's to handle (it closes our stdin): ignored here, so a worker
    never prints a KeyboardInterrupt traceback."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)            # stray prints from libraries go to stderr, not the protocol
    sys.stdout = sys.stderr
    inp = sys.stdin.buffer
    ops = {"utterance": _utterance_task, "features": _features_task}
    with _single_thread_blas():
        while True:
            got = _recv(inp)
            if got is None:
                break
            head, _ = got
            try:
                res_head, res_arrays = ops[head["op"]](head["args"])
            except Exception as exc:  # noqa: BLE001 - re-raised by the parent
                _send(out, {"error": str(exc), "type": type(exc).__name__})
                continue
            _send(out, res_head, res_arrays)


def _utterance_task(a: dict) -> tuple[dict, dict]:
    """Synthesise utterance ``a["index"]``, drive and render the face, write its files."""
    from bayes_talk.data.face import face_landmarks
    from bayes_talk.data.render import render_frames
    from bayes_talk.data.speech import SpeechRequest, write_wav
    from bayes_talk.data.speech import _worker as synthesize_fresh

    out_dir, i, seed, image_size = Path(a["out_dir"]), int(a["index"]), int(a["seed"]), int(a["image_size"])
    res = synthesize_fresh(SpeechRequest(**a["request"]))
    sr = res.sample_rate
    n_samples = int(res.samples.shape[0])
    T = frame_count(n_samples, sr, FPS)
    # the file of record is the .lab (100 ns grid): drive the face from the same times
    intervals = [(round(s * 1e7) / 1e7, round(e * 1e7) / 1e7, p) for s, e, p in res.intervals]
    rng = np.random.default_rng([seed, i, 1])
    lm = face_landmarks(intervals, T, fps=FPS, image_size=image_size, rng=rng)
    frames = render_frames(lm, image_size=image_size, **renderer_settings(FORMAT_VERSION))
    name = f"utt{i:04d}"
    rel = {k: f"utterances/{name}{ext}" for k, ext in
           (("wav", ".wav"), ("lab", ".lab"), ("landmarks", ".landmarks.npz"),
            ("frames", ".frames.npz"))}
    write_wav(out_dir / rel["wav"], res.samples, sr)
    write_lab(out_dir / rel["lab"], intervals)
    save_npz(out_dir / rel["landmarks"], landmarks=np.asarray(lm, dtype=np.float64))
    save_npz(out_dir / rel["frames"], frames=np.asarray(frames, dtype=np.uint8))
    head = {"name": name, "sample_rate": int(sr), "n_samples": n_samples, "n_frames": int(T),
            "n_landmarks": int(lm.shape[1]), "labels": frame_labels(intervals, T, FPS),
            "rel": rel}
    return head, {}


_AAM_CACHE: dict[str, tuple[bytes, object]] = {}


def _cached_aam(path: str):
    from bayes_talk.features.aam import AAM

    stamp = Path(path).with_suffix(".json").read_bytes()
    hit = _AAM_CACHE.get(path)
    if hit is None or hit[0] != stamp:
        hit = (stamp, AAM.load(path))
        _AAM_CACHE[path] = hit
    return hit[1]


def _features_task(a: dict) -> tuple[dict, dict]:
    """MFCC and visual features (AAM parameters) of one item."""
    it = _Item(a["name"], Path(a["wav"]), Path(a["labels"]), int(a["n_frames"]), [],
               visual=None if a["visual"] is None else Path(a["visual"]),
               landmarks=None if a["landmarks"] is None else Path(a["landmarks"]),
               features=None if a["features"] is None else Path(a["features"]))
    y, sr = load_wav(it.wav)
    mf = mfcc(y, sr, it.n_frames, fps=FPS, where=str(it.wav), fmax=a.get("fmax", FMAX_HZ))
    frames, lm, feats = _load_visual(it)
    if feats is not None:
        vis = feats
    else:
        vis = np.asarray(_cached_aam(a["aam"]).project(frames, lm), np.float64)
    return {}, {"mfcc": mf, "visual": vis}

