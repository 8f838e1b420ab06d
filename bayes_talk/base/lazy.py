"""Public names of a package imported on first access (PEP 562), so that importing the
package (``import bayes_talk``, the command line's start-up) loads no more than it needs.

A package lists its public names and the modules that define them, and takes the two
module-level hooks from :func:`lazy_exports`::

    __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals(), __all__)
"""
from __future__ import annotations

import importlib
from collections.abc import Callable, Sequence
from typing import Any

__all__ = ["lazy_exports"]


def lazy_exports(package: str, exports: dict[str, str], namespace: dict[str, Any],
                 names: Sequence[str]) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """The module ``__getattr__`` and ``__dir__`` of ``package``: a name of ``exports``
    (public name -> defining module) is imported on first access and cached in
    ``namespace`` (the package's ``globals()``); any other name raises AttributeError, as
    a missing module attribute does. ``__dir__`` lists ``names`` (the package's ``__all__``)."""
    def __getattr__(name: str) -> Any:
        if name in exports:
            value = getattr(importlib.import_module(exports[name]), name)
            namespace[name] = value
            return value
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    def __dir__() -> list[str]:
        return list(names)

    return __getattr__, __dir__
