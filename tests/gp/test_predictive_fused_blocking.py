"""The forward substitution of the compiled GP predictives takes four inputs per load of
L: it must solve L v = k (against LAPACK) and agree with the one-input loop it replaced
(compiled with the same flags) to rounding, for every remainder of T mod 4.

Both loops are compiled with ``fastmath={"reassoc"}``, so the order of the inner sums is
the compiler's choice and depends on the CPU's vector width: the two agree bit for bit on
some machines and to a few units in the last place on others (seen: 1.7e-12 relative on
an AMD EPYC). Rounding, not bits, is what holds on every machine; a wrong index or a
missed remainder row is off by O(1)."""
import numba
import numpy as np
import pytest
from scipy.linalg import solve_triangular

from bayes_talk.gp.predictive_fused import forward_solve_rows


@numba.njit(fastmath={"reassoc"})
def _one_input_at_a_time(L, k):
    T, N = k.shape
    v = np.empty((T, N))
    for i in range(N):
        piv = L[i, i]
        for t in range(T):
            acc = k[t, i]
            for j in range(i):
                acc -= L[i, j] * v[t, j]
            v[t, i] = acc / piv
    return v


def _factor(n: int, rng: np.random.Generator) -> np.ndarray:
    X = rng.standard_normal((n, 4))
    K = np.exp(-0.5 * ((X[:, None] - X[None]) ** 2).sum(-1)) + 1e-2 * np.eye(n)
    return np.ascontiguousarray(np.linalg.cholesky(K))


@pytest.mark.parametrize("n", [1, 3, 40, 257])
def test_the_blocked_forward_substitution_solves_and_keeps_the_bits(n):
    rng = np.random.default_rng(n)
    L = _factor(n, rng)
    for T in (1, 2, 3, 4, 5, 7, 8, 9, 13):
        k = rng.random((T, n))
        v = forward_solve_rows(L, k)
        np.testing.assert_allclose(v, solve_triangular(L, k.T, lower=True).T, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(v, _one_input_at_a_time(L, k), rtol=1e-10, atol=1e-13, err_msg=f"T = {T}")
