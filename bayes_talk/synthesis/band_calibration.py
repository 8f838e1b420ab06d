"""Band recalibration fitted on held-out training utterances (issue 10 item 3).

The whole-utterance posterior's bands are too narrow on new sentences (90 % band ≈ 0.79
on the deena2010 held-out test, docs/results.md): the synthesis posterior is conditional
on the trained hyperparameters and training latents, whose own uncertainty is not
propagated, and the GP noise levels are fitted to training frames. The remedy here is
one scale factor s_d per AAM parameter d applied to the whole predictive mixture about
its mean m_td,

    z' = m_td + s_d (z − m_td):   μ'^k_td = m_td + s_d (μ^k_td − m_td),   v'^k_td = s_d² v^k_td,   (1)

an affine map of the mixture, so its mean is unchanged, its standard deviation and every
central band's half-widths are multiplied by s_d, and samples, quantiles, CDF and density
of the calibrated result follow exactly (it is again a
:class:`~bayes_talk.synthesis.result.SynthesisResult`).

**Fitting s_d** (:meth:`BandCalibration.fit`). For each held-out entry with truth y,
mixture mean m and raw central band [l_q, u_q] at level q, the smallest scale whose band
(1) contains y is

    s*_q = (y − m)/(u_q − m)  if y > m,   (m − y)/(m − l_q)  if y < m,   0 if y = m,

so the calibrated coverage at level q is the empirical CDF of s*_q at s_d, exactly, with
no re-synthesis. s_d minimises Σ_q (cov_q(s) − q)² over q ∈ {0.5, 0.8, 0.9, 0.95} on a log
grid of s in [1/8, 8] (the middle of the minimising set when it is flat). One factor
per parameter cannot fix a wrong *shape* (e.g. heavy tails): the fitted in-sample
coverage at every level is stored beside the factors so that shows.

**Where the held-out utterances come from** (:func:`fit_band_calibration`): a seeded
``holdout`` fraction (default 20 %) of the *training* utterances; a second model of the
same configuration is trained on the other 80 %, the held-out ones are synthesised by
the posterior method, and the factors are fitted to them. The factors are then applied
to the model trained on all utterances. Cost: one extra fit (on 80 % of the data) and
the synthesis of the held-out utterances; K-fold cross-validation would cost K fits,
and the state models' own training residuals are in-sample (too small by construction).
The full model has seen 25 % more data than the calibration model, so its bands are if
anything slightly conservative after calibration.

Saved with the model as ``band_calibration.json`` (:meth:`BandCalibration.save`;
``bayes-talk train --calibrate-bands``), applied by ``synth`` to the posterior method it
was fitted on, and reported calibrated and raw side by side by ``evaluate``.
"""
from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from bayes_talk.files import write_json
from bayes_talk.synthesis.result import DEFAULT_LEVELS, SynthesisResult

__all__ = ["CALIBRATION_FILE", "HOLDOUT_FRACTION", "BandCalibration", "fit_band_calibration", "min_scales",
           "split_for_calibration"]

log = logging.getLogger(__name__)

CALIBRATION_FILE = "band_calibration.json"
_FORMAT = "bayes_talk.band_calibration"
_VERSION = 1
#: default fraction of the training utterances held out to fit the calibration
HOLDOUT_FRACTION = 0.2
_GRID = np.exp(np.linspace(math.log(1 / 8), math.log(8), 2001))


def min_scales(result: SynthesisResult, truth: np.ndarray, levels: Sequence[float] = DEFAULT_LEVELS
               ) -> np.ndarray:
    """s*_q (L, T, D): the smallest scale (1) whose central band at each level contains the
    truth (T, D) (inf where no scale does: a band that does not reach past the mean)."""
    y = np.asarray(truth, dtype=np.float64)
    m = result.mean
    if y.shape != m.shape:
        raise ValueError(f"truth: expected shape {m.shape} (the prediction's), found {y.shape}")
    out = []
    with np.errstate(divide="ignore", invalid="ignore"):
        for q in levels:
            lo, hi = result.interval(q)
            up = np.where(hi > m, (y - m) / (hi - m), np.inf)
            down = np.where(lo < m, (m - y) / (m - lo), np.inf)
            out.append(np.where(y > m, up, np.where(y < m, down, 0.0)))
    return np.asarray(out)


def _coverage_at(s_star: np.ndarray, scale: np.ndarray | float) -> np.ndarray:
    """(L,) coverage at each level of bands scaled by ``scale`` (per last axis)."""
    return np.mean(s_star <= scale, axis=tuple(range(1, s_star.ndim)))


@dataclass
class BandCalibration:
    """Per-parameter scale factors (1) of one synthesis method's predictive.

    scale: (D,) factors s_d; method: the synthesis method they were fitted on
    ("laplace", ...); levels: the levels fitted; n_utterances / n_frames: the held-out data;
    coverage_raw / coverage_calibrated: {level: pooled coverage} on that data before and
    after (in-sample); held_out: the held-out utterance names; info: how it was made
    (hold-out fraction, seed, draws).
    """

    scale: np.ndarray
    method: str
    levels: tuple[float, ...] = tuple(DEFAULT_LEVELS)
    n_utterances: int = 0
    n_frames: int = 0
    coverage_raw: dict[str, float] = field(default_factory=dict)
    coverage_calibrated: dict[str, float] = field(default_factory=dict)
    held_out: list[str] = field(default_factory=list)
    info: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.scale = np.asarray(self.scale, dtype=np.float64)
        if self.scale.ndim != 1 or self.scale.size == 0:
            raise ValueError(f"scale: expected a non-empty 1-D array (one factor per AAM parameter), "
                             f"found shape {self.scale.shape}")
        if not np.all(np.isfinite(self.scale) & (self.scale > 0)):
            raise ValueError("scale: expected finite factors > 0")
        self.levels = tuple(float(q) for q in self.levels)

    # ------------------------------------------------------------------ fit / apply
    @classmethod
    def fit(cls, results: Sequence[SynthesisResult], truths: Sequence[np.ndarray], method: str | None = None,
            levels: Sequence[float] = DEFAULT_LEVELS, per_parameter: bool = True,
            names: Sequence[str] = ()) -> BandCalibration:
        """Fit s_d on held-out predictions ``results`` and their truths (each (T_i, D)).

        per_parameter=False fits one factor for all parameters (pooled)."""
        if not results or len(results) != len(truths):
            raise ValueError(f"fit: need one truth per result and at least one, got {len(results)} results "
                             f"and {len(truths)} truths")
        levels = tuple(float(q) for q in levels)
        s_star = np.concatenate([min_scales(r, z, levels) for r, z in zip(results, truths)], axis=1)  # (L, N, D)
        L, N, D = s_star.shape
        target = np.asarray(levels)[:, None]
        cols = [s_star.reshape(L, -1)] if not per_parameter else [s_star[:, :, d] for d in range(D)]
        scale = []
        for col in cols:
            srt = np.sort(col, axis=1)
            cov = np.stack([np.searchsorted(srt[j], _GRID, side="right") for j in range(L)]) / srt.shape[1]
            loss = np.sum((cov - target) ** 2, axis=0)
            best = np.flatnonzero(loss <= loss.min() + 1e-12)
            scale.append(float(_GRID[best[len(best) // 2]]))
        scale = np.full(D, scale[0]) if not per_parameter else np.asarray(scale)
        raw, cal = _coverage_at(s_star, 1.0), _coverage_at(s_star, scale)
        meth = method if method is not None else results[0].method
        return cls(scale, meth, levels, len(results), int(N),
                   {f"{q:g}": float(c) for q, c in zip(levels, raw)},
                   {f"{q:g}": float(c) for q, c in zip(levels, cal)}, list(names),
                   {"per_parameter": bool(per_parameter)})

    def apply(self, result: SynthesisResult) -> SynthesisResult:
        """The calibrated result: (1) applied to every component; the factors are recorded in
        its diagnostics under ``band_calibration``."""
        if result.n_dims != self.scale.size:
            raise ValueError(f"band calibration has {self.scale.size} factors but the prediction has "
                             f"{result.n_dims} AAM parameters: it belongs to another model")
        m = result.mean[None, None]
        s = self.scale
        diag = dict(result.diagnostics)
        diag["band_calibration"] = {"method": self.method, "scale_min": float(s.min()),
                                    "scale_median": float(np.median(s)), "scale_max": float(s.max())}
        return replace(result, draw_mean=m + s * (result.draw_mean - m), draw_var=result.draw_var * s * s,
                       diagnostics=diag)

    # ------------------------------------------------------------------ persistence
    def to_dict(self) -> dict[str, Any]:
        """JSON-able form (format, version, method, levels, factors, fit information)."""
        return {"format": _FORMAT, "version": _VERSION, "method": self.method, "levels": list(self.levels),
                "scale": self.scale.tolist(), "n_utterances": self.n_utterances, "n_frames": self.n_frames,
                "coverage_raw": self.coverage_raw, "coverage_calibrated": self.coverage_calibrated,
                "held_out": list(self.held_out), "info": self.info}

    @classmethod
    def from_dict(cls, d: dict[str, Any], where: str = "band calibration") -> BandCalibration:
        """The calibration saved by :meth:`to_dict` (ValueError naming ``where`` if malformed)."""
        if not isinstance(d, dict) or d.get("format") != _FORMAT:
            raise ValueError(f"{where}: expected format {_FORMAT!r}, found "
                             f"{d.get('format') if isinstance(d, dict) else type(d).__name__!r}")
        if d.get("version") != _VERSION:
            raise ValueError(f"{where}: format version {d.get('version')!r}; this bayes_talk reads {_VERSION}")
        try:
            return cls(np.asarray(d["scale"], dtype=np.float64), str(d["method"]), tuple(d["levels"]),
                       int(d["n_utterances"]), int(d["n_frames"]), dict(d["coverage_raw"]),
                       dict(d["coverage_calibrated"]), list(d["held_out"]), dict(d.get("info", {})))
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{where}: incomplete or invalid band calibration ({exc})") from None

    def save(self, directory: str | Path) -> Path:
        """Write ``band_calibration.json`` into ``directory`` (atomically)."""
        return write_json(Path(directory) / CALIBRATION_FILE, self.to_dict())

    @classmethod
    def load(cls, directory: str | Path) -> BandCalibration | None:
        """The calibration saved in ``directory``, or None when there is none."""
        import json

        p = Path(directory) / CALIBRATION_FILE
        if not p.is_file():
            return None
        try:
            d = json.loads(p.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise ValueError(f"{p}: unreadable band calibration ({exc})") from None
        return cls.from_dict(d, where=str(p))


def split_for_calibration(n: int, holdout: float = HOLDOUT_FRACTION, seed: int = 0) -> tuple[list[int], list[int]]:
    """(fit indices, held-out indices) of ``n`` utterances: a seeded ``holdout`` fraction
    (at least one) is held out, at least two are left to fit on."""
    if not 0.0 < holdout < 1.0:
        raise ValueError(f"holdout: expected a fraction in (0, 1), found {holdout!r}")
    n_hold = max(1, round(holdout * n))
    if n - n_hold < 2:
        raise ValueError(f"band calibration needs at least 3 training utterances (2 to fit, 1 held out); "
                         f"found {n}")
    held = sorted(int(i) for i in np.random.default_rng([seed, 2**17]).choice(n, n_hold, replace=False))
    hs = set(held)
    return [i for i in range(n) if i not in hs], held


def fit_band_calibration(model, train: Sequence, method: str = "laplace", holdout: float = HOLDOUT_FRACTION,
                         n_draws: int = 64, seed: int = 0, executor=None,
                         progress: Callable[[str], None] | None = None,
                         fit: Callable | None = None) -> BandCalibration:
    """Fit the calibration of a switching model's ``method`` posterior on held-out
    training utterances (module docstring): a model of ``model``'s configuration is
    trained on the other utterances of ``train`` (through ``executor`` as
    ``SwitchingSGPDM.fit``), the held-out ones are synthesised with ``n_draws`` draws
    (seed ``seed``) and the factors fitted to their AAM parameters. ``fit(model, utterances)``
    replaces the training call (e.g. the CLI's, with its progress bar and process pool)."""
    from bayes_talk.models.switching import SwitchingModel
    from bayes_talk.synthesis.posterior import sample_synthesis

    if not isinstance(model, SwitchingModel):
        raise TypeError(f"band calibration needs a switching SGPDM, found {type(model).__name__}")
    seqs = list(train)
    fit_idx, held_idx = split_for_calibration(len(seqs), holdout, seed)
    say = progress or (lambda msg: log.info("%s", msg))
    say(f"band calibration: training a {model.name} model on {len(fit_idx)} utterances, "
        f"holding out {len(held_idx)}")
    sub = type(model)(**asdict(model.config))
    rest = [seqs[i] for i in fit_idx]
    sub = fit(sub, rest) if fit is not None else sub.fit(rest, executor=executor)
    results, truths = [], []
    for j, i in enumerate(held_idx):
        s = seqs[i]
        results.append(sample_synthesis(sub, s.mfcc, s.labels, method=method, n_draws=n_draws, seed=seed,
                                        log_warnings=False))
        truths.append(s.aam)
        if (j + 1) % 10 == 0 or j + 1 == len(held_idx):
            say(f"band calibration: synthesised {j + 1}/{len(held_idx)} held-out utterances")
    cal = BandCalibration.fit(results, truths, method=method, names=[seqs[i].name for i in held_idx])
    cal.info.update(holdout=float(holdout), seed=int(seed), n_draws=int(n_draws), n_fit=len(fit_idx))
    say("band calibration: 90 % coverage on the held-out utterances {:.3f} raw -> {:.3f} calibrated; "
        "factors {:.2f}-{:.2f} (median {:.2f})".format(cal.coverage_raw.get("0.9", float("nan")),
                                                      cal.coverage_calibrated.get("0.9", float("nan")),
                                                      cal.scale.min(), cal.scale.max(), np.median(cal.scale)))
    return cal
