"""The per-utterance tasks of the corpus build (speech + face + frames + files) and load
(MFCC + AAM projection), and how they are run: through :mod:`bayes_talk.base.executor`
("local", "processes" or "dask"), one BLAS thread per task; nothing depends on which
process did the work."""
from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from bayes_talk.base.executor import Executor, executor_for
from bayes_talk.corpus.format import (
    FORMAT_VERSION,
    FPS,
    MIN_ITEMS_FOR_WORKERS,
    renderer_settings,
    save_npz,
)
from bayes_talk.corpus.layouts import CorpusItem, load_visual
from bayes_talk.data.labels import frame_labels, write_lab
from bayes_talk.features.mfcc import FLOOR_DBFS, FMAX_HZ, LEVEL_DBFS, frame_count, load_wav, mfcc


def suggested_workers(n_tasks: int) -> int:
    """What the command line uses without ``--workers``: 2 processes from
    ``MIN_ITEMS_FOR_WORKERS`` tasks on, else 1 (a worker's start-up, ~1-3 s of imports,
    outweighs the gain on small jobs). Library calls never choose processes themselves."""
    return 2 if int(n_tasks) >= MIN_ITEMS_FOR_WORKERS else 1


def resolve_workers(n_workers: int | None, n_tasks: int) -> int:
    """``n_workers`` checked; None: 1 (this process). A library call starts worker processes
    only when its caller asks for them: spawned workers re-import the caller's main module,
    which a plain script without the ``if __name__ == "__main__":`` guard cannot survive."""
    if n_workers is None:
        return 1
    if int(n_workers) < 1:
        raise ValueError(f"n_workers: expected >= 1 or None, found {n_workers}")
    return int(n_workers)


def run_tasks(fn: Callable[[dict], tuple[dict, dict]], op: str, tasks: list[dict], n_workers: int,
               executor: Executor | str | None = None,
               scheduler: str | None = None) -> list[tuple[dict, dict[str, np.ndarray]]]:
    """``[fn(t) for t in tasks]`` by ``executor`` (an :class:`~bayes_talk.base.executor.Executor`,
    left open; or a kind, None: ``n_workers`` processes when > 1 and there are several
    tasks, else this process), with a progress bar on a terminal (bayes_talk.base.progress)."""
    if executor is None and scheduler is None and len(tasks) <= 1:
        n_workers = 1
    with executor_for(executor, min(n_workers, max(1, len(tasks))), scheduler) as ex:
        return ex.map(fn, tasks, desc=_PROGRESS.get(op, op), unit="utt")


_PROGRESS = {"utterance": "building utterances", "features": "featurising"}


def utterance_task(a: dict) -> tuple[dict, dict]:
    """Synthesise utterance ``a["index"]``, drive and render the face, write its files.

    ``a["speech"]``: "espeak" (espeak-ng's audio; the face from the phones) or "vtl"
    (espeak-ng's phones and durations, VocalTractLab's audio and the face's jaw, lip
    opening, rounding and protrusion from the same varied tract; stream ``[seed, i, 3]``).
    """
    from bayes_talk.corpus.render import render_frames
    from bayes_talk.data.face import face_landmarks
    from bayes_talk.data.speech import SpeechRequest, write_wav
    from bayes_talk.data.speech import synthesize_in_subprocess as synthesize_fresh

    out_dir, i, seed, image_size = Path(a["out_dir"]), int(a["index"]), int(a["seed"]), int(a["image_size"])
    res = synthesize_fresh(SpeechRequest(**a["request"]))
    sr = res.sample_rate
    n_samples = int(res.samples.shape[0])
    T = frame_count(n_samples, sr, FPS)
    # the file of record is the .lab (100 ns grid): drive the face from the same times
    intervals = [(round(s * 1e7) / 1e7, round(e * 1e7) / 1e7, p) for s, e, p in res.intervals]
    samples, given = res.samples, None
    if a.get("speech", "espeak") == "vtl":
        # espeak gave the phones and durations; one vocal tract now makes the voice and
        # the face's jaw, lips and rounding (bayes_talk.data.articulatory)
        from bayes_talk.data.articulatory import face_articulators, synthesize_articulatory

        art = synthesize_articulatory(intervals, n_samples, sr, (seed, i, 3),
                                      where=f"utterance {i} ({a['request']['text']!r})")
        samples, given = art.audio, face_articulators(art.tract, T, FPS)
    rng = np.random.default_rng([seed, i, 1])
    lm = face_landmarks(intervals, T, fps=FPS, image_size=image_size, rng=rng, given=given)
    frames = render_frames(lm, image_size=image_size, **renderer_settings(FORMAT_VERSION))
    name = f"utt{i:04d}"
    rel = {k: f"utterances/{name}{ext}" for k, ext in
           (("wav", ".wav"), ("lab", ".lab"), ("landmarks", ".landmarks.npz"),
            ("frames", ".frames.npz"))}
    write_wav(out_dir / rel["wav"], samples, sr)
    write_lab(out_dir / rel["lab"], intervals)
    save_npz(out_dir / rel["landmarks"], landmarks=np.asarray(lm, dtype=np.float64))
    save_npz(out_dir / rel["frames"], frames=np.asarray(frames, dtype=np.uint8))
    head = {"name": name, "sample_rate": int(sr), "n_samples": n_samples, "n_frames": int(T),
            "n_landmarks": int(lm.shape[1]), "labels": frame_labels(intervals, T, FPS),
            "rel": rel}
    return head, {}


AAM_CACHE: dict[str, tuple[bytes, object]] = {}


def cached_aam(path: str):
    """The AAM saved at ``path``, loaded once per process (reloaded when its JSON changes)."""
    from bayes_talk.features.aam import AAM

    stamp = Path(path).with_suffix(".json").read_bytes()
    hit = AAM_CACHE.get(path)
    if hit is None or hit[0] != stamp:
        hit = (stamp, AAM.load(path))
        AAM_CACHE[path] = hit
    return hit[1]


def features_task(a: dict) -> tuple[dict, dict]:
    """MFCC and visual features (AAM parameters) of one item."""
    it = CorpusItem(a["name"], Path(a["wav"]), Path(a["labels"]), int(a["n_frames"]), [],
               visual=None if a["visual"] is None else Path(a["visual"]),
               landmarks=None if a["landmarks"] is None else Path(a["landmarks"]),
               features=None if a["features"] is None else Path(a["features"]))
    y, sr = load_wav(it.wav)
    mf = mfcc(y, sr, it.n_frames, fps=FPS, where=str(it.wav), fmax=a.get("fmax", FMAX_HZ),
              floor_dbfs=a.get("floor_dbfs", FLOOR_DBFS), level_dbfs=a.get("level_dbfs", LEVEL_DBFS))
    frames, lm, feats = load_visual(it)
    if feats is not None:
        vis = feats
    else:
        vis = np.asarray(cached_aam(a["aam"]).project(frames, lm), np.float64)
    return {}, {"mfcc": mf, "visual": vis}

