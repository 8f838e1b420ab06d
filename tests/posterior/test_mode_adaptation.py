"""The warm-up tallies of the own-mode proposals (bayes_talk.posterior.mode_adaptation)."""
from __future__ import annotations

import numpy as np
import pytest

from bayes_talk.posterior.mode_adaptation import OWN_COVARIANCE_FLOOR, ModeTally, component_logpdf


def test_mode_tally_sums_both_estimates_of_each_modes_mass_mean_and_covariance():
    """Five updates of random tries, weights, responsibilities and states: the masses are the
    mean over the updates of Σ_i ½ w_i r_ik + ½ r_k(x); each mode's mean and covariance are
    those of the tries and states weighted by ½ w_i r_ik and ½ r_k(x) (numpy's weighted
    covariance), plus the floor × the own covariance; ``min_mass`` leaves out the lighter mode."""
    rng = np.random.default_rng(3)
    K, d, N = 2, 3, 16
    tally = ModeTally(K, d)
    pts, wts = [], []
    for _ in range(5):
        Y, x = rng.normal(size=(N, d)), rng.normal(size=d)
        w, r, rx = rng.dirichlet(np.ones(N)), rng.dirichlet(np.ones(K), size=N), rng.dirichlet([1.0, 3.0])
        tally.add(Y, w, r, x, rx)
        pts.append(np.vstack([Y, x]))
        wts.append(np.vstack([0.5 * w[:, None] * r, 0.5 * rx]))
    pts, wts = np.vstack(pts), np.vstack(wts)
    assert tally.n == 5
    np.testing.assert_allclose(tally.masses(), wts.sum(0) / 5, rtol=1e-12)
    assert tally.masses().sum() == pytest.approx(1.0, rel=1e-12)
    own = np.stack([np.diag([0.5, 1.0, 2.0])] * K)
    idx, mu, C = tally.moments(own, min_mass=0.0)
    assert list(idx) == [0, 1]
    for k in range(K):
        np.testing.assert_allclose(mu[k], np.average(pts, axis=0, weights=wts[:, k]), rtol=1e-10)
        np.testing.assert_allclose(C[k], np.cov(pts.T, aweights=wts[:, k], bias=True) + OWN_COVARIANCE_FLOOR * own[k],
                                   rtol=1e-10, atol=1e-14)
    heavy = int(np.argmax(tally.mass))
    idx, mu, _ = tally.moments(own, min_mass=float(tally.mass.min()) + 1e-9)
    assert list(idx) == [heavy] and mu.shape == (1, d)


def test_mode_tally_leaves_out_a_mode_whose_covariance_is_degenerate():
    """Every try and state of mode 0 at one point: with no floor its covariance is zero, so the
    mode gets no learnt component; with the floor it does, at that point."""
    tally = ModeTally(2, 2)
    p = np.array([0.3, -0.2])
    r = np.tile([1.0, 0.0], (4, 1))
    for _ in range(3):
        tally.add(np.tile(p, (4, 1)), np.full(4, 0.25), r, p, np.array([1.0, 0.0]))
    own = np.stack([np.eye(2)] * 2)
    idx, _, _ = tally.moments(own, min_mass=1.0, floor=0.0)
    assert len(idx) == 0
    idx, mu, C = tally.moments(own, min_mass=1.0)
    assert list(idx) == [0]
    np.testing.assert_allclose(mu[0], p, rtol=1e-12)
    np.testing.assert_allclose(C[0], OWN_COVARIANCE_FLOOR * np.eye(2), atol=1e-12)


def test_component_logpdf_is_the_gaussian_log_density():
    """ln N(x; m_k, L_k L_kᵀ) against scipy for two components."""
    from scipy.stats import multivariate_normal

    rng = np.random.default_rng(0)
    m = rng.normal(size=(2, 3))
    A = rng.normal(size=(2, 3, 3))
    S = A @ np.swapaxes(A, 1, 2) + 0.1 * np.eye(3)
    X = rng.normal(size=(5, 3))
    got = component_logpdf(X, m, np.linalg.cholesky(S))
    want = np.stack([multivariate_normal(m[k], S[k]).logpdf(X) for k in range(2)], 1)
    np.testing.assert_allclose(got, want, rtol=1e-10)
