"""Band calibration offline (issue 10, item 3): synthesise once, try calibrations in seconds.

    # once (≈ 1-1.5 h on the loaded 2-core machine): two switching models, 50 + 40 syntheses
    PYTHONPATH=. nice -n 15 .venv/bin/python benchmarks/analysis/band_calibration_offline.py dump /tmp/wt10cal/raw
    # then, in seconds: fit the calibration on the held-out training utterances, score the test set
    PYTHONPATH=. .venv/bin/python benchmarks/analysis/band_calibration_offline.py score /tmp/wt10cal/raw [OUT.json]

``dump`` does what ``evaluate --protocol deena2010 --corpus data/v2/train250
--test-corpus data/v2/heldout40 --methods ssgpdm-vlmm-posterior`` does for this
method, with the same functions and seeds: the calibration's model on 80 % of the training
utterances (:func:`bayes_talk.calibration.bands.split_for_calibration`) and the
Laplace posterior of each held-out training utterance (``fit/``), then the model on all of
them and the posterior of each test sentence (``test/``, projected through the training
AAM). It stores each raw :class:`~bayes_talk.synthesis.result.SynthesisResult`'s mixture
(``draw_mean``, ``draw_var``) and the truth, one ``.npz`` per utterance, written as it goes.

``score`` fits :class:`~bayes_talk.calibration.bands.BandCalibration` on ``fit/``,
applies it to ``test/`` and scores raw and calibrated with
:func:`bayes_talk.evaluation.calibration.score_utterance` / ``summarise_calibration``
(the functions ``evaluate`` uses), with and without the 4 Hz post-filter
(``--lowpass-hz 4``).
"""
from __future__ import annotations

import json
import sys
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

TRAIN, TEST = "data/v2/train250", "data/v2/heldout40"


def _save(path: Path, res, truth: np.ndarray, seconds: float) -> None:
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, draw_mean=res.draw_mean, draw_var=res.draw_var, truth=truth, seconds=seconds)
    tmp.replace(path)


def dump(out: Path) -> None:
    from bayes_talk.corpus import load_corpus
    from bayes_talk.evaluation.protocols import get_protocol
    from bayes_talk.evaluation.systems import _build, fit_family
    from bayes_talk.gp.threads import torch_threads
    from bayes_talk.calibration.bands import split_for_calibration
    from bayes_talk.posterior.sampling import sample_synthesis

    cfg = get_protocol("deena2010").system
    tr = load_corpus(TRAIN, cmvn="mean")
    te = load_corpus(TEST, aam=tr.aam_path, cmvn="mean")
    seqs = list(tr.sequences)
    fit_idx, held_idx = split_for_calibration(len(seqs), cfg.band_calibration, cfg.seed)
    (out / "fit").mkdir(parents=True, exist_ok=True)
    (out / "test").mkdir(parents=True, exist_ok=True)

    def log(msg: str) -> None:
        print(time.strftime("%H:%M:%S"), msg, flush=True)

    with torch_threads(cfg.torch_threads):
        base = _build("ssgpdm-vlmm", cfg)
        t0 = time.perf_counter()
        sub = type(base)(**asdict(base.config)).fit([seqs[i] for i in fit_idx])
        log(f"calibration model on {len(fit_idx)} utterances: {time.perf_counter() - t0:.0f} s")
        for i in held_idx:
            t0 = time.perf_counter()
            r = sample_synthesis(sub, seqs[i].mfcc, seqs[i].labels, method="laplace",
                                 n_draws=cfg.posterior_draws, seed=cfg.seed, log_warnings=False)
            _save(out / "fit" / f"{seqs[i].name}.npz", r, seqs[i].aam, time.perf_counter() - t0)
        log(f"{len(held_idx)} held-out training utterances synthesised")
        del sub
    t0 = time.perf_counter()
    model = fit_family("ssgpdm-vlmm", seqs, cfg)
    log(f"full model on {len(seqs)} utterances: {time.perf_counter() - t0:.0f} s")
    with torch_threads(cfg.torch_threads):
        for s in te.sequences:
            t0 = time.perf_counter()
            r = sample_synthesis(model, s.mfcc, s.labels, method="laplace", n_draws=cfg.posterior_draws,
                                 seed=cfg.seed)
            _save(out / "test" / f"{s.name}.npz", r, s.aam, time.perf_counter() - t0)
    log(f"{len(te.sequences)} test utterances synthesised")
    (out / "DONE").write_text(json.dumps({"fit": [seqs[i].name for i in held_idx],
                                          "test": [s.name for s in te.sequences]}))


def _load(folder: Path) -> tuple[list, list]:
    from bayes_talk.synthesis.result import SynthesisResult

    res, truths = [], []
    for f in sorted(folder.glob("*.npz")):
        if f.name.endswith(".tmp.npz"):
            continue
        with np.load(f) as z:
            res.append(SynthesisResult("laplace", None, z["draw_mean"], z["draw_var"]))
            truths.append(z["truth"])
    return res, truths


def _variants(fit_res, fit_truths) -> dict:
    """raw, stage 1 alone (the former calibration), stage 2 alone, both stages (the default)."""
    from bayes_talk.calibration.bands import LEVEL_KNOTS, BandCalibration

    cal = BandCalibration.fit(fit_res, fit_truths, method="laplace")
    D = cal.scale.size
    ones = BandCalibration(np.ones(D), "laplace")
    c = np.concatenate([np.abs(2 * r.cdf(z) - 1) for r, z in zip(fit_res, fit_truths)])
    r_dj = np.maximum.accumulate(np.clip(np.quantile(c, LEVEL_KNOTS, axis=0).T, 1e-9, 1 - 1e-7)
                                 + 1e-9 * np.arange(len(LEVEL_KNOTS)), axis=1)
    return {"raw": None, "stage 1 (scale)": BandCalibration(cal.scale, "laplace"),
            "stage 2 (level map)": BandCalibration(ones.scale, "laplace", level_raw=r_dj),
            "stages 1+2 (default)": cal}, cal


def score(where: Path, out: Path | None) -> None:
    from bayes_talk.evaluation.calibration import score_utterance, summarise_calibration
    from bayes_talk.synthesis.sequential import lowpass

    fit_res, fit_truths = _load(where / "fit")
    test_res, test_truths = _load(where / "test")
    report: dict = {"n_fit": len(fit_res), "n_test": len(test_res)}
    if not test_res:  # only the calibration data so far: two-fold cross-validation on it
        half = len(fit_res) // 2
        test_res, test_truths = fit_res[half:], fit_truths[half:]
        fit_res, fit_truths = fit_res[:half], fit_truths[:half]
        report["note"] = f"no test set yet: fitted on {half} held-out training utterances, scored on the rest"
    variants, cal = _variants(fit_res, fit_truths)
    report["calibration"] = cal.to_dict()
    for lp in (None, 4.0):
        if lp is not None:  # also: the calibration fitted on post-filtered held-out predictions
            from bayes_talk.calibration.bands import BandCalibration

            variants["stages 1+2 fitted post-filtered"] = BandCalibration.fit(
                [r.shift(lowpass(r.mean, lp) - r.mean) for r in fit_res], fit_truths, method="laplace")
        for name, v in variants.items():
            t0 = time.perf_counter()
            scores = []
            for r, z in zip(test_res, test_truths):
                rr = r if v is None else v.apply(r)
                if lp is not None:
                    rr = rr.shift(lowpass(rr.mean, lp) - rr.mean)
                scores.append(score_utterance(rr, z, seed=0))
            s = summarise_calibration(scores)
            key = name + ("" if lp is None else f", {lp:g} Hz low-pass")
            report[key] = s
            cov = "  ".join(f"cov{round(100 * float(q))} {c['pooled']:.3f}±{c['pooled_se']:.3f}"
                            for q, c in s["coverage"].items())
            print(f"{key:40s} {cov}  in-range90 {s['params_in_range_90']:.2f}  NLPD {s['nlpd']['mean']:.4f}  "
                  f"CRPS {s['crps']['mean']:.4f}  PIT-KS {s['pit']['ks']:.3f}  ({time.perf_counter() - t0:.0f} s)",
                  flush=True)
    if out is not None:
        out.write_text(json.dumps(report, indent=1, default=float))


if __name__ == "__main__":
    cmd, where = sys.argv[1], Path(sys.argv[2])
    if cmd == "dump":
        dump(where)
    elif cmd == "score":
        score(where, Path(sys.argv[3]) if len(sys.argv) > 3 else None)
    else:
        raise SystemExit(f"unknown command {cmd!r} (dump | score)")
