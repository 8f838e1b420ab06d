"""The evaluation harness: run a protocol (train every method family on each split, predict
and score every test utterance), and the ``bayes-talk evaluate`` job around it.

Reported per method (over all test utterances of all splits pooled; ``n`` = number of
test utterances scored): ``mse`` (its mean is AMSE), ``rms``, ``l1``, ``linf``, ``nmse``
(MSE over the ground-truth variance of the split's test frames), ``corr`` (its mean is
ACC), ``log_likelihood_per_frame`` where defined, and for methods with a predictive
variance ``coverage_50``, ``coverage_90`` (fraction of entries inside the central 50 / 90 %
band of the method's predictive: the exact mixture interval of its
:class:`~bayes_talk.synthesis.result.SynthesisResult`, the bands ``synth`` writes; a
Gaussian one for a baseline's variance), ``crps`` and ``nlpd`` (per entry, Gaussian); each as
:func:`~bayes_talk.evaluation.metrics.summarise` gives it ({"mean", "std", "ci95", "n"}).
Also ``train_seconds`` (total over splits; methods sharing a family report the shared
training time and name each other in ``train_shared_with``) and
``synth_frames_per_second``.

Landmark metrics (the field's, :mod:`bayes_talk.evaluation.metrics`; every method, null where
undefined): the landmarks of the predicted mean and of the truth, both reconstructed through the
AAM the test frames were projected through with the utterance's own removed mean added
(:func:`~bayes_talk.evaluation.scoring.landmark_space`), give ``lve``, ``mouth_opening_mae`` and
``fdd``; a method whose predictive mixes over draws of the path also gets ``diversity``,
``mean_of_samples_lve`` and ``best_of_n_lve`` from ``SystemConfig.sample_draws`` seeded draws of
it. A corpus without an AAM (precomputed features) or a user corpus (its own landmark layout)
gets null for all six.

Calibration (:mod:`bayes_talk.evaluation.calibration`): every method with a predictive
variance also gets ``calibration`` — coverage of the exact central 50/80/90/95 % bands
pooled and per AAM parameter with standard errors over utterances, the PIT histogram,
mixture NLPD and CRPS. The ``*-posterior`` methods use a band calibration fitted on
held-out *training* utterances (``SystemConfig.band_calibration``, one extra fit per
split: :func:`~bayes_talk.evaluation.systems.fit_band_calibration`; its seconds are
added to ``train_seconds`` and reported as ``calibration_seconds``); their
``calibration_raw`` scores the same predictive before it, ``band_calibration``
holds the fitted factors, ``calibration_control`` scores the constant-band control (the
calibrated mean with a constant per-parameter band, calibrated the same way:
:meth:`~bayes_talk.calibration.bands.BandCalibration.control_result`) and
``uncertainty_beats_control`` says whether the calibrated predictive's NLPD and CRPS are
below the control's (:func:`~bayes_talk.evaluation.calibration.control_verdict`).
"""
from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bayes_talk.base.files import check_writable_json
from bayes_talk.data.utterance import Utterance
from bayes_talk.estimators.calibrated import BandCalibrated
from bayes_talk.evaluation import calibration as CAL
from bayes_talk.evaluation.ceiling import add_gain_fractions, corpus_generator
from bayes_talk.evaluation.protocols import Protocol, get_protocol, scale_protocol
from bayes_talk.evaluation.scoring import (
    calibration_inputs,
    json_safe,
    landmark_space,
    summary_stats,
    utterance_metrics,
)
from bayes_talk.evaluation.splits import Split, check_test_set, feature_dims, make_splits
from bayes_talk.evaluation.systems import (
    build_family,
    calibrated_method,
    fit_calibrated_family,
    fit_family,
    get_method,
    group_by_family,
    log_likelihood,
    predict,
    resolve_methods,
)
from bayes_talk.features.audio import DEFAULT_CMVN

__all__ = ["Trajectory", "evaluate", "run_protocol"]

log = logging.getLogger(__name__)



# ---------------------------------------------------------------------------- the harness
@dataclass
class Trajectory:
    """Material of the trajectory figure: one test utterance, first split."""

    utterance: str
    truth: np.ndarray
    predictions: dict[str, Any] = field(default_factory=dict)


@dataclass
class _SplitJob:
    """One split's work for :func:`_run_split` (what a worker receives)."""

    split: Split
    n_splits: int
    train: list[Utterance]
    test: list[Utterance]
    families: dict[str, list[str]]
    cfg: Any
    first: bool


@dataclass
class _SplitOutcome:
    """One split's scores and timings (what a worker sends back)."""

    rows: dict[str, list[dict[str, float]]]
    per_split: dict[str, dict[str, Any]]
    train_seconds: dict[str, float]
    synth_seconds: dict[str, float]
    synth_frames: dict[str, int]
    trajectory: Trajectory | None
    calibration: dict[str, dict[str, list]] = field(default_factory=dict)   # method -> key -> scores
    band_calibration: dict[str, dict[str, Any]] = field(default_factory=dict)
    calibration_seconds: dict[str, float] = field(default_factory=dict)


def _mean_skipping_nan(values: list[float]) -> float:
    """Mean of ``values`` without the nan ones; nan (no warning) when every one is nan (a metric
    the method or the corpus does not define)."""
    v = np.asarray(values, dtype=np.float64)
    v = v[~np.isnan(v)]
    return float(v.mean()) if v.size else float("nan")


def _say_split(say: Callable[[str], None], job: _SplitJob, out: _SplitOutcome) -> None:
    for name, row in out.per_split.items():
        say(f"split {job.split.index + 1}/{job.n_splits}: {name} "
            + ", ".join(f"{k}={row[k]:.4g}" for k in ("mse", "corr")))


def _run_split(job: _SplitJob, executor=None, say: Callable[[str], None] | None = None,
               model_cache: dict | None = None) -> _SplitOutcome:
    """Train every family on ``job.train`` and score each method on every test utterance.

    ``executor`` trains the switching models' states (None: in turn); ``model_cache``
    as in :func:`run_protocol`. A module-level function: executors run it in workers."""
    split, test, cfg = job.split, job.test, job.cfg
    variance = np.concatenate([s.aam for s in test]).var(axis=0)
    traj = Trajectory(test[0].name, test[0].aam.copy()) if job.first else None
    spaces = [landmark_space(seq, cfg.sample_draws, cfg.seed) for seq in test]
    rows_all: dict[str, list[dict[str, float]]] = {}
    per_split: dict[str, dict[str, Any]] = {}
    train_s: dict[str, float] = {}
    synth_s: dict[str, float] = {}
    synth_frames: dict[str, int] = {}
    cal_rows: dict[str, dict[str, list]] = {}
    band_cal: dict[str, dict[str, Any]] = {}
    calib_s: dict[str, float] = {}
    for fam, fam_methods in job.families.items():
        if say is not None:
            say(f"split {split.index + 1}/{job.n_splits}: training {fam} on {len(job.train)} utterances")
        t0 = time.perf_counter()
        cal_method = calibrated_method(fam_methods)
        calibrates = cfg.band_calibration is not None and cal_method is not None
        calib_s[fam] = 0.0
        if model_cache is not None and (fam, split.index) in model_cache:
            model = model_cache[(fam, split.index)]
        elif calibrates:   # as train ships it: the calibration fitted on held-out training utterances
            model = fit_calibrated_family(fam, job.train, cfg, cal_method, executor=executor,
                                          progress=None if say is None else
                                          (lambda msg: say(f"split {split.index + 1}/{job.n_splits}: {msg}")))
            calib_s[fam] = time.perf_counter() - t0
        else:
            model = fit_family(fam, job.train, cfg, executor=executor)
        train_s[fam] = time.perf_counter() - t0
        if model_cache is not None:   # with its calibration: label sources reuse both
            model_cache[(fam, split.index)] = model
        for name in fam_methods:
            rows = []
            cal_rows[name] = {k: [] for k in CAL.CALIBRATION_KEYS}
            synth_s[name], synth_frames[name] = 0.0, 0
            ceiling_means = []   # a reference with bands (the oracle): its mean, for its constant band
            for j, seq in enumerate(test):
                t0 = time.perf_counter()
                pred = predict(name, model, seq, cfg)
                synth_s[name] += time.perf_counter() - t0
                synth_frames[name] += seq.n_frames
                if pred.mean.shape != seq.aam.shape:
                    raise RuntimeError(f"{name} predicted shape {pred.mean.shape} for {seq.name}, "
                                       f"expected {seq.aam.shape}")
                ll = log_likelihood(name, model, seq, pred)
                rows.append(utterance_metrics(seq.aam, pred, variance, ll, spaces[j]))
                for key, res in calibration_inputs(name, pred).items():
                    cal_rows[name][key].append(CAL.score_utterance(res, seq.aam, seed=cfg.seed))
                if getattr(model, "reference", False) and pred.result is not None:
                    ceiling_means.append(pred.mean)
                if traj is not None and j == 0:
                    traj.predictions[name] = pred
            if ceiling_means:
                cal_rows[name]["calibration_control"] = CAL.ceiling_control(ceiling_means, [s.aam for s in test])
            rows_all[name] = rows
            cal = (model.calibration_ if isinstance(model, BandCalibrated)
                   else getattr(model, "face_noise_", None))
            if cal is not None and "posterior" in get_method(name).options:
                band_cal[name] = {"split": split.index, **cal.to_dict()}
            per_split[name] = {"split": split.index, "n_test": len(rows),
                               **{k: _mean_skipping_nan([r[k] for r in rows]) for k in rows[0]}}
            if say is not None:
                say(f"split {split.index + 1}/{job.n_splits}: {name} " + ", ".join(
                    f"{k}={per_split[name][k]:.4g}" for k in ("mse", "corr")))
        del model  # one family's model alive at a time
    return _SplitOutcome(rows_all, per_split, train_s, synth_s, synth_frames, traj, cal_rows, band_cal, calib_s)


def run_protocol(
    protocol: Protocol,
    sequences: Sequence[Utterance],
    methods: str | Sequence[str] | None = None,
    test_sequences: Sequence[Utterance] | None = None,
    train_phone_set: Sequence[str] | None = None,
    test_phone_set: Sequence[str] | None = None,
    executor=None,
    progress: Callable[[str], None] | None = None,
    model_cache: dict | None = None,
) -> tuple[dict[str, Any], Trajectory]:
    """Run ``protocol`` on ``sequences`` (or train on them and test on ``test_sequences``).

    Returns (result, trajectory): ``result`` is the JSON-ready dict (see the module
    docstring); ``trajectory`` holds the ground truth and every method's prediction for
    the first test utterance of the first split (for :mod:`bayes_talk.evaluation.report`).
    ``model_cache``: a dict reused across calls with the same training utterances: the
    fitted model of each (family, split) is taken from it or stored in it (label sources).

    ``executor``: a parallel :class:`~bayes_talk.base.executor.Executor` runs the splits (repeats,
    folds) as its tasks when there are several (and no ``model_cache``), each training its
    switching states in turn; with one split it trains the states (as does anything else
    with a ``map``). The numbers do not depend on it (timings aside).
    """
    from bayes_talk.base.memory import release_large_blocks

    release_large_blocks()  # freed N×N matrices leave the process
    names = resolve_methods(methods, protocol.default_methods)
    seqs = list(sequences)
    say = progress or (lambda msg: log.info("%s", msg))
    if test_sequences is not None:
        tests = list(test_sequences)
        check_test_set(seqs, tests, train_phone_set, test_phone_set)
        pool = seqs + tests
        splits = [Split(0, tuple(range(len(seqs))), tuple(range(len(seqs), len(pool))))]
    else:
        feature_dims(seqs, "corpus")
        pool = seqs
        splits = make_splits(protocol, len(seqs))
    families = group_by_family(names)
    cfg = protocol.system
    per_utt: dict[str, list[dict[str, float]]] = {n: [] for n in names}
    per_split: dict[str, list[dict[str, Any]]] = {n: [] for n in names}
    train_s = {f: 0.0 for f in families}
    synth_s = {n: 0.0 for n in names}
    synth_frames = {n: 0 for n in names}
    calib_s = {f: 0.0 for f in families}
    cal_rows: dict[str, dict[str, list]] = {n: {k: [] for k in CAL.CALIBRATION_KEYS} for n in names}
    band_cal: dict[str, list[dict[str, Any]]] = {n: [] for n in names}
    t_start = time.perf_counter()
    jobs = [_SplitJob(split, len(splits), [pool[i] for i in split.train], [pool[i] for i in split.test],
                      families, cfg, first=k == 0) for k, split in enumerate(splits)]
    from bayes_talk.base.executor import Executor

    if isinstance(executor, Executor) and executor.parallel and len(jobs) > 1 and model_cache is None:
        # the splits in parallel (each trains its states in turn); a split's numbers do not
        # depend on where it ran: every model is seeded by cfg.seed
        say(f"{len(jobs)} splits on {executor!r}")
        outcomes = executor.map(_run_split, jobs, desc="protocol splits", unit="split")
        for job, out in zip(jobs, outcomes):
            _say_split(say, job, out)
    else:
        outcomes = [_run_split(job, executor, say, model_cache) for job in jobs]
    traj: Trajectory | None = None
    for out in outcomes:
        if traj is None:
            traj = out.trajectory
        for fam, sec in out.train_seconds.items():
            train_s[fam] += sec
            calib_s[fam] += out.calibration_seconds.get(fam, 0.0)
        for name in names:
            per_utt[name].extend(out.rows[name])
            per_split[name].append(out.per_split[name])
            synth_s[name] += out.synth_seconds[name]
            synth_frames[name] += out.synth_frames[name]
            for key, sc in out.calibration.get(name, {}).items():
                cal_rows[name][key].extend(sc)
            if name in out.band_calibration:
                band_cal[name].append(out.band_calibration[name])
    result_methods: dict[str, Any] = {}
    for name in names:
        m = get_method(name)
        rows = per_utt[name]
        entry: dict[str, Any] = {"label": m.label, "family": m.family, "has_variance": m.has_variance}
        for k in rows[0]:
            entry[k] = summary_stats([r[k] for r in rows])
        entry["headline"] = {lab: (entry[k]["mean"] if k in entry else None) for lab, k in protocol.headline}
        for key, sc in cal_rows[name].items():
            if sc:
                entry[key] = CAL.summarise_calibration(sc)
        verdict = CAL.control_verdict(entry)
        if verdict is not None:
            entry["uncertainty_beats_control"] = verdict
        if band_cal[name]:
            entry["band_calibration"] = band_cal[name]
            entry["calibration_seconds"] = calib_s[m.family]
        entry["train_seconds"] = train_s[m.family]
        entry["train_shared_with"] = [n for n in families[m.family] if n != name]
        entry["synth_seconds"] = synth_s[name]
        entry["synth_frames_per_second"] = synth_frames[name] / synth_s[name] if synth_s[name] > 0 else None
        entry["n_test_frames"] = synth_frames[name]
        entry["per_split"] = per_split[name]
        result_methods[name] = entry
    add_gain_fractions(result_methods)
    n_train = [len(s.train) for s in splits]
    n_test = [len(s.test) for s in splits]
    result = {
        "protocol": protocol.name,
        "quick": bool(protocol.quick),
        "description": protocol.describe() if test_sequences is None else
        f"{'quick variant of ' if protocol.quick else ''}{protocol.name} settings, trained on all "
        f"{len(seqs)} utterances of the training corpus, tested on all {len(pool) - len(seqs)} of the test corpus",
        "paper": protocol.paper,
        "scheme": "test-corpus" if test_sequences is not None else protocol.scheme,
        "seed": protocol.seed,
        "n_train": int(min(n_train)),
        "n_test": int(min(n_test)),
        "n_splits": len(splits),
        "n_scored": int(sum(n_test)),
        "headline_metrics": [{"label": lab, "key": k} for lab, k in protocol.headline],
        # the protocol's settings, and the constructor arguments every trained family was built with
        "settings": {**asdict(cfg), "families": {f: build_family(f, cfg).saved_params() for f in families}},
        "splits": [{"index": s.index, "train": [pool[i].name for i in s.train],
                    "test": [pool[i].name for i in s.test]} for s in splits],
        "methods": result_methods,
        "elapsed_seconds": time.perf_counter() - t_start,
    }
    section = CAL.markdown_calibration(result_methods)
    if section:
        result["markdown_sections"] = [section]
    return json_safe(result), traj


def evaluate(
    protocol: str,
    corpus: str | Path,
    json_path: str | Path,
    test_corpus: str | Path | None = None,
    methods: str | Sequence[str] | None = None,
    quick: bool = False,
    seed: int | None = None,
    figures: bool = True,
    lowpass_hz: float | None = None,
    oracle_draws: int | None = None,
    sample_draws: int | None = None,
    calibrated_model: str | None = None,
    calibration: str | None = None,
    min_utterances: int | None = None,
    cmvn: str = DEFAULT_CMVN,
    labels: str | Sequence[str] | None = None,
    executor: Any = None,
    workers: int = 1,
    scheduler: str | None = None,
) -> dict[str, Any]:
    """The ``bayes-talk evaluate`` job: load corpora, run, write JSON + Markdown + figure.

    lowpass_hz: apply deena2010's zero-phase low-pass to every method's predicted mean
    (recorded in the JSON under ``settings``); None: off, the protocols' default.
    oracle_draws: generator draws per utterance of method ``oracle`` (>= 2: its bias
    correction needs an across-draw variance; the ``oracle`` model's ``n_draws``); None: its default.
    sample_draws: predictive draws of the sample-based landmark metrics (>= 2;
    ``SystemConfig.sample_draws``); None: the protocol's, 16.
    calibrated_model: which model the band calibration is scored with (``SystemConfig``; None:
    the protocol's, "refit"). calibration: what is fitted on held-out training utterances
    (``SystemConfig.calibration``, as ``train --calibration``; None: the protocol's, "noise").
    min_utterances: let a corpus smaller than the protocol needs (but with at least this
    many utterances) be evaluated with the split scaled down (:func:`scale_protocol`); the
    JSON and Markdown carry a warning saying so. cmvn: the per-utterance cepstral
    normalisation of both corpora's MFCCs (``load_corpus(cmvn=...)``; "mean" as ``train``).
    labels: test-label sources, e.g. ``"true,aligned,recognised"`` (default ``"true"``;
    :mod:`bayes_talk.evaluation.label_sources`).
    executor: "local" (default), "processes" (``workers`` processes) or "dask" (a
    ``LocalCluster`` of ``workers`` processes, or the running scheduler at ``scheduler``), or
    an :class:`~bayes_talk.base.executor.Executor` (left open): what runs the splits, or the
    per-state models of a single split, and the featurisation (docs/scaling.md). Without
    ``executor`` the protocol runs here and ``workers`` > 1 featurises in that many
    processes (``bayes-talk evaluate``: 2); the default 1 starts no process.

    Checks the protocol, the methods and that ``json_path`` is writable *before* loading
    or training anything. Writes ``json_path``, ``json_path`` with suffix ``.md`` and
    ``<stem>_trajectories.png`` beside it (each atomically).
    """
    from bayes_talk.corpus import load_corpus
    from bayes_talk.data.phones import PHONES
    from bayes_talk.evaluation import report

    if oracle_draws is not None and not (isinstance(oracle_draws, (int, np.integer)) and oracle_draws >= 2):
        raise ValueError(f"oracle_draws must be >= 2 (the oracle's bias correction needs an across-draw "
                         f"variance), got {oracle_draws!r}")
    proto = get_protocol(protocol, quick=quick, seed=seed,
                         **({"lowpass_hz": float(lowpass_hz)} if lowpass_hz is not None else {}),
                         **({"models": {"oracle": {"n_draws": int(oracle_draws)}}} if oracle_draws is not None
                            else {}),
                         **({"sample_draws": sample_draws} if sample_draws is not None else {}),
                         **({"calibrated_model": calibrated_model} if calibrated_model is not None else {}),
                         **({"calibration": calibration} if calibration is not None else {}))
    names = resolve_methods(methods, proto.default_methods)
    from bayes_talk.evaluation.label_sources import parse_label_sources, run_label_sources

    sources = parse_label_sources(labels)
    out = check_writable_json(json_path)
    from bayes_talk.base.executor import executor_for

    kind = executor if executor is not None else ("dask" if scheduler else "local")
    with executor_for(kind, workers, scheduler) as ex:
        feat_ex = ex if ex.parallel else None
        feat_workers = workers if executor is None and not scheduler else None
        t0 = time.perf_counter()
        train_c = load_corpus(corpus, cmvn=cmvn, executor=feat_ex, n_workers=feat_workers)
        test_c = None
        if test_corpus is not None:
            # score the test frames in the training corpus's AAM space: project them through it
            try:
                test_c = load_corpus(test_corpus, aam=train_c.aam_path, cmvn=cmvn, executor=feat_ex,
                                     n_workers=feat_workers)
            except ValueError as exc:
                raise ValueError(f"test corpus {test_corpus} cannot be scored against training corpus "
                                 f"{corpus}: {exc}") from exc
        load_s = time.perf_counter() - t0
        small_note = None
        if min_utterances is not None and test_c is None:
            proto, small_note = scale_protocol(proto, len(train_c.sequences), min_utterances)
        elif test_c is None and len(train_c.sequences) < proto.n_needed:
            n = len(train_c.sequences)
            raise ValueError(f"protocol {proto.name}{' --quick' if proto.quick else ''} needs at least "
                             f"{proto.n_needed} utterances, corpus {corpus} has {n}: build a larger corpus "
                             f"(corpus build --n-utterances {proto.n_needed}), or pass --min-utterances {n} "
                             "to run the protocol with its split scaled to this corpus (not the paper's "
                             "protocol; the report says so)")

        def phone_set(c):
            return list(c.manifest.get("phone_set", PHONES))

        if sources != ("true",):  # test labels from the aligner / recogniser
            result, traj = run_label_sources(
                run_protocol, proto, train_c.sequences, test_c.sequences if test_c is not None else None, names,
                sources, train_phone_set=phone_set(train_c),
                test_phone_set=phone_set(test_c) if test_c is not None else None, executor=ex)
        else:
            result, traj = run_protocol(
                proto, train_c.sequences, names,
                test_sequences=test_c.sequences if test_c is not None else None,
                train_phone_set=phone_set(train_c),
                test_phone_set=phone_set(test_c) if test_c is not None else None, executor=ex)
    # the corpora as given (relative stays relative): a result file names no machine's
    # directory unless the user gave one
    result["corpus"] = str(Path(corpus))
    result["generator"] = corpus_generator(train_c.manifest)
    if test_c is not None:
        result["test_generator"] = corpus_generator(test_c.manifest)
    result["test_corpus"] = str(Path(test_corpus)) if test_corpus is not None else None
    result["test_features"] = (None if test_c is None else "projected through the training corpus's AAM"
                               if train_c.aam_path is not None else "the test corpus's precomputed features")
    result["load_seconds"] = load_s
    result["cmvn"] = cmvn
    result["executor"] = {"kind": kind, "workers": workers, "scheduler": scheduler}
    if small_note:
        result["warnings"] = [*(result.get("warnings") or []), small_note]
        result["scaled_for_small_corpus"] = True
    md_path = out.with_suffix(".md")
    png_path = out.with_name(out.stem + "_trajectories.png")
    result["outputs"] = {"json": out.name, "markdown": md_path.name, "figure": png_path.name if figures else None}
    if figures:
        report.plot_trajectories(traj, png_path, title=f"{result['description']} — first AAM parameter, "
                                 f"utterance {traj.utterance}")
        summaries = {f"{n}{tag}": e[k] for n, e in result["methods"].items()
                     for k, tag in CAL.calibration_tags().items() if isinstance(e.get(k), dict)}
        if summaries:
            from bayes_talk.evaluation.calibration import plot_calibration

            cal_png = out.with_name(out.stem + "_calibration.png")
            plot_calibration(summaries, cal_png, title=result["description"])
            result["outputs"]["calibration_figure"] = cal_png.name
            result.setdefault("markdown_sections", []).append(
                f"![PIT histogram and coverage diagram]({cal_png.name})\n")
    report.write_markdown(result, md_path)
    report.write_json(result, out)
    return result

