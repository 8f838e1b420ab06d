"""The built-in talking-head corpus and the user-corpus loader (DESIGN.md §8).

Built corpus (:func:`build_corpus`), a self-describing directory::

    OUT_DIR/
      manifest.json                 format, version, fps, audio rate, phone set, image size,
                                    seed, voice, AAM files + prototype frames, sequences,
                                    and the list of every file the build wrote
      utterances/utt0000.wav        16-bit mono PCM, 22050 Hz, length = whole frames
      utterances/utt0000.lab        HTK phone segmentation (100 ns units), ARPAbet 39 + sil
      utterances/utt0000.landmarks.npz   "landmarks": (T, P, 2) float64 pixels (x, y)
      utterances/utt0000.frames.npz      "frames": (T, H, W) uint8 grayscale, deflated
      aam*                          the AAM learned from prototype frames (AAM.save)
      features.npz                  cache written by load_corpus (not part of the build)

Reproducibility: speech is synthesised one utterance per fresh process (see
:mod:`bayes_talk.data.speech`); every random draw comes from ``np.random.default_rng``
seeded with ``[seed, utterance_index, stream]``; ``.npz`` files are written by
:func:`save_npz`, which pins every zip member's timestamp to 1980-01-01 (verified: with
Python 3.11 and numpy 2.4, ``np.savez_compressed`` also writes that fixed stamp, because
``ZipFile.open(name, "w")`` uses the ``ZipInfo`` default; ``save_npz`` makes it explicit
rather than relying on that detail) -- so the same arguments give a byte-identical
directory, and utterance i does not depend on ``n_utterances``.

Random streams: utterance i's rate/pitch jitter ``[seed, i]``; its face ``[seed, i, 1]``;
the AAM prototype choice ``[seed, 2**31]``.

Speed: utterances are built end to end (speech, face, frames, files) and featurised
(MFCC, AAM projection) in worker processes with one BLAS thread each (see the section
"worker processes" below); nothing depends on which process did the work.

AAM prototypes (deena2010 §3.2: 4 random frames per phoneme + 1 silence frame): up to
``AAM_FRAMES_PER_PHONE`` frames drawn at random (without replacement) among the frames
whose majority-vote label is that phone, for every phone present, ``sil`` included.

See ``docs/data.md`` for the user-corpus layout read by :func:`load_corpus`.
"""
from __future__ import annotations

import contextlib
import hashlib
import importlib.resources
import json
import logging
import os
import queue
import subprocess
import sys
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Self

import numpy as np

from bayes_talk.data.checks import LABEL_TOLERANCE_S
from bayes_talk.data.labels import frame_labels, read_labels, write_lab
from bayes_talk.data.phones import PHONE_INDEX, PHONES
from bayes_talk.data.sequence import Sequence
from bayes_talk.features.mfcc import FMAX_HZ, frame_count, load_wav, mfcc, samples_per_frame
from bayes_talk.files import sha256_file, write_json, write_npz

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "FPS",
    "Corpus",
    "build_corpus",
    "load_corpus",
    "load_npz",
    "load_sentences",
    "save_npz",
]

log = logging.getLogger(__name__)

FORMAT_NAME = "bayes_talk-corpus"
#: 2: frames rendered with camera area integration and optics (render.RENDER_SUPERSAMPLE,
#: render.CAMERA_PSF_PX, recorded in the manifest's "renderer"); 1: point-sampled
#: frames. The file layout is the same, so both are read.
FORMAT_VERSION = 2
_READABLE_VERSIONS = (1, 2)
FPS = 25.0
AAM_FRAMES_PER_PHONE = 4
AAM_VARIANCE = 0.99
#: texture pixels of the corpus AAM lie at least this far (px) inside the mean-shape hull
#: (``AAM.fit(texture_inset=...)``): the outermost ring straddles the face outline and
#: samples the background, which alone doubled the number of modes (docs/data.md)
AAM_TEXTURE_INSET = 1.0
#: default ``n_workers=None``: 2 worker processes from this many utterances on, else
#: none (a worker's start-up, ~1-3 s of imports, outweighs the gain on small jobs)
_MIN_ITEMS_FOR_WORKERS = 16
#: bump when the derived features (MFCC settings, label rule, AAM projection) change
FEATURE_VERSION = 1
_CACHE_NAME = "features.npz"
_MANIFEST = "manifest.json"
_ZIP_DATE = (1980, 1, 1, 0, 0, 0)
_LABEL_TOL_S = LABEL_TOLERANCE_S  # one tolerance for the corpus and synthesis (bayes_talk.data.checks)
_VIDEO_EXT = (".mp4", ".avi", ".mov", ".mkv", ".webm")
_IMAGE_EXT = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


# ---------------------------------------------------------------------------------------
# deterministic .npz and JSON
# ---------------------------------------------------------------------------------------

def save_npz(path: str | Path, compress: bool = True, **arrays: np.ndarray) -> None:
    """Byte-deterministic ``.npz`` (see :func:`bayes_talk.files.write_npz`), compressed by default."""
    write_npz(path, arrays, compress=compress)


def load_npz(path: str | Path, keys: tuple[str, ...] = ()) -> dict[str, np.ndarray]:
    """Read an ``.npz`` (no pickle); error naming the file if unreadable or a key is missing."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            out = {k: z[k] for k in z.files}
    except Exception as exc:
        raise ValueError(f"{path}: cannot read .npz ({exc})") from exc
    for k in keys:
        if k not in out:
            raise ValueError(f"{path}: expected array {k!r}, found {sorted(out)}")
    return out


def _write_json(path: Path, obj: dict) -> None:
    write_json(path, obj, sort_keys=True)


_sha256 = sha256_file


# ---------------------------------------------------------------------------------------
# worker processes (build: speech + face + frames per utterance; load: MFCC + AAM)
# ---------------------------------------------------------------------------------------
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
_WORKER_PROGRAM = "from bayes_talk.data.corpus import _worker_main; _worker_main()"


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


def renderer_settings(format_version: int) -> dict:
    """How the frames of a built corpus of ``format_version`` were rendered: keyword
    arguments of :func:`~bayes_talk.data.render.render_frames` (a version-1 manifest has
    no "renderer" entry: point sampling, ideal lens)."""
    from bayes_talk.data import render

    if int(format_version) < 2:
        return {"supersample": 1, "psf_px": 0.0}
    return {"supersample": int(render.RENDER_SUPERSAMPLE), "psf_px": float(render.CAMERA_PSF_PX)}


# ---------------------------------------------------------------------------------------
# sentences
# ---------------------------------------------------------------------------------------

def load_sentences(sentences: str | Path | list[str] | None, n: int) -> list[str]:
    """The first ``n`` sentences, in order, from a file (one a line; blank lines skipped),
    a list, or the built-in list (``bayes_talk/data/sentences.txt``, None).

    ValueError if there are fewer than ``n`` or one is repeated among the first ``n``.
    """
    if sentences is None:
        src = "bayes_talk/data/sentences.txt"
        text = importlib.resources.files("bayes_talk.data").joinpath("sentences.txt").read_text("utf-8")
        lines = text.splitlines()
    elif isinstance(sentences, (str, Path)):
        src = str(sentences)
        try:
            lines = Path(sentences).read_text(encoding="utf-8").splitlines()
        except (OSError, UnicodeDecodeError) as exc:
            raise ValueError(f"{src}: cannot read sentence file ({exc})") from exc
    else:
        src = "sentences list"
        lines = [str(s) for s in sentences]
    items = [(i + 1, ln.strip()) for i, ln in enumerate(lines) if ln.strip()]
    if len(items) < n:
        raise ValueError(f"{src}: {n} utterances requested but only {len(items)} sentences found")
    seen: dict[str, int] = {}
    for lineno, s in items[:n]:
        key = " ".join(s.lower().split())
        if key in seen:
            raise ValueError(f"{src}: line {lineno} repeats line {seen[key]} ({s!r}); "
                             "sentences must be distinct within a corpus")
        seen[key] = lineno
    return [s for _, s in items[:n]]


# ---------------------------------------------------------------------------------------
# build
# ---------------------------------------------------------------------------------------

def _check_out_dir(out_dir: Path, force: bool) -> set[str]:
    """Refuse a non-empty dir unless force; return files a previous build listed (ours)."""
    if out_dir.exists() and not out_dir.is_dir():
        raise ValueError(f"{out_dir}: exists and is not a directory")
    if not out_dir.exists() or not any(out_dir.iterdir()):
        return set()
    if not force:
        raise FileExistsError(
            f"{out_dir}: directory is not empty; refusing to build a corpus into it "
            "(pass --force to overwrite the corpus files there)"
        )
    old = out_dir / _MANIFEST
    try:
        m = json.loads(old.read_text(encoding="utf-8"))
        if m.get("format") == FORMAT_NAME:
            return {f for f in m.get("files", []) if isinstance(f, str)}
    except (OSError, ValueError):
        pass
    return set()


def _prototype_frames(labels: list[list[str]], rng: np.random.Generator,
                      per_phone: int) -> list[tuple[int, int]]:
    """(sequence, frame) pairs: up to ``per_phone`` random frames of each phone present."""
    by_phone: dict[str, list[tuple[int, int]]] = {}
    for s, labs in enumerate(labels):
        for t, lab in enumerate(labs):
            by_phone.setdefault(lab, []).append((s, t))
    chosen: list[tuple[int, int]] = []
    for p in PHONES:  # fixed order -> fixed sequence of draws
        cands = by_phone.get(p)
        if not cands:
            continue
        k = min(per_phone, len(cands))
        idx = rng.choice(len(cands), size=k, replace=False)
        chosen.extend(cands[i] for i in sorted(idx))
    return sorted(chosen)


def _snapshot(d: Path) -> dict[str, tuple[int, int]]:
    return {str(p.relative_to(d)): (p.stat().st_size, p.stat().st_mtime_ns)
            for p in d.rglob("*") if p.is_file()}


def build_corpus(
    out_dir: str | Path,
    n_utterances: int = 300,
    seed: int = 0,
    sentences: str | Path | list[str] | None = None,
    voice: str = "en",
    image_size: int = 128,
    force: bool = False,
    *,
    n_workers: int | None = None,
    aam_frames_per_phone: int = AAM_FRAMES_PER_PHONE,
    rate: int | None = None,
    pitch: int | None = None,
) -> Path:
    """Synthesise speech, faces and frames into ``out_dir`` and learn an AAM; return the path.

    ``out_dir`` must be empty or absent unless ``force``; with ``force`` the corpus files
    are overwritten and files listed in a previous manifest of ours but not produced now
    are removed -- nothing else is deleted. ``manifest.json`` is written last, so a
    directory without it is an incomplete build.

    ``n_workers`` worker processes (one BLAS thread each; None: 2 from 16 utterances on,
    else 1 = in this process) each take whole utterances: speech in a fresh espeak-ng
    process, face, frames, files -- so one renders while the other waits for speech. The
    output does not depend on ``n_workers``.

    ``rate`` (words/min) and ``pitch`` (0-100): the centre of the per-utterance jitter
    (None: espeak's defaults, 175 and 50) -- e.g. a held-out voice outside the training range.
    """
    from bayes_talk.data.text_check import check_pronounceable, check_voice

    out_dir = Path(out_dir)
    if int(n_utterances) < 1:
        raise ValueError(f"n_utterances: expected >= 1, found {n_utterances}")
    if int(seed) < 0:
        raise ValueError(f"seed: expected an integer >= 0, found {seed}")
    check_voice(voice)
    workers = _n_workers(n_workers, int(n_utterances))
    if int(image_size) < 32:
        raise ValueError(f"image_size: expected >= 32 pixels, found {image_size}")
    texts = load_sentences(sentences, int(n_utterances))
    check_pronounceable(texts, voice, str(sentences) if isinstance(sentences, (str, Path)) else "sentences")
    previous = _check_out_dir(out_dir, force)
    created = _CreatedFiles(out_dir)
    try:
        return _build(out_dir, texts, seed, voice, image_size, previous, workers, aam_frames_per_phone,
                      int(n_utterances), rate, pitch)
    except BaseException:
        created.remove()
        raise


class _CreatedFiles:
    """Files and directories under ``out_dir`` that did not exist when created; :meth:`remove`
    deletes them again (a build that failed before writing its manifest is unusable)."""

    def __init__(self, out_dir: Path) -> None:
        self.out_dir = out_dir
        self.existed = out_dir.exists()
        self.before = {p for p in out_dir.rglob("*")} if self.existed else set()

    def remove(self) -> None:
        import shutil

        if not self.out_dir.exists() or (self.out_dir / _MANIFEST).exists():
            return
        if not self.existed:
            shutil.rmtree(self.out_dir, ignore_errors=True)
            return
        new = sorted((p for p in self.out_dir.rglob("*") if p not in self.before),
                     key=lambda p: len(p.parts), reverse=True)
        for p in new:
            if p.is_dir():
                shutil.rmtree(p, ignore_errors=True)
            elif p.exists():
                p.unlink()
        log.info("%s: removed the %d files of the failed build", self.out_dir, len(new))


def _build(out_dir: Path, texts: list[str], seed: int, voice: str, image_size: int, previous: set[str],
           workers: int, aam_frames_per_phone: int, n_utterances: int, rate: int | None,
           pitch: int | None) -> Path:
    """The body of :func:`build_corpus` after its checks."""
    from bayes_talk.data.speech import DEFAULT_PITCH, DEFAULT_RATE, jittered_requests
    from bayes_talk.features.aam import AAM

    udir = out_dir / "utterances"
    udir.mkdir(parents=True, exist_ok=True)
    old_manifest = out_dir / _MANIFEST
    if old_manifest.exists():  # an incomplete rebuild must not look complete
        old_manifest.unlink()

    requests = jittered_requests(texts, seed, voice=voice, fps=FPS,
                                 rate=DEFAULT_RATE if rate is None else int(rate),
                                 pitch=DEFAULT_PITCH if pitch is None else int(pitch))
    tasks = [{"out_dir": str(out_dir), "index": i, "seed": int(seed), "image_size": int(image_size),
              "request": {"text": r.text, "voice": r.voice, "rate": int(r.rate),
                          "pitch": int(r.pitch), "lead_silence": r.lead_silence,
                          "trail_silence": r.trail_silence, "fps": r.fps}}
             for i, r in enumerate(requests)]
    # every utterance end to end (fresh espeak process, face, frames, files) in a worker:
    # one worker renders while the other waits for its speech
    results = _run_tasks(_utterance_task, "utterance", tasks, workers)
    written: list[str] = []
    seqs_meta: list[dict] = []
    all_labels: list[list[str]] = []
    sr_ref = None
    for req, (res, _) in zip(requests, results):
        sr = res["sample_rate"]
        sr_ref = sr if sr_ref is None else sr_ref
        if sr != sr_ref:
            raise RuntimeError(f"espeak-ng changed its sample rate ({sr} vs {sr_ref})")
        rel = res["rel"]
        written.extend(rel.values())
        all_labels.append(res["labels"])
        seqs_meta.append({
            "name": res["name"], "text": req.text, "voice": voice, "rate": req.rate,
            "pitch": req.pitch, "n_samples": res["n_samples"], "n_frames": res["n_frames"],
            "n_landmarks": res["n_landmarks"], **rel,
        })
        log.info("utterance %s: %d frames", res["name"], res["n_frames"])

    # AAM from prototype frames
    protos = _prototype_frames(all_labels, np.random.default_rng([int(seed), 2**31]),
                               int(aam_frames_per_phone))
    imgs, lms = [], []
    for s in sorted({s for s, _ in protos}):
        ts = [t for ss, t in protos if ss == s]
        fr = load_npz(out_dir / seqs_meta[s]["frames"], ("frames",))["frames"]
        lm = load_npz(out_dir / seqs_meta[s]["landmarks"], ("landmarks",))["landmarks"]
        imgs.append(fr[ts])
        lms.append(lm[ts])
    with _single_thread_blas():
        aam = AAM.fit(np.concatenate(imgs), np.concatenate(lms), variance=AAM_VARIANCE,
                      texture_inset=AAM_TEXTURE_INSET)
    before = _snapshot(out_dir)
    aam.save(out_dir / "aam.npz")
    after = _snapshot(out_dir)
    aam_files = sorted(k for k, v in after.items() if before.get(k) != v)
    if not aam_files:
        raise RuntimeError("AAM.save wrote no file into the corpus directory")
    written.extend(aam_files)

    manifest = {
        "format": FORMAT_NAME,
        "format_version": FORMAT_VERSION,
        "kind": "built",
        "fps": FPS,
        "audio_rate": int(sr_ref),
        "phone_set": list(PHONES),
        "image_size": int(image_size),
        "seed": int(seed),
        "voice": voice,
        "n_utterances": int(n_utterances),
        "synthesiser": "espeak-ng via espeakng-loader (one fresh process per utterance)",
        "renderer": renderer_settings(int(FORMAT_VERSION)),
        "aam": {"path": "aam.npz", "files": aam_files, "variance": AAM_VARIANCE,
                "texture_inset": AAM_TEXTURE_INSET,
                "n_params": int(aam.n_params), "frames_per_phone": int(aam_frames_per_phone),
                "prototypes": [[seqs_meta[s]["name"], int(t)] for s, t in protos]},
        "sequences": seqs_meta,
        "files": sorted(written + [_MANIFEST]),
    }
    for stale in sorted(previous - set(manifest["files"]) - {_CACHE_NAME}):
        p = out_dir / stale
        if p.is_file() and ".." not in Path(stale).parts:
            p.unlink()
    _write_json(out_dir / _MANIFEST, manifest)
    return out_dir


# ---------------------------------------------------------------------------------------
# load
# ---------------------------------------------------------------------------------------

@dataclass
class Corpus:
    """A loaded corpus: :class:`Sequence` objects plus where they came from.

    ``kind`` is ``"built"`` or ``"user"``; ``aam`` is the AAM (None when the user gave
    precomputed visual features); ``manifest`` the parsed manifest (built) or a summary.
    ``Sequence.meta["aam_mean"]`` holds the per-sequence mean removed from ``aam`` (zeros
    when mean removal is off): add it back before reconstructing or rendering.
    """

    path: Path
    kind: str
    sequences: list[Sequence]
    manifest: dict = field(default_factory=dict)
    aam: object | None = None
    fps: float = FPS
    sample_rate: int = 0
    #: the ``aam.npz`` the visual features were projected through (None: precomputed)
    aam_path: Path | None = None

    def __len__(self) -> int:
        return len(self.sequences)

    def __iter__(self) -> Iterator[Sequence]:
        return iter(self.sequences)

    def __getitem__(self, key: int | str) -> Sequence:
        if isinstance(key, str):
            for s in self.sequences:
                if s.name == key:
                    return s
            raise KeyError(key)
        return self.sequences[key]

    @property
    def names(self) -> list[str]:
        return [s.name for s in self.sequences]


@dataclass
class _Item:
    """One utterance's inputs before featurisation."""

    name: str
    wav: Path
    labels: Path
    n_frames: int
    intervals: list
    visual: Path | None = None            # frames .npz, image folder or video
    landmarks: Path | None = None
    features: Path | None = None          # precomputed visual features (.npy)
    meta: dict = field(default_factory=dict)
    inputs: list[Path] = field(default_factory=list)


def _check_audio_vs_labels(wav: Path, lab: Path, n_samples: int, sr: int, intervals) -> None:
    dur = n_samples / sr
    end = intervals[-1][1]
    if abs(end - dur) > _LABEL_TOL_S + 1e-9:
        raise ValueError(
            f"{lab}: labels end at {end:.4f} s but {wav} lasts {dur:.4f} s "
            f"({n_samples} samples at {sr} Hz); expected agreement within {_LABEL_TOL_S:.3f} s"
        )


def _built_items(root: Path, m: dict) -> tuple[list[_Item], int]:
    if m.get("format_version") not in _READABLE_VERSIONS:
        raise ValueError(f"{root / _MANIFEST}: format_version {m.get('format_version')!r}, "
                         f"expected one of {list(_READABLE_VERSIONS)}")
    if float(m.get("fps", -1)) != FPS:
        raise ValueError(f"{root / _MANIFEST}: fps {m.get('fps')!r}, expected {FPS}")
    rate = int(m["audio_rate"])
    items = []
    for sm in m["sequences"]:
        wav, lab = root / sm["wav"], root / sm["lab"]
        y, sr = load_wav(wav)
        if sr != rate:
            raise ValueError(f"{wav}: sample rate {sr} Hz, expected {rate} Hz (manifest audio_rate)")
        intervals = read_labels(lab)
        _check_audio_vs_labels(wav, lab, y.size, sr, intervals)
        T = frame_count(y.size, sr, FPS)
        if T != int(sm["n_frames"]):
            raise ValueError(f"{wav}: {T} frames of audio, manifest says {sm['n_frames']}")
        item = _Item(sm["name"], wav, lab, T, intervals, visual=root / sm["frames"],
                     landmarks=root / sm["landmarks"],
                     meta={k: sm[k] for k in ("text", "voice", "rate", "pitch") if k in sm})
        item.inputs = [wav, lab, item.visual, item.landmarks]
        items.append(item)
    return items, rate


def _read_images(folder: Path) -> np.ndarray:
    import imageio.v3 as iio

    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in _IMAGE_EXT)
    if not files:
        raise ValueError(f"{folder}: no image files ({', '.join(_IMAGE_EXT)})")
    out = []
    for f in files:
        try:
            im = np.asarray(iio.imread(f))
        except Exception as exc:
            raise ValueError(f"{f}: cannot read image ({exc})") from exc
        out.append(_to_gray(im, f))
    shapes = {im.shape for im in out}
    if len(shapes) != 1:
        raise ValueError(f"{folder}: images differ in size {sorted(shapes)}")
    return np.stack(out)


def _to_gray(im: np.ndarray, where: Path) -> np.ndarray:
    if im.ndim == 3:
        from skimage.color import rgb2gray

        im = im[..., :3]
        im = np.rint(rgb2gray(im) * (255.0 if im.dtype == np.uint8 else 1.0))
    if im.ndim != 2:
        raise ValueError(f"{where}: expected a grayscale or RGB image, found shape {im.shape}")
    return np.clip(im, 0, 255).astype(np.uint8)


def _read_video(path: Path) -> np.ndarray:
    import imageio_ffmpeg

    try:
        gen = imageio_ffmpeg.read_frames(str(path), pix_fmt="gray", bpp=1)
        meta = next(gen)
        w, h = meta["size"]
        fps = float(meta.get("fps", FPS))
        frames = [np.frombuffer(b, dtype=np.uint8).reshape(h, w) for b in gen]
    except Exception as exc:
        raise ValueError(f"{path}: cannot read video ({exc})") from exc
    if abs(fps - FPS) > 1e-3:
        raise ValueError(f"{path}: video at {fps} fps, expected {FPS} fps")
    if not frames:
        raise ValueError(f"{path}: video has no frames")
    return np.stack(frames)


def _label_file(root: Path, wav: Path) -> Path:
    """The label file beside a user corpus's ``NAME.wav``: ``NAME.lab`` or ``NAME.TextGrid``."""
    name = wav.stem
    labs = [p for p in (root / f"{name}.lab", root / f"{name}.TextGrid",
                        root / f"{name}.textgrid") if p.exists()]
    if not labs:
        raise ValueError(f"{wav}: no label file {name}.lab or {name}.TextGrid beside it")
    return labs[0]


def _user_items(root: Path) -> tuple[list[_Item], int]:
    wavs = sorted(root.glob("*.wav"))
    if not wavs:
        raise ValueError(f"{root}: no manifest.json and no *.wav files; not a corpus directory "
                         "(see docs/data.md for the user-corpus layout)")
    items: list[_Item] = []
    rate = None
    for wav in wavs:
        name = wav.stem
        lab = _label_file(root, wav)
        y, sr = load_wav(wav)
        samples_per_frame(sr, FPS)
        if rate is None:
            rate = sr
        elif sr != rate:
            raise ValueError(f"{wav}: sample rate {sr} Hz, expected {rate} Hz like {wavs[0]}")
        intervals = read_labels(lab)
        _check_audio_vs_labels(wav, lab, y.size, sr, intervals)
        T = frame_count(y.size, sr, FPS)
        item = _Item(name, wav, lab, T, intervals, meta={})
        feat = root / f"{name}.visual.npy"
        lmk = root / f"{name}.landmarks.npy"
        vids = [root / f"{name}{e}" for e in _VIDEO_EXT if (root / f"{name}{e}").exists()]
        if feat.exists():
            item.features = feat
        elif (root / name).is_dir() or vids:
            item.visual = root / name if (root / name).is_dir() else vids[0]
            if not lmk.exists():
                raise ValueError(f"{item.visual}: frames need per-frame landmarks in {lmk} "
                                 "(with only some frames annotated, run `bayes-talk corpus track`; "
                                 "docs/data.md)")
            item.landmarks = lmk
        else:
            raise ValueError(
                f"{wav}: no visual data; expected {feat.name} (features), a folder {name}/ of "
                f"images or a video {name}.mp4, with {lmk.name}"
            )
        item.inputs = [wav, lab] + [p for p in (item.features, item.landmarks) if p is not None]
        if item.visual is not None:
            item.inputs += (sorted(item.visual.iterdir()) if item.visual.is_dir() else [item.visual])
        items.append(item)
    return items, int(rate)


def _load_visual(item: _Item) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray | None]:
    """(frames, landmarks, features) of one item, checked for frame-count agreement.

    The sequence length is the audio frame count T; visual data may hold T or T+1 frames
    (a trailing partial frame), anything else is an error naming both files.
    """
    T = item.n_frames

    def fit_len(n: int, what: Path) -> None:
        if n not in (T, T + 1):
            raise ValueError(f"{what}: {n} frames, but {item.wav} holds {T} whole 40 ms frames "
                             f"(expected {T} or {T + 1})")

    if item.features is not None:
        try:
            f = np.load(item.features, allow_pickle=False)
        except Exception as exc:
            raise ValueError(f"{item.features}: cannot read ({exc})") from exc
        if f.ndim != 2 or not np.all(np.isfinite(f)):
            raise ValueError(f"{item.features}: expected finite (T, D) features, found shape {f.shape}")
        fit_len(f.shape[0], item.features)
        return None, None, np.asarray(f[:T], dtype=np.float64)
    if item.visual.suffix == ".npz":
        frames = load_npz(item.visual, ("frames",))["frames"]
        lm = load_npz(item.landmarks, ("landmarks",))["landmarks"]
    else:
        frames = _read_images(item.visual) if item.visual.is_dir() else _read_video(item.visual)
        try:
            lm = np.load(item.landmarks, allow_pickle=False)
        except Exception as exc:
            raise ValueError(f"{item.landmarks}: cannot read ({exc})") from exc
    if lm.ndim != 3 or lm.shape[2] != 2:
        raise ValueError(f"{item.landmarks}: expected (T, P, 2) landmarks, found shape {lm.shape}")
    if not np.all(np.isfinite(lm)):
        bad = np.flatnonzero(~np.isfinite(lm).reshape(lm.shape[0], -1).all(axis=1))
        raise ValueError(f"{item.landmarks}: landmarks contain NaN or inf (first at frame {bad[0]}); frames "
                         f"{bad[:10].tolist()} have no finite landmarks; for sparse annotations use "
                         "NAME.annotations.npy and `bayes-talk corpus track` (docs/data.md)")
    if lm.shape[0] != frames.shape[0]:
        raise ValueError(f"{item.landmarks}: {lm.shape[0]} landmark frames but {item.visual} "
                         f"has {frames.shape[0]} image frames")
    fit_len(frames.shape[0], item.visual)
    return frames[:T], np.asarray(lm[:T], dtype=np.float64), None


def _cache_key(items: list[_Item], extra: list[Path], mode: str) -> str:
    h = hashlib.sha256()
    h.update(f"{FORMAT_NAME}/features v{FEATURE_VERSION}/{mode}/fps={FPS}".encode())
    for it in items:
        h.update(f"|{it.name}|{it.n_frames}".encode())
        for p in it.inputs:
            h.update(f"|{p.name}:{_sha256(p)}".encode())
    for p in extra:
        h.update(f"|{p.name}:{_sha256(p)}".encode())
    return h.hexdigest()


def _read_cache(path: Path, key: str, names: list[str]) -> dict | None:
    if not path.exists():
        return None
    try:
        z = load_npz(path)
    except ValueError:
        return None
    if "key" not in z or str(z["key"]) != key:
        return None
    try:
        out = {n: (z[f"mfcc/{n}"], z[f"visual/{n}"], z[f"labels/{n}"]) for n in names}
    except KeyError:
        return None
    bad = [n for n, (mf, vis, _) in out.items() if not (np.all(np.isfinite(mf)) and np.all(np.isfinite(vis)))]
    if bad:
        log.warning("%s: cached features of %s contain NaN or inf; recomputing them and rewriting "
                    "the cache (delete the file to force this)", path, bad[0])
        return None
    return out


def _fit_user_aam(root: Path, items: list[_Item], labels: list[list[str]], seed: int):
    from bayes_talk.features.aam import AAM

    protos = _prototype_frames(labels, np.random.default_rng([int(seed), 2**31]),
                               AAM_FRAMES_PER_PHONE)
    imgs, lms = [], []
    for s in sorted({s for s, _ in protos}):
        ts = [t for ss, t in protos if ss == s]
        fr, lm, _ = _load_visual(items[s])
        imgs.append(fr[ts])
        lms.append(lm[ts])
    with _single_thread_blas():
        return AAM.fit(np.concatenate(imgs), np.concatenate(lms), variance=AAM_VARIANCE,
                       texture_inset=AAM_TEXTURE_INSET)


def _check_projectable(root: Path, kind: str, manifest: dict, items: list[_Item], aam,
                       aam_path: Path) -> None:
    """Refuse (ValueError naming both) frames that ``aam`` cannot project: another image
    size or landmark count than the AAM was learned on."""
    size = manifest.get("image_size") if kind == "built" else None
    n_lm = {s.get("n_landmarks") for s in manifest.get("sequences", [])} if kind == "built" else set()
    if size is not None and (int(size), int(size)) != tuple(aam.image_shape):
        raise ValueError(f"cannot project {root} through {aam_path}: its frames are {size}x{size} "
                         f"pixels, the AAM's are {aam.image_shape[0]}x{aam.image_shape[1]}")
    bad = sorted(n for n in n_lm if n is not None and int(n) != aam.n_landmarks)
    if bad:
        raise ValueError(f"cannot project {root} through {aam_path}: its frames have {bad[0]} landmarks, "
                         f"the AAM has {aam.n_landmarks}")


def load_corpus(path: str | Path, *, mean_removal: bool = True, cache: bool = True,
                seed: int = 0, n_workers: int | None = None,
                aam: str | Path | None = None, cmvn: str = "mean",
                fmax: float | None = FMAX_HZ) -> Corpus:
    """Load a built corpus (``manifest.json``) or a user corpus (docs/data.md) as Sequences.

    Each :class:`Sequence` gets ``mfcc`` (T, 20), ``aam`` (T, n_params) AAM parameters of
    the frames (or the user's precomputed visual features), 25 Hz majority-vote
    ``labels``, ``landmarks`` (T, P, 2) when available, ``audio_path`` and ``meta``
    (sentence text etc., ``intervals``, ``aam_mean``).

    ``mean_removal`` (default on, deena2010 §3.2): subtract each sequence's mean visual
    feature vector (recorded in ``meta["aam_mean"]``). ``cache``: derived features are
    stored in ``<path>/features.npz`` keyed by a SHA-256 of every input file, the AAM
    and the feature settings; any change recomputes them. For a user corpus with image
    or video frames an AAM is fitted on prototype frames (random draw from ``seed``) and
    saved as ``<path>/aam.npz`` (also cached; delete it to refit). Errors name the
    offending file. ``n_workers``: worker processes for featurisation (None: 2 from 16
    sequences on, else none); the features do not depend on it.

    ``aam``: the ``aam.npz`` of *another* corpus (or model) to project this corpus's
    frames through instead of its own AAM -- how a separately built test corpus is scored
    in the training corpus's parameter space (``evaluate --test-corpus``). The frames'
    image size and landmark count must match that AAM (ValueError naming both); the
    features are cached in ``<path>/features-<aam hash>.npz``, beside the corpus's own.

    ``cmvn``: per-utterance cepstral normalisation of the MFCCs (:func:`bayes_talk.audio.cmvn`:
    "mean" by default, "mean+var" or "off"), applied after the cache (which holds the raw
    MFCCs), so every consumer -- ``train``, ``evaluate``, the benchmarks -- sees the features
    ``synth`` computes from the model's recorded setting. Recorded in ``meta["cmvn"]``.
    ``fmax``: the mel filterbank's upper edge (Hz; :data:`bayes_talk.features.mfcc.FMAX_HZ`,
    7.6 kHz; None: sr/2, the features before issue 12); part of the cache key.
    """
    from bayes_talk.audio import cmvn as _cmvn

    _cmvn(np.zeros((1, 1)), cmvn)  # validate the mode before any work
    root = Path(path)
    foreign_aam = aam
    if not root.is_dir():
        raise ValueError(f"{root}: corpus directory not found")
    mpath = root / _MANIFEST
    manifest: dict = {}
    if mpath.exists():
        try:
            manifest = json.loads(mpath.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise ValueError(f"{mpath}: cannot read manifest ({exc})") from exc
        if manifest.get("format") != FORMAT_NAME:
            raise ValueError(f"{mpath}: format {manifest.get('format')!r}, expected {FORMAT_NAME!r}")
        kind = "built"
        items, rate = _built_items(root, manifest)
    else:
        kind = "user"
        items, rate = _user_items(root)

    labels = [frame_labels(it.intervals, it.n_frames, FPS) for it in items]
    aam = None
    aam_files: list[Path] = []
    needs_aam = any(it.features is None for it in items)
    if needs_aam and any(it.features is not None for it in items):
        raise ValueError(f"{root}: mixes precomputed visual features (*.visual.npy) and frames; "
                         "use one kind for the whole corpus")
    if foreign_aam is not None and not needs_aam:
        raise ValueError(f"{root}: has precomputed visual features (*.visual.npy), which cannot be "
                         f"projected through another AAM ({foreign_aam})")
    if foreign_aam is not None:
        from bayes_talk.features.aam import AAM

        aam_path = Path(foreign_aam)
        aam = AAM.load(aam_path)
        aam_files = [aam_path.with_suffix(".json"), aam_path.with_suffix(".npz")]
        _check_projectable(root, kind, manifest, items, aam, aam_path)
    elif needs_aam:
        from bayes_talk.features.aam import AAM

        if kind == "built":
            aam_path = root / manifest["aam"]["path"]
            aam_files = [root / f for f in manifest["aam"]["files"]]
            aam = AAM.load(aam_path)
        else:
            aam_path = root / "aam.npz"
            if aam_path.exists():
                aam = AAM.load(aam_path)
            else:
                aam = _fit_user_aam(root, items, labels, seed)
                aam.save(aam_path)
            aam_files = sorted(p for p in root.iterdir() if p.name.startswith("aam") and p.is_file())
    key = _cache_key(items, aam_files, kind)
    cpath = root / _CACHE_NAME
    if aam_files and aam_files[0].parent.resolve() != root.resolve():  # a foreign AAM
        cpath = root / f"features-{_sha256(aam_files[0])[:12]}.npz"
    if fmax is not None:  # the issue-12 front end: its own key (None keeps the older caches valid)
        key = hashlib.sha256(f"{key}|fmax={float(fmax)}".encode()).hexdigest()
    names = [it.name for it in items]
    cached = _read_cache(cpath, key, names) if cache else None
    if cached is None:
        tasks = [{"name": it.name, "wav": str(it.wav), "labels": str(it.labels),
                  "n_frames": it.n_frames,
                  "visual": None if it.visual is None else str(it.visual),
                  "landmarks": None if it.landmarks is None else str(it.landmarks),
                  "features": None if it.features is None else str(it.features),
                  "aam": None if aam is None else str(aam_path), "fmax": fmax} for it in items]
        if aam is not None:
            _AAM_CACHE[str(aam_path)] = (aam_path.with_suffix(".json").read_bytes(), aam)
        results = _run_tasks(_features_task, "features", tasks, _n_workers(n_workers, len(items)))
        cached = {}
        for it, labs, (_, arr) in zip(items, labels, results):
            cached[it.name] = (arr["mfcc"], arr["visual"],
                               np.array([PHONE_INDEX[p] for p in labs], dtype=np.int8))
        if cache:
            if cpath.exists():
                try:
                    old = load_npz(cpath)
                except ValueError:
                    old = {}
                if "key" not in old:
                    raise ValueError(f"{cpath}: exists and is not a bayes_talk feature cache; "
                                     "refusing to overwrite it (move or delete that file)")
            arrays = {"key": np.array(key)}
            for n, (mf, vis, lab) in cached.items():
                arrays[f"mfcc/{n}"], arrays[f"visual/{n}"], arrays[f"labels/{n}"] = mf, vis, lab
            save_npz(cpath, **arrays)

    # how the visual features were made, for method "oracle" (bayes_talk.evaluation.ceiling)
    gen = {"corpus_kind": kind, "aam_path": str(aam_path) if aam is not None else None}
    if kind == "built":
        gen.update(image_size=int(manifest["image_size"]),
                   renderer=manifest.get("renderer") or renderer_settings(manifest["format_version"]))
    seqs = []
    for it in items:
        mf, vis, lab = cached[it.name]
        vis = np.asarray(vis, dtype=np.float64)
        mean = vis.mean(axis=0) if mean_removal else np.zeros(vis.shape[1])
        lm = None
        if it.landmarks is not None:
            lm = (load_npz(it.landmarks, ("landmarks",))["landmarks"] if it.landmarks.suffix == ".npz"
                  else np.load(it.landmarks, allow_pickle=False))[: it.n_frames].astype(np.float64)
        meta = dict(it.meta, intervals=list(it.intervals), aam_mean=mean,
                    label_path=str(it.labels), mean_removed=bool(mean_removal), cmvn=cmvn, **gen)
        seqs.append(Sequence(name=it.name, mfcc=_cmvn(mf, cmvn), aam=vis - mean,
                             labels=[PHONES[i] for i in lab], landmarks=lm, audio_path=it.wav,
                             meta=meta))
    summary = manifest if kind == "built" else {"kind": "user", "audio_rate": rate, "fps": FPS,
                                                 "n_utterances": len(items)}
    return Corpus(path=root, kind=kind, sequences=seqs, manifest=summary, aam=aam, fps=FPS,
                  sample_rate=rate, aam_path=aam_path if aam is not None else None)
