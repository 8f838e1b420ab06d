"""Exceptions shared by every layer of the package.

:class:`NotFittedError` is the one failure of a model or estimator used before ``fit``
(or ``load``). It subclasses scikit-learn's ``NotFittedError`` (itself a ``ValueError``
and an ``AttributeError``), so ``except ValueError`` and scikit-learn's own checks catch
it too. :func:`check_level` is the one check of a probability level (a quantile or an
interval's coverage).
"""
from __future__ import annotations

from sklearn.exceptions import NotFittedError as _SklearnNotFittedError

__all__ = ["NotFittedError", "check_level", "not_fitted"]


class NotFittedError(_SklearnNotFittedError):
    """A model or estimator was used before ``fit`` or ``load``."""


def not_fitted(obj: object, how: str = "call fit() or load() first") -> NotFittedError:
    """The error for ``obj`` used before fitting, naming its class."""
    return NotFittedError(f"this {type(obj).__name__} is not fitted yet: {how}")


def check_level(level: float, what: str = "level") -> float:
    """``level`` as a float in the open interval (0, 1); ValueError naming ``what`` otherwise."""
    q = float(level)
    if not 0.0 < q < 1.0:
        raise ValueError(f"{what} must be in (0, 1), got {level!r}")
    return q
