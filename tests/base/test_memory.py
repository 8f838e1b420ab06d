"""Memory of the GP work (issue 14, item 4): large freed blocks leave the process; the memory-
saving ways of computing the SGPDM's initial kernel width, a predictor's kernel matrix and
the synthesis objective's Cholesky factor give the same numbers bit for bit."""
from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch

from bayes_talk.gp.kernels import train_cov
from bayes_talk.gp.numpy_gp import numpy_gp
from bayes_talk.gp.predictive import GPPredictor
from bayes_talk.models.sgpdm_program import median_sq_dist

# Free four 24 MB arrays that sit below a fifth one still alive (the pattern of N×N
# temporaries around a kept Cholesky factor); print how much of the 96 MB stays resident.
_FRAGMENT = textwrap.dedent("""
    import sys
    import numpy as np
    from bayes_talk.base.memory import release_large_blocks

    def rss_mb():
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * 4096 / 2**20

    on = release_large_blocks()
    n = 3 * 2**20  # float64s: 24 MB
    first = np.ones(n)
    del first  # with glibc's dynamic threshold, from here on 24 MB blocks come from the heap
    base = rss_mb()
    blocks = [np.ones(n) for _ in range(5)]
    del blocks[:4]
    print(on, rss_mb() - base)
""")


def _run(env_extra: dict) -> tuple[bool, float]:
    env = {**os.environ, **env_extra}
    # glibc's own malloc settings turn its dynamic threshold off (dask's nanny puts
    # MALLOC_TRIM_THRESHOLD_ into os.environ of the process that starts a LocalCluster,
    # as earlier tests do): the fragment must see glibc's defaults
    for k in ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_TOP_PAD_", "MALLOC_MMAP_MAX_",
              "GLIBC_TUNABLES"):
        env.pop(k, None)
    out = subprocess.run([sys.executable, "-c", _FRAGMENT], capture_output=True, text=True, env=env, check=True)
    on, kept = out.stdout.split()
    return on == "True", float(kept)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc and /proc")
def test_freed_large_blocks_leave_the_process():
    on, kept = _run({})
    assert on
    assert kept < 40.0  # the live 24 MB block (and small change), not the freed 72-96 MB
    off, kept_off = _run({"BAYES_TALK_MALLOC": "0"})  # glibc's default: the check can fail
    assert not off
    assert kept_off > 70.0


@pytest.mark.parametrize("n, d, block", [(2, 3, 1 << 20), (7, 2, 5), (300, 8, 1 << 20), (301, 8, 1000),
                                         (1001, 6, 1 << 20)])
def test_median_sq_dist_equals_the_full_array(n, d, block):
    X = np.random.default_rng(n).normal(size=(n, d))
    sq = ((X[:, None, :] - X[None, :, :]) ** 2).sum(-1)
    assert median_sq_dist(X, block_elems=block) == float(np.median(sq[np.triu_indices(n, 1)]))


@pytest.mark.parametrize("n, hyper", [(5, (1.3, 0.7, 100.0, None)), (300, (0.01, 0.2, 1e6, None)),
                                      (301, (1.0, 0.5, 10.0, 0.3)), (64, "tensors")])
def test_train_cov_fixed_is_train_cov_bit_for_bit(n, hyper):
    X = torch.randn(n, 8, dtype=torch.float64, generator=torch.Generator().manual_seed(n), requires_grad=True)
    if hyper == "tensors":
        hyper = tuple(torch.tensor(v, dtype=torch.float64) for v in (2.0, 0.3, 50.0)) + (None,)
    K = train_cov(X, *hyper, fixed=True)
    assert not K.requires_grad
    assert torch.equal(K, train_cov(X, *hyper).detach())


def test_numpy_gp_keeps_one_factor_and_makes_the_column_major_one_on_demand():
    X = torch.randn(40, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    p = GPPredictor(X, torch.sin(X[:, :2]), 1.0, 0.8, 100.0)
    gp = numpy_gp(p)
    assert gp.Lc.flags.c_contiguous and np.array_equal(gp.Lc, p.L.numpy())
    assert gp._L is None  # nothing column-major until the NumPy path asks for it
    assert gp.L.flags.f_contiguous and np.array_equal(gp.L, p.L.numpy())
    assert not np.shares_memory(gp.Lc, p.L.numpy())  # copies: torch may move its storage
