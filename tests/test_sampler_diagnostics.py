"""Diagnostics on what users consume (issue 24, item 5): R-hat, ESS and MCSE of the AAM
parameters per frame beside the latents, and per-draw ``sample_stats`` for every sampler."""
from __future__ import annotations

import numpy as np
import pytest
from toydata import make_utterances

from bayes_talk.synthesis.diagnostics import convergence_problems, frame_diagnostics
from bayes_talk.synthesis.joint import UtteranceDensity, make_plan
from bayes_talk.synthesis.posterior import sample_synthesis


def test_frame_diagnostics_find_the_frame_where_chains_disagree():
    rng = np.random.default_rng(0)
    s = rng.standard_normal((4, 200, 6, 2))
    s[0, :, 2] += 3.0                           # chain 0 sits elsewhere in frame 2 only
    fd = frame_diagnostics(s, "aam_")
    r = np.array(fd["aam_rhat_per_frame"])
    assert r.shape == (6,) and r[2] > 1.2 and np.all(np.delete(r, 2) < 1.05), r
    assert fd["aam_rhat_max"] == pytest.approx(r.max())
    assert np.argmin(fd["aam_ess_bulk_per_frame"]) == 2 and len(fd["aam_ess_tail_per_frame"]) == 6
    assert any("AAM-parameter R-hat" in p for p in convergence_problems(fd))
    assert not convergence_problems({"aam_rhat_max": 1.005, "aam_ess_bulk_min": 500.0, "aam_ess_tail_min": 450.0})


@pytest.fixture(scope="module")
def toy(toy_vlmm):
    u = make_utterances(1, seed=1, mean_len=20)[0]
    return toy_vlmm, u.mfcc[:8], u.labels[:8]


@pytest.mark.parametrize("method", ["laplace", "vi", "emcee"])
def test_every_sampler_records_the_log_density_of_each_draw(toy, method):
    model, mfcc, labels = toy
    kw = {"emcee": {"warmup": 20, "n_draws": 32, "sampler_kw": {"max_steps": 60}},
          "vi": {"n_draws": 16, "sampler_kw": {"steps": 30}}, "laplace": {"n_draws": 16}}[method]
    r = sample_synthesis(model, mfcc, labels, method=method, seed=2, log_warnings=False, map_restarts=0, **kw)
    C, S = r.latent_draws.shape[:2]
    lp = r.sample_stats["lp"]
    assert lp.shape == (C, S)
    dens = UtteranceDensity(make_plan(model, mfcc, labels))
    np.testing.assert_allclose(lp, dens.values(r.latent_draws.reshape(C * S, 8, 3)).reshape(C, S), rtol=1e-9)
    idata = r.to_inference_data()
    assert "lp" in idata.sample_stats
    if method == "emcee":
        assert len(r.diagnostics["aam_rhat_per_frame"]) == 8 and len(r.diagnostics["rhat_per_frame"]) == 8
        assert np.isfinite(r.diagnostics["aam_ess_bulk_min"])
    else:
        assert r.sample_stats["log_weight"].shape == (C, S)
