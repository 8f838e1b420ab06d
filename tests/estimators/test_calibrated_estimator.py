"""The band calibration as a wrapping estimator (issue 26, item 3):
:class:`bayes_talk.estimators.calibrated.BandCalibrated` recalibrates the results of every
inference method alike, and saves / loads as every estimator (the calibration in its
descriptor, the wrapped estimator in a sub-directory), reading every calibration format
version."""
from __future__ import annotations

import json

import numpy as np
import pytest
from toydata import make_utterances

from bayes_talk.base.bundle import write_bundle_manifest
from bayes_talk.calibration.bands import BandCalibration
from bayes_talk.estimators.base import ESTIMATOR_FILE
from bayes_talk.estimators.calibrated import BandCalibrated
from bayes_talk.estimators.ceiling import ZeroModel
from bayes_talk.estimators.registry import load_estimator


@pytest.fixture(scope="module")
def utts():
    return make_utterances(4, seed=2)


def test_every_method_is_recalibrated_alike(utts):
    zero = ZeroModel().fit(utts[:3])
    D = utts[0].aam.shape[1]
    scale = np.linspace(0.5, 2.0, D)
    test = utts[3]
    raw = zero.predict_dist(test)
    same = BandCalibrated.wrap(zero, BandCalibration(scale, "zero"))
    got = same.predict_dist(test)
    np.testing.assert_array_equal(got.mean, raw.mean)
    np.testing.assert_allclose(got.var, raw.var * scale**2, rtol=1e-12)
    np.testing.assert_array_equal(got.var, BandCalibration(scale, "zero").apply(raw).var)
    other = BandCalibrated.wrap(zero, BandCalibration(scale, "laplace")).predict_dist(test)
    np.testing.assert_array_equal(other.var, got.var)   # fitted on another method's syntheses: applied alike
    np.testing.assert_array_equal(same.predict(test), zero.predict(test))


def test_save_and_load_round_trip_and_every_calibration_version_loads(utts, tmp_path):
    zero = ZeroModel().fit(utts[:3])
    D = utts[0].aam.shape[1]
    model = BandCalibrated.wrap(zero, BandCalibration(np.linspace(0.5, 2.0, D), "zero"))
    d = model.save(tmp_path / "m")
    assert (d / ESTIMATOR_FILE).is_file() and (d / "estimator" / ESTIMATOR_FILE).is_file()
    back = load_estimator(d)                                       # no class passed in
    assert isinstance(back, BandCalibrated) and isinstance(back.estimator_, ZeroModel)
    np.testing.assert_array_equal(back.predict_dist(utts[3]).var, model.predict_dist(utts[3]).var)
    assert type(BandCalibrated.load(d)) is BandCalibrated
    # a version-1 calibration (the band scale only) is read as stage 1 alone
    desc = json.loads((d / ESTIMATOR_FILE).read_text())
    old = desc["state"]["calibration"]
    old = {k: old[k] for k in ("format", "method", "levels", "scale", "level_cal", "n_utterances", "n_frames",
                               "coverage_raw", "coverage_calibrated", "held_out")} | {"version": 1}
    (d / ESTIMATOR_FILE).write_text(json.dumps({**desc, "state": {"calibration": old}}))
    write_bundle_manifest(d)
    v1 = load_estimator(d)
    np.testing.assert_allclose(v1.predict_dist(utts[3]).var, model.predict_dist(utts[3]).var, rtol=1e-12)
    (d / ESTIMATOR_FILE).write_text(json.dumps({**desc, "state": {}}))
    write_bundle_manifest(d)
    with pytest.raises(ValueError, match=f"{ESTIMATOR_FILE}: incomplete or corrupt.*calibration"):
        load_estimator(d)
    (d / ESTIMATOR_FILE).write_text(json.dumps({**desc, "state": {"calibration": {**old, "version": 99}}}))
    write_bundle_manifest(d)
    with pytest.raises(ValueError, match=f"{ESTIMATOR_FILE}: calibration: format version 99"):
        load_estimator(d)


def test_fit_is_the_estimator_fit_then_the_calibration_of_its_posterior():
    from bayes_talk.calibration.bands import fit_band_calibration
    from bayes_talk.estimators.registry import make_estimator

    small = {"latent_dim": 2, "max_iter": 10, "min_count": 4, "max_frames_per_state": 60, "fallback_frames": 80}
    train = make_utterances(8, seed=4)
    wrapped = BandCalibrated(make_estimator("ssgpdm-vlmm", **small), holdout=0.3, n_draws=8, seed=1).fit(train)
    by_hand = make_estimator("ssgpdm-vlmm", **small).fit(train)
    cal = fit_band_calibration(by_hand, train, method="laplace", holdout=0.3, n_draws=8, seed=1)
    np.testing.assert_array_equal(wrapped.calibration_.scale, cal.scale)
    assert wrapped.calibration_.held_out == cal.held_out and wrapped.calibration_.method == "laplace"
    test = make_utterances(1, seed=9)[0]
    got = wrapped.predict_dist(test, posterior="laplace", n_draws=8, seed=0)
    want = cal.apply(by_hand.predict_dist(test, posterior="laplace", n_draws=8, seed=0))
    np.testing.assert_allclose(got.var, want.var, rtol=1e-10)
    path = wrapped.predict_dist(test)                    # the sequential path: recalibrated alike
    np.testing.assert_allclose(path.var, cal.apply(by_hand.predict_dist(test)).var, rtol=1e-10)


def test_evaluate_scores_the_wrapped_model_and_caches_it_with_its_calibration(monkeypatch):
    """The harness wraps a posterior family's model once per split (label sources reuse the
    cached, calibrated model) and scores the calibrated predictive beside the raw one."""
    from bayes_talk.evaluation import harness as H
    from bayes_talk.evaluation import protocols as P
    from bayes_talk.evaluation import systems as S

    cfg = S.SystemConfig(latent_dim=2, posterior_draws=8, band_calibration=0.3, calibration="bands",
                         models={"ssgpdm": {"max_frames_per_state": 30, "min_frames_per_state": 50, "min_count": 5,
                                            "max_iter": 5, "fallback_frames": 40}})
    proto = P.Protocol(name="tiny", paper="test", scheme="holdout", headline=(("AMSE", "mse"),),
                       default_methods=("ssgpdm-vlmm-posterior",), system=cfg, n_train=6, n_test=2)
    calls = []
    orig = H.fit_calibrated_family

    def counting(*a, **k):
        calls.append(1)
        return orig(*a, **k)

    monkeypatch.setattr(H, "fit_calibrated_family", counting)
    utts, cache = make_utterances(8, seed=3), {}
    first, _ = H.run_protocol(proto, utts, ["ssgpdm-vlmm-posterior", "ssgpdm-vlmm-optimise"], model_cache=cache)
    second, _ = H.run_protocol(proto, utts, ["ssgpdm-vlmm-posterior", "ssgpdm-vlmm-optimise"], model_cache=cache)
    assert len(calls) == 1 and isinstance(cache[("ssgpdm-vlmm", 0)], BandCalibrated)
    post = first["methods"]["ssgpdm-vlmm-posterior"]
    assert "calibration_raw" in post and len(post["band_calibration"]) == 1
    assert "calibration_raw" in first["methods"]["ssgpdm-vlmm-optimise"]     # another method: calibrated alike
    assert second["methods"]["ssgpdm-vlmm-posterior"]["mse"] == post["mse"]
