"""A posterior method is one module and one line of the inference table
(:data:`bayes_talk.posterior.methods.INFERENCE`): a toy method, written here as a module and
registered by one table entry, runs through ``synth --posterior toy`` and through the
evaluation harness, and its draws are what those outputs are made of."""
from __future__ import annotations

import importlib
import json
import sys
import textwrap

import numpy as np
import pytest
from toydata import make_utterances

from bayes_talk.posterior.methods import INFERENCE, InferenceMethod

#: the whole of the toy method: its options and its run (the interface of every method)
TOY_MODULE = '''
from dataclasses import dataclass

from bayes_talk.posterior.methods import Context, Output

#: every run's (plan, latents), for the test to read back
CALLS = []


@dataclass(frozen=True)
class Options:
    spread: float = 0.05

    def __post_init__(self):
        if not self.spread >= 0:
            raise ValueError(f"spread must be >= 0, got {self.spread}")


def run(context: Context, options: Options) -> Output:
    T, d = context.shape
    X = context.x_map + options.spread * context.rng.standard_normal((context.n_draws, T * d))
    latents = X.reshape(1, context.n_draws, T, d)
    CALLS.append((context.plan, latents))
    return Output(latents, {"toy_spread": options.spread})
'''


@pytest.fixture
def toy(tmp_path, monkeypatch):
    """The toy method registered: its module on the path and its line in the table."""
    (tmp_path / "toy_posterior.py").write_text(textwrap.dedent(TOY_MODULE), encoding="utf-8")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "toy_posterior", raising=False)
    monkeypatch.setitem(INFERENCE, "toy", InferenceMethod("toy", "the MAP plus Gaussian noise (a test)",
                                                          "toy_posterior", draws=8, map_restarts=0,
                                                          diagnostics=()))
    return importlib.import_module("toy_posterior")


def _predictive_mean(plan, latents: np.ndarray) -> np.ndarray:
    from bayes_talk.posterior.sampling import visual_predictive

    zm, _ = visual_predictive(plan, latents)
    return zm.mean(axis=(0, 1))


def test_a_registered_method_is_a_choice_of_the_command_line(toy):
    from bayes_talk.app.cli import build_parser

    args = build_parser().parse_args(["synth", "M", "--audio", "x.wav", "--out", "o", "--posterior", "toy"])
    assert args.posterior == "toy"


def test_a_registered_method_runs_through_sample_synthesis_with_its_options(toy, toy_vlmm):
    from bayes_talk.posterior.sampling import sample_synthesis

    u = make_utterances(1, seed=1, mean_len=20)[0]
    r = sample_synthesis(toy_vlmm, u.mfcc[:10], u.labels[:10], method="toy", n_draws=8, seed=2,
                         sampler_kw={"spread": 0.1}, log_warnings=False)
    plan, latents = toy.CALLS[-1]
    assert r.method == "toy" and np.array_equal(r.latent_draws, latents)
    assert r.diagnostics["toy_spread"] == 0.1 and "map_converged" in r.diagnostics   # its own and the common ones
    np.testing.assert_allclose(r.mean, _predictive_mean(plan, latents), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(latents.mean(axis=(0, 1)), r.map_latents, atol=0.25)   # the MAP plus noise
    with pytest.raises(ValueError, match="spread must be >= 0"):
        sample_synthesis(toy_vlmm, u.mfcc[:10], u.labels[:10], method="toy", sampler_kw={"spread": -1.0})
    with pytest.raises(ValueError, match=r"\['steps'\] are not options of 'toy'; its options: spread"):
        sample_synthesis(toy_vlmm, u.mfcc[:10], u.labels[:10], method="toy", sampler_kw={"steps": 3})


def test_a_registered_method_runs_through_synth(toy, shared_built_corpus, tmp_path):
    from bayes_talk.app.cli import main
    from bayes_talk.pipeline import train

    model_dir = tmp_path / "model"
    train(shared_built_corpus, "ssgpdm-vlmm", model_dir, workers=1, latent_dim=3, max_iter=20, min_count=3,
          max_frames_per_state=80, fallback_frames=100)
    wav = min((shared_built_corpus / "utterances").rglob("*.wav"))
    out = tmp_path / "synth"
    assert main(["synth", str(model_dir), "--audio", str(wav), "--labels", str(wav.with_suffix(".lab")),
                 "--no-video", "--posterior", "toy", "--draws", "8", "--lowpass-hz", "0", "--out", str(out)]) == 0
    plan, latents = toy.CALLS[-1]
    diag = json.loads((out / "diagnostics.json").read_text())
    assert diag["method"] == "toy" and diag["n_draws"] == 8 and diag["diagnostics"]["toy_spread"] == 0.05
    np.testing.assert_allclose(np.load(out / "trajectory.npy"), _predictive_mean(plan, latents),
                               rtol=1e-10, atol=1e-12)


def test_a_registered_method_runs_through_the_evaluation_harness(toy, monkeypatch):
    import dataclasses

    from test_protocols import TINY_GP, tiny

    from bayes_talk.estimators import registry
    from bayes_talk.evaluation import harness as H

    # an evaluated method using the toy posterior: one more method of the switching family
    method = registry.Method("ssgpdm-vlmm-toy", "ssgpdm-vlmm", "SSGPDM-VLMM, toy posterior", True,
                             {"posterior": "toy"}, {"n_draws": "posterior_draws", "seed": "seed"})
    monkeypatch.setattr(registry, "NAMED_METHODS", (*registry.NAMED_METHODS, method))
    system = dataclasses.replace(TINY_GP, band_calibration=None, posterior_draws=8)
    res, traj = H.run_protocol(tiny("holdout", n_train=5, n_test=2, system=system), make_utterances(7, seed=3),
                               [method.name])
    entry = res["methods"][method.name]
    assert entry["per_split"][0]["n_test"] == 2 and len(toy.CALLS) == 2   # one run per test utterance
    assert np.isfinite(entry["mse"]["mean"]) and "nlpd" in entry            # scored, with its predictive
    pred = traj.predictions[method.name]
    plan, latents = toy.CALLS[0]                                                 # the first test utterance's
    assert pred.result.method == "toy" and np.array_equal(pred.result.latent_draws, latents)
    np.testing.assert_allclose(pred.mean, _predictive_mean(plan, latents), rtol=1e-12, atol=1e-12)
