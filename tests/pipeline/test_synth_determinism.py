"""Same input, same output: one utterance synthesised by a saved model in a fresh process
and in a process that has already synthesised other utterances, trained a model, drawn
from the global random generators and lowered its thread count gives the same bits.

What this guards: a model's GP factors (Cholesky factor L, K⁻¹Y) were computed with the
thread count of the process that built the model, at training or at loading; MKL's
factorisation on one thread and on two differ in the last bits, and a whole-utterance
MAP (a multimodal density) amplifies them: the same model synthesised the same utterance
0.2 AAM units apart when loaded with one torch thread and with two. The factors are now
computed on one thread whatever the caller's count (bayes_talk.gp.threads.one_thread).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

TESTS = Path(__file__).resolve().parents[1]

#: the fresh process: two torch threads (a fresh process on a two-core machine), the model
#: loaded and the utterance synthesised as ``synth`` does (its default posterior)
SCRIPT = r"""
import json, sys
import numpy as np
import torch
sys.path[:0] = [sys.argv[3], sys.argv[4]]
from test_synth_determinism import synthesise, target
from bayes_talk.estimators.registry import load_estimator

torch.set_num_threads(2)
model = load_estimator(sys.argv[1])
np.savez(sys.argv[2], **synthesise(model, target()))
print(json.dumps({"threads": torch.get_num_threads()}))
"""


def target():
    """The utterance every run synthesises (its audio features and labels)."""
    from toydata import make_utterances

    return make_utterances(1, seed=11)[0]


def synthesise(model, utt) -> dict[str, np.ndarray]:
    """``model.predict_dist`` as ``synth`` calls it (the default posterior, seed 0): the
    mean, the variance and the 50 % / 90 % bands."""
    from bayes_talk.posterior.methods import DEFAULT_METHOD

    res = model.predict_dist(utt, posterior=DEFAULT_METHOD, n_draws=None, seed=0)
    out = {"mean": np.asarray(res.mean), "var": np.asarray(res.var)}
    for q in (0.5, 0.9):
        out[f"lower{round(100 * q)}"], out[f"upper{round(100 * q)}"] = res.interval(q)
    return out


def _differences(a: dict, b: dict) -> dict[str, float]:
    return {k: float(np.abs(np.asarray(a[k]) - np.asarray(b[k])).max()) for k in a
            if not np.array_equal(a[k], b[k])}


def test_an_utterance_synthesised_fresh_and_after_other_work_has_the_same_bits(tmp_path, toy_vlmm):
    import torch
    from toydata import make_utterances

    from bayes_talk.estimators.registry import load_estimator
    from bayes_talk.estimators.switching import SwitchingSGPDM
    from bayes_talk.gp.threads import torch_threads

    toy_vlmm.save(tmp_path / "model")
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "MKL_NUM_THREADS")}
    done = subprocess.run([sys.executable, "-c", SCRIPT, str(tmp_path / "model"), str(tmp_path / "fresh.npz"),
                           str(TESTS), str(Path(__file__).parent)],
                          env=env, capture_output=True, text=True, timeout=600, check=False)
    assert done.returncode == 0, done.stderr[-3000:]
    assert json.loads(done.stdout.strip().splitlines()[-1])["threads"] == 2
    fresh = dict(np.load(tmp_path / "fresh.npz"))

    # this process: the model loaded with one thread (as an evaluation or a worker runs),
    # other utterances synthesised, a model trained, the global generators moved on
    with torch_threads(1):
        loaded = load_estimator(tmp_path / "model")
        for other in make_utterances(2, seed=12):
            synthesise(loaded, other)
    SwitchingSGPDM(states="phone", latent_dim=2, max_iter=10, min_count=4, max_frames_per_state=60,
                   fallback_frames=80).fit(make_utterances(6, seed=13))
    np.random.seed(5)
    np.random.random(17)
    torch.manual_seed(7)
    torch.rand(23)
    prev = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        after = synthesise(loaded, target())
        trained_here = synthesise(toy_vlmm, target())   # the fitted object itself, never saved and loaded
    finally:
        torch.set_num_threads(prev)

    assert fresh.keys() == after.keys()
    assert not _differences(fresh, after), f"fresh process vs after other work: {_differences(fresh, after)}"
    assert not _differences(fresh, trained_here), \
        f"fresh process vs the model as trained here: {_differences(fresh, trained_here)}"
