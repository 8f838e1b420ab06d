"""Block-tridiagonal precisions (bayes_talk.synthesis.banded) against dense linear algebra, and
the trust-region step of the joint MAP against the exact subproblem solution."""
from __future__ import annotations

import numpy as np
import pytest

from bayes_talk.synthesis.banded import BlockTridiagonal, modified_cholesky
from bayes_talk.synthesis.joint_map import _trust_region_step


def _random(T: int, d: int, seed: int, shift: float = 4.0) -> BlockTridiagonal:
    rng = np.random.default_rng(seed)
    D = rng.standard_normal((T, d, d))
    D = D @ np.transpose(D, (0, 2, 1)) + shift * np.eye(d)
    return BlockTridiagonal(D, 0.7 * rng.standard_normal((T - 1, d, d)))


@pytest.mark.parametrize("T,d", [(1, 3), (2, 1), (7, 2), (30, 3)])
def test_factor_solves_scales_and_selected_inverse_equal_dense(T, d):
    P = _random(T, d, seed=T * 10 + d, shift=6.0)
    A = P.dense()
    assert np.array_equal(A, A.T) and np.array_equal(BlockTridiagonal.from_dense(A, d).dense(), A)
    assert np.linalg.eigvalsh(A)[0] > 0
    rng = np.random.default_rng(1)
    v = rng.standard_normal((T * d, 3))
    np.testing.assert_allclose(P.matvec(v), A @ v, rtol=1e-13, atol=1e-12)
    f = P.cholesky()
    assert f.shift == 0.0
    Ainv = np.linalg.inv(A)
    np.testing.assert_allclose(f.solve(v), Ainv @ v, rtol=1e-9, atol=1e-10)
    L, Linv = f.dense_scale()
    np.testing.assert_allclose(L @ L.T, Ainv, rtol=1e-9, atol=1e-11)
    np.testing.assert_allclose(Linv @ L, np.eye(T * d), atol=1e-10)
    np.testing.assert_allclose(f.scale_rmatvec(v), L.T @ v, rtol=1e-9, atol=1e-11)
    assert f.logdet() == pytest.approx(np.linalg.slogdet(A)[1], rel=1e-12)
    S = f.marginal_covariances()
    for t in range(T):
        np.testing.assert_allclose(S[t], Ainv[t * d:(t + 1) * d, t * d:(t + 1) * d], rtol=1e-9, atol=1e-12)


def test_inertia_counts_the_nonpositive_eigenvalues():
    for seed, shift in [(0, 6.0), (1, -3.0), (2, -8.0), (3, 0.5)]:
        P = _random(12, 3, seed, shift)
        lam = np.linalg.eigvalsh(P.dense())
        assert P.inertia() == int(np.sum(lam <= 0))


def test_modified_cholesky_shifts_an_indefinite_matrix_by_the_least_tenfold_step():
    P = _random(10, 2, seed=5, shift=-3.0)
    assert np.linalg.eigvalsh(P.dense())[0] < 0
    f = modified_cholesky(P)
    assert f.shift > 0
    scale = np.abs(P.diagonal())
    np.testing.assert_allclose(f.matrix.dense(), P.dense() + f.shift * np.diag(scale), rtol=1e-14, atol=1e-14)
    assert np.linalg.eigvalsh(f.matrix.dense())[0] > 0
    assert np.linalg.eigvalsh(P.dense() + 0.1 * f.shift * np.diag(scale))[0] <= 1e-9   # a tenth was not enough
    with pytest.raises(np.linalg.LinAlgError, match="not finite"):
        modified_cholesky(BlockTridiagonal(np.full((2, 1, 1), np.nan), np.zeros((1, 1, 1))))


def _exact_step(A: np.ndarray, g: np.ndarray, radius: float) -> np.ndarray:
    """argmax gᵀs − ½ sᵀAs over ‖s‖ ≤ radius by the eigen-decomposition (the easy case)."""
    lam, U = np.linalg.eigh(A)
    c = U.T @ g
    if lam[0] > 0 and np.linalg.norm(c / lam) <= radius:
        return U @ (c / lam)
    lo, hi = max(0.0, -lam[0]) + 1e-14, max(0.0, -lam[0]) + np.linalg.norm(g) / radius + 1.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if np.linalg.norm(c / (lam + mid)) > radius else (lo, mid)
    return U @ (c / (lam + 0.5 * (lo + hi)))


@pytest.mark.parametrize("shift,radius", [(6.0, 100.0), (6.0, 0.3), (-2.0, 0.5), (-6.0, 2.0)])
def test_trust_region_step_solves_the_subproblem(shift, radius):
    """Interior Newton step, boundary step of a definite and of an indefinite model: the step's
    model value is within the tolerance's reach of the exact subproblem's (‖s‖ within 10 % of
    the radius on the boundary), in the identity metric and in a scaled one."""
    T, d = 8, 2
    P = _random(T, d, seed=11, shift=shift)
    g = np.random.default_rng(2).standard_normal(T * d)
    for Mmat in (BlockTridiagonal(np.tile(np.eye(d), (T, 1, 1)), np.zeros((T - 1, d, d))), _random(T, d, 3, 5.0)):
        M = Mmat.cholesky()
        Lm, Lminv = M.dense_scale()                                  # s = L w: the subproblem in w is the identity-metric one
        A = Lm.T @ P.dense() @ Lm
        gw = Lm.T @ g
        s, boundary = _trust_region_step(P, M, g, radius)
        w = Lminv @ s
        exact = _exact_step(A, gw, radius)

        def model(w, gw=gw, A=A):
            return gw @ w - 0.5 * w @ A @ w

        assert np.linalg.norm(w) <= 1.1 * radius + 1e-12
        interior = np.linalg.norm(exact) < radius * (1 - 1e-9)
        assert boundary == (not interior)
        if interior:
            np.testing.assert_allclose(w, exact, rtol=1e-8, atol=1e-10)
        else:
            assert model(w) >= 0.8 * model(exact) > 0
