"""The estimator protocol over the one registry (issue 11): every family saves and loads
with identical predictions, refuses to predict before ``fit``, clones with
``sklearn.base.clone``, and refuses a saved model with a file swapped from another
model or truncated, naming the file."""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from sklearn.base import clone
from toydata import make_utterances

from bayes_talk.errors import NotFittedError
from bayes_talk.estimators.registry import ESTIMATORS, make_estimator
from bayes_talk.synthesis.result import SynthesisResult

#: families without a predictive variance: ``predict_dist`` refuses
POINT_PREDICTORS = {"voice-puppetry", "slds", "dpds"}
#: predicts only utterances of a built corpus (its generator), learns nothing to swap:
#: tests/test_ceiling.py covers its predictions
GENERATOR = {"oracle"}

#: small settings so that every family fits in about a second on the toy data
FAST: dict[str, dict] = {
    "ssgpdm-vlmm": {"latent_dim": 2, "max_iter": 15, "min_count": 4, "max_frames_per_state": 60,
                    "fallback_frames": 80},
    "ssgpdm-phone": {"latent_dim": 2, "max_iter": 15, "max_frames_per_state": 60, "fallback_frames": 80},
    "ssgpdm-vlmm-rc": {"latent_dim": 2, "max_iter": 15, "min_count": 4, "max_frames_per_state": 60,
                       "fallback_frames": 80},
    "ssgpdm-phone-rc": {"latent_dim": 2, "max_iter": 15, "max_frames_per_state": 60, "fallback_frames": 80},
    "ssgpdm-phone-ctx": {"latent_dim": 2, "max_iter": 15, "max_frames_per_state": 60, "fallback_frames": 80,
                         "context_view": 2},
    "ssgpdm-phone-ctx-mean": {"latent_dim": 2, "max_iter": 15, "max_frames_per_state": 60, "fallback_frames": 80,
                              "context_view": 2},
    "sgplvm": {"latent_dim": 2, "max_frames": 150, "max_iter": 15, "validation_frames": 50},
    "voice-puppetry": {"n_states": 4, "n_iter": 5},
    "slds": {"n_iter": 5},
    "dpds": {"max_iter": 10},
    "hmm-mean": {},
    "context-ridge": {"label_window": 1, "mfcc_window": 1, "alphas": (1.0,), "n_splits": 2},
    "context-mlp": {"label_window": 1, "mfcc_window": 1, "hidden": 8, "max_epochs": 3, "n_splits": 2},
    "zero": {},
    "oracle": {"n_draws": 2},
    "sparse-sgpdm": {"latent_dim": 2, "n_inducing": 8, "max_iter": 5, "synth_max_iter": 3},
}


def test_every_registered_family_has_fast_settings():
    assert set(FAST) == set(ESTIMATORS)


@pytest.fixture(scope="module")
def data():
    return make_utterances(8, seed=0), make_utterances(2, seed=5), make_utterances(8, seed=9)


@pytest.fixture(scope="module")
def fitted(data):
    train = data[0]
    return {name: make_estimator(name, **FAST[name]).fit(train) for name in ESTIMATORS}


def _bundle_files(root: Path) -> list[Path]:
    return sorted(p for p in root.rglob("*") if p.is_file() and p.suffix in (".json", ".npz")
                  and p.name != "bundle_manifest.json")


@pytest.mark.parametrize("name", list(ESTIMATORS))
def test_save_load_round_trip_gives_identical_predictions(name, fitted, data, tmp_path):
    model = fitted[name]
    test = data[1][0]
    model.save(tmp_path / "m")
    cls = type(model)
    back = cls.load(tmp_path / "m")
    assert back.get_params() == model.get_params()
    if name in GENERATOR:
        return
    np.testing.assert_array_equal(back.predict(test), model.predict(test))
    if name in POINT_PREDICTORS:
        for m in (model, back):
            with pytest.raises(NotImplementedError, match="point predictor"):
                m.predict_dist(test)
    else:
        d0, d1 = model.predict_dist(test), back.predict_dist(test)
        assert isinstance(d0, SynthesisResult) and isinstance(d1, SynthesisResult)
        np.testing.assert_array_equal(d1.mean, d0.mean)
        np.testing.assert_array_equal(d1.var, d0.var)
        np.testing.assert_array_equal(d0.mean, model.predict(test))
        assert d0.var.shape == d0.mean.shape and np.all(d0.var > 0)
    assert back.get_params() == model.get_params()


@pytest.mark.parametrize("name", list(ESTIMATORS))
def test_not_fitted_error_before_fit(name, data):
    model = make_estimator(name, **FAST[name])
    with pytest.raises(NotFittedError, match="not fitted"):
        model.predict(data[1][0])
    with pytest.raises(NotFittedError):
        model.save("/nonexistent/never-written")
    assert isinstance(NotFittedError("x"), ValueError)  # scikit-learn's contract


@pytest.mark.parametrize("name", list(ESTIMATORS))
def test_clone_and_params(name, fitted):
    model = fitted[name]
    c = clone(model)
    assert type(c) is type(model) and c is not model
    assert c.get_params() == model.get_params()
    with pytest.raises(NotFittedError):
        c.predict(make_utterances(1, seed=3)[0])
    key = next(iter(FAST[name]), None)
    if key is not None:
        c.set_params(**{key: FAST[name][key]})
        assert c.get_params()[key] == FAST[name][key]


@pytest.mark.parametrize("name", list(ESTIMATORS))
def test_swapped_or_truncated_file_refuses_to_load_naming_it(name, fitted, data, tmp_path):
    if name in GENERATOR:
        pytest.skip(f"{name} learns nothing: no fitted arrays to swap")
    model = fitted[name]
    other = make_estimator(name, **FAST[name]).fit(data[2])
    model.save(tmp_path / "a" / "m")
    other.save(tmp_path / "b" / "m")
    cls = type(model)
    files_a = _bundle_files(tmp_path / "a")
    files_b = _bundle_files(tmp_path / "b")
    npz = [p for p in files_a if p.suffix == ".npz"]
    assert npz, f"{name} wrote no .npz: {files_a}"
    target = npz[0]
    donor = files_b[files_a.index(target)]
    backup = target.read_bytes()
    shutil.copyfile(donor, target)  # arrays from another model
    with pytest.raises(ValueError, match=target.name):
        cls.load(tmp_path / "a" / "m")
    target.write_bytes(backup[: len(backup) // 2])  # half-written
    with pytest.raises(ValueError, match=target.name):
        cls.load(tmp_path / "a" / "m")


def test_the_default_family_sets_its_audio_context_and_the_paper_families_do_not():
    """ssgpdm-phone-rc (the default model) sees ±2 frames of audio unless told otherwise;
    deena2010's families keep the paper's per-frame audio."""
    from bayes_talk.pipeline import DEFAULT_MODEL

    assert DEFAULT_MODEL == "ssgpdm-phone-ctx-mean"
    assert make_estimator(DEFAULT_MODEL).audio_context == 2
    assert make_estimator(DEFAULT_MODEL, audio_context=0).audio_context == 0
    for paper in ("ssgpdm-vlmm", "ssgpdm-phone"):
        assert make_estimator(paper).audio_context == 0
    with pytest.raises(ValueError, match="fixed by the family name"):
        make_estimator(DEFAULT_MODEL, right_context=False)


def test_a_family_default_wins_in_evaluate_unless_the_protocol_changes_the_setting():
    """``evaluate`` builds families with the protocol's switching settings; a setting that a
    family sets itself (registry.FAMILY_DEFAULTS) is kept unless the protocol moved it off
    the library default."""
    from bayes_talk.estimators.registry import FAMILY_DEFAULTS
    from bayes_talk.evaluation.systems import SystemConfig, build_family
    from bayes_talk.models.switching import SwitchingConfig

    own = FAMILY_DEFAULTS["ssgpdm-phone-ctx-mean"]["min_frames_per_state"]
    assert own != SwitchingConfig().min_frames_per_state
    assert build_family("ssgpdm-phone-ctx-mean", SystemConfig()).config.min_frames_per_state == own
    assert build_family("ssgpdm-phone-ctx-mean", SystemConfig(ssgpdm_min_frames_per_state=30)).config.min_frames_per_state == 30
    assert build_family("ssgpdm-phone-rc", SystemConfig()).config.min_frames_per_state == SwitchingConfig().min_frames_per_state
    assert build_family("ssgpdm-phone-ctx-mean", SystemConfig()).config.context_mean is True
