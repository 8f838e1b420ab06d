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
from bayes_talk.synthesis.joint import UtteranceDensity, make_plan
from bayes_talk.synthesis.posterior import sample_synthesis
from bayes_talk.synthesis.predictive_checks import (
    posterior_predictive,
    predictive_check,
    prior_predictive,
)

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
