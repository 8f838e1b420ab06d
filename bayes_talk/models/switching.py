"""The switching shared GPDM (deena2010 §2.1.2, §4.1; docs/model.md).

One :class:`~bayes_talk.models.sgpdm.SGPDM` per switching state π. The states are either
VLMM contexts over frame-level phone labels (the paper's model) or the current phone
(the paper's baseline "SSGPDM-phoneme"). Within a state the latent points follow that
state's GP dynamics (eq. 11); when the state changes, x_t is drawn from the state's entry
distribution N(μ_π, Σ_π) (eq. 12), estimated from the first latent points of the state's
training subsequences.

Training (§4.1): the traversal of each training label sequence assigns a state to every
frame; the M_π frames ending at a frame of state π form one training subsequence of π
(they overlap across states by design). Each state's SGPDM is trained on its
subsequences as multiple sequences: PCA-averaged initialisation, no back-constraint,
dynamics fixed at signal-to-noise 100:1, d = 6. At most ``max_frames_per_state`` frames
per state (a seeded random choice of whole subsequences) bound the O(N³) cost. States are
independent, so they are fitted through ``executor.map`` (any ``concurrent.futures``
executor, or a Dask/Ray one with the same ``map``); the default runs them in turn.
``fit`` is :meth:`SwitchingModel.plan_fit` (this process), the state fits
(:func:`fit_state`), :meth:`SwitchingModel.finish_fit`: a caller can queue the state fits
itself beside other work (the band calibration's "refit" scheme does).

Back-off: a state with fewer than ``min_frames_per_state`` training frames gets no model
of its own; at synthesis it uses the model of its longest suffix that has one, and a
single phone without a model uses the global fallback SGPDM (trained on a random subset
of all frames). A phone never seen in training is replaced, with a warning, by the
package's one unseen-phone policy (:func:`bayes_talk.data.phones.substitute_unseen`: the
most frequent training phone of its viseme).

Synthesis is in :mod:`bayes_talk.synthesis.sequential` (Algorithms 1-2) and
:mod:`bayes_talk.posterior.sampling`; the estimator is
:class:`bayes_talk.estimators.switching.SwitchingSGPDM`.
"""
from __future__ import annotations

import logging
from collections import Counter, defaultdict
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np

from bayes_talk.base.errors import not_fitted
from bayes_talk.base.files import check_format, read_model_files
from bayes_talk.data.phones import replace_unseen
from bayes_talk.data.utterance import Utterance
from bayes_talk.features.audio_context import AudioContext
from bayes_talk.features.context_view import ContextView
from bayes_talk.gp.threads import torch_threads
from bayes_talk.models.right_context import RightContextStates
from bayes_talk.models.sgpdm import SGPDM, SGPDMConfig
from bayes_talk.models.vlmm import VLMM, Segment

log = logging.getLogger(__name__)

FORMAT_NAME = "bayes_talk.switching_sgpdm"
FORMAT_VERSION = 1
FALLBACK = ("<fallback>",)


class PhoneStates:
    """Switching state = current phone (deena2010's SSGPDM-phoneme baseline).

    The segmentation of a label sequence is its runs of equal labels; the training
    subsequences are those runs.
    """

    def __init__(self) -> None:
        self.alphabet_: list[str] = []

    def fit(self, sequences: Iterable[Sequence[str]]) -> PhoneStates:
        """Learn the phone alphabet; returns ``self``."""
        self.alphabet_ = sorted({lab for s in sequences for lab in s})
        return self

    def _map_unknown(self, labels: Sequence[str], unknown: str) -> list[str]:
        known = set(self.alphabet_)
        out = []
        for lab in labels:
            if lab not in known:
                if unknown == "error":
                    raise ValueError(f"label {lab!r} never seen in training")
                lab = "sil"
            out.append(lab)
        return out

    def segment(self, labels: Sequence[str], unknown: str = "error") -> list[Segment]:
        """Runs of equal labels as segments; ``unknown``: "error" or "sil" for unseen phones."""
        labs = self._map_unknown(labels, unknown)
        segs, start = [], 0
        for t in range(1, len(labs) + 1):
            if t == len(labs) or labs[t] != labs[start]:
                segs.append(Segment((labs[start],), start, t))
                start = t
        return segs

    training_subsequences = segment

    def to_dict(self) -> dict:
        """JSON-able description (saved with the switching model)."""
        return {"kind": "phone", "alphabet": self.alphabet_}

    @classmethod
    def from_dict(cls, d: dict) -> PhoneStates:
        """Phone states from :meth:`to_dict`'s dict."""
        obj = cls()
        obj.alphabet_ = list(d["alphabet"])
        return obj


@dataclass
class SwitchingConfig:
    """Settings of :class:`SwitchingModel` (documented in docs/switching.md).

    states: "vlmm" (deena2010) or "phone" (its baseline).
    max_memory, epsilon, min_count: VLMM settings; epsilon=None scales the VLMM default
        2e-4 (tuned for ~19,000 frames) by 19,000 / (training frames); min_count=None gives
        max(10, round(40 · training frames / 15,000)). A context must occur that often to
        become a state. On the deena2010 split of the built-in corpus (250 utterances,
        15,111 frames; benchmarks/switching.py) min_count 10 gave 533 state models of
        median 45 frames and AMSE / ACC 7.391 / 0.191 (sequential optimisation, phone
        states: 7.473 / 0.196); min_count 40 gave 131 models of median 179 frames and
        7.351 / 0.204: the state models need data more than the VLMM needs contexts.
    latent_dim: d of every state's SGPDM (6 in deena2010).
    max_frames_per_state: cap on the frames a state is trained on.
    min_frames_per_state: a state with fewer frames backs off to its suffix.
    max_iter: L-BFGS iterations per state model.
    fallback_frames: frames of the global fallback SGPDM.
    seed: seeds subsequence selection and every state model.
    audio_context: k, the audio view of frame t is the PCA-reduced MFCCs of frames t−k..t+k
        (:mod:`bayes_talk.features.audio_context`); 0 (the default) is deena2010's per-frame
        MFCC. On our 40 held-out sentences (deena2010 settings, 4 Hz post-filter) k = 2 took
        the posterior from AMSE 8.42 / ACC 0.345 / NMSE 0.887 to 7.37 / 0.377 / 0.872
        (docs/results.md); the default model's families set it
        (``bayes_talk.estimators.registry.AUDIO_CONTEXT``), deena2010's keep 0.
    context_view: L, the phonetic-context view (:mod:`bayes_talk.features.context_view`):
        the audio view of frame t is joined by a supervised reduction of the phone labels
        t−L..t+L and the MFCCs t−4..t+4 to D_z columns, which the latent space must explain
        too; 0 (the default) is deena2010's audio-only view.
    context_mean: with ``context_view`` > 0, the view is also the *explicit mean function*
        of every state's visual mapping (docs/model.md; Rasmussen & Williams 2006 §2.7,
        "explicit basis functions"): z_t = c_t + f_π(x_t) + ε, so the state SGPDMs model the
        residual face z_t − c_t (c_t out-of-fold on the training frames, as the view) and
        synthesis adds c_t back to every predictive component. The smoothness factor and
        its motion variance then act on the residual. False (the default) models z_t itself.
    private_dims: p, latent dimensions of every state's SGPDM that the audio GP does not
        read (SGPDMConfig.view_dims = {"audio": d − p}): they are private to the face
        (shared and private latent spaces, Ek et al. 2008), so the synthesis posterior over
        them is set by the dynamics, the entry density and the smoothness factor, not by
        the audio. 0 (the default): the papers' model, every view reads all d.
    """

    states: str = "vlmm"
    max_memory: int = 5
    epsilon: float | None = None
    min_count: int | None = None
    latent_dim: int = 6
    max_frames_per_state: int = 300
    min_frames_per_state: int = 12
    max_iter: int = 100
    fallback_frames: int = 400
    seed: int = 0
    audio_context: int = 0
    right_context: bool = False
    context_view: int = 0
    context_mean: bool = False
    private_dims: int = 0


@dataclass(frozen=True)
class StateFitPlan:
    """The state fits of a :class:`SwitchingModel` still to do (:meth:`SwitchingModel.plan_fit`):
    ``jobs[i]`` = (audio, visual, subsequence lengths, SGPDM settings) of state ``keys[i]``,
    largest first, each the argument of :func:`fit_state`."""

    keys: list[tuple[str, ...]]
    jobs: list[tuple]


def _state_order(key: tuple[str, ...]) -> tuple[int, tuple[str, ...]]:
    """Saved order of the state models: the states sorted, the fallback last."""
    return (key == FALLBACK, key)


def fit_state(job: tuple) -> tuple[dict, dict]:
    """Fit one state's SGPDM (a top-level function so process pools can pickle it)."""
    audio, visual, lengths, cfg_dict = job
    with torch_threads(1):
        m = SGPDM(**cfg_dict).fit({"audio": audio, "visual": visual}, seq_lengths=lengths)
    return m.state()


def _states_from_dict(d: dict):
    """The state model saved by its ``to_dict`` (phone, VLMM, or right-context around either)."""
    kind = d.get("kind")
    if kind == "right-context":
        return RightContextStates(_states_from_dict(d["base"]))
    return PhoneStates.from_dict(d) if kind == "phone" else VLMM.from_dict(d)


_DEFAULTS = SwitchingConfig()


class SwitchingModel:
    """Switching shared GPDM, the generative model: ``fit`` on utterances (the state model
    and one SGPDM per state), the state lookup with back-off, and persistence.

    The keyword arguments are the fields of :class:`SwitchingConfig` (their one source of
    defaults), stored as given; :attr:`config` gathers them. Synthesis from new audio is
    in :mod:`bayes_talk.synthesis.sequential` and :mod:`bayes_talk.posterior.sampling`;
    the estimator with ``predict`` / ``predict_dist`` is
    :class:`bayes_talk.estimators.switching.SwitchingSGPDM`.
    """

    def __init__(self, *, states: str = _DEFAULTS.states, max_memory: int = _DEFAULTS.max_memory,
                 epsilon: float | None = _DEFAULTS.epsilon, min_count: int | None = _DEFAULTS.min_count,
                 latent_dim: int = _DEFAULTS.latent_dim, max_frames_per_state: int = _DEFAULTS.max_frames_per_state,
                 min_frames_per_state: int = _DEFAULTS.min_frames_per_state, max_iter: int = _DEFAULTS.max_iter,
                 fallback_frames: int = _DEFAULTS.fallback_frames, seed: int = _DEFAULTS.seed,
                 audio_context: int = _DEFAULTS.audio_context, right_context: bool = _DEFAULTS.right_context,
                 context_view: int = _DEFAULTS.context_view, context_mean: bool = _DEFAULTS.context_mean,
                 private_dims: int = _DEFAULTS.private_dims):
        if states not in ("vlmm", "phone"):
            raise ValueError(f"states must be 'vlmm' or 'phone', got {states!r}")
        if not isinstance(right_context, (bool, np.bool_)):
            raise ValueError(f"right_context must be True or False, got {right_context!r}")  # noqa: TRY004 - package convention: bad input is a ValueError
        self.states, self.max_memory, self.epsilon, self.min_count = states, max_memory, epsilon, min_count
        self.latent_dim, self.max_frames_per_state = latent_dim, max_frames_per_state
        self.min_frames_per_state, self.max_iter = min_frames_per_state, max_iter
        self.fallback_frames, self.seed = fallback_frames, seed
        self.audio_context = audio_context
        self.right_context = bool(right_context)
        self.audio_ = AudioContext(audio_context)
        if not isinstance(context_mean, (bool, np.bool_)):
            raise ValueError(f"context_mean must be True or False, got {context_mean!r}")  # noqa: TRY004 - package convention: bad input is a ValueError
        if context_mean and not context_view:
            raise ValueError("context_mean=True needs the phonetic-context view (context_view > 0), "
                             f"found context_view={context_view!r}")
        self.context_view = context_view
        self.context_mean = bool(context_mean)
        if not isinstance(private_dims, (int, np.integer)) or not 0 <= private_dims < latent_dim:
            raise ValueError(f"private_dims must be an integer in 0..latent_dim-1 = {latent_dim - 1} (the audio "
                             f"reads at least one latent dimension), got {private_dims!r}")
        self.private_dims = int(private_dims)
        self.context_ = ContextView(context_view)
        self.models_: dict[tuple[str, ...], SGPDM] = {}
        #: training frames per phone (the unseen-phone policy, data.phones.substitute_unseen)
        self.phone_counts_: dict[str, int] = {}
        self.entry_: dict[tuple[str, ...], tuple[np.ndarray, np.ndarray]] = {}

    @property
    def config(self) -> SwitchingConfig:
        """The settings, gathered from the constructor arguments."""
        return SwitchingConfig(**{f.name: getattr(self, f.name) for f in fields(SwitchingConfig)})

    @property
    def name(self) -> str:
        """Method family name: ``ssgpdm-vlmm`` or ``ssgpdm-phone``, with ``-rc`` for
        right-context states."""
        return f"ssgpdm-{self.config.states}" + ("-rc" if self.config.right_context else "")

    def audio_input(self, mfcc: np.ndarray, labels=None) -> np.ndarray:
        """The observed view the state models' "audio" GPs explain for these MFCCs (T, D):
        the MFCCs themselves, or with ``audio_context`` > 0 their context window (eq. 1 of
        :mod:`bayes_talk.features.audio_context`), joined with ``context_view`` > 0 by the
        phonetic-context view of the frame labels ``labels`` (eq. 1 of
        :mod:`bayes_talk.features.context_view`)."""
        a = self.audio_.transform(mfcc)
        if not self.context_.enabled:
            return a
        return np.hstack([a, self.context_.transform(mfcc, labels)])

    @property
    def audio_view_dim(self) -> int:
        """Columns of :meth:`audio_input`'s view: D_y (the MFCCs, or their context window
        projected back to D_y dimensions) plus the phonetic-context view's D_z when it is on."""
        return int(self.dims_[0]) + self.context_.n_dims

    def visual_offset(self, audio_view: np.ndarray) -> np.ndarray:
        """The explicit mean function c_t of the visual mapping (``context_mean``; (T, D_z))
        read off an audio view made by :meth:`audio_input` (its last D_z columns are the
        context view), or zeros (T, D_z) without it."""
        audio_view = np.asarray(audio_view, dtype=np.float64)
        n = self.dims_[1]
        if not self.context_mean:
            return np.zeros((audio_view.shape[0], n))
        if audio_view.ndim != 2 or audio_view.shape[1] < n:
            raise ValueError(f"audio view: expected (T, >= {n}) columns ending in the context view, "
                             f"found shape {audio_view.shape}")
        return audio_view[:, -n:].copy()

    # ------------------------------------------------------------------ training
    def _state_cfg(self) -> dict:
        cfg = self.config
        private = {"audio": cfg.latent_dim - cfg.private_dims} if cfg.private_dims else None
        return asdict(SGPDMConfig(latent_dim=cfg.latent_dim, dynamics=True, learn_dynamics=False,
                                  back_constraint=None, init="pca-average", max_iter=cfg.max_iter,
                                  seed=cfg.seed, view_dims=private))

    def fit(self, train: Sequence[Utterance], executor=None) -> SwitchingModel:
        """Train the state model (VLMM or phones) and one SGPDM per state: :meth:`plan_fit`,
        the state fits (:func:`fit_state`, through ``executor``), :meth:`finish_fit`.

        executor: anything with ``map(fn, iterable)`` that runs ``fn`` in other processes
        (``concurrent.futures.ProcessPoolExecutor``, Dask/Ray process-based executors);
        None fits the states one after another in this process. Thread pools are not
        supported: Pyro keeps one handler stack per process.
        """
        plan = self.plan_fit(train)
        mapper: Callable = executor.map if executor is not None else map
        return self.finish_fit(plan, list(mapper(fit_state, plan.jobs)))

    def plan_fit(self, train: Sequence[Utterance]) -> StateFitPlan:
        """The part of :meth:`fit` done in this process (the audio and context views, the state
        model, each state's training frames): fits the views and the state model into this
        object and returns the state fits still to do, largest first. A caller that runs the
        state fits itself (e.g. beside another model's, band_calibration) passes their
        results, in the plan's order, to :meth:`finish_fit`."""
        cfg = self.config
        if not train:
            raise ValueError("no training sequences")
        dims = {(s.mfcc.shape[1], None if s.aam is None else s.aam.shape[1]) for s in train}
        if len(dims) != 1 or next(iter(dims))[1] is None:
            raise ValueError(f"training sequences need aam features of one dimension; found (D_y, D_z) = {dims}")
        self.dims_ = next(iter(dims))
        n_frames = sum(s.n_frames for s in train)
        self.audio_ = AudioContext(cfg.audio_context).fit([s.mfcc for s in train])
        self.context_ = ContextView(cfg.context_view)
        context_in = self.context_.fit(train)   # out-of-fold on the training frames
        audio_in = [np.hstack([self.audio_.transform(s.mfcc), c]) for s, c in zip(train, context_in)]
        # the face the state models explain: z_t, or the residual z_t − c_t (context_mean)
        face = [s.aam - c if cfg.context_mean else s.aam for s, c in zip(train, context_in)]
        if cfg.states == "vlmm":
            eps = cfg.epsilon if cfg.epsilon is not None else 2e-4 * 19000.0 / n_frames
            mc = cfg.min_count if cfg.min_count is not None else max(10, round(40 * n_frames / 15000))
            self.states_model_ = VLMM(cfg.max_memory, eps, mc).fit([s.labels for s in train])
        else:
            self.states_model_ = PhoneStates().fit([s.labels for s in train])
        if cfg.right_context:
            self.states_model_ = RightContextStates(self.states_model_)
        # training subsequences per state (overlapping by design)
        subs: dict[tuple[str, ...], list[tuple[int, int, int]]] = defaultdict(list)
        for i, s in enumerate(train):
            for seg in self.states_model_.training_subsequences(s.labels):
                subs[tuple(seg.state)].append((i, seg.start, seg.stop))
        rng = np.random.default_rng(cfg.seed)
        jobs, keys = [], []
        for state in sorted(subs):
            chosen = self._cap(subs[state], rng)
            n = sum(b - a for _, a, b in chosen)
            if n < max(cfg.min_frames_per_state, cfg.latent_dim + 1):
                continue
            audio = np.vstack([audio_in[i][a:b] for i, a, b in chosen])
            visual = np.vstack([face[i][a:b] for i, a, b in chosen])
            jobs.append((audio, visual, [b - a for _, a, b in chosen], self._state_cfg()))
            keys.append(state)
        # global fallback: random whole utterance chunks up to fallback_frames
        chunks = [(i, a, min(a + 25, s.n_frames)) for i, s in enumerate(train) for a in range(0, s.n_frames, 25)]
        chosen = self._cap(chunks, rng, cfg.fallback_frames)
        jobs.append((np.vstack([audio_in[i][a:b] for i, a, b in chosen]),
                     np.vstack([face[i][a:b] for i, a, b in chosen]),
                     [b - a for _, a, b in chosen], self._state_cfg()))
        keys.append(FALLBACK)
        log.info("training %d state models (%d states seen)", len(jobs), len(subs))
        self.n_training_frames_ = n_frames
        self.phone_counts_ = dict(sorted(Counter(lab for s in train for lab in s.labels).items()))
        # per-dimension mean square frame-to-frame motion of the visual features
        self.motion_var_ = np.mean(np.vstack([np.diff(f, axis=0) for f in face if len(f) > 1]) ** 2, 0)
        # largest first (the fallback, then the capped states): parallel workers finish together
        order = sorted(range(len(jobs)), key=lambda j: -len(jobs[j][0]))
        return StateFitPlan([keys[j] for j in order], [jobs[j] for j in order])

    def finish_fit(self, plan: StateFitPlan, results: Sequence[tuple[dict, dict]]) -> SwitchingModel:
        """The fitted model from :meth:`plan_fit`'s plan and the results of ``fit_state`` on
        its jobs (same order): each state's SGPDM and its entry distribution (eq. 12), in
        state order."""
        if len(results) != len(plan.jobs):
            raise ValueError(f"finish_fit: the plan has {len(plan.jobs)} state fits, found {len(results)} results")
        models = dict(zip(plan.keys, results))
        self.models_ = {k: SGPDM.from_state(*models[k]) for k in sorted(models, key=_state_order)}
        self.entry_ = {k: self._entry(m) for k, m in self.models_.items()}
        return self

    def _cap(self, subs: list, rng: np.random.Generator, cap: int | None = None) -> list:
        cap = self.config.max_frames_per_state if cap is None else cap
        if sum(b - a for _, a, b in subs) <= cap:
            return list(subs)
        out, n = [], 0
        for j in rng.permutation(len(subs)):
            _, a, b = subs[j]
            if n + (b - a) > cap:
                continue
            out.append(subs[j])
            n += b - a
        return sorted(out)

    @staticmethod
    def _entry(m: SGPDM) -> tuple[np.ndarray, np.ndarray]:
        """Entry distribution N(μ_π, Σ_π) of eq. 12 from the first latent points."""
        starts = np.cumsum([0] + m.seq_lengths_[:-1])
        first = m.X_[starts]
        d = m.X_.shape[1]
        pool = first if len(first) > d else m.X_
        cov = np.cov(pool.T) + 1e-6 * np.eye(d) * max(1.0, float(np.trace(np.cov(pool.T))) / d)
        return first.mean(0), cov

    # ------------------------------------------------------------------ lookup
    def model_for(self, state: Sequence[str]) -> tuple[tuple[str, ...], SGPDM]:
        """The model of ``state`` or of its longest suffix that has one (else fallback)."""
        st = tuple(state)
        while st:
            if st in self.models_:
                return st, self.models_[st]
            st = st[1:]
        return FALLBACK, self.models_[FALLBACK]

    def segment(self, labels: Sequence[str]) -> list[Segment]:
        """Non-overlapping state segmentation of a label sequence (§4.2.1)."""
        counts = self.phone_counts_ or {p: 1 for p in self.states_model_.alphabet_}
        return self.states_model_.segment(replace_unseen(list(labels), counts, stacklevel=3), unknown="error")

    # ------------------------------------------------------------------ persistence
    def state(self) -> tuple[dict, dict[str, np.ndarray]]:
        """(JSON-able metadata, arrays) that fully describe the fitted model: the state model,
        the views, and each state's SGPDM (:meth:`SGPDM.state`) with its entry distribution.
        The estimator saves them (:meth:`bayes_talk.estimators.base.Estimator.save`)."""
        if not self.models_:
            raise not_fitted(self, "call fit(train) or load() first")
        meta = {"format": FORMAT_NAME, "version": FORMAT_VERSION, "config": asdict(self.config),
                "dims": list(self.dims_), "states_model": self.states_model_.to_dict(),
                "n_training_frames": self.n_training_frames_, "phone_counts": self.phone_counts_, "models": []}
        arrays: dict[str, np.ndarray] = {"motion_var": self.motion_var_, **self.audio_.arrays(),
                                         **self.context_.arrays()}
        meta["context_view"] = self.context_.to_meta()
        for j, (st, m) in enumerate(self.models_.items()):
            mmeta, marr = m.state()
            meta["models"].append({"state": list(st), "meta": mmeta})
            for k, a in marr.items():
                arrays[f"{j}/{k}"] = a
            arrays[f"{j}/entry_mean"], arrays[f"{j}/entry_cov"] = self.entry_[st]
        return meta, arrays

    def restore(self, meta: dict, arrays: dict[str, np.ndarray]) -> None:
        """Set the fitted model from :meth:`state`'s output (self built with the same settings);
        ValueError when the format is another's, KeyError / TypeError when a part is missing."""
        check_format(meta, FORMAT_NAME, FORMAT_VERSION, "switching model")
        self.dims_ = tuple(meta["dims"])
        self.n_training_frames_ = meta["n_training_frames"]
        # models saved before the counts were recorded: every seen phone counts once
        self.phone_counts_ = {k: int(v) for k, v in meta.get("phone_counts", {}).items()}
        self.states_model_ = _states_from_dict(meta["states_model"])
        self.motion_var_ = np.asarray(arrays["motion_var"], dtype=np.float64)
        self.audio_ = AudioContext.from_arrays(self.audio_context, arrays)
        self.context_ = ContextView.from_saved(meta.get("context_view"), arrays)
        grouped: dict[str, dict[str, np.ndarray]] = defaultdict(dict)
        for k, a in arrays.items():
            if "/" not in k:
                continue
            j, rest = k.split("/", 1)
            grouped[j][rest] = a
        self.models_, self.entry_ = {}, {}
        for j, entry in enumerate(meta["models"]):
            st = tuple(entry["state"])
            sub = grouped[str(j)]
            self.models_[st] = SGPDM.from_state(entry["meta"], sub)
            self.entry_[st] = (sub["entry_mean"], sub["entry_cov"])

    @classmethod
    def read_legacy(cls, directory: str | Path) -> SwitchingModel:
        """A model saved in the earlier per-family layout: ``model.json`` + ``arrays.npz`` in
        ``directory`` (a trained-model directory's top); errors name the file."""
        directory = Path(directory)
        meta, arrays = read_model_files(directory / "model.json", directory / "arrays.npz")
        check_format(meta, FORMAT_NAME, FORMAT_VERSION, f"{directory / 'model.json'}")
        try:
            obj = cls(**meta["config"])
            obj.restore(meta, arrays)
        except (KeyError, TypeError) as exc:
            raise ValueError(f"{directory}: switching model is incomplete or corrupt (missing {exc})") from None
        return obj


