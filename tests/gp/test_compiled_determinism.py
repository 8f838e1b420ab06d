"""The compiled GP loops give the same bits whether numba compiled them in the running
process or loaded them from its on-disk cache (``cache=True``).

Why it matters: the executor's workers are fresh interpreters that load what the first
process compiled and cached, while that first process runs the code it compiled itself; a
synthesis, a NUTS chain or a per-state fit then depends on which process ran it (seen in
CI on a clean clone: chains run in this process and in worker processes differed from the
8th digit, Algorithm 2's means by 1e-13). The cause was ``fastmath={"reassoc", "contract"}``:
with both flags the machine code of the segment objective differed between the fresh and
the cached compilation; with reassociation alone (the reductions still vectorise) or with
none it does not (measured, session 16). The test compiles every compiled entry point into
an empty cache directory in one interpreter, then loads them from it in a second, on the
same inputs, and compares the output bits per function.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys

SCRIPT = r"""
import hashlib, json
import numpy as np
from bayes_talk.gp.fused import rbf_matrix_normal_grad
from bayes_talk.gp.predictive_fused import PackedGPs, Runs
from bayes_talk.posterior.proposal_tables import kernel_mixture_logpdf, smoothness_weights
from bayes_talk.synthesis.segment_objective import _segment_compiled

rng = np.random.default_rng(0)


class GP:   # the arrays of a fitted predictor (bayes_talk.gp.numpy_gp.NumpyGP)
    def __init__(self, N, d, D):
        self.X = rng.normal(size=(N, d))
        self.A = rng.normal(size=(N, D))
        K = np.exp(-0.5 * ((self.X[:, None] - self.X[None]) ** 2).sum(-1)) + 1e-2 * np.eye(N)
        self.Lc = np.ascontiguousarray(np.linalg.cholesky(K))
        self.mean = rng.normal(size=D)
        self.alpha, self.gamma, self.beta = 1.3, 0.7, 1e3
        self.w2 = rng.uniform(0.5, 2.0, D)

    def args(self):
        return (self.X, self.A, self.Lc, self.mean, self.alpha, self.gamma, self.beta, self.w2)


def digest(*arrays):
    return hashlib.sha1(b"".join(np.ascontiguousarray(a, dtype=np.float64).tobytes() for a in arrays)).hexdigest()


d, T = 3, 11
obs, dyn, vis = GP(57, d, 13), GP(56, d, d), GP(63, d, 18)
X, Y = rng.normal(size=(T, d)), rng.normal(size=(T, 13))
z, e = rng.normal(size=(1, 18)), np.full(18, 0.1)
out = {}
g = np.empty((T, d))
lp = _segment_compiled(X, Y, obs.args(), dyn.args(), True, rng.normal(size=d), 2.0 * np.eye(d), 0.3, True,
                       vis.args(), z, e, True, g)
out["segment_objective"] = digest(np.array([lp]), g)

pack = PackedGPs([GP(40, d, 13), obs, GP(71, d, 13)])
runs = Runs.of(np.repeat([0, 1, 2], [5, 9, 7]))
Xs, Ys = rng.normal(size=(21, d)), rng.normal(size=(21, 13))
out["packed_loglik"] = digest(*pack.loglik(runs, Ys, Xs))
out["packed_mean_var"] = digest(*pack.mean_var(runs, Xs))
out["packed_mean_vjp"] = digest(pack.mean_vjp(runs, Xs, rng.normal(size=(21, 13))))
out["packed_mean_var_vjp"] = digest(pack.mean_var_vjp(runs, Xs, rng.normal(size=(21, 13)), rng.normal(size=21)))
ll, gX, ga, gg, gb, gV = rbf_matrix_normal_grad(rng.normal(size=(90, d)), 1.1, 0.8, 50.0, rng.normal(size=(90, 5)))
out["rbf_matrix_normal_grad"] = digest(np.array([ll, ga, gg, gb]), gX, gV)
var = rng.uniform(0.5, 2.0, size=(37, 18))
lw = smoothness_weights(rng.normal(size=37), rng.normal(size=(29, 18)), rng.normal(size=(37, 18)), 1.0 / var,
                        0.5 * np.log(var).sum(1))
out["proposal_smoothness_weights"] = digest(lw)
out["proposal_kernel_mixture_logpdf"] = digest(kernel_mixture_logpdf(rng.normal(size=(29, d)), rng.normal(size=(37, d)),
                                                                     lw, np.array([0.05, 0.2, 0.5])))
print(json.dumps(out))
"""


def _run(cache_dir) -> dict:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache_dir), "BAYES_TALK_FUSED": "1"}
    done = subprocess.run([sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, timeout=600, check=False)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_fresh_and_cached_compilations_give_the_same_bits(tmp_path):
    fresh = _run(tmp_path)                                   # compiles, writes the cache
    assert any(tmp_path.rglob("*.nbi")), "numba wrote no cache: the second run would compile again"
    cached = _run(tmp_path)                                  # loads every function from it
    assert fresh.keys() == cached.keys()
    differ = sorted(k for k in fresh if fresh[k] != cached[k])
    assert not differ, f"compiled in-process and loaded from numba's cache differ: {differ}"
