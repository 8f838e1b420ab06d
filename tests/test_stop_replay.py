"""benchmarks/analysis/stop_replay.py: pg-nuts's stopping rule replayed on the prefixes of saved
draws stops at the first check the draws pass, and not at all when they never do."""
from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent


def _replay():
    spec = importlib.util.spec_from_file_location("stop_replay", ROOT / "benchmarks" / "analysis" / "stop_replay.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.replay


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
