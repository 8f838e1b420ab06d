"""pg-nuts's stopping rule (:class:`bayes_talk.posterior.sampling.TargetCheck`) asked on the
prefixes of a run's draws stops at the first check the draws pass, and not at all when they never do."""
from __future__ import annotations

import numpy as np

from bayes_talk.posterior.sampling import TargetCheck


def _replay():
    """The rule asked after ``first`` draws per chain and every ``every`` after, as a run asks it."""
    def replay(latents: np.ndarray, aam: np.ndarray, first: int, every: int) -> dict:
        S = latents.shape[1]
        check, kept = TargetCheck(), S
        for n in range(min(first, S), S, every):
            if check.judge(latents[:, :n], aam[:, :n]):
                kept = n
                break
        return {"draws_per_chain_kept": int(kept), "stopped_early": kept < S, "checks": check.history}
    return replay


def test_replay_stops_at_the_first_passing_check_or_runs_to_the_end():
    """Four chains of independent draws (T = 5 frames, d = 2, D_z = 3): at 60 draws per chain the
    bulk ESS (≈ 240) is short of 400, and some later check passes — the replay keeps the draws
    up to the first that did (checks every 60 draws, the failed ones before it); with one chain
    shifted R-hat never passes and all 300 are kept, every check failing."""
    replay = _replay()
    rng = np.random.default_rng(0)
    lat, aam = rng.standard_normal((4, 300, 5, 2)), rng.standard_normal((4, 300, 5, 3))
    r = replay(lat, aam, first=60, every=60)
    checks = r["checks"]
    assert r["stopped_early"] is True and 60 < r["draws_per_chain_kept"] < 300
    assert [c["draws_per_chain"] for c in checks] == list(range(60, r["draws_per_chain_kept"] + 1, 60))
    assert any("bulk ESS" in f for f in checks[0]["failed"]) and checks[0]["ess_bulk_min"] < 400
    assert all(c["failed"] for c in checks[:-1]) and checks[-1]["failed"] == []
    lat[0] += 1.0
    r = replay(lat, aam, first=60, every=60)
    assert (r["draws_per_chain_kept"], r["stopped_early"]) == (300, False)
    assert [c["draws_per_chain"] for c in r["checks"]] == [60, 120, 180, 240]
    assert all(any(f.startswith("R-hat") for f in c["failed"]) for c in r["checks"])
