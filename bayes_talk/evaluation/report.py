"""Reports of an evaluation run: JSON, a Markdown table and trajectory figures.

Every file is written atomically: to a temporary file in the target directory, then
``os.replace``-d onto the target, so a reader never sees a half-written report.

The trajectory figure follows deena2009 Figs. 5-7: the first AAM parameter of one test
utterance, synthesis against ground truth, one panel per method; methods with a
predictive variance also show their ±2σ band.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from bayes_talk.base.files import write_figure, write_text

__all__ = ["gain_table", "landmark_table", "markdown_table", "plot_trajectories", "write_json",
           "write_markdown"]

_COLUMNS = (  # (metric key, column label)
    ("mse", "AMSE"), ("corr", "ACC"), ("rms", "RMS"), ("nmse", "NMSE"), ("l1", "L1"), ("linf", "L∞"),
    ("log_likelihood_per_frame", "log-lik/frame"), ("coverage_50", "cov50"), ("coverage_90", "cov90"),
    ("crps", "CRPS (Gauss.)"), ("nlpd", "NLPD (Gauss.)"),
    ("mse_corrected", "AMSE (bias-corr.)"), ("nmse_corrected", "NMSE (bias-corr.)"),
)


def write_json(result: dict[str, Any], path: str | Path) -> Path:
    """Write ``result`` as strict JSON (no NaN: missing values are null)."""
    text = json.dumps(result, indent=2, allow_nan=False) + "\n"
    return write_text(path, text)


def _fmt(s: Any) -> str:
    if not isinstance(s, dict) or s.get("mean") is None:
        return "–"
    m, sd = s["mean"], s.get("std")
    digits = 4
    if sd is None:
        return f"{m:.{digits}g}"
    return f"{m:.{digits}g} ± {sd:.2g}"


def markdown_table(result: dict[str, Any]) -> str:
    """A Markdown table of every method: mean ± std over test utterances of each metric
    present, training seconds and synthesis frames per second."""
    methods = result.get("methods", {})
    if not methods:
        raise ValueError("result has no methods to tabulate")
    cols = [(k, lab) for k, lab in _COLUMNS if any(k in e for e in methods.values())]
    head = ["method"] + [lab for _, lab in cols] + ["train s", "synth frames/s"]
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join(["---"] + ["---:"] * (len(head) - 1)) + "|"]
    for name, e in methods.items():
        fps = e.get("synth_frames_per_second")
        shared = " (shared)" if e.get("train_shared_with") else ""
        row = [f"{name}"] + [_fmt(e.get(k)) for k, _ in cols] + [
            f"{e.get('train_seconds', float('nan')):.1f}{shared}", "–" if fps is None else f"{fps:.1f}"]
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines) + "\n"

#: the field's landmark metrics (bayes_talk.evaluation.scoring.LANDMARK_KEYS): (key, column label)
_LANDMARK_COLUMNS = (
    ("lve", "LVE (px²)"), ("mouth_opening_mae", "mouth opening MAE (px)"), ("fdd", "FDD (px²)"),
    ("diversity", "diversity (px)"), ("mean_of_samples_lve", "mean-of-N LVE (px²)"),
    ("best_of_n_lve", "best-of-N LVE (px²)"),
)


def landmark_table(result: dict[str, Any]) -> str:
    """Markdown table of every method's landmark metrics (mean ± std over test utterances; "–"
    where undefined: the sample metrics of a method without draws of its path, every one on
    a corpus without an AAM); "" when the result has none."""
    methods = result.get("methods", {})
    if not any(k in e for e in methods.values() for k, _ in _LANDMARK_COLUMNS):
        return ""
    n = (result.get("settings") or {}).get("sample_draws")
    intro = ("Landmark metrics (the field's conventions, on the landmarks the AAM reconstructs from the "
             "predicted mean and from the truth; docs/evaluation.md): LVE = mean over frames of the largest "
             "squared lip-landmark error; mouth opening = distance of the inner-lip midpoints; FDD = mean over "
             "upper-face landmarks of |sd over time of the squared displacement, predicted − true|; for a "
             f"predictive mixed over draws of the path, {n if n is not None else 'N'} seeded draws give the "
             "diversity (mean landmark distance between two draws), the LVE of their average and the best "
             "draw's LVE.\n")
    lines = [intro,
             "| method | " + " | ".join(lab for _, lab in _LANDMARK_COLUMNS) + " |",
             "|---|" + "|".join(["---:"] * len(_LANDMARK_COLUMNS)) + "|"]
    for name, e in methods.items():
        lines.append(f"| {name} | " + " | ".join(_fmt(e.get(k)) for k, _ in _LANDMARK_COLUMNS) + " |")
    return "\n".join(lines) + "\n"


def gain_table(result: dict[str, Any]) -> str:
    """Markdown table of every method's fraction of the achievable gain on AMSE and NMSE,
    ``(zero - method) / (zero - oracle)`` (:mod:`bayes_talk.evaluation.ceiling`); "" when
    the run had no ``zero`` and ``oracle``."""
    methods = result.get("methods", {})
    rows = [(n, e["gain_fraction"]) for n, e in methods.items() if isinstance(e.get("gain_fraction"), dict)]
    if not rows:
        return ""
    o = methods.get("oracle", {})
    note = ""
    if isinstance(o.get("mse_corrected"), dict):
        note = (f" The oracle's figures are bias-corrected for its {((result.get('settings') or {}).get('families') or {}).get('oracle', {}).get('n_draws')} "
                f"draws: AMSE {_fmt(o['mse_corrected'])}, NMSE {_fmt(o.get('nmse_corrected'))} (raw: "
                f"{_fmt(o.get('mse'))}, {_fmt(o.get('nmse'))}).")
    lines = ["Fraction of the achievable gain, (zero − method) / (zero − oracle): 0 = a still face, "
             "1 = the generator's own mean given the true phone timing." + note + "\n",
             "| method | gain AMSE | gain NMSE |", "|---|---:|---:|"]
    for n, g in rows:
        cells = ["–" if g.get(k) is None else f"{g[k]:.3f}" for k in ("amse", "nmse")]
        lines.append(f"| {n} | {cells[0]} | {cells[1]} |")
    return "\n".join(lines) + "\n"


def write_markdown(result: dict[str, Any], path: str | Path) -> Path:
    """Markdown report: title, what was run, the table and a pointer to the figure."""
    quick = " (QUICK variant — not the paper's protocol)" if result.get("quick") else ""
    intro = (f"Training utterances per split: {result.get('n_train')}; test utterances per split: "
             f"{result.get('n_test')}; splits: {result.get('n_splits')}; utterances scored: "
             f"{result.get('n_scored')}. Values are mean ± std over scored test utterances. "
             "AMSE is the mean per-utterance MSE and ACC the mean per-utterance correlation "
             "(deena2010 §5); NMSE divides by the ground-truth variance of the test frames; "
             "cov50/cov90 are the fractions of entries inside the central 50/90 % band of the "
             "method's predictive (the mixture's exact interval for the posterior methods; ideal "
             "0.5/0.9); CRPS (Gauss.) and NLPD (Gauss.) score a Gaussian with the predictive's "
             "mean and variance per entry: for a mixture predictive its own NLPD and CRPS are in "
             "the calibration table.\n")
    gen = result.get("generator")
    if gen:
        names = {"espeak": "built-in corpus, espeak-ng speech (face driven by the phones)",
                 "vtl": "built-in corpus, VocalTractLab speech (one vocal tract drives voice and face)",
                 "user": "user corpus (recorded data)"}
        intro += f"Corpus generator: {names.get(gen, gen)}"
        tg = result.get("test_generator")
        intro += (f"; test corpus: {names.get(tg, tg)}.\n" if tg else ".\n")
    lp = (result.get("settings") or {}).get("lowpass_hz")
    if lp:
        intro += (f"Every method's predicted mean was low-passed at {lp:g} Hz (zero-phase, "
                  "deena2010 §4.2.3) before scoring; variances are unfiltered.\n")
    parts = [f"# Evaluation: {result.get('protocol')}{quick}\n",
             f"{result.get('description', '')}.\n", intro, markdown_table(result)]
    if landmark_table(result):
        parts.append(landmark_table(result))
    if gain_table(result):
        parts.append(gain_table(result))
    for w in result.get("warnings", []) or []:
        parts.append(f"> Warning: {w}\n")
    parts.extend(result.get("markdown_sections", []) or [])
    fig = (result.get("outputs") or {}).get("figure")
    if fig:
        parts.append(f"![first AAM parameter, synthesis vs ground truth]({fig})\n")
    text = "\n".join(parts)
    return write_text(path, text)


def plot_trajectories(traj: Any, path: str | Path, dim: int = 0, title: str | None = None,
                      fps: float = 25.0) -> Path:
    """One panel per method: predicted vs true AAM parameter ``dim`` over time (PNG, Agg)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    preds = traj.predictions
    if not preds:
        raise ValueError("no predictions to plot")
    truth = np.asarray(traj.truth)
    if not 0 <= dim < truth.shape[1]:
        raise ValueError(f"dim must be in [0, {truth.shape[1]}), got {dim}")
    t = np.arange(truth.shape[0]) / fps
    n = len(preds)
    fig, axes = plt.subplots(n, 1, figsize=(7, 1.9 * n + 0.6), sharex=True, squeeze=False)
    for ax, (name, p) in zip(axes[:, 0], preds.items()):
        ax.plot(t, truth[:, dim], color="k", lw=1.4, label="ground truth")
        ax.plot(t, p.mean[:, dim], color="tab:red", lw=1.2, label="synthesis")
        if p.var is not None:  # the 90 % band evaluate scores (and synth writes)
            lo, hi = p.band(0.9)
            ax.fill_between(t, lo[:, dim], hi[:, dim], color="tab:red", alpha=0.2, lw=0, label="90 % band")
        ax.set_ylabel(f"AAM {dim + 1}")
        ax.set_title(name, fontsize=9, loc="left")
    axes[0, 0].legend(fontsize=7, loc="upper right", ncol=3)
    axes[-1, 0].set_xlabel("time (s)")
    if title:
        fig.suptitle(title, fontsize=8)
    fig.tight_layout()
    return write_figure(path, fig, dpi=110)
