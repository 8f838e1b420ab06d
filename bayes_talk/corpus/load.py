"""Load a built or user corpus as :class:`~bayes_talk.data.utterance.Utterance` objects,
with derived features (MFCC, AAM parameters) cached by a SHA-256 of every input."""
from __future__ import annotations

import hashlib
import json
import logging
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bayes_talk.base.executor import Executor
from bayes_talk.base.executor import single_thread as _single_thread_blas
from bayes_talk.base.files import sha256_file
from bayes_talk.corpus.format import (
    AAM_FRAMES_PER_PHONE,
    AAM_TEXTURE_INSET,
    AAM_VARIANCE,
    CACHE_NAME,
    FEATURE_VERSION,
    FORMAT_NAME,
    FPS,
    MANIFEST,
    load_npz,
    prototype_frames,
    renderer_settings,
    save_npz,
)
from bayes_talk.corpus.layouts import CorpusItem, built_items, load_visual, user_items
from bayes_talk.corpus.workers import (
    AAM_CACHE,
    features_task,
    resolve_workers,
    run_tasks,
)
from bayes_talk.data.labels import frame_labels
from bayes_talk.data.phones import PHONE_INDEX, PHONES
from bayes_talk.data.utterance import Utterance
from bayes_talk.features.mfcc import FLOOR_DBFS, FMAX_HZ, LEVEL_DBFS

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------------------
# load
# ---------------------------------------------------------------------------------------

@dataclass
class Corpus:
    """A loaded corpus: :class:`Utterance` objects plus where they came from.

    ``kind`` is ``"built"`` or ``"user"``; ``aam`` is the AAM (None when the user gave
    precomputed visual features); ``manifest`` the parsed manifest (built) or a summary.
    ``Utterance.meta["aam_mean"]`` holds the per-sequence mean removed from ``aam`` (zeros
    when mean removal is off): add it back before reconstructing or rendering.
    """

    path: Path
    kind: str
    sequences: list[Utterance]
    manifest: dict = field(default_factory=dict)
    aam: object | None = None
    fps: float = FPS
    sample_rate: int = 0
    #: the ``aam.npz`` the visual features were projected through (None: precomputed)
    aam_path: Path | None = None

    def __len__(self) -> int:
        return len(self.sequences)

    def __iter__(self) -> Iterator[Utterance]:
        return iter(self.sequences)

    def __getitem__(self, key: int | str) -> Utterance:
        if isinstance(key, str):
            for s in self.sequences:
                if s.name == key:
                    return s
            raise KeyError(key)
        return self.sequences[key]

    @property
    def names(self) -> list[str]:
        """The utterance names, in corpus order."""
        return [s.name for s in self.sequences]



def _cache_key(items: list[CorpusItem], extra: list[Path], mode: str) -> str:
    h = hashlib.sha256()
    h.update(f"{FORMAT_NAME}/features v{FEATURE_VERSION}/{mode}/fps={FPS}".encode())
    for it in items:
        h.update(f"|{it.name}|{it.n_frames}".encode())
        for p in it.inputs:
            h.update(f"|{p.name}:{sha256_file(p)}".encode())
    for p in extra:
        h.update(f"|{p.name}:{sha256_file(p)}".encode())
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


def _fit_user_aam(root: Path, items: list[CorpusItem], labels: list[list[str]], seed: int):
    from bayes_talk.features.aam import AAM

    protos = prototype_frames(labels, np.random.default_rng([int(seed), 2**31]),
                               AAM_FRAMES_PER_PHONE)
    imgs, lms = [], []
    for s in sorted({s for s, _ in protos}):
        ts = [t for ss, t in protos if ss == s]
        fr, lm, _ = load_visual(items[s])
        imgs.append(fr[ts])
        lms.append(lm[ts])
    with _single_thread_blas():
        return AAM.fit(np.concatenate(imgs), np.concatenate(lms), variance=AAM_VARIANCE,
                       texture_inset=AAM_TEXTURE_INSET)


def _check_projectable(root: Path, kind: str, manifest: dict, items: list[CorpusItem], aam,
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
                executor: Executor | str | None = None, scheduler: str | None = None,
                aam: str | Path | None = None, cmvn: str = "mean",
                fmax: float | None = FMAX_HZ, floor_dbfs: float | None = FLOOR_DBFS,
                level_dbfs: float | None = LEVEL_DBFS) -> Corpus:
    """Load a built corpus (``manifest.json``) or a user corpus (docs/data.md) as Sequences.

    Each :class:`Utterance` gets ``mfcc`` (T, 20), ``aam`` (T, n_params) AAM parameters of
    the frames (or the user's precomputed visual features), 25 Hz majority-vote
    ``labels``, ``landmarks`` (T, P, 2) when available, ``audio_path`` and ``meta``
    (sentence text etc., ``intervals``, ``aam_mean``).

    ``mean_removal`` (default on, deena2010 §3.2): subtract each sequence's mean visual
    feature vector (recorded in ``meta["aam_mean"]``). ``cache``: derived features are
    stored in ``<path>/features.npz`` keyed by a SHA-256 of every input file, the AAM
    and the feature settings; any change recomputes them (a directory that cannot be
    written to -- read-only, full -- gets a warning and the features are used uncached).
    For a user corpus with image or video frames an AAM is fitted on prototype frames (random draw from ``seed``) and
    saved as ``<path>/aam.npz`` (also cached; delete it to refit). Errors name the
    offending file. ``n_workers``: worker processes for featurisation (None: none, the work
    runs in this process -- safe in a plain script); the features do not depend on it. ``executor`` / ``scheduler``: as
    in :func:`~bayes_talk.corpus.build_corpus` (bayes_talk.base.executor).

    ``aam``: the ``aam.npz`` of *another* corpus (or model) to project this corpus's
    frames through instead of its own AAM -- how a separately built test corpus is scored
    in the training corpus's parameter space (``evaluate --test-corpus``). The frames'
    image size and landmark count must match that AAM (ValueError naming both); the
    features are cached in ``<path>/features-<aam hash>.npz``, beside the corpus's own.

    ``cmvn``: per-utterance cepstral normalisation of the MFCCs (:func:`bayes_talk.features.audio.cmvn`:
    "mean" by default, "mean+var" or "off"), applied after the cache (which holds the raw
    MFCCs), so every consumer -- ``train``, ``evaluate``, the benchmarks -- sees the features
    ``synth`` computes from the model's recorded setting. Recorded in ``meta["cmvn"]``.
    ``fmax``: the mel filterbank's upper edge (Hz; :data:`bayes_talk.features.mfcc.FMAX_HZ`,
    7.6 kHz; None: sr/2); ``floor_dbfs``: the absolute
    mel-power floor (:data:`bayes_talk.features.frontend.FLOOR_DBFS`; None: none);
    ``level_dbfs``: the active-speech level every recording is scaled to before its MFCCs
    are computed (:data:`bayes_talk.features.frontend.LEVEL_DBFS`; None: none); all three
    part of the cache key (None for any keeps the key of a cache written without it).
    """
    from bayes_talk.features.audio import cmvn as _cmvn

    _cmvn(np.zeros((1, 1)), cmvn)  # validate the mode before any work
    root = Path(path)
    foreign_aam = aam
    if not root.is_dir():
        raise ValueError(f"{root}: corpus directory not found")
    mpath = root / MANIFEST
    manifest: dict = {}
    if mpath.exists():
        try:
            manifest = json.loads(mpath.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise ValueError(f"{mpath}: cannot read manifest ({exc})") from exc
        if manifest.get("format") != FORMAT_NAME:
            raise ValueError(f"{mpath}: format {manifest.get('format')!r}, expected {FORMAT_NAME!r}")
        kind = "built"
        items, rate = built_items(root, manifest)
    else:
        kind = "user"
        items, rate = user_items(root)

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
                try:
                    aam.save(aam_path)
                except OSError as exc:  # the featurisation workers read the AAM from this file
                    raise ValueError(f"{aam_path}: cannot save the AAM fitted for this corpus ({exc}); "
                                     f"make {root} writable or give a fitted AAM with aam=") from exc
            aam_files = sorted(p for p in root.iterdir() if p.name.startswith("aam") and p.is_file())
    key = _cache_key(items, aam_files, kind)
    cpath = root / CACHE_NAME
    if aam_files and aam_files[0].parent.resolve() != root.resolve():  # a foreign AAM
        cpath = root / f"features-{sha256_file(aam_files[0])[:12]}.npz"
    if fmax is not None:  # its own key (None keeps the key of caches written without it)
        key = hashlib.sha256(f"{key}|fmax={float(fmax)}".encode()).hexdigest()
    if floor_dbfs is not None:  # its own key, likewise
        key = hashlib.sha256(f"{key}|floor={float(floor_dbfs)}".encode()).hexdigest()
    if level_dbfs is not None:  # its own key, likewise
        key = hashlib.sha256(f"{key}|level={float(level_dbfs)}".encode()).hexdigest()
    names = [it.name for it in items]
    cached = _read_cache(cpath, key, names) if cache else None
    if cached is None:
        tasks = [{"name": it.name, "wav": str(it.wav), "labels": str(it.labels),
                  "n_frames": it.n_frames,
                  "visual": None if it.visual is None else str(it.visual),
                  "landmarks": None if it.landmarks is None else str(it.landmarks),
                  "features": None if it.features is None else str(it.features),
                  "aam": None if aam is None else str(aam_path), "fmax": fmax, "floor_dbfs": floor_dbfs,
                  "level_dbfs": level_dbfs} for it in items]
        if aam is not None:
            AAM_CACHE[str(aam_path)] = (aam_path.with_suffix(".json").read_bytes(), aam)
        results = run_tasks(features_task, "features", tasks, resolve_workers(n_workers, len(items)),
                             executor, scheduler)
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
            try:
                save_npz(cpath, **arrays)
            except OSError as exc:  # a read-only or full corpus directory: keep the features
                log.warning("%s: cannot write the feature cache (%s); the features computed now are "
                            "used uncached and recomputed on the next load (cache=False skips this)",
                            cpath, exc)

    # how the visual features were made, for method "oracle" (bayes_talk.evaluation.ceiling)
    gen = {"corpus_kind": kind, "aam_path": str(aam_path) if aam is not None else None}
    if kind == "built":
        gen.update(image_size=int(manifest["image_size"]), speech=manifest.get("speech", "espeak"),
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
        seqs.append(Utterance(name=it.name, mfcc=_cmvn(mf, cmvn), aam=vis - mean,
                             labels=[PHONES[i] for i in lab], landmarks=lm, audio_path=it.wav,
                             meta=meta))
    summary = manifest if kind == "built" else {"kind": "user", "audio_rate": rate, "fps": FPS,
                                                 "n_utterances": len(items)}
    return Corpus(path=root, kind=kind, sequences=seqs, manifest=summary, aam=aam, fps=FPS,
                  sample_rate=rate, aam_path=aam_path if aam is not None else None)

