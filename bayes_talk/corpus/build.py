"""Build the talking-head corpus: sentences, speech, faces, frames, AAM, manifest."""
from __future__ import annotations

import importlib.resources
import json
import logging
from pathlib import Path

import numpy as np

from bayes_talk.base.executor import Executor
from bayes_talk.base.executor import single_thread as _single_thread_blas
from bayes_talk.base.files import write_json
from bayes_talk.corpus.format import (
    AAM_FRAMES_PER_PHONE,
    AAM_TEXTURE_INSET,
    AAM_VARIANCE,
    CACHE_NAME,
    FORMAT_NAME,
    FORMAT_VERSION,
    FPS,
    MANIFEST,
    load_npz,
    prototype_frames,
    renderer_settings,
)
from bayes_talk.corpus.workers import (
    resolve_workers,
    run_tasks,
    utterance_task,
)
from bayes_talk.data.phones import PHONES

log = logging.getLogger(__name__)


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
    old = out_dir / MANIFEST
    try:
        m = json.loads(old.read_text(encoding="utf-8"))
        if m.get("format") == FORMAT_NAME:
            return {f for f in m.get("files", []) if isinstance(f, str)}
    except (OSError, ValueError):
        pass
    return set()



#: ``speech`` generators of the built-in corpus and how the manifest describes them.
SPEECH_GENERATORS: dict[str, str] = {
    "espeak": "espeak-ng via espeakng-loader (one fresh process per utterance)",
    "vtl": ("VocalTractLab (vocaltractlab-cython, GPL-3.0) from espeak-ng's phones and "
            "durations; the same varied vocal tract drives the face's jaw and lips"),
}


def _articulatory_manifest() -> dict:
    """What a ``--speech vtl`` corpus records about its generator."""
    from bayes_talk.data.articulatory import (
        FACE_MAP,
        GENERATOR_VERSION,
        LICENCE,
        VARIATION,
        require_vtl,
    )

    return {"generator_version": GENERATOR_VERSION, "vtl_version": str(require_vtl().get_version()),
            "licence": LICENCE, "variation": dict(VARIATION), "face_map": dict(FACE_MAP),
            "stream": "numpy default_rng([seed, i, 3])"}


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
    executor: Executor | str | None = None,
    scheduler: str | None = None,
    aam_frames_per_phone: int = AAM_FRAMES_PER_PHONE,
    rate: int | None = None,
    pitch: int | None = None,
    speech: str = "espeak",
) -> Path:
    """Synthesise speech, faces and frames into ``out_dir`` and learn an AAM; return the path.

    ``out_dir`` must be empty or absent unless ``force``; with ``force`` the corpus files
    are overwritten and files listed in a previous manifest of ours but not produced now
    are removed -- nothing else is deleted. ``manifest.json`` is written last, so a
    directory without it is an incomplete build.

    ``n_workers`` worker processes (one BLAS thread each; None or 1: in this process, the
    default of a library call; ``bayes-talk corpus build`` uses 2 from 16 utterances on)
    each take whole utterances: speech in a fresh espeak-ng
    process, face, frames, files -- so one renders while the other waits for speech. The
    output does not depend on ``n_workers``. ``executor``: "local", "processes" or "dask"
    (or an :class:`~bayes_talk.base.executor.Executor`, left open), ``scheduler`` a running dask
    scheduler's address (docs/scaling.md); None: processes when ``n_workers`` > 1.

    ``rate`` (words/min) and ``pitch`` (0-100): the centre of the per-utterance jitter
    (None: espeak's defaults, 175 and 50) -- e.g. a held-out voice outside the training range.

    ``speech``: "espeak" (espeak-ng's audio) or "vtl" (articulatory: espeak-ng's phones
    and durations drive VocalTractLab, whose varied tract makes both the audio and the
    face's jaw and lips; :mod:`bayes_talk.data.articulatory`, needs
    ``pip install 'bayes_talk[articulatory]'``, GPL-3.0).
    """
    from bayes_talk.data.text_check import check_pronounceable, check_voice

    out_dir = Path(out_dir)
    if int(n_utterances) < 1:
        raise ValueError(f"n_utterances: expected >= 1, found {n_utterances}")
    if int(seed) < 0:
        raise ValueError(f"seed: expected an integer >= 0, found {seed}")
    check_voice(voice)
    if speech not in SPEECH_GENERATORS:
        raise ValueError(f"speech: expected one of {sorted(SPEECH_GENERATORS)}, found {speech!r}")
    if speech == "vtl":
        from bayes_talk.data.articulatory import require_vtl

        require_vtl()
    workers = resolve_workers(n_workers, int(n_utterances))
    if int(image_size) < 32:
        raise ValueError(f"image_size: expected >= 32 pixels, found {image_size}")
    texts = load_sentences(sentences, int(n_utterances))
    check_pronounceable(texts, voice, str(sentences) if isinstance(sentences, (str, Path)) else "sentences")
    previous = _check_out_dir(out_dir, force)
    created = _CreatedFiles(out_dir)
    try:
        return _build(out_dir, texts, seed, voice, image_size, previous, workers, aam_frames_per_phone,
                      int(n_utterances), rate, pitch, executor, scheduler, speech)
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

        if not self.out_dir.exists() or (self.out_dir / MANIFEST).exists():
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
           pitch: int | None, executor: Executor | str | None = None,
           scheduler: str | None = None, speech: str = "espeak") -> Path:
    """The body of :func:`build_corpus` after its checks."""
    from bayes_talk.data.speech import DEFAULT_PITCH, DEFAULT_RATE, jittered_requests
    from bayes_talk.features.aam import AAM

    udir = out_dir / "utterances"
    udir.mkdir(parents=True, exist_ok=True)
    old_manifest = out_dir / MANIFEST
    if old_manifest.exists():  # an incomplete rebuild must not look complete
        old_manifest.unlink()

    requests = jittered_requests(texts, seed, voice=voice, fps=FPS,
                                 rate=DEFAULT_RATE if rate is None else int(rate),
                                 pitch=DEFAULT_PITCH if pitch is None else int(pitch))
    tasks = [{"out_dir": str(out_dir), "index": i, "seed": int(seed), "image_size": int(image_size),
              "speech": speech,
              "request": {"text": r.text, "voice": r.voice, "rate": int(r.rate),
                          "pitch": int(r.pitch), "lead_silence": r.lead_silence,
                          "trail_silence": r.trail_silence, "fps": r.fps}}
             for i, r in enumerate(requests)]
    # every utterance end to end (fresh espeak process, face, frames, files) in a worker:
    # one worker renders while the other waits for its speech
    results = run_tasks(utterance_task, "utterance", tasks, workers, executor, scheduler)
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
    protos = prototype_frames(all_labels, np.random.default_rng([int(seed), 2**31]),
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
        "speech": speech,
        "synthesiser": SPEECH_GENERATORS[speech],
        **({"articulatory": _articulatory_manifest()} if speech == "vtl" else {}),
        "renderer": renderer_settings(int(FORMAT_VERSION)),
        "aam": {"path": "aam.npz", "files": aam_files, "variance": AAM_VARIANCE,
                "texture_inset": AAM_TEXTURE_INSET,
                "n_params": int(aam.n_params), "frames_per_phone": int(aam_frames_per_phone),
                "prototypes": [[seqs_meta[s]["name"], int(t)] for s, t in protos]},
        "sequences": seqs_meta,
        "files": sorted(written + [MANIFEST]),
    }
    for stale in sorted(previous - set(manifest["files"]) - {CACHE_NAME}):
        p = out_dir / stale
        if p.is_file() and ".." not in Path(stale).parts:
            p.unlink()
    write_json(out_dir / MANIFEST, manifest, sort_keys=True)
    return out_dir


