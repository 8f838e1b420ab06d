"""The particle sweep's compiled proposal tables (issue 24, speed) against their NumPy
formulas, and the pieces the sweep now computes once: the ancestor terms ``link_logf`` (f_t
minus the terms of x_t alone) and the reference row's ln q evaluated with the draws (``ref``)."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.special import logsumexp
from toydata import make_utterances

from bayes_talk.posterior.particle_gibbs import FrameFactors, MixtureProposal
from bayes_talk.posterior.proposal_tables import kernel_mixture_logpdf, smoothness_weights
from bayes_talk.synthesis.joint import UtteranceDensity, make_plan


def test_smoothness_weights_are_the_normalised_gaussian_table():
    rng = np.random.default_rng(0)
    N, M, D = 7, 40, 5
    lw0 = rng.standard_normal(M)
    z, mu = rng.standard_normal((N, D)), rng.standard_normal((M, D))
    var = rng.uniform(1e-6, 2.0, (M, D))            # down to the tiny motion variances of real models
    out = smoothness_weights(lw0, z, mu, 1.0 / var, 0.5 * np.log(var).sum(1))
    w = lw0[None] - 0.5 * (np.log(var)[None] + (z[:, None] - mu[None]) ** 2 / var[None]).sum(-1)
    np.testing.assert_allclose(out, w - logsumexp(w, axis=1, keepdims=True), rtol=1e-10, atol=1e-8)
    assert np.allclose(logsumexp(out, axis=1), 0.0, atol=1e-12)


@pytest.mark.parametrize("shared", [True, False])
def test_kernel_mixture_logpdf_is_the_mixture_density(shared):
    rng = np.random.default_rng(1)
    N, M, d = 9, 30, 3
    X, C = rng.standard_normal((N, d)), rng.standard_normal((M, d))
    X[0] = C[4] + 1e-3                                   # on a centre
    X[1] = 50.0                                          # far from every centre: no underflow to −inf
    lw = rng.standard_normal((1 if shared else N, M))
    lw -= logsumexp(lw, axis=1, keepdims=True)
    hs = np.array([0.005, 0.02, 0.05])
    out = kernel_mixture_logpdf(X, C, lw, hs)
    r2 = ((X[:, None] - C[None]) ** 2).sum(-1)[..., None]
    ref = logsumexp(np.broadcast_to(lw, (N, M))[..., None] - 0.5 * r2 / hs**2 - d * np.log(hs), axis=(1, 2)) \
        - np.log(len(hs)) - 0.5 * d * np.log(2 * np.pi)
    np.testing.assert_allclose(out, ref, rtol=1e-12)
    assert np.isfinite(out[1])


@pytest.fixture(scope="module")
def frames(toy_vlmm):
    u = make_utterances(1, seed=1, mean_len=20)[0]
    plan = make_plan(toy_vlmm, u.mfcc, u.labels, "frame")
    return plan, FrameFactors(UtteranceDensity(plan))


def test_link_terms_are_the_factor_less_the_frames_own_terms(frames):
    """f_t − link_logf_t depends on x_t alone (audio and entry): the same for every ancestor;
    and link_logf_t is 0 at a frame with neither dynamics nor smoothness factor."""
    _, ff = frames
    rng = np.random.default_rng(2)
    linked = [t for t in range(1, ff.T) if t in ff.dyn_gp or t in ff.smooth]
    assert any(t in ff.smooth for t in linked) and any(t in ff.dyn_gp for t in linked)
    for t in linked:
        x = np.repeat(0.1 * rng.standard_normal((1, ff.d)), 6, 0)
        Xprev = 0.3 * rng.standard_normal((6, ff.d))
        own = ff.log_f(t, Xprev, x) - ff.link_logf(t, Xprev, x)
        np.testing.assert_allclose(own, own[0], rtol=1e-10, atol=1e-8)
        ref = ff.audio_loglik(t, x[:1]) + (ff.entry_logpdf(t, x[:1]) if t in ff.entry else 0.0)
        np.testing.assert_allclose(own[0], ref[0], rtol=1e-10, atol=1e-8)
        assert np.ptp(ff.link_logf(t, Xprev, x)) > 1e-6          # the ancestor matters
    unlinked = [t for t in range(1, ff.T) if t not in ff.dyn_gp and t not in ff.smooth]
    for t in unlinked:
        assert not ff.link_logf(t, np.zeros((2, ff.d)), np.ones((2, ff.d))).any()


def test_the_reference_rows_log_q_is_its_own_evaluation(frames):
    """sample_logq(..., ref=x): the last row is x and its ln q is what evaluating x alone gives;
    the other rows are the draws made without ``ref`` (the same random numbers)."""
    plan, ff = frames
    q = MixtureProposal(ff, plan, rho=0.5, h=(0.005, 0.02, 0.05))
    t = next(t for t in range(1, ff.T) if t in ff.smooth)
    rng = np.random.default_rng(3)
    Xprev = 0.2 * rng.standard_normal((8, ff.d))
    x_ref = 0.1 * rng.standard_normal(ff.d)
    X, lq = q.sample_logq(t, Xprev, 8, np.random.default_rng(4), ref=x_ref)
    X0, lq0 = q.sample_logq(t, Xprev, 8, np.random.default_rng(4))
    np.testing.assert_array_equal(X[-1], x_ref)
    np.testing.assert_array_equal(X[:-1], X0[:-1])
    np.testing.assert_allclose(lq[:-1], lq0[:-1], rtol=1e-12)
    _, lq1 = q.sample_logq(t, Xprev[-1:], 1, rng, x_ref[None])
    np.testing.assert_allclose(lq[-1], lq1[0], rtol=1e-12)
