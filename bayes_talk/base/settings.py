"""The environment switches of :mod:`bayes_talk`, in one place, read when used.

Every switch is read from the environment each time :func:`get` is called (never at
import), so setting a variable after ``import bayes_talk`` takes effect; a program (a test,
a benchmark's command-line flag) sets one for a block with :func:`override` or for the
rest of the process with :func:`set_switch`, which win over the environment.

==============  ============================  ===========  ==========================================
switch          environment variable          default      effect
==============  ============================  ===========  ==========================================
``fused``       ``BAYES_TALK_FUSED``          ``1``        ``0``: the GP terms and the synthesis
                                                           densities through torch / NumPy-LAPACK
                                                           (the reference the tests compare with)
                                                           instead of the compiled loops of
                                                           :mod:`bayes_talk.gp.fused` and
                                                           :mod:`bayes_talk.gp.predictive_fused`
``direct_fit``  ``BAYES_TALK_DIRECT_FIT``     ``1``        ``0``: SGPDM MAP fits through torch autograd
                                                           and ``torch.optim.LBFGS`` (the reference)
                                                           instead of the hand-written gradient of
                                                           :mod:`bayes_talk.models.sgpdm_objective`
                                                           and the NumPy port of that L-BFGS
                                                           (:mod:`bayes_talk.gp.lbfgs`)
``lapack``      ``BAYES_TALK_LAPACK``         torch-mkl    ``scipy``: scipy's LAPACK for the
                                                           in-place Cholesky routines of
                                                           :mod:`bayes_talk.gp.lapack`
``potri_threads`` ``BAYES_TALK_POTRI_THREADS`` ``1``       the most MKL threads of ``dpotri``
                                                           (``0``: as many as torch)
``malloc``      ``BAYES_TALK_MALLOC``         ``1``        ``0``: leave glibc's mmap threshold alone
                                                           (:func:`bayes_talk.base.memory.release_large_blocks`)
``cache``       ``BAYES_TALK_CACHE``          (none)       the cache root of the articulatory
                                                           synthesiser (:func:`bayes_talk.data.articulatory.cache_dir`)
==============  ============================  ===========  ==========================================

A malformed value is a ValueError naming the variable, what was expected and what was found.
"""
from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

__all__ = ["SWITCHES", "Switch", "get", "override", "set_switch"]


def _flag(name: str, raw: str) -> bool:
    if raw not in ("0", "1"):
        raise ValueError(f"{name}: expected 0 or 1, found {raw!r}")
    return raw == "1"


def _lapack(name: str, raw: str) -> str:
    if raw not in ("torch-mkl", "scipy"):
        raise ValueError(f"{name}: expected 'torch-mkl' or 'scipy', found {raw!r}")
    return raw


def _threads(name: str, raw: str) -> int | None:
    try:
        n = int(raw)
    except ValueError:
        n = -1
    if n < 0:
        raise ValueError(f"{name}: expected a whole number >= 0 (0: as many as torch), found {raw!r}")
    return n or None


@dataclass(frozen=True)
class Switch:
    """One switch: its environment variable, the value when unset, and the parser of a set
    value (``parse(variable, text)``, ValueError naming the variable when malformed)."""

    variable: str
    default: Any
    parse: Callable[[str, str], Any]


#: every switch of the package (module docstring)
SWITCHES: dict[str, Switch] = {
    "fused": Switch("BAYES_TALK_FUSED", True, _flag),
    "direct_fit": Switch("BAYES_TALK_DIRECT_FIT", True, _flag),
    "lapack": Switch("BAYES_TALK_LAPACK", "torch-mkl", _lapack),
    "potri_threads": Switch("BAYES_TALK_POTRI_THREADS", 1, _threads),
    "malloc": Switch("BAYES_TALK_MALLOC", True, _flag),
    "cache": Switch("BAYES_TALK_CACHE", None, lambda name, raw: raw or None),
}

_overrides: dict[str, Any] = {}


def _switch(name: str) -> Switch:
    try:
        return SWITCHES[name]
    except KeyError:
        raise KeyError(f"unknown switch {name!r}: expected one of {sorted(SWITCHES)}") from None


def get(name: str) -> Any:
    """The value of switch ``name`` now: an override, else the environment, else the default."""
    sw = _switch(name)
    if name in _overrides:
        return _overrides[name]
    raw = os.environ.get(sw.variable)
    return sw.default if raw is None else sw.parse(sw.variable, raw)


def set_switch(name: str, value: Any) -> None:
    """Set switch ``name`` for the rest of the process (over the environment)."""
    _switch(name)
    _overrides[name] = value


@contextmanager
def override(**values: Any) -> Iterator[None]:
    """Set switches for the block (``with override(fused=False): ...``), then restore them."""
    for name in values:
        _switch(name)
    saved = {n: _overrides[n] for n in values if n in _overrides}
    _overrides.update(values)
    try:
        yield
    finally:
        for n in values:
            _overrides.pop(n, None)
        _overrides.update(saved)
