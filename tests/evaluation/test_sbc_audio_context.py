"""Simulated audio round-trips into the samplers when the model sees an audio context window
(issue 24, item 6): the synthesis model simulates the audio *view* (PCA-projected spliced
MFCCs when ``audio_context`` > 0), and SBC and the predictive checks must condition on that
view, not splice and project it a second time."""
from __future__ import annotations

import numpy as np
import pytest
from toydata import make_utterances

from bayes_talk.estimators.switching import SwitchingSGPDM
from bayes_talk.evaluation.sbc import sampler_posterior, scaled_laplace
from bayes_talk.posterior.predictive_checks import (
    posterior_predictive,
    predictive_check,
    prior_predictive,
)
from bayes_talk.posterior.sampling import sample_synthesis
from bayes_talk.synthesis.joint import UtteranceDensity, make_plan

SMALL = {"latent_dim": 3, "max_iter": 40, "min_count": 4, "max_frames_per_state": 120, "fallback_frames": 150}


@pytest.fixture(scope="module")
def ctx_model():
    train = make_utterances(24, seed=0)
    test = make_utterances(2, seed=1, mean_len=20)
    model = SwitchingSGPDM(states="vlmm", seed=0, audio_context=2, **SMALL).fit(train)
    return model, test


def _simulated(model, labels, seed):
    plan = make_plan(model, np.zeros((len(labels), model.dims_[0])), labels, smoothness="off")
    X, Y = prior_predictive(plan, 1, seed=seed)
    plan.audio = Y[0]
    return plan, X[0], Y[0]


def test_the_audio_view_differs_from_the_mfcc_it_came_from(ctx_model):
    """The premise: with audio_context = 2, transforming the view again changes it."""
    model, test = ctx_model
    labels = test[0].labels[2:9]
    _, _, y = _simulated(model, labels, 0)
    assert np.max(np.abs(model.audio_input(y) - y)) > 0.1
    assert np.array_equal(make_plan(model, y, labels, audio_view=True).audio, y)


@pytest.mark.parametrize("posterior", ["laplace-method", "scaled-laplace"])
def test_sbc_posteriors_condition_on_the_simulated_audio_view(ctx_model, posterior):
    """The SBC posteriors' MAP is a mode of the density *of the simulated audio*: its log
    density there equals the one the sampler reports, and its gradient vanishes."""
    model, test = ctx_model
    labels = test[0].labels[2:9]   # 7 frames across phone changes
    plan, _, y = _simulated(model, labels, 1)
    post = sampler_posterior("laplace", n_draws=16) if posterior == "laplace-method" else scaled_laplace(1.0, 16)
    _, diag = post(model, y, labels, 5)
    r = sample_synthesis(model, y, labels, method="map", smoothness="off", log_warnings=False, audio_view=True)
    dens = UtteranceDensity(plan)
    lp, g = dens(r.map_latents)
    assert lp == pytest.approx(diag["map_log_density"], rel=1e-9, abs=1e-9)
    assert diag["map_converged"] and r.map.converged
    # the MAP of the density of the re-projected audio is not a mode of this one
    wrong = sample_synthesis(model, y, labels, method="map", smoothness="off", log_warnings=False)
    assert np.max(np.abs(dens(wrong.map_latents)[1])) > 1e3 * max(np.max(np.abs(g)), 1e-6)


def test_posterior_predictive_check_on_the_audio_view(ctx_model):
    """Replications at the posterior's draws cover the simulated view; compared with the
    view re-projected (the former documented mix-up), they do not."""
    model, test = ctx_model
    labels = test[1].labels[:10]
    plan, _, y = _simulated(model, labels, 3)
    post = sample_synthesis(model, y, labels, method="laplace", n_draws=64, seed=0, smoothness="off",
                            audio_view=True, log_warnings=False)
    rep = posterior_predictive(plan, post.latent_draws, seed=1)
    ok = predictive_check(plan.audio, rep)
    assert 0.75 <= ok.coverage[0.9] <= 1.0, ok.to_dict()
    bad = predictive_check(model.audio_input(y), rep)
    assert bad.coverage[0.9] < ok.coverage[0.9] - 0.2, (bad.coverage, ok.coverage)


@pytest.fixture(scope="module")
def ctx_view_model():
    """The default family's configuration (phone states with right context, audio context
    ±2, the phonetic-context view as the visual mean), small: its audio view has D_y + D_z
    columns, not D_y."""
    train = make_utterances(16, seed=0)
    model = SwitchingSGPDM(states="phone", right_context=True, context_mean=True, audio_context=2, context_view=2,
                           seed=0, latent_dim=3, max_iter=20, min_frames_per_state=10, max_frames_per_state=80,
                           fallback_frames=90).fit(train)
    return model, make_utterances(1, seed=1, mean_len=20)[0]


def test_the_audio_view_of_a_context_view_model_goes_back_into_the_samplers(ctx_view_model):
    """With the phonetic-context view on, the audio view is wider than the MFCCs
    (``audio_view_dim`` = D_y + D_z); ``sample_synthesis(..., audio_view=True)`` takes that
    view (it used to be refused as "expected shape (T, D_y)", so SBC could not run on the
    default family), gives the synthesis of the MFCCs it came from, and refuses the raw MFCCs
    as an audio view, naming the shape."""
    model, utt = ctx_view_model
    labels, mfcc = utt.labels[:12], utt.mfcc[:12]
    view = model.audio_input(mfcc, labels)
    assert view.shape[1] == model.audio_view_dim == model.dims_[0] + model.dims_[1] > model.dims_[0]
    a = sample_synthesis(model, mfcc, labels, method="laplace", n_draws=16, seed=2, log_warnings=False)
    b = sample_synthesis(model, view, labels, method="laplace", n_draws=16, seed=2, log_warnings=False,
                         audio_view=True)
    np.testing.assert_array_equal(b.map_latents, a.map_latents)
    np.testing.assert_array_equal(b.mean, a.mean)
    with pytest.raises(ValueError, match=rf"audio view: expected shape \(T, {model.audio_view_dim}\)"):
        sample_synthesis(model, mfcc, labels, method="map", log_warnings=False, audio_view=True)
    post = scaled_laplace(1.0, 16)
    draws, diag = post(model, view, labels, 5)
    assert draws.shape == (16, 12 * 3) and diag["map_converged"]     # T·d, latent_dim 3
