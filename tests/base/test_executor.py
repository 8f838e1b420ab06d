"""The executor interface (bayes_talk.base.executor): a dask LocalCluster on the loopback
interface with two worker processes gives bit-for-bit the results of the local run --
per-state training, protocol splits, corpus build and featurisation -- and a worker
killed in the middle of training loses nothing (its tasks are recomputed)."""
from __future__ import annotations

import os
import signal
import threading
import time

import numpy as np
import pytest
from toydata import make_utterances

from bayes_talk.base.executor import DaskExecutor, LocalExecutor, make_executor
from bayes_talk.estimators.switching import SwitchingSGPDM

#: the caller's environment before this module's LocalCluster (a dask nanny writes its
#: pre-spawn variables into its own process's os.environ)
ENV_BEFORE = dict(os.environ)

SMALL = {"latent_dim": 3, "max_iter": 20, "min_count": 4, "max_frames_per_state": 80, "fallback_frames": 100}


@pytest.fixture(scope="module")
def dask_ex():
    """One LocalCluster for the module: 2 worker processes, 1 thread each, on 127.0.0.1."""
    with DaskExecutor(n_workers=2, host="127.0.0.1") as ex:
        yield ex


@pytest.fixture(scope="module")
def train():
    return make_utterances(6, seed=0)


@pytest.fixture(scope="module")
def local_model(train):
    with LocalExecutor() as ex:
        return SwitchingSGPDM(states="phone", **SMALL).fit(train, executor=ex)


def assert_same_model(a: SwitchingSGPDM, b: SwitchingSGPDM) -> None:
    """Every array of every state model equal bit for bit."""
    assert a.models_.keys() == b.models_.keys()
    for k in a.models_:
        for da, db in zip(a.models_[k].state(), b.models_[k].state(), strict=True):
            assert da.keys() == db.keys(), k
            for name, va in da.items():
                if isinstance(va, np.ndarray):
                    np.testing.assert_array_equal(va, db[name], err_msg=f"state {k}: {name}")
                else:
                    assert va == db[name], (k, name)


def test_cluster_is_on_loopback_with_two_workers(dask_ex):
    assert dask_ex.scheduler.startswith("tcp://127.0.0.1:")
    workers = dask_ex.client.scheduler_info(n_workers=-1)["workers"]
    assert len(workers) == 2 and all(a.startswith("tcp://127.0.0.1:") for a in workers)
    assert dask_ex.n_workers == 2


def test_dask_per_state_training_equals_local_bit_for_bit(dask_ex, train, local_model):
    model = SwitchingSGPDM(states="phone", **SMALL).fit(train, executor=dask_ex)
    assert len(model.models_) >= 4
    assert_same_model(local_model, model)


def test_killed_worker_in_mid_training_loses_nothing(dask_ex, train, local_model):
    client = dask_ex.client
    pids = client.run(os.getpid)  # worker address -> process id (processes this test started)
    killed: dict = {}

    def kill_a_busy_worker() -> None:
        t_end = time.monotonic() + 120
        while time.monotonic() < t_end and not killed:
            busy = [a for a, keys in client.processing().items() if keys]
            if busy:
                killed["pid"], killed["tasks"] = pids[busy[0]], len(client.processing()[busy[0]])
                os.kill(killed["pid"], signal.SIGKILL)
                killed["at"] = time.monotonic()
                return
            time.sleep(0.02)

    killer = threading.Thread(target=kill_a_busy_worker, daemon=True)
    killer.start()
    model = SwitchingSGPDM(states="phone", **SMALL).fit(train, executor=dask_ex)
    done = time.monotonic()
    killer.join(timeout=5)
    assert killed.get("pid") is not None and killed["tasks"] >= 1, "no worker was killed mid-training"
    assert killed["at"] < done
    with pytest.raises(ProcessLookupError):
        os.kill(killed["pid"], 0)  # that process is gone
    assert_same_model(local_model, model)
    # the nanny restarts the worker: the cluster is whole again for the next test
    client.wait_for_workers(2, timeout=120)


def test_the_cluster_leaves_the_callers_environment_alone(dask_ex, train):
    """Starting the LocalCluster, running tasks and restarting a lost worker must not leave
    the nannies' worker settings (MALLOC_TRIM_THRESHOLD_, PYTHONHASHSEED, ...) in the
    caller's environment: they change every process the caller starts later."""
    import dask

    keys = set(dask.config.get("distributed.nanny.pre-spawn-environ")) | {"PYTHONHASHSEED"}
    dask_ex.map(len, [[1], [1, 2]])
    assert {k: os.environ.get(k) for k in keys} == {k: ENV_BEFORE.get(k) for k in keys}


def test_protocol_splits_on_dask_equal_the_local_run(dask_ex):
    from test_protocols import TINY_GP

    from bayes_talk.evaluation.harness import run_protocol
    from bayes_talk.evaluation.protocols import Protocol

    proto = Protocol("tiny", "test", "repeats", (("AMSE", "mse"),), ("hmm-mean", "context-ridge"),
                     TINY_GP, n_train=5, n_test=2, n_repeats=3)
    utts = make_utterances(9, seed=3)
    local, traj_l = run_protocol(proto, utts, executor=LocalExecutor())
    par, traj_d = run_protocol(proto, utts, executor=dask_ex)
    timing = {"train_seconds", "synth_seconds", "synth_frames_per_second"}
    for name, e in local["methods"].items():
        assert {k: v for k, v in e.items() if k not in timing} == \
            {k: v for k, v in par["methods"][name].items() if k not in timing}
    assert local["splits"] == par["splits"] and len(par["splits"]) == 3
    np.testing.assert_array_equal(traj_l.predictions["hmm-mean"].mean, traj_d.predictions["hmm-mean"].mean)


def test_corpus_build_and_features_on_dask_equal_local(dask_ex, tmp_path):
    from bayes_talk.corpus import build_corpus, load_corpus

    a = build_corpus(tmp_path / "local", n_utterances=2, seed=4, image_size=64, executor="local")
    b = build_corpus(tmp_path / "dask", n_utterances=2, seed=4, image_size=64, executor=dask_ex)
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    for f in files:
        assert (a / f).read_bytes() == (b / f).read_bytes(), f
    ca = load_corpus(a, cache=False, executor="local")
    cb = load_corpus(a, cache=False, executor=dask_ex)
    for sa, sb in zip(ca.sequences, cb.sequences, strict=True):
        np.testing.assert_array_equal(sa.mfcc, sb.mfcc)
        np.testing.assert_array_equal(sa.aam, sb.aam)


def test_a_failing_task_raises_its_own_error(dask_ex):
    with pytest.raises(ValueError, match="math domain"):
        dask_ex.map(_sqrt, [4.0, -1.0, 9.0])
    assert LocalExecutor().map(_sqrt, [4.0, 9.0]) == [2.0, 3.0]


def _sqrt(x: float) -> float:
    import math

    return math.sqrt(x)


def test_make_executor_refuses_bad_choices():
    with pytest.raises(ValueError, match="local, processes, dask"):
        make_executor("threads")
    with pytest.raises(ValueError, match="needs --executor dask"):
        make_executor("processes", 2, scheduler="tcp://127.0.0.1:8786")
    with pytest.raises(ValueError, match="workers"):
        make_executor("processes", 0)
    assert isinstance(make_executor("processes", 1), LocalExecutor)


def test_cli_rejects_an_unknown_executor(capsys):
    from bayes_talk.app import cli

    with pytest.raises(SystemExit):
        cli.main(["train", "corpus", "--out", "m", "--executor", "threads"])
    assert "invalid choice: 'threads'" in capsys.readouterr().err


def _square_or_fail(x: int) -> int:
    if x < 0:
        raise ValueError(f"negative input {x}")
    return x * x


@pytest.mark.parametrize("kind", ["local", "processes", "dask"])
def test_submit_runs_beside_a_map_and_gives_its_value(kind, dask_ex):
    """``submit`` starts one task and returns at once; a map run meanwhile is unchanged, the
    pending value is the task's (asked twice: the same), and its failure is raised by ``result``."""
    ex = dask_ex if kind == "dask" else make_executor(kind, 2)
    try:
        pending = ex.submit(_square_or_fail, 7)
        failing = ex.submit(_square_or_fail, -3)
        assert ex.map(_square_or_fail, [1, 2, 3]) == [1, 4, 9]
        assert pending.result() == 49 and pending.result() == 49
        with pytest.raises(ValueError, match="negative input -3"):
            failing.result()
    finally:
        if ex is not dask_ex:
            ex.close()
