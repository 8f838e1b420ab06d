"""The switching SGPDM: training per state, Algorithms 1 and 2, persistence, bad input."""
from __future__ import annotations

import json
from concurrent.futures import ProcessPoolExecutor

import numpy as np
import pytest
from toydata import make_utterances

from bayes_talk.base.bundle import write_bundle_manifest
from bayes_talk.estimators.switching import SwitchingSGPDM
from bayes_talk.models.switching import FALLBACK
from bayes_talk.synthesis.sequential import lowpass

SMALL = {"latent_dim": 3, "max_iter": 40, "min_count": 4, "max_frames_per_state": 120, "fallback_frames": 150}


@pytest.fixture(scope="module")
def data():
    return make_utterances(24, seed=0), make_utterances(4, seed=1)


@pytest.fixture(scope="module")
def vlmm_model(toy_vlmm):
    """``SwitchingSGPDM(states="vlmm", **SMALL)`` on ``data[0]``: the session's toy model
    (tests/conftest.py, the same settings and data; read-only)."""
    return toy_vlmm


@pytest.fixture(scope="module")
def phone_model(data):
    return SwitchingSGPDM(states="phone", **SMALL).fit(data[0])


def test_training_subsequences_match_their_state(vlmm_model, data):
    train = data[0]
    n_checked = 0
    for state, m in vlmm_model.models_.items():
        if state == FALLBACK:
            continue
        # every subsequence of a state model is as long as the state's memory
        assert all(L == len(state) for L in m.seq_lengths_), state
        n_checked += 1
    assert n_checked >= 5
    # the fallback model exists and covers all phones' frames
    assert FALLBACK in vlmm_model.models_
    assert sum(vlmm_model.models_[FALLBACK].seq_lengths_) <= SMALL["fallback_frames"]
    assert len(train) == 24


@pytest.mark.parametrize("algorithm", ["optimise", "predict"])
def test_synthesis_beats_the_per_phone_mean_on_toy_data(vlmm_model, data, algorithm):
    train, test = data
    means = {}
    for s in train:
        for lab, z in zip(s.labels, s.aam):
            means.setdefault(lab, []).append(z)
    means = {k: np.mean(v, 0) for k, v in means.items()}
    err_ours, err_mean = [], []
    for s in test:
        r = vlmm_model.synthesize(s.mfcc, s.labels, algorithm=algorithm)
        assert r.mean.shape == s.aam.shape and r.var.shape == s.aam.shape and np.all(r.var > 0)
        # the segmentation covers every frame once, in order
        assert next(seg.start for seg in r.segments) == 0 and r.segments[-1].stop == s.n_frames
        assert all(a.stop == b.start for a, b in zip(r.segments, r.segments[1:]))
        err_ours.append(((r.mean - s.aam) ** 2).mean())
        err_mean.append(((np.array([means[lab] for lab in s.labels]) - s.aam) ** 2).mean())
    assert np.mean(err_ours) < np.mean(err_mean), (np.mean(err_ours), np.mean(err_mean))


def test_phone_states_segment_into_runs(phone_model, data):
    s = data[1][0]
    r = phone_model.synthesize(s.mfcc, s.labels)
    for seg in r.segments:
        assert set(s.labels[seg.start:seg.stop]) == {seg.state[0]}
    assert all(a.state != b.state for a, b in zip(r.segments, r.segments[1:]))


def test_smoothness_term_reduces_jumps_at_segment_boundaries(vlmm_model, data):
    jumps = {}
    for smooth in (True, False):
        j = []
        for s in data[1]:
            r = vlmm_model.synthesize(s.mfcc, s.labels, smoothness=smooth)
            for seg in r.segments[1:]:
                j.append(np.abs(r.mean[seg.start] - r.mean[seg.start - 1]).mean())
        jumps[smooth] = np.mean(j)
    assert jumps[True] < jumps[False], jumps


def test_save_load_round_trip_gives_identical_synthesis(vlmm_model, data, tmp_path):
    vlmm_model.save(tmp_path / "m")
    loaded = SwitchingSGPDM.load(tmp_path / "m")
    s = data[1][0]
    a = vlmm_model.synthesize(s.mfcc, s.labels)
    b = loaded.synthesize(s.mfcc, s.labels)
    np.testing.assert_array_equal(a.mean, b.mean)
    assert a.segments == b.segments


def test_executor_gives_the_same_model_as_sequential(data):
    train = data[0][:6]
    seq = SwitchingSGPDM(states="phone", **SMALL).fit(train)
    with ProcessPoolExecutor(2) as ex:  # Pyro's handler stack is per process: no thread pools
        par = SwitchingSGPDM(states="phone", **SMALL).fit(train, executor=ex)
    assert seq.models_.keys() == par.models_.keys()
    for k in seq.models_:
        np.testing.assert_allclose(seq.models_[k].X_, par.models_[k].X_, rtol=0, atol=1e-10)


def test_unseen_phone_warns_and_backs_off(vlmm_model, data):
    s = data[1][0]
    labels = list(s.labels)
    labels[5:8] = ["zh"] * 3  # toy data never uses zh
    with pytest.warns(UserWarning, match="zh"):
        r = vlmm_model.synthesize(s.mfcc, labels)
    assert np.all(np.isfinite(r.mean))


def test_bad_input_is_refused_with_a_clear_message(vlmm_model, data, tmp_path):
    s = data[1][0]
    with pytest.raises(ValueError, match="labels have"):
        vlmm_model.synthesize(s.mfcc, s.labels[:-3])
    with pytest.raises(ValueError, match="expected shape"):
        vlmm_model.synthesize(s.mfcc[:, :3], s.labels)
    with pytest.raises(ValueError, match="algorithm"):
        vlmm_model.synthesize(s.mfcc, s.labels, algorithm="viterbi")
    d = vlmm_model.save(tmp_path / "m")
    desc = json.loads((d / "estimator.json").read_text())
    desc["state"]["version"] = 99                       # the switching model's own format version
    (d / "estimator.json").write_text(json.dumps(desc))
    write_bundle_manifest(d)
    with pytest.raises(ValueError, match="estimator.json: switching model: version expected 1, found 99"):
        SwitchingSGPDM.load(d)


def test_lowpass_is_zero_phase_and_removes_high_frequencies():
    t = np.arange(200) / 25.0
    slow, fast = np.sin(2 * np.pi * 1.0 * t), 0.5 * np.sin(2 * np.pi * 10.0 * t)
    out = lowpass((slow + fast)[:, None], cutoff_hz=4.0)[:, 0]
    inner = slice(25, 175)
    assert np.abs(out[inner] - slow[inner]).max() < 0.05  # no delay, fast part gone
    with pytest.raises(ValueError, match="cutoff"):
        lowpass(slow[:, None], cutoff_hz=20.0)


def test_synthesize_many_in_processes_equals_one_process(vlmm_model, data):
    from bayes_talk.synthesis.sequential import synthesize_many

    utts = [(s.mfcc, s.labels) for s in data[1][:2]]
    before = [vlmm_model.synthesize(mfcc, labels, algorithm="predict").mean for mfcc, labels in utts]
    par = synthesize_many(vlmm_model, utts, workers=2, algorithm="predict")
    for b, r in zip(before, par, strict=True):
        np.testing.assert_array_equal(r.mean, b)
    # sending the model to the workers leaves it as it was (torch's shared-memory
    # pickling once swapped its storage under the cached NumPy views: garbage latents)
    for (mfcc, labels), b in zip(utts, before, strict=True):
        np.testing.assert_array_equal(vlmm_model.synthesize(mfcc, labels, algorithm="predict").mean, b)
    key = next(iter(vlmm_model.models_))
    assert not vlmm_model.models_[key].predictors_["audio"].X.is_shared()


def test_closed_form_segment_objective_equals_the_torch_reference(vlmm_model):
    import torch

    from bayes_talk.synthesis.optimise import sequence_log_density
    from bayes_talk.synthesis.segment_objective import segment_objective

    key = next(k for k, m in vlmm_model.models_.items() if m.dynamics_predictor_ is not None)
    m = vlmm_model.models_[key]
    rng = np.random.default_rng(0)
    X = m.X_[:4] + 0.05 * rng.normal(size=(4, m.X_.shape[1]))
    Y = (m._Y["audio"].numpy() + m.means_["audio"])[:4] + 0.1
    z = (m._Y["visual"].numpy() + m.means_["visual"])[5:6]
    mu, cov = vlmm_model.entry_[key]
    e = vlmm_model.motion_var_
    vis = m.predictors_["visual"]
    f, g = segment_objective(X, Y, m.predictors_["audio"], m.dynamics_predictor_,
                             (mu, np.linalg.inv(cov), np.linalg.slogdet(cov)[1]), (vis, z, e))
    Xt = torch.as_tensor(X).requires_grad_(True)
    ref = sequence_log_density(
        Xt, torch.as_tensor(Y), m.predictors_["audio"], m.dynamics_predictor_,
        (torch.as_tensor(mu), torch.linalg.cholesky(torch.as_tensor(cov))),
        lambda Xs: vis.log_lik(torch.as_tensor(z), Xs[:1], torch.as_tensor(e)).sum())
    ref.backward()
    assert f == pytest.approx(float(ref.detach()), rel=1e-9)
    np.testing.assert_allclose(g, Xt.grad.numpy(), rtol=1e-6, atol=1e-6 * np.abs(g).max())


def test_compiled_segment_objective_equals_the_term_by_term_one_bit_for_bit(vlmm_model):
    """Algorithm 1's L-BFGS evaluates the segment objective in one compiled call; it must be
    the per-term sum exactly (an iteration-capped L-BFGS path turns a last-bit difference
    into a different segment), with and without each optional term, for segments short and
    longer than NumPy's 8-way and 128-element summation blocks."""
    from bayes_talk.synthesis.segment_objective import (
        _numpy_sum,
        compiled_segment_objective,
        segment_objective,
    )

    rng = np.random.default_rng(3)
    for n in (0, 1, 7, 8, 9, 127, 128, 129, 300, 1031):
        a = rng.normal(size=n) * 10.0 ** rng.uniform(-3, 6, n)
        assert _numpy_sum(a) == a.sum()
    key = next(k for k, m in vlmm_model.models_.items() if m.dynamics_predictor_ is not None)
    m = vlmm_model.models_[key]
    mu, cov = vlmm_model.entry_[key]
    first = (mu, np.linalg.inv(cov), float(np.linalg.slogdet(cov)[1]))
    vis = m.predictors_["visual"]
    z = (m._Y["visual"].numpy() + m.means_["visual"])[5:6]
    smooth = (vis, z, vlmm_model.motion_var_)
    Ytr = m._Y["audio"].numpy() + m.means_["audio"]
    for T in (1, 2, 9, 140):
        idx = rng.integers(0, len(m.X_), T)
        X = m.X_[idx] + 0.05 * rng.normal(size=(T, m.X_.shape[1]))
        Y = Ytr[idx] + 0.1 * rng.normal(size=(T, Ytr.shape[1]))
        for dyn, fi, sm in [(m.dynamics_predictor_, first, smooth), (None, None, None),
                            (m.dynamics_predictor_, None, None), (None, first, smooth)]:
            f_ref, g_ref = segment_objective(X, Y, m.predictors_["audio"], dyn, fi, sm)
            f, g = compiled_segment_objective(Y, m.predictors_["audio"], dyn, fi, sm)(X)
            assert f == f_ref
            np.testing.assert_array_equal(g, g_ref)


def test_audio_context_window_is_fitted_used_and_saved(data, tmp_path):
    """audio_context=k: the state models see the PCA-reduced MFCCs of frames t−k..t+k, the
    transform travels with the model, and a later frame's audio changes an earlier frame's
    synthesis (which per-frame MFCCs cannot do)."""
    from bayes_talk.features.audio_context import AudioContext, splice
    from bayes_talk.posterior.sampling import sample_synthesis

    train, test = data
    # 8 utterances (~300 frames) are plenty to fit the 5·D-column window's PCA and some states
    m = SwitchingSGPDM(states="vlmm", seed=0, audio_context=2, **SMALL).fit(train[:8])
    D = train[0].mfcc.shape[1]
    s = test[0]
    a = m.audio_input(s.mfcc)
    assert a.shape == s.mfcc.shape and not np.allclose(a, s.mfcc)
    ref = (splice(s.mfcc, 2) - m.audio_.mean_) @ m.audio_.projection_
    np.testing.assert_allclose(a, ref)
    assert m.audio_.projection_.shape == (5 * D, D)
    # the state models were trained on the transformed audio
    sm = next(v for k, v in m.models_.items() if k != FALLBACK)
    assert sm.predictors_["audio"].X.shape[0] > 0
    r = m.synthesize(s.mfcc, s.labels)
    # change only the last two frames' audio: with context, frame T−3's audio view changes
    mf = s.mfcc.copy()
    mf[-2:] += 3.0
    assert not np.allclose(m.audio_input(mf)[-3], a[-3])
    assert np.allclose(AudioContext(0).fit([s.mfcc]).transform(mf)[-3], mf[-3])
    m.save(tmp_path / "m")
    m2 = SwitchingSGPDM.load(tmp_path / "m")
    assert m2.audio_context == 2
    np.testing.assert_array_equal(m2.audio_input(s.mfcc), a)
    np.testing.assert_array_equal(m2.synthesize(s.mfcc, s.labels).mean, r.mean)
    p = sample_synthesis(m2, s.mfcc, s.labels, method="map", seed=0, log_warnings=False)
    assert p.mean.shape == r.mean.shape and np.all(np.isfinite(p.mean))
    with pytest.raises(ValueError, match="audio context"):
        AudioContext(-1)


def test_direct_log_joint_trains_the_same_switching_model_as_the_pyro_trace(data, monkeypatch):
    """Issue 29: the state models fitted through the direct log joint (the default) have
    the hyperparameters and latents of the Pyro-trace path (``sgpdm_program.trace_log_joint``,
    kept as the reference)."""
    import bayes_talk.models.sgpdm as sgpdm_mod
    from bayes_talk.base import settings
    from bayes_talk.models.sgpdm_program import sgpdm_log_joint, trace_log_joint

    train = data[0][:5]
    fits = {}
    for path, fn in (("pyro", trace_log_joint), ("direct", sgpdm_log_joint)):
        monkeypatch.setattr(sgpdm_mod, "program_log_joint", fn)
        with settings.override(direct_fit=False):  # torch's L-BFGS through autograd of the log joint
            fits[path] = SwitchingSGPDM(states="phone", **SMALL).fit(train)
    ref, new = fits["pyro"], fits["direct"]
    assert ref.models_.keys() == new.models_.keys()
    for k in ref.models_:
        np.testing.assert_array_equal(new.models_[k].X_, ref.models_[k].X_)
        for h, v in ref.models_[k].hyper_.items():
            np.testing.assert_array_equal(np.asarray(new.models_[k].hyper_[h]), np.asarray(v), err_msg=f"{k} {h}")
