"""The observation term as part of the switching model: ``calibrate_model`` fits it on held-out
training utterances, every inference method's predictive ends with it, and it is saved and
loaded with the model."""
from __future__ import annotations

import numpy as np
import pytest
from conftest import TOY_SMALL
from toydata import make_utterances

from bayes_talk.estimators.calibrated import calibrate_model
from bayes_talk.estimators.registry import load_estimator
from bayes_talk.estimators.switching import SwitchingSGPDM


@pytest.fixture(scope="module")
def noisy_model():
    train = make_utterances(20, seed=0)
    return calibrate_model(SwitchingSGPDM(states="vlmm", **TOY_SMALL), train, "holdout", holdout=0.25, n_draws=16)


def test_calibrate_model_fits_the_term_on_held_out_utterances(noisy_model):
    noise = noisy_model.face_noise_
    assert noise is not None and noise.n_dims == noisy_model.dims_[1]
    assert noise.info["n_utterances"] == 5 and noise.info["n_fit"] == 15
    assert len(noise.info["names"]) == 5
    assert np.all(noise.control_var > 0)


@pytest.mark.parametrize("options", [{"posterior": "laplace", "n_draws": 16}, {"posterior": "map"}, {}])
def test_every_method_ends_with_the_term(noisy_model, options):
    utt = make_utterances(1, seed=9)[0]
    raw = noisy_model.predict_dist(utt, face_noise=False, **options)
    got = noisy_model.predict_dist(utt, **options)
    assert got.diagnostics.get("face_noise") and not raw.diagnostics.get("face_noise")
    want = noisy_model.face_noise_.apply(raw, utt.labels)
    np.testing.assert_allclose(got.mean, want.mean, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(got.var, want.var, rtol=1e-10)
    assert np.all(got.var >= noisy_model.face_noise_.scale.min() ** 2 * 0.01)
    np.testing.assert_allclose(noisy_model.predict(utt), noisy_model.predict_dist(utt).mean, rtol=1e-12)


def test_saved_and_loaded_with_the_model(noisy_model, tmp_path):
    d = noisy_model.save(tmp_path / "m")
    back = load_estimator(d)
    assert isinstance(back, SwitchingSGPDM) and back.face_noise_ is not None
    for k in ("shrink", "gp_scale", "scale", "dof", "class_offset", "control_var"):
        np.testing.assert_array_equal(getattr(back.face_noise_, k), getattr(noisy_model.face_noise_, k))
    utt = make_utterances(1, seed=9)[0]
    np.testing.assert_array_equal(back.predict_dist(utt, posterior="laplace", n_draws=16).var,
                                  noisy_model.predict_dist(utt, posterior="laplace", n_draws=16).var)
    with pytest.raises(ValueError, match="AAM parameters"):
        back.with_face_noise(type(back.face_noise_)(*(np.r_[v, v[:1]] if v.ndim == 1 else np.c_[v, v[:, :1]]
                                                      for v in (back.face_noise_.shrink, back.face_noise_.gp_scale,
                                                                back.face_noise_.scale, back.face_noise_.dof,
                                                                back.face_noise_.class_offset,
                                                                back.face_noise_.control_var))))


def test_evaluate_scores_the_term_its_controls_and_ablations():
    """A protocol run trains the posterior family with its term (as train ships it) and
    scores the predictive, the GP predictive alone, the plain constant band and both
    ablations, with the paired difference's standard error in the verdict."""
    from bayes_talk.evaluation import harness as H
    from bayes_talk.evaluation import protocols as P
    from bayes_talk.evaluation import systems as S

    cfg = S.SystemConfig(latent_dim=2, posterior_draws=8, band_calibration=0.3,
                         models={"ssgpdm": {"max_frames_per_state": 30, "min_frames_per_state": 50, "min_count": 5,
                                            "max_iter": 5, "fallback_frames": 40}})
    proto = P.Protocol(name="tiny", paper="test", scheme="holdout", headline=(("AMSE", "mse"),),
                       default_methods=("ssgpdm-vlmm-posterior",), system=cfg, n_train=7, n_test=3)
    cache = {}
    res, _ = H.run_protocol(proto, make_utterances(10, seed=3), ["ssgpdm-vlmm-posterior"], model_cache=cache)
    model = cache[("ssgpdm-vlmm", 0)]
    assert isinstance(model, SwitchingSGPDM) and model.face_noise_ is not None
    assert set(model.face_noise_.info["ablations"]) == {"context-only", "unshrunk"}
    post = res["methods"]["ssgpdm-vlmm-posterior"]
    for key in ("calibration", "calibration_raw", "calibration_control", "calibration_context_only",
                "calibration_unshrunk"):
        assert post[key]["n_utterances"] == 3 and "resolution" in post[key] and post[key]["mse"]["mean"] > 0
    verdict = post["uncertainty_beats_control"]
    assert verdict["nlpd"]["difference_se"] is not None and verdict["nlpd"]["difference_se"] > 0
    assert post["band_calibration"][0]["format"] == "bayes_talk.face_noise"
    # the plain control is centred on the predictive's own mean
    assert post["calibration_control"]["mse"]["mean"] == pytest.approx(post["calibration"]["mse"]["mean"], rel=1e-9)


def test_the_khat_is_recorded_not_gated_and_other_checks_stand(noisy_model):
    """The term was fitted on Laplace syntheses whose k̂ exceeded 0.7 as well: a large finite
    k̂ is recorded, not warned about; an infinite one, or a failed MAP, still warns."""
    from dataclasses import replace

    from bayes_talk.posterior.diagnostics import sampler_warning

    utt = make_utterances(1, seed=9)[0]
    raw = noisy_model.predict_dist(utt, posterior="laplace", n_draws=16, face_noise=False)
    big = replace(raw, diagnostics={**raw.diagnostics, "khat": 2.0},
                  warnings=sampler_warning("laplace", ["PSIS k̂ 2 > 0.7"]))
    got = noisy_model.observe(big, utt.labels)
    assert got.warnings == [] and got.diagnostics["face_noise"]["domain"]["khat"] == 2.0
    assert got.diagnostics["face_noise"]["domain"]["khat_calibration_max"] is not None
    inf = replace(big, diagnostics={**big.diagnostics, "khat": float("inf")})
    assert any("not finite" in w for w in noisy_model.observe(inf, utt.labels).warnings)
