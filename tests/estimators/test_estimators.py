"""The estimator protocol over the one registry (issue 11): every family saves to a directory
and loads back through the registry, without naming its class (issue 26: one layout, one
signature), with identical predictions; refuses to predict before ``fit``; clones with
``sklearn.base.clone``; and refuses a saved model with a file swapped from another model or
truncated, naming the file."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from sklearn.base import clone
from toydata import make_utterances

from bayes_talk.base.errors import NotFittedError
from bayes_talk.estimators.base import ARRAYS_FILE, ESTIMATOR_FILE, FORMAT_VERSION, Estimator
from bayes_talk.estimators.registry import ESTIMATORS, load_estimator, make_estimator
from bayes_talk.synthesis.result import SynthesisResult

#: families without a predictive variance: ``predict_dist`` refuses
POINT_PREDICTORS = {"voice-puppetry", "slds", "dpds"}
#: predicts only utterances of a built corpus (its generator), learns nothing to swap:
#: tests/evaluation/test_ceiling.py covers its predictions
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


class _FittedOnDemand(dict):
    """Family name -> its estimator with :data:`FAST` settings fitted on the training toy
    data, fitted the first time a test asks for it: under pytest-xdist the parametrised tests
    of one module run on both workers, and each worker fits only the families its own tests
    read (the whole registry fitted in each worker cost 20-30 s twice; issue 29)."""

    def __init__(self, train):
        super().__init__()
        self.train = train

    def __missing__(self, name: str):
        self[name] = model = make_estimator(name, **FAST[name]).fit(self.train)
        return model


@pytest.fixture(scope="module")
def fitted(data):
    return _FittedOnDemand(data[0])


def _bundle_files(root: Path) -> list[Path]:
    return sorted(p for p in root.rglob("*") if p.is_file() and p.suffix in (".json", ".npz")
                  and p.name != "bundle_manifest.json")


@pytest.mark.parametrize("name", list(ESTIMATORS))
def test_save_load_round_trip_gives_identical_predictions(name, fitted, data, tmp_path):
    model = fitted[name]
    test = data[1][0]
    d = model.save(tmp_path / "m")
    # one layout: a directory with the descriptor naming the class, the arrays and the manifest
    assert d == tmp_path / "m" and {p.name for p in d.iterdir()} >= {ESTIMATOR_FILE, ARRAYS_FILE,
                                                                     "bundle_manifest.json"}
    desc = json.loads((d / ESTIMATOR_FILE).read_text())
    assert desc["version"] == FORMAT_VERSION and desc["class"] == type(model).__qualname__
    assert desc["module"] == type(model).__module__
    back = load_estimator(d)                           # no class passed in
    assert type(back) is type(model)
    assert type(Estimator.load(d)) is type(model) and type(type(model).load(d)) is type(model)
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
    # the saved arrays are the fitted state's, unchanged
    with np.load(d / ARRAYS_FILE) as z:
        saved = {k: z[k] for k in z.files}
    state = model._get_state()[1]
    assert sorted(saved) == sorted(state)
    for k, a in state.items():
        np.testing.assert_array_equal(saved[k], a)


def test_another_class_s_bundle_is_refused_by_a_class_load(fitted, tmp_path):
    from bayes_talk.estimators.ceiling import ZeroModel

    d = fitted["hmm-mean"].save(tmp_path / "m")
    with pytest.raises(ValueError, match="a saved HMMMean.*not a ZeroModel"):
        ZeroModel.load(d)
    with pytest.raises(FileNotFoundError, match="holds no saved estimator"):
        load_estimator(tmp_path / "nothing")


def test_the_band_calibrated_wrapper_round_trips_with_the_estimator_it_wraps(fitted, data, tmp_path):
    """The wrapper (issue 26, item 3) saves and loads like any estimator: its descriptor holds
    the calibration, the sub-directory ``estimator`` the wrapped one; nothing names a class."""
    from bayes_talk.calibration.bands import fit_band_calibration
    from bayes_talk.estimators.calibrated import BandCalibrated

    model = fitted["ssgpdm-vlmm"]
    train, test = data[0], data[1][0]
    cal = fit_band_calibration(model, train, method="laplace", holdout=0.3, n_draws=8, seed=1)
    wrapped = BandCalibrated.wrap(model, cal)
    d = wrapped.save(tmp_path / "m")
    assert (d / "estimator" / ESTIMATOR_FILE).is_file()
    back = load_estimator(d)
    assert type(back) is BandCalibrated and type(back.estimator_) is type(model)
    assert back.estimator_ is back.estimator and back.calibration_.to_dict() == cal.to_dict()
    for opts in ({"posterior": "laplace", "n_draws": 8}, {}):
        r0, r1 = wrapped.predict_dist(test, **opts), back.predict_dist(test, **opts)
        np.testing.assert_array_equal(r1.mean, r0.mean)
        np.testing.assert_array_equal(r1.var, r0.var)
        np.testing.assert_array_equal(r1.interval(0.9)[1], r0.interval(0.9)[1])
    assert back.synthesis_options == model.synthesis_options and back.post_filter is model.post_filter


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
    files_a = _bundle_files(tmp_path / "a")
    files_b = _bundle_files(tmp_path / "b")
    npz = [p for p in files_a if p.suffix == ".npz"]
    assert npz, f"{name} wrote no .npz: {files_a}"
    target = npz[0]
    donor = files_b[files_a.index(target)]
    backup = target.read_bytes()
    shutil.copyfile(donor, target)  # arrays from another model
    with pytest.raises(ValueError, match=target.name):
        load_estimator(tmp_path / "a" / "m")
    target.write_bytes(backup[: len(backup) // 2])  # half-written
    with pytest.raises(ValueError, match=target.name):
        load_estimator(tmp_path / "a" / "m")


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
    family sets itself (registry.FAMILY_DEFAULTS) is kept unless the protocol sets it."""
    from bayes_talk.estimators.registry import FAMILY_DEFAULTS
    from bayes_talk.evaluation.systems import SystemConfig, build_family
    from bayes_talk.models.switching import SwitchingConfig

    own = FAMILY_DEFAULTS["ssgpdm-phone-ctx-mean"]["min_frames_per_state"]
    assert own != SwitchingConfig().min_frames_per_state
    assert build_family("ssgpdm-phone-ctx-mean", SystemConfig()).config.min_frames_per_state == own
    moved = SystemConfig(models={"ssgpdm": {"min_frames_per_state": 30}})
    assert build_family("ssgpdm-phone-ctx-mean", moved).config.min_frames_per_state == 30
    assert build_family("ssgpdm-phone-rc", SystemConfig()).config.min_frames_per_state == SwitchingConfig().min_frames_per_state
    assert build_family("ssgpdm-phone-ctx-mean", SystemConfig()).config.context_mean is True


@pytest.mark.parametrize("name", ["ssgpdm-vlmm", "sgplvm", "sparse-sgpdm"])
def test_the_layouts_of_earlier_versions_are_read(name, fitted, data, tmp_path):
    """Before issue 26 the switching SGPDM saved ``model.json`` + ``arrays.npz`` into a
    directory, deena2009's SGPLVM and the sparse SGPDM ``<base>.json`` + ``<base>.npz``
    (with their settings under ``estimator``): ``load_estimator`` reads them, predictions equal."""
    from bayes_talk.base.files import write_model_files

    model, test = fitted[name], data[1][0]
    meta, arrays = model._get_state()
    if name == "ssgpdm-vlmm":
        path = tmp_path / "m"
        write_model_files(path / "model.json", path / "arrays.npz", meta, arrays)
    else:
        path = tmp_path / "sgpdm"
        old = {**meta["model"], "estimator": {"name": name, "params": model.get_params()}}
        write_model_files(path.with_suffix(".json"), path.with_suffix(".npz"), old, arrays)
    back = load_estimator(path)
    assert type(back) is type(model) and back.get_params() == model.get_params()
    d0, d1 = model.predict_dist(test), back.predict_dist(test)
    np.testing.assert_array_equal(d1.mean, d0.mean)
    np.testing.assert_array_equal(d1.var, d0.var)
