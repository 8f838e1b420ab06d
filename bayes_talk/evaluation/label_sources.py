"""``evaluate --labels true|aligned|recognised``: where the test utterances' labels come from.

The protocols score synthesis from the test audio *and its phone labels*; deena2010 takes
the labels from the truth. Here the test utterances are transformed before the harness
runs: their ``labels`` (25 Hz majority vote) and ``meta["intervals"]`` are replaced by
those of

* ``true`` -- unchanged (the corpus's espeak-ng boundaries);
* ``aligned`` -- the default aligner (:data:`~bayes_talk.alignment.commands.DEFAULT_ALIGN_METHOD`)
  run on the utterance's audio and its sentence text (``meta["text"]``, recorded by
  ``corpus build``);
* ``recognised`` -- the phone recogniser on the audio alone.

The alignment models are fitted on the *training* utterances only. The visual features,
audio features and everything else are untouched, so the method scores under each source
differ only through the labels. The switching models are trained once and reused for
every source (``run_protocol(model_cache=...)``). The segmentation of every source is
scored against the truth (:mod:`bayes_talk.alignment.scoring`): phone error rate, median
and 90th-percentile boundary error (ms), 25 Hz frame-label agreement.
"""
from __future__ import annotations

import logging
import time
from dataclasses import replace
from typing import Any

from bayes_talk.data.utterance import Utterance

__all__ = ["LABEL_SOURCES", "parse_label_sources", "relabel", "run_label_sources"]

log = logging.getLogger(__name__)

LABEL_SOURCES = ("true", "aligned", "recognised")


def parse_label_sources(labels: str | list[str] | tuple[str, ...] | None) -> tuple[str, ...]:
    """``"true,aligned"`` or a list -> validated tuple (ValueError naming an unknown source)."""
    if labels is None:
        return ("true",)
    items = [s.strip() for s in (labels.split(",") if isinstance(labels, str) else labels) if s.strip()]
    bad = [s for s in items if s not in LABEL_SOURCES]
    if bad or not items:
        raise ValueError(f"--labels: unknown label source(s) {bad or items}; valid: {', '.join(LABEL_SOURCES)}")
    return tuple(dict.fromkeys(items))


def relabel(tests: list[Utterance], source: str, model=None, fps: float = 25.0) -> tuple[list[Utterance], dict]:
    """Copies of ``tests`` with labels from ``source``, and the segmentation scores."""
    from bayes_talk.alignment.commands import DEFAULT_ALIGN_METHOD
    from bayes_talk.alignment.scoring import score_segmentation, summarise_scores
    from bayes_talk.data.labels import frame_labels

    out, rows, secs, audio_s = [], [], 0.0, 0.0
    for s in tests:
        truth = [tuple(iv) for iv in s.meta.get("intervals", [])]
        if source == "true":
            out.append(s)
            continue
        if s.audio_path is None or not truth:
            raise ValueError(f"--labels {source}: test utterance {s.name!r} has no audio file or true intervals")
        if source == "aligned":
            text = s.meta.get("text")
            if not text:
                raise ValueError(f"--labels aligned: test utterance {s.name!r} has no sentence text "
                                 "(meta['text']; built corpora record it in manifest.json)")
            res = model.align(s.audio_path, text, method=DEFAULT_ALIGN_METHOD, where=str(s.audio_path))
        else:
            res = model.recognise(s.audio_path, where=str(s.audio_path))
        secs += res.seconds
        audio_s += truth[-1][1]
        rows.append(score_segmentation(truth, res.intervals, s.n_frames, fps))
        meta = dict(s.meta, intervals=list(res.intervals), true_intervals=truth, label_source=source)
        out.append(replace(s, labels=frame_labels(res.intervals, s.n_frames, fps), meta=meta))
    if source == "true":
        return out, {"source": "true"}
    summary = summarise_scores(rows)
    summary.update(source=source, method=DEFAULT_ALIGN_METHOD if source == "aligned" else "recogniser",
                   seconds=secs, audio_seconds=audio_s, realtime_factor=audio_s / secs if secs else None)
    return out, summary


def run_label_sources(run_protocol, protocol, train: list[Utterance], tests: list[Utterance] | None,
                      names, sources: tuple[str, ...], **kw) -> tuple[dict[str, Any], Any]:
    """Run the harness once per label source (models trained once; see module docstring).

    ``tests`` None: the protocol must be a single hold-out split, taken here. Returns the
    first source's (result, trajectory) with ``result["label_sources"]`` holding every
    source's segmentation scores and method scores, and a Markdown section.
    """
    from bayes_talk.alignment.commands import fit_alignment
    from bayes_talk.evaluation.splits import make_splits

    if tests is None:
        if protocol.scheme != "holdout":
            raise ValueError(f"--labels aligned/recognised needs one training set: use --test-corpus, "
                             f"or a hold-out protocol (deena2010); {protocol.name} has scheme {protocol.scheme!r}")
        split = make_splits(protocol, len(train))[0]
        train, tests = [train[i] for i in split.train], [train[i] for i in split.test]
    t0 = time.perf_counter()
    model = fit_alignment(train, seed=protocol.seed) if set(sources) - {"true"} else None
    fit_s = time.perf_counter() - t0
    cache: dict = {}
    first = None
    per_source: dict[str, Any] = {}
    for src in sources:
        relabelled, seg = relabel(tests, src, model)
        log.info("label source %s: %s", src, seg)
        result, traj = run_protocol(protocol, train, names, test_sequences=relabelled, model_cache=cache, **kw)
        per_source[src] = {"segmentation": seg, "methods": {
            n: {"AMSE": e["mse"]["mean"], "ACC": e["corr"]["mean"], "NMSE": e["nmse"]["mean"],
                "mse": e["mse"], "corr": e["corr"], "nmse": e["nmse"]} for n, e in result["methods"].items()}}
        if first is None:
            first = (result, traj)
    result, traj = first
    result["label_sources"] = per_source
    result["label_source_of_methods_table"] = sources[0]
    result["alignment_fit_seconds"] = fit_s
    result.setdefault("markdown_sections", []).append(_markdown(per_source))
    return result, traj


def _markdown(per_source: dict[str, Any]) -> str:
    f = lambda v, d=4: "–" if v is None else f"{v:.{d}g}"
    lines = ["## Test labels: truth, aligner, recogniser\n",
             "| labels | PER | boundary err. median ms | p90 ms | frame agreement |",
             "|---|---:|---:|---:|---:|"]
    for src, e in per_source.items():
        s = e["segmentation"]
        lines.append(f"| {src} | {f(s.get('phone_error_rate', 0.0))} | {f(s.get('boundary_error_ms_median', 0.0))} | "
                     f"{f(s.get('boundary_error_ms_p90', 0.0))} | {f(s.get('frame_label_agreement', 1.0))} |")
    lines += ["", "| method | labels | AMSE | ACC | NMSE |", "|---|---|---:|---:|---:|"]
    names = next(iter(per_source.values()))["methods"]
    for n in names:
        for src, e in per_source.items():
            m = e["methods"][n]
            lines.append(f"| {n} | {src} | {f(m['AMSE'])} | {f(m['ACC'])} | {f(m['NMSE'])} |")
    return "\n".join(lines) + "\n"
