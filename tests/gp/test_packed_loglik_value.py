"""``PackedGPs.loglik_value`` (the particle sweeps' log-likelihood without a gradient) must
equal ``PackedGPs.loglik``'s ℓ row by row, over runs of several GPs, with added variances,
and where the predictive variance is floored at β⁻¹ (inputs far from the training points)."""
from types import SimpleNamespace

import numpy as np
import pytest

from bayes_talk.gp.predictive_fused import PackedGPs, Runs


def _gp(n: int, d: int, D: int, rng: np.random.Generator) -> SimpleNamespace:
    X = rng.standard_normal((n, d))
    alpha, gamma, beta = 1.3, 0.7, 50.0
    K = alpha * np.exp(-0.5 * gamma * ((X[:, None] - X[None]) ** 2).sum(-1)) + np.eye(n) / beta
    L = np.linalg.cholesky(K)
    Y = rng.standard_normal((n, D))
    return SimpleNamespace(X=X, A=np.linalg.solve(K, Y), Lc=np.ascontiguousarray(L), alpha=alpha, gamma=gamma,
                           beta=beta, w2=rng.uniform(0.5, 2.0, D), mean=rng.standard_normal(D))


@pytest.mark.parametrize("extra", [None, "motion"])
def test_loglik_value_is_logliks_value(extra):
    rng = np.random.default_rng(3)
    d, D = 3, 4
    pack = PackedGPs([_gp(30, d, D, rng), _gp(57, d, D, rng), _gp(5, d, D, rng)])
    runs = Runs.of(np.array([1] * 7 + [0] * 64 + [2] * 3))
    Xs = rng.standard_normal((74, d))
    Xs[:4] += 40.0                                     # far away: the variance floor β⁻¹
    Y = rng.standard_normal((74, D))
    ex = None if extra is None else rng.uniform(0.01, 0.1, D)
    ll, _, _ = pack.loglik(runs, Y, Xs, ex)
    val = pack.loglik_value(runs, Y, Xs, ex)
    np.testing.assert_allclose(val, ll, rtol=1e-12, atol=1e-10)
    # each row depends on its GP: the rows of GP 0 evaluated under GP 1 differ
    wrong = pack.loglik_value(Runs.of(np.array([1] * 74)), Y, Xs, ex)
    assert np.abs(wrong[7:71] - ll[7:71]).max() > 1e-3
