"""benchmarks/sbc.py --pool: runs of benchmarks/sbc.py that differ only in the seed are pooled into
one SBC of their summed simulations, and runs that ran something else are refused."""
from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import numpy as np
import pytest

from bayes_talk.evaluation.sbc import uniformity_test

ROOT = Path(__file__).resolve().parents[2]
L = 19   # ranked draws: ranks take the values 0..L
K = 6    # latent coordinates


def _sbc_pool():
    """The benchmark module (benchmarks/ is a package, imported from the repository root)."""
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    from benchmarks import sbc
    return sbc


def _run(seed: int, n: int, *, options: dict | None = None, rank_draws: int = L, rhat: float = 1.01,
         divergences: int = 0, le_ess: bool = True, with_control: bool = True) -> dict:
    """A run as benchmarks/sbc.py writes it: a calibrated sampler's ranks (each coordinate's
    histogram flat when n is a multiple of L + 1, in random order) and a control whose ranks
    pile up at both ends (too narrow)."""
    rng = np.random.default_rng(seed)
    flat = np.stack([rng.permutation(np.arange(n) % (L + 1)) for _ in range(K)], axis=1)
    samplers = {"pg-nuts": {"n_draws": L, "n_sims": n, "ranks": flat.tolist(),
                            "worst_rhat_max": rhat, "worst_ess_bulk_min": 40.0 + seed, "divergences": divergences,
                            "ranked_draws_le_ess": le_ess,
                            "sampler_options": options or {"chains": 4, "pg_particles": 64}}}
    if with_control:
        ends = rng.choice([0, L], size=(n, K))
        middle = rng.integers(0, L + 1, size=(n, K))
        samplers["laplace-0.85sd"] = {"n_draws": L, "n_sims": n,
                                      "ranks": np.where(rng.random((n, K)) < 0.5, ends, middle).tolist(),
                                      "sampler_options": {"khat_draws": 200}}
    return {"source": {"model": "data/model_default", "corpus": "data/dev40", "utterance": "utt0000"},
            "settings": {"utterance": "utt0000", "start": 10, "frames": 20, "sims": n, "seed": seed,
                         "rank_draws": rank_draws, "nuts_chains": 2, "smoothness": "frame", "workers": 2,
                         "methods": "laplace-0.85sd,pg-nuts"},
            "samplers": samplers}


def test_pooled_runs_are_one_sbc_of_the_summed_simulations():
    pool = _sbc_pool()
    runs = [("a.json", _run(11, 40, rhat=1.02)), ("b.json", _run(12, 40, divergences=2)),
            ("c.json", _run(13, 20, le_ess=False))]
    out = pool.pool(runs)["samplers"]
    pg = out["pg-nuts"]
    ranks = np.concatenate([np.asarray(r["samplers"]["pg-nuts"]["ranks"]) for _, r in runs])
    p, p_adj, _ = uniformity_test(ranks, L)
    assert pg["n_sims"] == 100 and pg["sims_per_run"] == [40, 40, 20]
    assert pg["min_p"] == pytest.approx(float(np.min(p))) and pg["n_rejected"] == int(np.sum(p_adj < 0.05))
    # the worst convergence over the runs, divergences summed, ranked ≤ ESS only if in every run
    assert pg["worst_rhat_max"] == 1.02 and pg["worst_ess_bulk_min"] == 51.0
    assert pg["divergences"] == 2 and pg["ranked_draws_le_ess"] is False
    assert pg["verdict"]["passed"]                       # uniform ranks
    assert not out["laplace-0.85sd"]["verdict"]["passed"]   # the too-narrow control


def test_a_sampler_missing_from_a_run_is_not_pooled():
    out = _sbc_pool().pool([("a.json", _run(11, 30)), ("b.json", _run(12, 30, with_control=False))])
    assert set(out["samplers"]) == {"pg-nuts"} and out["not_pooled"] == ["laplace-0.85sd"]


@pytest.mark.parametrize("second, message", [
    (_run(11, 40), "share --seed 11"),
    (_run(12, 40, rank_draws=9), "settings ['rank_draws'] differ"),
    (_run(12, 40, options={"chains": 4, "pg_particles": 32}), "sampler options differ"),
])
def test_runs_that_ran_something_else_are_refused(second, message):
    with pytest.raises(SystemExit, match=re.escape(message)):
        _sbc_pool().pool([("a.json", _run(11, 40)), ("b.json", second)])


def test_main_writes_the_pooled_json(tmp_path):
    paths = []
    for seed in (11, 12):
        path = tmp_path / f"run{seed}.json"
        path.write_text(json.dumps(_run(seed, 30)))
        paths.append(str(path))
    out = tmp_path / "pooled.json"
    _sbc_pool().main(["--pool", *paths, "--out", str(out)])
    saved = json.loads(out.read_text())
    assert saved["command"].startswith("python ") and set(saved["machine"]) >= {"cpu_count", "python", "packages"}
    assert "sha" in saved["commit"]
    assert saved["seeds"] == [11, 12] and saved["samplers"]["pg-nuts"]["n_sims"] == 60
    assert "sims" not in saved["settings"] and saved["settings"]["rank_draws"] == L
