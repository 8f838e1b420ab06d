"""Progress of long work, for the person waiting for it: every stage of a command, every long loop.

One mechanism, :func:`stage`; :func:`bar` and :class:`ProgressMapper` are built on it::

    with stage("synthesis", total=n_frames, unit="frames") as s:
        for ...:
            s.advance()          # or s.update(done) (absolute), s.set_total(total)

``stage(name, total=None, unit="frames", interval=None)`` is a context manager returning a
:class:`Stage`: ``advance(n=1)`` adds ``n`` to what is done, ``update(done)`` sets it,
``set_total(total)`` sets (or corrects) the total; ``total`` None is an unknown total.
:func:`current` is the innermost open stage (a stand-in that does nothing when none is
open): code deep inside a stage, such as an optimiser's loop, reports through
``current().advance(k)`` without being handed the stage. Stages nest; a stage opened inside
another names its path (``synthesis / MAP``).

What is shown, and where (all on stderr):

* progress switched off (:func:`set_enabled`, ``bayes-talk -q``): nothing;
* stderr a terminal: a tqdm bar per stage (done / total, rate, time left), redrawn every
  :data:`HEARTBEAT_S` seconds even while the stage's code is busy in one long call;
* otherwise (a pipe, a log file, a batch job): a heartbeat, one log line every
  :data:`HEARTBEAT_S` seconds (5 s) while a stage runs, on the logger ``bayes_talk.progress``
  (:data:`HEARTBEAT_LOGGER`) at INFO, from the innermost open stage: its name, done / total,
  the elapsed time and, when the total is known and something is done, an estimate of the
  time left (``synthesis: 120/900 frames (13 %), 42 s elapsed, about 4 min 33 s left``). A
  stage shorter than the interval prints none. The heartbeat comes from a daemon timer
  thread that logs the stage's latest state, so it fires while the stage's code sits in one
  call without advancing; the thread stops, and is joined, when the stage ends. The command
  line sets that logger to INFO, so a run that is not on a terminal prints the heartbeat by
  default; a library user sees it by configuring logging (``logging.basicConfig(level=logging.INFO)``);
* with INFO logging on this module's logger (``bayes-talk -v``): a line at the start and at
  the end of every stage, the end with the stage's wall time.

:func:`bar` wraps an iterable (a stage advanced per item), :class:`ProgressMapper` wraps an
executor's ``map`` (``SwitchingSGPDM.fit(executor=...)``) so each finished item advances it.
"""
from __future__ import annotations

import contextlib
import logging
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from typing import Any, Self

__all__ = ["HEARTBEAT_LOGGER", "HEARTBEAT_S", "ProgressMapper", "Stage", "bar", "current", "enabled",
           "set_enabled", "stage"]

#: seconds between two heartbeat lines (or bar redraws) of a running stage
HEARTBEAT_S = 5.0
#: the logger of the heartbeat lines (INFO); ``bayes-talk`` shows it by default
HEARTBEAT_LOGGER = "bayes_talk.progress"
#: seconds :meth:`Stage.close` waits for the heartbeat thread (it only ever waits for one
#: log line being written; the thread is a daemon and writes nothing after the stage ends)
JOIN_TIMEOUT_S = 10.0

_ENABLED = True
log = logging.getLogger(__name__)
heartbeat_log = logging.getLogger(HEARTBEAT_LOGGER)

_OPEN: list[Stage] = []          # the open stages, outermost first
_OPEN_LOCK = threading.Lock()


def set_enabled(on: bool) -> None:
    """Switch all progress output on (bars on a terminal, heartbeats and stage lines
    elsewhere) or off."""
    global _ENABLED
    _ENABLED = bool(on)


def _terminal() -> bool:
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):
        return False


def enabled() -> bool:
    """True when bars would be drawn: progress enabled and stderr is a terminal."""
    return _ENABLED and _terminal()


def _number(x: float) -> str:
    x = float(x)
    return str(int(x)) if x.is_integer() else f"{x:.3g}"


def _duration(seconds: float) -> str:
    """``4.2 s``, ``42 s``, ``3 min 05 s``, ``1 h 02 min``."""
    s = max(0.0, float(seconds))
    if s < 10:
        return f"{s:.1f} s"
    if s < 60:
        return f"{s:.0f} s"
    m, sec = divmod(round(s), 60)
    if m < 60:
        return f"{m} min {sec:02d} s"
    h, m = divmod(m, 60)
    return f"{h} h {m:02d} min"


class Stage:
    """One open stage (see the module docstring); made by :func:`stage`. ``advance``,
    ``update`` and ``set_total`` may be called from any thread."""

    def __init__(self, name: str, total: float | None = None, unit: str = "frames",
                 interval: float | None = None) -> None:
        self.name, self.unit = str(name), str(unit)
        self.interval = float(HEARTBEAT_S if interval is None else interval)
        if self.interval <= 0:
            raise ValueError(f"progress interval must be > 0 s, got {self.interval}")
        self._total = total
        self._done: float = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._bar: Any = None
        self._t0 = time.monotonic()
        self._t_end: float | None = None
        self.path = self.name
        #: the heartbeat lines this stage has written
        self.beats = 0

    # ---------------------------------------------------------------- reporting
    def advance(self, n: float = 1) -> None:
        """``n`` more done."""
        with self._lock:
            self._done += n
            if self._bar is not None:
                self._bar.update(n)

    def update(self, done: float) -> None:
        """``done`` done in all (absolute)."""
        with self._lock:
            step = done - self._done
            self._done = done
            if self._bar is not None:
                self._bar.update(step)

    def set_total(self, total: float | None) -> None:
        """The total (None: unknown)."""
        with self._lock:
            self._total = total
            if self._bar is not None:
                self._bar.total = self._total
                self._bar.refresh()

    @property
    def done(self) -> float:
        """What is done so far."""
        return self._done

    @property
    def total(self) -> float | None:
        """The total, or None when unknown."""
        return self._total

    @property
    def elapsed(self) -> float:
        """Seconds since the stage opened (until it closed, once closed)."""
        return (self._t_end if self._t_end is not None else time.monotonic()) - self._t0

    def status(self) -> str:
        """The heartbeat line: path, done / total, elapsed time and the time left."""
        with self._lock:
            done, total, elapsed = self._done, self._total, self.elapsed
        parts = []
        if total is not None:
            pct = f" ({100.0 * done / total:.0f} %)" if total > 0 else ""
            parts.append(f"{_number(done)}/{_number(total)} {self.unit}{pct}")
        elif done > 0:
            parts.append(f"{_number(done)} {self.unit}")
        parts.append(f"{_duration(elapsed)} elapsed")
        if total is not None:
            if done >= total:
                parts.append("finishing")
            elif done > 0 and elapsed > 0:
                parts.append(f"about {_duration(max(total - done, 0.0) * elapsed / done)} left")
            else:
                parts.append("time left unknown")
        return f"{self.path}: " + ", ".join(parts)

    # ---------------------------------------------------------------- lifetime
    def open(self) -> Self:
        """Start the stage: the bar or the heartbeat thread, the start line (with INFO)."""
        with _OPEN_LOCK:
            if _OPEN:
                self.path = f"{_OPEN[-1].path} / {self.name}"
            _OPEN.append(self)
        self._t0 = time.monotonic()
        if not _ENABLED:
            return self
        if log.isEnabledFor(logging.INFO):
            size = f" ({_number(self._total)} {self.unit})" if self._total is not None else ""
            log.info("%s: started%s", self.path, size)
        if _terminal():
            from tqdm.auto import tqdm

            self._bar = tqdm(total=self._total, desc=self.path, unit=self.unit, leave=False, dynamic_ncols=True,
                             file=sys.stderr)
        elif not heartbeat_log.isEnabledFor(logging.INFO):
            return self
        self._thread = threading.Thread(target=self._beat, name=f"bayes_talk progress: {self.path}", daemon=True)
        self._thread.start()
        return self

    def _beat(self) -> None:
        while not self._stop.wait(self.interval):
            try:
                if self._bar is not None:
                    with self._lock:
                        if not self._stop.is_set():
                            self._bar.refresh()
                    continue
                with _OPEN_LOCK:
                    innermost = bool(_OPEN) and _OPEN[-1] is self
                if innermost and not self._stop.is_set():
                    heartbeat_log.info("%s", self.status())
                    self.beats += 1
            except Exception:   # progress must never break the work it reports on
                log.debug("progress heartbeat failed", exc_info=True)
                return

    def close(self, failed: bool = False) -> None:
        """End the stage: stop and join the heartbeat thread, close the bar, the end line."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(JOIN_TIMEOUT_S)
        self._thread = None
        self._t_end = time.monotonic()
        with _OPEN_LOCK:
            for i in range(len(_OPEN) - 1, -1, -1):
                if _OPEN[i] is self:
                    del _OPEN[i]
                    break
        if self._bar is not None:
            with self._lock:
                self._bar.close()
                self._bar = None
        if _ENABLED and log.isEnabledFor(logging.INFO):
            size = (f" ({_number(self._done)}/{_number(self._total)} {self.unit})" if self._total is not None
                    else f" ({_number(self._done)} {self.unit})" if self._done else "")
            log.info("%s: %s %s%s", self.path, "failed after" if failed else "done in", _duration(self.elapsed), size)

    def __enter__(self) -> Self:
        return self.open()

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close(failed=exc_type is not None)


class _NoStage:
    """:func:`current` when no stage is open: reports go nowhere."""

    name = path = ""
    unit = ""
    done, total = 0.0, None

    def advance(self, n: float = 1) -> None:
        """Nothing (no stage is open)."""

    def update(self, done: float) -> None:
        """Nothing (no stage is open)."""

    def set_total(self, total: float | None) -> None:
        """Nothing (no stage is open)."""


_NO_STAGE = _NoStage()


def stage(name: str, total: float | None = None, unit: str = "frames", interval: float | None = None) -> Stage:
    """A stage of work named ``name`` with ``total`` ``unit`` to do (None: unknown), as a
    context manager (the module docstring says what it shows); ``interval``: seconds between
    heartbeats (None: :data:`HEARTBEAT_S`)."""
    return Stage(name, total, unit, interval)


def current() -> Stage | _NoStage:
    """The innermost open stage (of any thread), or a stand-in whose ``advance``,
    ``update`` and ``set_total`` do nothing when none is open."""
    with _OPEN_LOCK:
        return _OPEN[-1] if _OPEN else _NO_STAGE


def bar(iterable: Iterable, total: int | None = None, desc: str = "", unit: str = "it") -> Iterator:
    """``iterable`` inside a :func:`stage` named ``desc`` advanced per item (a tqdm bar on a
    terminal, heartbeats elsewhere); ``total`` defaults to ``len(iterable)`` where it has one.
    The stage opens at the first item and closes after the last (or when the iterator is
    closed)."""
    if total is None:
        with contextlib.suppress(TypeError):
            total = len(iterable)  # type: ignore[arg-type]
    if not _ENABLED:
        return iter(iterable)
    return _staged(iterable, total, desc or "progress", unit)


def _staged(iterable: Iterable, total: int | None, desc: str, unit: str) -> Iterator:
    with stage(desc, total, unit) as s:
        for item in iterable:
            yield item
            s.advance()


class ProgressMapper:
    """An executor stand-in whose ``map`` runs through ``executor.map`` (or the built-in
    ``map`` when None) and advances a stage per finished item (results stay in order)."""

    def __init__(self, executor: Any = None, desc: str = "", unit: str = "it") -> None:
        self.executor, self.desc, self.unit = executor, desc, unit

    def map(self, fn: Callable, iterable: Iterable) -> Iterator:
        """``executor.map(fn, iterable)`` (or the built-in ``map``), advancing the stage per result."""
        items = list(iterable)
        if getattr(self.executor, "draws_progress", False):  # a bayes_talk.base.executor.Executor: its own bar
            return iter(self.executor.map(fn, items, desc=self.desc, unit=self.unit))
        mapper = self.executor.map if self.executor is not None else map
        return bar(mapper(fn, items), total=len(items), desc=self.desc, unit=self.unit)
