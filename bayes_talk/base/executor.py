"""One executor interface for the library's parallel work.

Every parallel job of the library -- the per-state models of the switching SGPDM, the
splits (repeats, folds) of an evaluation protocol, the utterances of a corpus build and
their featurisation -- is a list of independent tasks ``fn(item)`` whose results are
wanted in order. :class:`Executor` runs such a list with one of three engines:

=============  ============================================================================
kind           what runs the tasks
=============  ============================================================================
``local``      this process, one after another
``processes``  ``concurrent.futures.ProcessPoolExecutor`` with ``workers`` fresh ("spawn")
               interpreters on this machine
``dask``       a ``dask.distributed`` cluster: the scheduler at ``scheduler`` (a running
               cluster the user started, docs/scaling.md), else a ``LocalCluster`` of
               ``workers`` processes on the loopback interface
=============  ============================================================================

Results do not depend on the engine: every task carries its own seed (the tasks are
seeded by what they compute -- a state, a split, an utterance index -- never by the worker
that runs them), and every task runs with one BLAS/OpenMP thread and one torch thread
(:func:`single_thread`; thread counts change the floating-point reduction order), in the
local engine too. A worker lost in the middle of a dask run is not fatal: the scheduler
recomputes its tasks on the other workers (tested by killing a worker process).

Functions given to :meth:`Executor.map` must be importable module-level functions (they
are pickled by reference), and ``bayes_talk`` must be importable on every worker.
Scripts that use the ``processes`` or ``dask`` engines need the usual
``if __name__ == "__main__":`` guard (both start fresh interpreters that import the
caller's main module).
"""
from __future__ import annotations

import contextlib
import logging
import os
import pickle
import sys
from collections.abc import Callable, Iterable, Iterator
from typing import Any, Self

__all__ = [
    "EXECUTORS",
    "DaskExecutor",
    "Executor",
    "LocalExecutor",
    "Pending",
    "ProcessExecutor",
    "Terminated",
    "executor_for",
    "interruptible",
    "make_executor",
    "sigterm_as_interrupt",
    "single_thread",
]

log = logging.getLogger(__name__)

EXECUTORS = ("local", "processes", "dask")

#: environment of a worker process: one thread in every BLAS/OpenMP runtime. With two
#: processes on two cores, multi-threaded BLAS only adds contention (measured: a
#: 70x5635 @ 5635x97 product took 0.28 s with 2 OpenBLAS threads under load, 0.002-0.01 s
#: with 1).
BLAS_ENV = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
            "NUMEXPR_NUM_THREADS": "1", "VECLIB_MAXIMUM_THREADS": "1"}


@contextlib.contextmanager
def single_thread() -> Iterator[None]:
    """One BLAS/OpenMP thread (threadpoolctl) and, when torch is loaded, one torch
    intra-op thread inside the block; the previous numbers are restored after it."""
    from threadpoolctl import threadpool_limits

    torch = sys.modules.get("torch")
    prev = torch.get_num_threads() if torch is not None else None
    if torch is not None:
        torch.set_num_threads(1)
    try:
        with threadpool_limits(limits=1):
            yield
    finally:
        if torch is not None:
            torch.set_num_threads(prev)


def run_task(fn: Callable[[Any], Any], item: Any) -> Any:
    """``fn(item)`` with one thread (:func:`single_thread`): what every engine runs.
    Large freed blocks go back to the system at once (:mod:`bayes_talk.base.memory`)."""
    from bayes_talk.base.memory import release_large_blocks

    release_large_blocks()
    with single_thread():
        return fn(item)


def _run_pickled(payload: bytes) -> bytes:
    """:func:`run_task` on ``pickle.loads(payload)``; the result pickled the same way.

    A process pool pickles with multiprocessing's ForkingPickler, for which torch moves
    every tensor it sends into shared memory (``Tensor.share_memory_``): the caller's
    model would change storage under any NumPy view of it and stay tied to the workers.
    The standard pickler copies tensors instead."""
    fn, item = pickle.loads(payload)
    return pickle.dumps(run_task(fn, item), protocol=pickle.HIGHEST_PROTOCOL)


def _init_process_worker(log_setup: dict | None = None) -> None:
    """Start-up of a ``processes`` worker: one BLAS thread; the parent's logging set-up
    (``log_setup``, :func:`bayes_talk.base.logs.snapshot`: its levels, format and third-party
    chatter held back); Ctrl-C is the parent's to handle (it shuts the pool down), so a
    worker never prints a KeyboardInterrupt."""
    import signal

    from bayes_talk.base import logs

    os.environ.update(BLAS_ENV)
    logs.apply(log_setup)
    signal.signal(signal.SIGINT, signal.SIG_IGN)


class Terminated(KeyboardInterrupt):
    """SIGTERM received (``kill``, a job scheduler's stop), raised in the main thread by
    :func:`sigterm_as_interrupt`. A KeyboardInterrupt, so a running process pool is stopped
    as on Ctrl-C (:meth:`ProcessExecutor.map` terminates its workers) instead of being left
    running without a parent, as Python's default SIGTERM handling (exit at once, no
    clean-up) leaves it."""


def _raise_terminated(signum, frame):
    raise Terminated(f"signal {signum}")


@contextlib.contextmanager
def sigterm_as_interrupt():
    """Within the block, SIGTERM raises :class:`Terminated` in the main thread; the previous
    handler is restored on exit. Outside the main thread (where ``signal.signal`` cannot
    be called) it does nothing. ``bayes-talk`` runs every command inside it."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def interruptible(main, *args, **kwargs):
    """``main(*args, **kwargs)`` inside :func:`sigterm_as_interrupt`, its value returned: how a
    script that runs tasks in worker processes (``benchmarks/*.py --workers``) runs its
    ``main``, so that a ``kill`` stops its workers with it instead of leaving them running."""
    with sigterm_as_interrupt():
        return main(*args, **kwargs)


class Executor:
    """Runs independent tasks ``fn(item)`` and returns their results in input order.

    ``kind`` names the engine (:data:`EXECUTORS`), ``n_workers`` how many tasks run at
    once. Use as a context manager (or call :meth:`close`). ``map`` shows a progress bar
    (bayes_talk.base.progress) when ``desc`` is given; the first task that raises stops the
    run and its exception is re-raised here.
    """

    kind = "local"
    #: map() draws its own progress bar (read by bayes_talk.base.progress.ProgressMapper)
    draws_progress = True
    n_workers = 1

    @property
    def parallel(self) -> bool:
        """True when tasks may run at the same time (in other processes)."""
        return self.n_workers > 1

    def map(self, fn: Callable[[Any], Any], items: Iterable[Any], desc: str | None = None,
            unit: str = "task") -> list[Any]:
        """``[fn(x) for x in items]``, computed by this executor's engine."""
        raise NotImplementedError

    def submit(self, fn: Callable[[Any], Any], item: Any) -> Pending:
        """Start ``fn(item)`` now (on an engine with workers) and return at once; its
        :meth:`Pending.result` waits for the value. Work done meanwhile by :meth:`map`
        shares the same workers, so one long task (e.g. the aligner's fit in ``train``)
        runs beside a map's tasks instead of after them. This engine: computed when the
        result is asked for, in this process (the same value)."""
        return _Deferred(fn, item)

    def close(self) -> None:
        """Release the engine's processes (the executor cannot be used afterwards)."""

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"{type(self).__name__}(n_workers={self.n_workers})"


class Pending:
    """A task started by :meth:`Executor.submit`; :meth:`result` waits for its value."""

    def result(self) -> Any:
        """The task's value (its exception re-raised here if it failed)."""
        raise NotImplementedError


class _Deferred(Pending):
    """``fn(item)`` computed by :func:`run_task` when the value is first asked for."""

    def __init__(self, fn: Callable[[Any], Any], item: Any) -> None:
        self._job: tuple | None = (fn, item)
        self._value: Any = None

    def result(self) -> Any:
        if self._job is not None:
            fn, item = self._job
            self._value, self._job = run_task(fn, item), None
        return self._value


class _PoolPending(Pending):
    """A task sent to a process pool pickled (:func:`_run_pickled`); its value is unpickled once."""

    def __init__(self, future: Any) -> None:
        self._future = future
        self._done = False
        self._value: Any = None

    def result(self) -> Any:
        if not self._done:
            self._value, self._done = pickle.loads(self._future.result()), True
        return self._value


class _DaskPending(Pending):
    """A task on a dask cluster (a ``distributed.Future``)."""

    def __init__(self, future: Any) -> None:
        self._future = future

    def result(self) -> Any:
        return self._future.result()


def _bar(iterable: Iterable, total: int, desc: str | None, unit: str) -> Iterator:
    if desc is None:
        return iter(iterable)
    from bayes_talk.base.progress import bar

    return bar(iterable, total, desc, unit)


class LocalExecutor(Executor):
    """The tasks one after another in this process (one thread each)."""

    kind = "local"

    def map(self, fn, items, desc=None, unit="task"):
        """Run the tasks one after another here, in input order."""
        items = list(items)
        return [run_task(fn, x) for x in _bar(items, len(items), desc, unit)]


class ProcessExecutor(Executor):
    """``concurrent.futures.ProcessPoolExecutor`` of ``n_workers`` fresh interpreters
    (the "spawn" start method: no copy of this process's threads or state), which log as
    this process did when the pool was made (:mod:`bayes_talk.base.logs`)."""

    kind = "processes"

    def __init__(self, n_workers: int = 2) -> None:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        from bayes_talk.base import logs

        self.n_workers = _check_workers(n_workers)
        self._pool = ProcessPoolExecutor(self.n_workers, mp_context=multiprocessing.get_context("spawn"),
                                         initializer=_init_process_worker, initargs=(logs.snapshot(),))

    def map(self, fn, items, desc=None, unit="task"):
        """Run the tasks in the worker processes; results in input order."""
        from concurrent.futures import as_completed

        items = list(items)
        futures = [self._pool.submit(_run_pickled, pickle.dumps((fn, x), protocol=pickle.HIGHEST_PROTOCOL))
                   for x in items]
        from concurrent.futures.process import BrokenProcessPool

        try:
            for f in _bar(as_completed(futures), len(futures), desc, unit):
                f.result()  # raises the first failure at once
            return [pickle.loads(f.result()) for f in futures]
        except BrokenProcessPool as exc:
            for f in futures:
                f.cancel()
            raise RuntimeError(
                f"a worker process died ({exc}). Worker processes are fresh interpreters that import "
                "your main module: a script that asks for workers (workers= / n_workers= > 1, "
                "executor=\"processes\") must run its work under `if __name__ == \"__main__\":`; "
                "or leave workers at 1 (this process). It also happens when a worker runs out of "
                "memory.") from exc
        except KeyboardInterrupt:
            self.terminate()   # the workers ignore SIGINT: without this, close() waits for their tasks
            raise
        except BaseException:
            for f in futures:
                f.cancel()
            raise

    def submit(self, fn, item):
        """Send the task to the pool now (a worker takes it before the tasks of a later map)."""
        return _PoolPending(self._pool.submit(_run_pickled, pickle.dumps((fn, item), protocol=pickle.HIGHEST_PROTOCOL)))

    def terminate(self) -> None:
        """Stop now (Ctrl-C): queued tasks are cancelled and the worker processes, which
        ignore SIGINT and would otherwise finish their running tasks first, are terminated.
        Their results are lost; nothing of theirs is written by this module."""
        # ProcessPoolExecutor has no public way to stop running tasks before Python 3.14
        # (terminate_workers); its worker processes are in _processes on 3.11-3.13
        procs = list((getattr(self._pool, "_processes", None) or {}).values())
        self._pool.shutdown(wait=False, cancel_futures=True)
        for p in procs:
            if p.is_alive():
                p.terminate()
        for p in procs:
            p.join(timeout=10)

    def close(self) -> None:
        """Shut the process pool down."""
        self._pool.shutdown(wait=True, cancel_futures=True)


class DaskExecutor(Executor):
    """A ``dask.distributed`` client: on the scheduler at ``scheduler`` (``"tcp://host:8786"``,
    a cluster the user runs), else on a ``LocalCluster`` of ``n_workers`` worker processes
    (one thread each) listening on ``host`` (the loopback interface by default).

    A worker that dies takes no result with it: every task is sent with its inputs, so
    the scheduler can run it again elsewhere (``distributed.scheduler.allowed-failures``
    tries before a task is declared lost). ``client``: an existing ``Client`` to use
    (not closed by :meth:`close`).
    """

    kind = "dask"

    def __init__(self, scheduler: str | None = None, n_workers: int = 2, *, host: str = "127.0.0.1",
                 client: Any = None, **cluster_kwargs: Any) -> None:
        try:
            from dask.distributed import Client, LocalCluster
        except ImportError as exc:  # pragma: no cover - dask is a dependency
            raise RuntimeError("the dask executor needs dask.distributed "
                               "(pip install 'dask[distributed]')") from exc
        self._own_client = client is None
        self._cluster = None
        self._environ = _nanny_environ()  # the caller's, before any nanny of ours runs
        if client is not None:
            self.client = client
        elif scheduler:
            try:
                self.client = Client(scheduler, timeout="20s")
            except OSError as exc:
                raise RuntimeError(f"cannot reach the dask scheduler at {scheduler} ({exc}); start it "
                                   "with `dask scheduler` and its workers with `dask worker "
                                   f"{scheduler}` (docs/scaling.md)") from exc
        else:
            kw = {"n_workers": _check_workers(n_workers), "threads_per_worker": 1, "processes": True,
                      "host": host, "dashboard_address": None}
            kw.update(cluster_kwargs)
            self._cluster = LocalCluster(**kw)
            self.client = Client(self._cluster)
        _restore_nanny_environ(self._environ)
        self.scheduler = self.client.scheduler.address
        if scheduler and self._own_client:
            self._check_worker_threads()

    def _check_worker_threads(self) -> None:
        """Refuse workers with several threads: Pyro keeps one handler stack per process,
        so two model fits must never share a worker process."""
        workers = self.client.scheduler_info(n_workers=-1).get("workers", {})
        bad = sorted(a for a, w in workers.items() if int(w.get("nthreads", 1)) != 1)
        if bad:
            self.close()
            raise RuntimeError(f"dask workers {', '.join(bad[:3])} run several threads; start them with "
                               "`dask worker ADDRESS --nthreads 1` (docs/scaling.md)")

    @property
    def n_workers(self) -> int:  # type: ignore[override]
        """Workers of the cluster (those connected now)."""
        return max(1, sum(int(w.get("nthreads", 1)) for w in
                          self.client.scheduler_info(n_workers=-1).get("workers", {}).values()))

    @property
    def parallel(self) -> bool:
        """True: the tasks run in other processes."""
        return True

    def map(self, fn, items, desc=None, unit="task"):
        """Submit every task to the cluster (seeded per task, retried on a lost worker); results in input order."""
        from dask.distributed import as_completed

        items = list(items)
        if not items:
            return []
        # pure=False: a fresh key per call (the same item twice is computed twice, as locally)
        futures = self.client.map(run_task, [fn] * len(items), items, pure=False)
        try:
            for f in _bar(as_completed(futures), len(futures), desc, unit):
                if f.status == "error":
                    f.result()  # raises the task's exception
            return self.client.gather(futures)
        finally:
            self.client.cancel(futures)
            _restore_nanny_environ(self._environ)  # a restarted worker's nanny set them again

    def submit(self, fn, item):
        """Send the task to the cluster now (retried on a lost worker, as in :meth:`map`)."""
        return _DaskPending(self.client.submit(run_task, fn, item, pure=False))

    def close(self) -> None:
        """Close the client (and the LocalCluster this executor started, if any)."""
        if self._own_client:
            self.client.close()
        if self._cluster is not None:
            self._cluster.close()
            self._cluster = None
        _restore_nanny_environ(self._environ)

    def __repr__(self) -> str:
        return f"DaskExecutor(scheduler={self.scheduler!r})"


def _nanny_keys() -> list[str]:
    """The variables a dask nanny writes into its *own* process's ``os.environ`` before it
    spawns a worker (``distributed.nanny.pre-spawn-environ``, e.g. MALLOC_TRIM_THRESHOLD_,
    and PYTHONHASHSEED)."""
    import dask

    return sorted(set(dask.config.get("distributed.nanny.pre-spawn-environ", {}) or {}) | {"PYTHONHASHSEED"})


def _nanny_environ() -> dict[str, str | None]:
    """The caller's values of :func:`_nanny_keys` (None: unset)."""
    return {k: os.environ.get(k) for k in _nanny_keys()}


def _restore_nanny_environ(saved: dict[str, str | None]) -> None:
    """Put back the caller's values: the nanny's settings are meant for the worker processes,
    but it leaves them in the caller's ``os.environ``, where they change every process the
    caller starts later (MALLOC_TRIM_THRESHOLD_ turns glibc's dynamic mmap threshold off)."""
    for k, v in saved.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v


def _check_workers(n: int) -> int:
    if int(n) != n or int(n) < 1:
        raise ValueError(f"workers: expected an integer >= 1, found {n!r}")
    return int(n)


def make_executor(kind: str = "local", workers: int = 2, scheduler: str | None = None) -> Executor:
    """An :class:`Executor` of ``kind`` (:data:`EXECUTORS`): ``workers`` processes for
    "processes" and for the dask ``LocalCluster``; ``scheduler`` the address of a running
    dask scheduler (kind "dask" only). ValueError naming the choices otherwise."""
    if kind not in EXECUTORS:
        raise ValueError(f"executor: expected one of {', '.join(EXECUTORS)}, found {kind!r}")
    if scheduler and kind != "dask":
        raise ValueError(f"--scheduler {scheduler} needs --executor dask (found --executor {kind})")
    workers = _check_workers(workers)
    if kind == "local":
        return LocalExecutor()
    if kind == "processes":
        return ProcessExecutor(workers) if workers > 1 else LocalExecutor()
    return DaskExecutor(scheduler, workers)


@contextlib.contextmanager
def executor_for(executor: Executor | str | None, workers: int = 1,
                 scheduler: str | None = None) -> Iterator[Executor]:
    """The executor to use inside a library call: ``executor`` itself when it is an
    :class:`Executor` (left open: the caller owns it), else a new one of that kind (None:
    "processes" when ``workers`` > 1, else "local"), closed when the block ends."""
    if isinstance(executor, Executor):
        yield executor
        return
    kind = executor if executor is not None else ("processes" if workers > 1 or scheduler else "local")
    if scheduler and executor is None:
        kind = "dask"
    ex = make_executor(kind, workers, scheduler)
    with ex:
        yield ex
