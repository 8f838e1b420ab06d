"""The alignment bundle: phone HMMs, phone-bigram language model, decoding settings.

:class:`AlignmentModel` is what a trained model directory holds next to the switching
model (``alignment.json`` + ``alignment.npz``; no pickle). It is fitted on a corpus with
known phone boundaries (the built corpus's espeak-ng labels, or a user corpus's
``.lab``/``.TextGrid``):

* :class:`~bayes_talk.alignment.phone_hmm.PhoneHMMs` on the 10 ms alignment features;
* the phone bigram ``P(q | p) = (c(p, q) + alpha) / (c(p) + alpha P)`` from the training
  phone sequences (add-alpha smoothing, ``alpha = 0.1``), and ``P(q | <s>)`` likewise
  from the first phones;
* the recogniser's language-model weight and insertion penalty, chosen on training
  utterances only (grid search minimising the phone error rate; :meth:`AlignmentModel.fit`).

Use: :meth:`AlignmentModel.align` (transcript + audio -> intervals; ``method="hmm"``
forced alignment, the default, or ``"dtw"``) and :meth:`AlignmentModel.recognise`
(audio -> intervals).
"""
from __future__ import annotations

import itertools
import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bayes_talk.alignment.errors import MissingAlignmentModelError
from bayes_talk.alignment.features import FeatureConfig, alignment_features
from bayes_talk.alignment.forced import MAX_ALIGNMENT_COST, force_align
from bayes_talk.alignment.phone_hmm import PhoneHMMs
from bayes_talk.alignment.scoring import score_segmentation, summarise_scores
from bayes_talk.alignment.segments import segments_to_intervals
from bayes_talk.alignment.viterbi import viterbi_phone_loop
from bayes_talk.base.files import check_format
from bayes_talk.data.phones import PHONES

__all__ = ["ALIGN_METHODS", "AlignmentModel", "AlignmentResult", "load_alignment_model"]

log = logging.getLogger(__name__)

FORMAT = "bayes_talk.alignment_model"
VERSION = 1
JSON_NAME, NPZ_NAME = "alignment.json", "alignment.npz"
ALIGN_METHODS = ("hmm", "dtw")
BIGRAM_ALPHA = 0.1
#: vocal-tract-length warps tried on every utterance (features.py); the one whose frames the
#: phone HMMs explain best (largest mean over frames of the best state's log-likelihood) is
#: used. Measured (docs/alignment.md): the training voice picks 1.0; voice en+f3 picks
#: 0.70-0.75, and the recogniser's PER on it falls from 0.80 to 0.44 (20 utterances).
#: A grid reaching 0.5 picked 0.5 too often and did worse (PER 0.58).
WARPS = (0.70, 0.75, 0.80, 0.85, 0.90, 0.95, 1.0, 1.05, 1.10, 1.15, 1.20)
LM_WEIGHTS = (2.0, 4.0, 8.0, 12.0, 16.0)
INSERTION_PENALTIES = (-20.0, -10.0, 0.0, 10.0)


@dataclass
class AlignmentResult:
    """Intervals ``(start_s, end_s, phone)`` covering the audio, and how they were found."""

    intervals: list[tuple[float, float, str]]
    method: str
    cost: float | None = None
    seconds: float = 0.0
    info: dict = field(default_factory=dict)


class AlignmentModel:
    """Phone HMMs + bigram LM + recogniser settings (see the module docstring)."""

    def __init__(self, n_iter: int = 8, n_tune: int = 20, seed: int = 0, voice: str = "en") -> None:
        self.n_iter, self.n_tune, self.seed, self.voice = int(n_iter), int(n_tune), int(seed), voice
        self.cfg = FeatureConfig()
        self.phones = PHONES
        self.lm_weight = 2.0
        self.insertion = 0.0
        self.max_cost = MAX_ALIGNMENT_COST
        self.info: dict = {}

    # ------------------------------------------------------------------ fitting
    def fit(self, sequences, sample_rate: int | None = None) -> AlignmentModel:
        """Fit on utterances with ``audio_path`` and ``meta["intervals"]`` (a loaded corpus)."""
        from bayes_talk.alignment.features import load_audio

        t0 = time.perf_counter()
        seqs = [s for s in sequences if s.audio_path is not None and s.meta.get("intervals")]
        if not seqs:
            raise ValueError("alignment training needs utterances with audio files and phone intervals")
        if sample_rate is None:
            import soundfile as sf

            sample_rate = int(sf.info(str(seqs[0].audio_path)).samplerate)
        self.cfg = FeatureConfig(sample_rate)
        index = {p: i for i, p in enumerate(self.phones)}
        segments: dict[str, list[np.ndarray]] = {p: [] for p in self.phones}
        P = len(self.phones)
        big = np.zeros((P, P))
        start = np.zeros(P)
        feats, truths = [], []
        for s in seqs:
            y = load_audio(s.audio_path, self.cfg.sample_rate)
            X = alignment_features(y, self.cfg, where=str(s.audio_path))
            ivs = [tuple(iv) for iv in s.meta["intervals"]]
            feats.append(X)
            truths.append((ivs, y.size / self.cfg.sample_rate, s.n_frames))
            t = np.arange(X.shape[0]) * self.cfg.frame_s
            which = np.searchsorted([a for a, _, _ in ivs], t, side="right") - 1
            for k, (a, b, p) in enumerate(ivs):
                rows = X[which == k]
                if len(rows):
                    segments[p].append(rows)
            ph = [index[p] for _, _, p in ivs]
            start[ph[0]] += 1
            for a, b in itertools.pairwise(ph):
                big[a, b] += 1
        self.hmms = PhoneHMMs(n_iter=self.n_iter, seed=self.seed, phones=self.phones).fit(segments)
        self.log_bigram = np.log((big + BIGRAM_ALPHA) / (big.sum(axis=1, keepdims=True) + BIGRAM_ALPHA * P))
        self.log_start = np.log((start + BIGRAM_ALPHA) / (start.sum() + BIGRAM_ALPHA * P))
        fit_s = time.perf_counter() - t0
        # recogniser settings: grid search on (a seeded subset of) the training utterances
        rng = np.random.default_rng([self.seed, 13])
        pick = sorted(rng.choice(len(seqs), size=min(self.n_tune, len(seqs)), replace=False).tolist())
        logbs = [self.hmms.log_emissions(feats[i]) for i in pick]
        grid = []
        for w in LM_WEIGHTS:
            for ins in INSERTION_PENALTIES:
                rows = []
                for i, lb in zip(pick, logbs):
                    ivs, dur, _nf = truths[i]
                    hyp = self._decode(lb, dur, w, ins)
                    rows.append(score_segmentation(ivs, hyp))
                grid.append((summarise_scores(rows)["phone_error_rate"], w, ins))
        per, self.lm_weight, self.insertion = min(grid)
        self.info = {"n_train": len(seqs), "n_tune": len(pick), "hmm_fit_seconds": fit_s,
                     "tune_seconds": time.perf_counter() - t0 - fit_s, "tune_phone_error_rate": per,
                     "grid": [{"phone_error_rate": g[0], "lm_weight": g[1], "insertion": g[2]} for g in grid],
                     "segments_per_phone": {p: int(c) for p, c in zip(self.phones, self.hmms.counts_)}}
        log.info("alignment models: %d utterances, recogniser lm_weight %g insertion %g (training PER %.3f)",
                 len(seqs), self.lm_weight, self.insertion, per)
        return self

    # ------------------------------------------------------------------ decoding
    def _decode(self, logb: np.ndarray, duration: float, lm_weight: float, insertion: float):
        segs, _ = viterbi_phone_loop(logb, self.hmms.log_stay_, self.hmms.log_move_, self.log_bigram,
                                     self.log_start, lm_weight, insertion)
        named = [(self.phones[q], a, b) for q, a, b in segs]
        return segments_to_intervals(named, logb.shape[0], duration, self.cfg)

    def _features(self, audio, where: str) -> tuple[np.ndarray, float]:
        """Features at the best vocal-tract warp (:data:`WARPS`) and the duration (s)."""
        from bayes_talk.alignment.features import features_for_warps, load_audio, power_spectrum

        y = load_audio(audio, self.cfg.sample_rate) if isinstance(audio, (str, Path)) else np.asarray(audio)
        spec = power_spectrum(y, self.cfg, where)
        best, self.last_warp = None, 1.0
        for w, X in zip(WARPS, features_for_warps(spec, self.cfg, WARPS, where), strict=True):
            score = float(self.hmms.log_emissions(X[::3]).max(axis=1).mean())  # every 3rd frame: 3x cheaper
            if best is None or score > best[0]:
                best, self.last_warp = (score, X), w
        return best[1], y.size / self.cfg.sample_rate

    def recognise(self, audio, where: str | None = None) -> AlignmentResult:
        """Phone intervals of a WAV path (or a waveform at ``cfg.sample_rate``), no transcript."""
        with _one_blas_thread():
            return self._recognise(audio, where)

    def _recognise(self, audio, where: str | None) -> AlignmentResult:
        t0 = time.perf_counter()
        where = where or str(audio if isinstance(audio, (str, Path)) else "audio")
        X, dur = self._features(audio, where)
        ivs = self._decode(self.hmms.log_emissions(X), dur, self.lm_weight, self.insertion)
        return AlignmentResult(ivs, "recognised", None, time.perf_counter() - t0, {"warp": self.last_warp})

    def align(self, audio, text: str, method: str = "hmm", where: str | None = None) -> AlignmentResult:
        """Align a transcript to a WAV path (or waveform); named errors for bad transcripts."""
        with _one_blas_thread():
            return self._align(audio, text, method, where)

    def _align(self, audio, text: str, method: str, where: str | None) -> AlignmentResult:
        from bayes_talk.alignment.dtw import dtw_align
        from bayes_talk.alignment.transcript import check_transcript, synthesise_transcript

        if method not in ALIGN_METHODS:
            raise ValueError(f"alignment method must be one of {ALIGN_METHODS}, got {method!r}")
        t0 = time.perf_counter()
        where = where or str(audio if isinstance(audio, (str, Path)) else "audio")
        check_transcript(text)
        X, dur = self._features(audio, where)
        synth = synthesise_transcript(text, self.voice)
        # the HMM forced alignment always runs: its cost is the "transcript does not fit
        # the audio" check (forced.py) for both methods
        phones = [p for _, _, p in synth.intervals]
        segs, cost = force_align(self.hmms.log_emissions(X), phones, self.hmms, where, self.max_cost)
        if method == "dtw":
            segs, _ = dtw_align(X, synth, self.cfg)
        ivs = segments_to_intervals(segs, X.shape[0], dur, self.cfg)
        return AlignmentResult(ivs, f"aligned-{method}", cost, time.perf_counter() - t0, {"warp": self.last_warp})

    # ------------------------------------------------------------------ persistence
    def save(self, model_dir: str | Path) -> Path:
        """Write ``alignment.json`` + ``alignment.npz`` into ``model_dir`` (atomically)."""
        from bayes_talk.base.files import write_json, write_npz

        d = Path(model_dir)
        write_npz(d / NPZ_NAME, {**self.hmms.arrays(), "log_bigram": self.log_bigram,
                                 "log_start": self.log_start})
        write_json(d / JSON_NAME, {"format": FORMAT, "version": VERSION, "phones": list(self.phones),
                                   "features": self.cfg.to_json(), "lm_weight": self.lm_weight,
                                   "insertion": self.insertion,
                                   "voice": self.voice, "n_iter": self.n_iter, "seed": self.seed,
                                   "info": self.info})
        return d / JSON_NAME

    @classmethod
    def load(cls, model_dir: str | Path) -> AlignmentModel:
        """Read what :meth:`save` wrote; errors name the file."""
        from bayes_talk.corpus import load_npz

        d = Path(model_dir)
        jp = d / JSON_NAME
        if not jp.exists():
            raise MissingAlignmentModelError(
                f"{d}: no alignment models ({JSON_NAME}); train them with "
                f"`bayes-talk align-train CORPUS_DIR --model-dir {d}` (or retrain with `bayes-talk train`)")
        try:
            meta = json.loads(jp.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise ValueError(f"{jp}: cannot read alignment model ({exc})") from exc
        check_format(meta, FORMAT, VERSION, str(jp))
        arrays = load_npz(d / NPZ_NAME, ("hmm_means", "hmm_vars", "hmm_log_stay", "hmm_log_move",
                                         "hmm_counts", "log_bigram", "log_start"))
        self = cls(n_iter=meta.get("n_iter", 8), seed=meta.get("seed", 0), voice=meta.get("voice", "en"))
        self.phones = tuple(meta["phones"])
        self.cfg = FeatureConfig.from_json(meta["features"])
        self.hmms = PhoneHMMs.from_arrays(arrays, self.phones)
        self.log_bigram = np.asarray(arrays["log_bigram"], dtype=np.float64)
        self.log_start = np.asarray(arrays["log_start"], dtype=np.float64)
        self.lm_weight, self.insertion = float(meta["lm_weight"]), float(meta["insertion"])
        self.info = meta.get("info", {})
        return self


def _one_blas_thread():
    """One BLAS thread: the products here are small, and with 2 threads on 2 busy cores a
    (40 x 257) @ (257 x 300) product took 60 ms instead of < 1 ms (measured)."""
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=1)


def load_alignment_model(model_dir: str | Path) -> AlignmentModel:
    """:meth:`AlignmentModel.load`."""
    return AlignmentModel.load(model_dir)
