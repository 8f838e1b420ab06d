"""Calibration of predictive distributions against held-out truth (docs/uncertainty.md).

Every predictive is a :class:`~bayes_talk.synthesis.result.SynthesisResult`: per entry
(frame t, AAM parameter d) the mixture over K components

    p(z_td) = (1/K) Σ_k N(z_td; μ_td^k, v_td^k)                                     (1)

(K = 1 for a point method or a baseline with a Gaussian variance:
``SynthesisResult.gaussian``). For each test utterance :func:`score_utterance` computes,
from that type only:

* **coverage**: whether z_td lies in the central band at level q, the exact mixture
  quantiles ``result.interval(q)`` (the bands ``synth`` writes), q ∈ {0.5, 0.8, 0.9, 0.95};
  and the band's width;
* **PIT** u_td = F_td(z_td) = (1/K) Σ_k Φ((z_td − μ^k)/√v^k) (``result.cdf``): uniform on
  [0, 1] for a calibrated predictive (Dawid 1984; Gneiting, Balabdaoui & Raftery 2007);
  a U-shaped histogram means too narrow bands, a hump too wide ones;
* **mixture NLPD** −ln p(z_td) of (1) itself (``result.logpdf``, a log-sum-exp over the
  components), not of a moment-matched Gaussian;
* **CRPS**: for K = 1 the closed form of the Gaussian; for a mixture the sample (energy)
  form E|X − z| − ½ E|X − X'| from ``crps_samples`` draws of (1) (``result.sample``,
  seeded), with the fair (unbiased) pair term (:func:`~bayes_talk.evaluation.metrics.crps_sample_entries`);
  the same for a band-calibrated result
  (:class:`~bayes_talk.calibration.recalibrated.RecalibratedResult`, whose ``cdf``,
  ``logpdf`` and ``interval`` are those of the recalibrated distribution, exactly, and
  whose draws are inverse-transform draws of it).
  (A maintained closed form for normal mixtures exists — ``scoringrules.crps_mixnorm`` —
  but it is O(K²) per entry: about 4 s for one 60-frame utterance with K = 64 on this
  machine; the sorted-sample form is O(m log m).)

:func:`summarise_calibration` pools utterances. Coverage, NLPD and CRPS are ratios of
sums over utterances (entries inside / entries); their standard errors are the
cluster-robust (ratio-estimator) standard errors with the utterance as the unit,

    r = Σ_i a_i / Σ_i b_i,   se(r) = √( n/(n−1) Σ_i (a_i − r b_i)² ) / Σ_i b_i,

so the strong correlation of neighbouring frames within an utterance is not mistaken for
independent evidence. Coverage is reported pooled over all parameters and per parameter,
with the fraction of parameters whose 90 % coverage lies in [0.80, 0.97] (the range
counted as acceptable, :data:`PARAM_RANGE_90`), and per switching state (the state model that synthesised each frame). :func:`plot_calibration` draws the PIT histogram and the coverage
(reliability) diagram of one or more summaries; :func:`markdown_calibration` tabulates
them for the ``evaluate`` report.
"""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from bayes_talk.evaluation.metrics import crps_gaussian_entries, crps_sample_entries
from bayes_talk.synthesis.result import DEFAULT_LEVELS, SynthesisResult

__all__ = [
    "CALIBRATION_KEYS",
    "CRPS_SAMPLES",
    "LEVELS",
    "MIN_STATE_ENTRIES",
    "PARAM_RANGE_90",
    "PIT_BINS",
    "UtteranceCalibration",
    "calibration_tags",
    "ceiling_control",
    "control_verdict",
    "markdown_calibration",
    "paired_difference_se",
    "plot_calibration",
    "ratio_se",
    "resolution",
    "score_utterance",
    "summarise_calibration",
]

#: central band levels scored
LEVELS: tuple[float, ...] = tuple(DEFAULT_LEVELS)
#: bins of the PIT histogram
PIT_BINS = 20
#: mixture samples per entry for the sample CRPS
CRPS_SAMPLES = 1000
#: the range of per-parameter 90 % coverage counted as acceptable (``params_in_range_90``)
PARAM_RANGE_90 = (0.80, 0.97)
#: a switching state's 90 % coverage counts towards ``states_in_range_90`` from this many
#: scored entries (frames × parameters) on
MIN_STATE_ENTRIES = 180
#: the predictives scored per method: as reported, before the band calibration, and the
#: constant-band control (:func:`bayes_talk.evaluation.scoring.calibration_inputs`)
CALIBRATION_KEYS: tuple[str, ...] = ("calibration", "calibration_raw", "calibration_control",
                                     "calibration_context_only", "calibration_unshrunk")
_TAGS = {"calibration": "", "calibration_raw": " (raw)", "calibration_control": " (constant-band control)",
         "calibration_context_only": " (c_t alone)", "calibration_unshrunk": " (unshrunk mean)"}
#: quantiles of the predicted band width the resolution's RMS errors are binned by
WIDTH_BINS = 5


def calibration_tags() -> dict[str, str]:
    """{calibration key: the suffix its rows carry in tables and figures}."""
    return dict(_TAGS)


def control_verdict(entry: Mapping[str, Any]) -> dict[str, Any] | None:
    """Whether a method's reported predictive (``entry["calibration"]``) beats its
    constant-band control (``entry["calibration_control"]``) on NLPD and on CRPS: the
    per-entry means, their difference (method − control; negative = better) and each one's
    standard error over utterances; ``beats`` is true only when both scores are lower.
    None without a control."""
    c, k = entry.get("calibration"), entry.get("calibration_control")
    if not isinstance(c, Mapping) or not isinstance(k, Mapping):
        return None
    out: dict[str, Any] = {}
    for key in ("nlpd", "crps"):
        out[key] = {"method": c[key]["mean"], "control": k[key]["mean"],
                    "difference": c[key]["mean"] - k[key]["mean"], "method_se": c[key]["se"],
                    "control_se": k[key]["se"], "difference_se": paired_difference_se(c[key], k[key])}
    out["beats"] = bool(out["nlpd"]["difference"] < 0 and out["crps"]["difference"] < 0)
    out["beats_by_2se"] = bool(all(out[k]["difference_se"] is not None and
                                   out[k]["difference"] < -2 * out[k]["difference_se"] for k in ("nlpd", "crps")))
    return out


def paired_difference_se(a: Mapping[str, Any], b: Mapping[str, Any]) -> float | None:
    """The cluster-robust standard error (utterances as clusters, :func:`ratio_se`) of the
    difference of two per-entry mean scores of the same utterances (``a`` and ``b``:
    summaries with ``per_utterance`` totals and ``entries``); None without them."""
    ta, tb = a.get("per_utterance"), b.get("per_utterance")
    if ta is None or tb is None or len(ta) != len(tb) or a.get("entries") != b.get("entries"):
        return None
    se = ratio_se(np.asarray(ta) - np.asarray(tb), np.asarray(a["entries"], np.float64))[1]
    return None if not math.isfinite(se) else se


@dataclass
class UtteranceCalibration:
    """Calibration sums of one utterance (T frames, D parameters, L levels).

    inside: (L, D) frames inside each level's band; width: (L, D) summed band widths;
    pit_counts: (PIT_BINS, D) PIT histogram counts; nlpd, crps: (D,) summed over frames;
    state_inside_90: {state model: [entries inside the 90 % band, entries]} over the frames
    each switching state's model synthesised (empty for a prediction without states);
    sq_err: (D,) summed squared error of the predictive mean; sd, abs_err: (T, D) the
    predictive standard deviation and the absolute error of the mean, entry by entry (the
    bands' resolution).
    """

    n_frames: int
    levels: tuple[float, ...]
    inside: np.ndarray
    width: np.ndarray
    pit_counts: np.ndarray
    nlpd: np.ndarray
    crps: np.ndarray
    state_inside_90: dict[str, list[float]] | None = None
    sq_err: np.ndarray | None = None
    sd: np.ndarray | None = None
    abs_err: np.ndarray | None = None


def score_utterance(result: SynthesisResult, truth: np.ndarray, levels: Sequence[float] = LEVELS,
                    crps_samples: int = CRPS_SAMPLES, seed: int = 0) -> UtteranceCalibration:
    """Coverage, band width, PIT, mixture NLPD and CRPS of ``result`` at ``truth`` (T, D)
    (see the module docstring). ``seed`` seeds the CRPS samples of a mixture."""
    if not isinstance(result, SynthesisResult):
        raise TypeError(f"result: expected a SynthesisResult, found {type(result).__name__}")
    z = np.asarray(truth, dtype=np.float64)
    if z.shape != (result.n_frames, result.n_dims):
        raise ValueError(f"truth: expected shape ({result.n_frames}, {result.n_dims}) (the prediction's), "
                         f"found {z.shape}")
    if not np.all(np.isfinite(z)):
        raise ValueError("truth: contains NaN or inf")
    levels = tuple(float(q) for q in levels)
    inside, width = [], []
    states: dict[str, list[float]] = {}
    for q in levels:
        lo, hi = result.interval(q)
        hit = (z >= lo) & (z <= hi)
        inside.append(np.sum(hit, axis=0))
        width.append(np.sum(hi - lo, axis=0))
        if q == 0.9 and len(result.segments) == len(result.model_states):
            for seg, key in zip(result.segments, result.model_states):
                acc = states.setdefault(" ".join(key), [0.0, 0.0])
                acc[0] += float(hit[seg.start:seg.stop].sum())
                acc[1] += float(hit[seg.start:seg.stop].size)
    pit = np.clip(result.cdf(z), 0.0, 1.0)
    bins = np.minimum((pit * PIT_BINS).astype(int), PIT_BINS - 1)
    pit_counts = np.stack([np.bincount(bins[:, d], minlength=PIT_BINS) for d in range(z.shape[1])], axis=1)
    nlpd = -np.sum(result.logpdf(z), axis=0)
    if result.is_gaussian:
        m, v = result.draw_mean[0, 0], result.draw_var[0, 0]
        crps = crps_gaussian_entries(z, m, np.sqrt(np.maximum(v, 1e-300)))
    else:
        crps = crps_sample_entries(z, result.sample(int(crps_samples), seed=seed), fair=True)
    err = z - result.mean
    return UtteranceCalibration(int(z.shape[0]), levels, np.asarray(inside, np.float64),
                                np.asarray(width, np.float64), pit_counts.astype(np.int64),
                                nlpd, np.sum(crps, axis=0), states, np.sum(err ** 2, axis=0),
                                np.sqrt(np.maximum(result.var, 0.0)), np.abs(err))


def ratio_se(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """(r, se): the ratio r = Σa/Σb and its cluster-robust standard error over the units
    of a, b (module docstring); se is nan with one unit."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    r = float(a.sum() / b.sum())
    n = a.size
    if n < 2:
        return r, float("nan")
    return r, float(math.sqrt(n / (n - 1) * np.sum((a - r * b) ** 2)) / b.sum())


def summarise_calibration(scores: Sequence[UtteranceCalibration],
                          param_range: tuple[float, float] = PARAM_RANGE_90) -> dict[str, Any]:
    """Pool per-utterance scores (JSON-ready dict).

    ``coverage``: {level: {"pooled", "pooled_se", "per_param", "per_param_se",
    "param_min", "param_max"}}; ``params_in_range_90``: fraction of parameters whose 90 %
    coverage lies in ``param_range``; ``width``: {level: mean band width}; ``pit``:
    {"edges", "counts" (pooled), "ks"} (KS distance of the pooled PIT histogram from
    uniform); ``nlpd`` / ``crps``: per-entry means with standard errors; ``n_utterances``,
    ``n_entries``; for switching predictions ``per_state_90``: each state model's pooled 90 %
    coverage and entries, and the fraction of states with at least ``MIN_STATE_ENTRIES``
    entries whose coverage lies in ``param_range``.
    """
    if not scores:
        raise ValueError("summarise_calibration: no utterances")
    levels = scores[0].levels
    if any(s.levels != levels for s in scores):
        raise ValueError("summarise_calibration: utterances scored at different levels")
    D = scores[0].inside.shape[1]
    T = np.array([s.n_frames for s in scores], np.float64)
    inside = np.stack([s.inside for s in scores])            # (n, L, D)
    cov: dict[str, Any] = {}
    for j, q in enumerate(levels):
        pooled, pooled_se = ratio_se(inside[:, j].sum(1), T * D)
        per = [ratio_se(inside[:, j, d], T) for d in range(D)]
        cov[f"{q:g}"] = {"pooled": pooled, "pooled_se": pooled_se,
                         "per_param": [p for p, _ in per], "per_param_se": [s for _, s in per],
                         "param_min": min(p for p, _ in per), "param_max": max(p for p, _ in per)}
    out: dict[str, Any] = {"levels": list(levels), "n_utterances": len(scores),
                           "n_entries": int(T.sum() * D), "coverage": cov}
    if 0.9 in levels:
        p90 = np.array(cov["0.9"]["per_param"])
        out["params_in_range_90"] = float(np.mean((p90 >= param_range[0]) & (p90 <= param_range[1])))
        out["param_range_90"] = list(param_range)
    width = np.stack([s.width for s in scores])               # (n, L, D)
    out["width"] = {f"{q:g}": float(width[:, j].sum() / (T.sum() * D)) for j, q in enumerate(levels)}
    counts = np.sum([s.pit_counts for s in scores], axis=0)   # (B, D)
    pooled_counts = counts.sum(1)
    cdf = np.cumsum(pooled_counts) / pooled_counts.sum()
    out["pit"] = {"edges": np.linspace(0.0, 1.0, PIT_BINS + 1).tolist(), "counts": pooled_counts.tolist(),
                  "ks": float(np.max(np.abs(cdf - np.arange(1, PIT_BINS + 1) / PIT_BINS)))}
    for key in ("nlpd", "crps"):
        totals = np.array([getattr(s, key).sum() for s in scores])
        mean, se = ratio_se(totals, T * D)
        out[key] = {"mean": mean, "se": se, "per_utterance": totals.tolist(), "entries": (T * D).tolist()}
    if all(s.sq_err is not None for s in scores):
        mse, mse_se = ratio_se(np.array([s.sq_err.sum() for s in scores]), T * D)
        out["mse"] = {"mean": mse, "se": mse_se}
    if all(s.sd is not None for s in scores):
        out["resolution"] = resolution(np.concatenate([s.sd for s in scores]),
                                       np.concatenate([s.abs_err for s in scores]))
    per_state: dict[str, list[float]] = {}
    for sc in scores:
        for k, (a, b) in (sc.state_inside_90 or {}).items():
            acc = per_state.setdefault(k, [0.0, 0.0])
            acc[0], acc[1] = acc[0] + a, acc[1] + b
    if per_state:
        cov_s = {k: {"coverage_90": a / b, "entries": int(b)} for k, (a, b) in sorted(per_state.items()) if b}
        big = [c["coverage_90"] for c in cov_s.values() if c["entries"] >= MIN_STATE_ENTRIES]
        out["per_state_90"] = {"states": cov_s, "min_entries": MIN_STATE_ENTRIES, "n_states_scored": len(big),
                               "states_in_range_90": float(np.mean([param_range[0] <= c <= param_range[1]
                                                                    for c in big])) if big else None}
    return out


def ceiling_control(means: Sequence[np.ndarray], truths: Sequence[np.ndarray]) -> list[UtteranceCalibration]:
    """Scores of the best constant band around a reference's means (the oracle's): N(m_td, v_d)
    with v_d the reference's own mean squared error on these utterances (in-sample, so as
    generous to the constant band as it can be). Beside the reference's own band it measures
    how much any band shape can win over a constant band here."""
    v = np.mean(np.concatenate([(y - m) ** 2 for m, y in zip(means, truths, strict=True)]), axis=0)
    v = np.maximum(v, 1e-12)
    return [score_utterance(SynthesisResult.gaussian(m, np.broadcast_to(v, m.shape).copy(), method="constant-band"), y)
            for m, y in zip(means, truths, strict=True)]


def resolution(sd: np.ndarray, abs_err: np.ndarray, n_bins: int = WIDTH_BINS) -> dict[str, Any]:
    """Whether the bands are wider where the errors are larger, per parameter d over the
    entries (N, D): the Spearman correlation of the predicted s.d. with the absolute error
    (0: no resolution, as a constant band), and the RMS error in each ``n_bins``-quantile bin
    of the predicted s.d. (narrowest first), pooled as the mean over parameters."""
    from scipy.stats import spearmanr

    D = sd.shape[1]
    rho, rms = [], []
    for d in range(D):
        s, e = sd[:, d], abs_err[:, d]
        rho.append(float(spearmanr(s, e).statistic) if np.ptp(s) > 0 else 0.0)
        order = np.argsort(s, kind="stable")
        rms.append([float(np.sqrt(np.mean(e[b] ** 2))) for b in np.array_split(order, n_bins)])
    rms_arr = np.asarray(rms)
    return {"spearman_per_param": rho, "spearman_median": float(np.median(rho)),
            "rms_by_width_bin_per_param": rms_arr.tolist(), "rms_by_width_bin": rms_arr.mean(0).tolist(),
            "n_bins": int(n_bins)}


def _cell(c: Mapping[str, Any] | None) -> str:
    if not c or c.get("pooled") is None:
        return "–"
    se = c.get("pooled_se")
    return f"{c['pooled']:.3f}" + ("" if se is None or not math.isfinite(se) else f" ± {se:.3f}")


def markdown_calibration(methods: Mapping[str, Mapping[str, Any]]) -> str:
    """Markdown section: for every method entry with a ``calibration`` summary (and a
    ``calibration_raw`` one, shown as a second row), pooled coverage at each level ±
    standard error over utterances, the range of per-parameter 90 % coverage, the fraction
    of parameters inside :data:`PARAM_RANGE_90`, mixture NLPD, CRPS and the PIT KS distance."""
    rows = []
    levels: list[float] = []
    verdicts = []
    for name, e in methods.items():
        v = e.get("uncertainty_beats_control")
        if isinstance(v, Mapping):
            def diff(k: str, v: Mapping[str, Any] = v) -> str:
                se = v[k].get("difference_se")
                return f"{v[k]['difference']:+.4f}" + ("" if se is None else f" ± {se:.4f}")
            by = " by more than 2 s.e." if v.get("beats_by_2se") else ""
            verdicts.append(f"- {name}: its uncertainty {'beats' if v['beats'] else 'does NOT beat'} the "
                            f"constant-band control{by if v['beats'] else ''} (NLPD {v['nlpd']['method']:.4g} vs "
                            f"{v['nlpd']['control']:.4g}, difference {diff('nlpd')}; CRPS {v['crps']['method']:.4g} "
                            f"vs {v['crps']['control']:.4g}, difference {diff('crps')}; ± paired s.e. over utterances).")
        for key, tag in _TAGS.items():
            c = e.get(key)
            if isinstance(c, Mapping) and c.get("coverage"):
                rows.append((name + tag, c))
                levels = levels or list(c["levels"])
    if not rows:
        return ""
    head = ["method"] + [f"cov{round(100 * q)}" for q in levels] + [
        "90 % per param. min–max", "params in [0.80, 0.97]", "states in [0.80, 0.97]", "NLPD (mixture)", "CRPS",
        "PIT KS"]
    intro = ("Coverage of the exact central bands of each method's predictive (mixture quantiles for "
             "the posterior methods), pooled over utterances and AAM parameters, ± the cluster-robust "
             "standard error over utterances; NLPD is the mixture's own log density per entry, CRPS "
             "per entry; PIT KS is the largest gap between the pooled PIT histogram's CDF and the "
             "uniform one; 'states in [0.80, 0.97]' is the fraction of switching states (with at least "
             f"{MIN_STATE_ENTRIES} scored entries) whose own 90 % coverage lies in that range. Rows marked "
             "(raw) are the same predictive before the band calibration "
             "fitted on held-out training utterances (docs/uncertainty.md); rows marked (constant-band "
             "control) have the calibrated mean with one constant band per AAM parameter, calibrated "
             "the same way: a method whose NLPD and CRPS do not beat it says no more about its "
             "uncertainty than a constant would.\n")
    lines = ["## Calibration\n", intro, "| " + " | ".join(head) + " |",
             "|" + "|".join(["---"] + ["---:"] * (len(head) - 1)) + "|"]
    for name, c in rows:
        cov = c["coverage"]
        c90 = cov.get("0.9")
        rng = "–" if c90 is None else f"{c90['param_min']:.2f}–{c90['param_max']:.2f}"
        frac = c.get("params_in_range_90")
        st = (c.get("per_state_90") or {}).get("states_in_range_90")
        cells = [name] + [_cell(cov.get(f"{q:g}")) for q in levels] + [
            rng, "–" if frac is None else f"{frac:.2f}", "–" if st is None else f"{st:.2f}",
            f"{c['nlpd']['mean']:.4g}", f"{c['crps']['mean']:.4g}",
            f"{c['pit']['ks']:.3f}"]
        lines.append("| " + " | ".join(cells) + " |")
    if verdicts:
        lines += ["", *verdicts]
    return "\n".join(lines) + "\n"


def plot_calibration(summaries: Mapping[str, Mapping[str, Any]], path: str | Path,
                     title: str | None = None) -> Path:
    """PNG: the PIT histogram (density; 1 = calibrated) and the coverage diagram (pooled
    coverage against the nominal level, per-parameter 90 % coverage as dots) of each
    summary in ``summaries`` (label -> :func:`summarise_calibration` output)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    from bayes_talk.base.files import write_figure

    if not summaries:
        raise ValueError("plot_calibration: no summaries")
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(9, 3.6))
    for i, (label, s) in enumerate(summaries.items()):
        edges = np.asarray(s["pit"]["edges"])
        counts = np.asarray(s["pit"]["counts"], np.float64)
        dens = counts / counts.sum() / np.diff(edges)
        color = f"C{i}"
        ax1.stairs(dens, edges, color=color, lw=1.5, label=label)
        levels = np.asarray(s["levels"])
        pooled = np.array([s["coverage"][f"{q:g}"]["pooled"] for q in levels])
        se = np.array([s["coverage"][f"{q:g}"]["pooled_se"] or 0.0 for q in levels], np.float64)
        ax2.errorbar(levels, pooled, yerr=2 * np.nan_to_num(se), color=color, marker="o", lw=1.2,
                     capsize=3, label=label)
        if "0.9" in s["coverage"]:
            per = np.asarray(s["coverage"]["0.9"]["per_param"])
            ax2.scatter(np.full(per.size, 0.9) + 0.006 * (i + 1), per, s=6, color=color, alpha=0.5)
    ax1.axhline(1.0, color="k", lw=0.8, ls="--")
    ax1.set_xlabel("PIT value F(z)")
    ax1.set_ylabel("density")
    ax1.set_title("PIT histogram (flat = calibrated)", fontsize=9)
    ax1.legend(fontsize=7)
    ax2.plot([0.4, 1.0], [0.4, 1.0], color="k", lw=0.8, ls="--")
    ax2.set_xlabel("nominal level")
    ax2.set_ylabel("coverage")
    ax2.set_title("coverage (±2 s.e.; dots: per parameter at 90 %)", fontsize=9)
    if title:
        fig.suptitle(title, fontsize=8)
    fig.tight_layout()
    return write_figure(path, fig, dpi=110)
