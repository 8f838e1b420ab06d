"""Progress bars (tqdm) for long work: corpus build, featurisation, training, sampling.

Bars go to stderr and are shown only when stderr is a terminal and progress is not
switched off (``bayes-talk -q`` / :func:`set_enabled`); in pipes, logs and tests they are
silent. :func:`bar` wraps an iterable, :class:`ProgressMapper` wraps an executor's ``map``
(``SwitchingSGPDM.fit(executor=...)``) so each finished state ticks the bar.
"""
from __future__ import annotations

import logging
import sys
from collections.abc import Callable, Iterable, Iterator
from typing import Any

__all__ = ["ProgressMapper", "bar", "enabled", "set_enabled"]

_ENABLED = True
log = logging.getLogger(__name__)


def set_enabled(on: bool) -> None:
    """Switch every progress bar on (still only on a terminal) or off."""
    global _ENABLED
    _ENABLED = bool(on)


def enabled() -> bool:
    """True when bars would be drawn: enabled and stderr is a terminal."""
    try:
        tty = sys.stderr.isatty()
    except (AttributeError, ValueError):
        tty = False
    return _ENABLED and tty


def bar(iterable: Iterable, total: int | None = None, desc: str = "", unit: str = "it") -> Iterator:
    """``iterable`` with a tqdm bar (done / total, rate, ETA) when :func:`enabled`; else, with
    INFO logging on (``-v``), one log line at every tenth of ``total``."""
    if not enabled():
        if total and log.isEnabledFor(logging.INFO):
            return _logged(iterable, total, desc or "progress", unit)
        return iter(iterable)
    from tqdm.auto import tqdm

    return iter(tqdm(iterable, total=total, desc=desc, unit=unit, leave=False, dynamic_ncols=True))


def _logged(iterable: Iterable, total: int, desc: str, unit: str) -> Iterator:
    step = max(1, total // 10)
    for k, item in enumerate(iterable, 1):
        yield item
        if k % step == 0 or k == total:
            log.info("%s: %d/%d %s", desc, k, total, unit)


class ProgressMapper:
    """An executor stand-in whose ``map`` runs through ``executor.map`` (or the built-in
    ``map`` when None) and advances a bar per finished item (results stay in order)."""

    def __init__(self, executor: Any = None, desc: str = "", unit: str = "it") -> None:
        self.executor, self.desc, self.unit = executor, desc, unit

    def map(self, fn: Callable, iterable: Iterable) -> Iterator:
        """``executor.map(fn, iterable)`` (or the built-in ``map``), ticking the bar per result."""
        items = list(iterable)
        if getattr(self.executor, "draws_progress", False):  # a bayes_talk.base.executor.Executor: its own bar
            return iter(self.executor.map(fn, items, desc=self.desc, unit=self.unit))
        mapper = self.executor.map if self.executor is not None else map
        return bar(mapper(fn, items), total=len(items), desc=self.desc, unit=self.unit)
