"""Metrics against hand-computed values on tiny arrays (bayes_talk.evaluation.metrics)."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.integrate
import scipy.stats

from bayes_talk.evaluation import metrics as M

# one utterance, T = 3, D = 2; e = pred - truth = [[1, -0.5], [0, -2], [-2, 0]]
T1 = np.array([[0.0, 1.0], [1.0, 3.0], [2.0, 2.0]])
P1 = np.array([[1.0, 0.5], [1.0, 1.0], [0.0, 2.0]])


def test_errors_by_hand():
    assert M.mse([T1], [P1])[0] == pytest.approx(9.25 / 6, abs=1e-15)
    assert M.rms([T1], [P1])[0] == pytest.approx(np.sqrt(9.25 / 6), abs=1e-15)
    assert M.l1([T1], [P1])[0] == pytest.approx((1.5 + 2 + 2) / 3, abs=1e-15)
    assert M.linf([T1], [P1])[0] == pytest.approx((1 + 2 + 2) / 3, abs=1e-15)
    # per-dim MSE (5/3, 4.25/3), truth variance (2/3, 2/3)
    assert M.normalised_mse([T1], [P1])[0] == pytest.approx((2.5 + 2.125) / 2, abs=1e-14)
    # explicit normaliser
    assert M.normalised_mse([T1], [P1], variance=np.array([1.0, 2.0]))[0] == pytest.approx(
        (5 / 3 + 4.25 / 6) / 2, abs=1e-14)


def test_single_array_is_one_utterance_and_amse_averages_utterances():
    T2, P2 = T1 + 1.0, T1 + 3.0  # MSE 4
    assert M.mse(T1, P1).shape == (1,)
    assert M.amse([T1, T2], [P1, P2]) == pytest.approx((9.25 / 6 + 4.0) / 2, abs=1e-14)
    stacked = M.mse(np.stack([T1, T2]), np.stack([P1, P2]))
    np.testing.assert_allclose(stacked, [9.25 / 6, 4.0], rtol=0, atol=1e-14)


def test_correlation_by_hand_constant_truth_skipped_constant_prediction_zero():
    r0 = -np.sqrt(3) / 2   # dim 0: truth (0,1,2), pred (1,1,0)
    r1 = 3 / np.sqrt(84)   # dim 1: truth (1,3,2), pred (0.5,1,2)
    assert M.correlation([T1], [P1])[0] == pytest.approx((r0 + r1) / 2, abs=1e-14)
    # a third, constant truth dimension is skipped, not counted as 0
    T3 = np.hstack([T1, np.full((3, 1), 7.0)])
    P3 = np.hstack([P1, np.array([[1.0], [2.0], [0.0]])])
    assert M.correlation([T3], [P3])[0] == pytest.approx((r0 + r1) / 2, abs=1e-14)
    # a constant *prediction* where the truth varies counts as 0, not skipped
    P4 = P1.copy()
    P4[:, 1] = 0.25
    assert M.correlation([T1], [P4])[0] == pytest.approx(r0 / 2, abs=1e-14)
    # perfect correlation under an affine map
    assert M.acc([T1], [3 * T1 - 1]) == pytest.approx(1.0, abs=1e-14)


def test_acc_skips_utterances_without_usable_dimension():
    const = np.ones((4, 2))
    with pytest.warns(RuntimeWarning, match="skipped"):
        a = M.acc([T1, const], [P1, np.arange(8.0).reshape(4, 2)])
    assert a == pytest.approx(M.correlation([T1], [P1])[0], abs=1e-14)
    assert np.isnan(M.correlation([const], [const])[0])


def test_summarise_t_interval():
    s = M.summarise([1.0, 2.0, 3.0, 4.0])
    std = np.sqrt(5 / 3)
    t975_3 = 3.182446305284263  # Student t, 3 dof, 97.5 % (tables)
    assert s["n"] == 4 and s["mean"] == pytest.approx(2.5)
    assert s["std"] == pytest.approx(std, abs=1e-14)
    assert s["ci95"][0] == pytest.approx(2.5 - t975_3 * std / 2, abs=1e-12)
    assert s["ci95"][1] == pytest.approx(2.5 + t975_3 * std / 2, abs=1e-12)
    with pytest.warns(RuntimeWarning):
        s2 = M.summarise([1.0, np.nan, 3.0])
    assert s2["n"] == 2 and s2["mean"] == pytest.approx(2.0)
    one = M.summarise([5.0])
    assert one["n"] == 1 and np.isnan(one["std"])


def test_coverage_by_hand():
    truth = [np.array([[0.0, 1.0], [2.0, 3.0]])]
    lower = [np.array([[-1.0, 2.0], [2.0, 0.0]])]
    upper = [np.array([[1.0, 3.0], [3.0, 2.0]])]
    assert M.coverage(truth, lower, upper) == 0.5  # 0 in, 1 out, 2 in (closed), 3 out


def test_crps_gaussian_closed_form_and_integral():
    # at z = mu: sigma (sqrt(2) - 1) / sqrt(pi)
    assert M.crps_gaussian([np.zeros((1, 1))], [np.zeros((1, 1))], [np.full((1, 1), 2.0)]) == \
        pytest.approx(2.0 * (np.sqrt(2) - 1) / np.sqrt(np.pi), abs=1e-14)
    # against the definition CRPS = ∫ (F(x) - 1{x >= z})² dx
    z, mu, sd = 0.7, -0.3, 1.5
    F = scipy.stats.norm(mu, sd).cdf
    ref = scipy.integrate.quad(lambda x: F(x) ** 2, -np.inf, z)[0] + \
        scipy.integrate.quad(lambda x: (1 - F(x)) ** 2, z, np.inf)[0]
    got = M.crps_gaussian([np.full((1, 1), z)], [np.full((1, 1), mu)], [np.full((1, 1), sd)])
    assert got == pytest.approx(ref, abs=1e-8)


def test_crps_ensemble_by_hand_and_against_gaussian():
    # samples {0, 1}, truth 0.5: E|X - z| = 0.5, ½E|X - X'| = ½ · ½ = 0.25
    samples = [np.array([0.0, 1.0]).reshape(2, 1, 1)]
    assert M.crps_ensemble([np.full((1, 1), 0.5)], samples) == pytest.approx(0.25, abs=1e-15)
    # naive double sum on random samples
    rng = np.random.default_rng(0)
    x = rng.normal(size=(7, 2, 3))
    z = rng.normal(size=(2, 3))
    naive = np.mean(np.abs(x - z).mean(0) - 0.5 * np.abs(x[:, None] - x[None]).mean((0, 1)))
    assert M.crps_ensemble([z], [x]) == pytest.approx(naive, abs=1e-14)


def test_nlpd_by_hand():
    got = M.nlpd_gaussian([np.array([[1.0, 0.0]])], [np.zeros((1, 2))], [np.array([[1.0, 4.0]])])
    want = ((0.5 * np.log(2 * np.pi) + 0.5) + 0.5 * np.log(2 * np.pi * 4.0)) / 2
    assert got == pytest.approx(want, abs=1e-14)


def test_bad_inputs_raise():
    with pytest.raises(ValueError, match="shape"):
        M.mse([T1], [P1[:2]])
    with pytest.raises(ValueError, match="NaN"):
        M.mse([T1], [np.where(P1 > 1.5, np.nan, P1)])
    with pytest.raises(ValueError, match="utterances"):
        M.mse([T1, T1], [P1])
    with pytest.raises(ValueError, match="no utterances"):
        M.amse([], [])
    with pytest.raises(ValueError, match="2-D"):
        M.rms([T1.ravel()], [P1.ravel()])
    with pytest.raises(ValueError, match="lower bound above"):
        M.coverage([T1], [P1 + 1], [P1])
    with pytest.raises(ValueError, match="std"):
        M.crps_gaussian([T1], [P1], [np.zeros_like(T1)])
    with pytest.raises(ValueError, match="var"):
        M.nlpd_gaussian([T1], [P1], [-np.ones_like(T1)])
    with pytest.raises(ValueError, match="samples"):
        M.crps_ensemble([T1], [np.zeros((5, 2, 2))])
    with pytest.raises(ValueError, match="variance"):
        M.normalised_mse([T1], [P1], variance=np.ones(3))
    with pytest.raises(ValueError, match="no values"):
        M.summarise([])
