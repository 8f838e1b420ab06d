"""What this process's logging looks like, carried to the worker processes it starts.

The command line sets up logging once (``bayes_talk.app.cli``): one stderr handler on the
root logger with its format, the level of ``-v``/``-q``, third-party chatter held back
(hmmlearn's "Model is not converging", :data:`QUIET_LOGGERS`) and warnings through logging,
one line each (:func:`brief_warning`). A worker process of
:class:`bayes_talk.base.executor.ProcessExecutor` is a fresh interpreter that knows none of
it: left alone, its records go to Python's last-resort handler, and hmmlearn's chatter from
the aligner's fit in ``train`` would reach the user whatever ``-v`` says. :func:`snapshot`
records the set-up (plain values, pickled to the worker) and :func:`apply` repeats it there.
"""
from __future__ import annotations

import logging
import sys
import warnings

__all__ = ["QUIET_LOGGERS", "apply", "brief_warning", "quiet_third_party", "snapshot"]

#: third-party loggers whose WARNINGs are noise to a user, shown with ``-v`` only: hmmlearn
#: logs "Model is not converging" for every EM step whose log-likelihood drops by rounding
#: (the aligner, the recogniser, the Voice Puppetry baseline)
QUIET_LOGGERS = ("hmmlearn",)


def quiet_third_party(verbose: bool) -> None:
    """:data:`QUIET_LOGGERS` at INFO with ``verbose``, else at ERROR."""
    for name in QUIET_LOGGERS:
        logging.getLogger(name).setLevel(logging.INFO if verbose else logging.ERROR)


def brief_warning(message, category, *args, **kwargs) -> str:
    """A warning as one line, ``Category: message`` (``warnings.formatwarning`` of the command line)."""
    return f"{category.__name__}: {message}"


def _stderr_format(root: logging.Logger) -> str | None:
    """The format of the root logger's handler that writes to the current stderr, if any."""
    for h in root.handlers:
        if isinstance(h, logging.StreamHandler) and getattr(h, "stream", None) is sys.stderr and h.formatter:
            return h.formatter._fmt
    return None


def snapshot() -> dict:
    """This process's logging set-up as plain values: the levels set on the root logger and on
    named loggers, the format of the root's stderr handler (None: no such handler) and whether
    warnings go through logging in one line."""
    root = logging.getLogger()
    levels = {name: lg.level for name, lg in logging.Logger.manager.loggerDict.items()
              if isinstance(lg, logging.Logger) and lg.level != logging.NOTSET}
    return {"root_level": root.level, "levels": levels, "format": _stderr_format(root),
            "capture_warnings": getattr(logging, "_warnings_showwarning", None) is not None,
            "brief_warnings": warnings.formatwarning is brief_warning}


def apply(setup: dict | None) -> None:
    """Repeat a :func:`snapshot` in this process (a worker's start-up); None: leave it as it is."""
    if not setup:
        return
    root = logging.getLogger()
    root.setLevel(setup["root_level"])
    for name, level in setup["levels"].items():
        logging.getLogger(name).setLevel(level)
    if setup["format"] is not None and _stderr_format(root) is None:
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter(setup["format"]))
        root.addHandler(handler)
    if setup["capture_warnings"]:
        logging.captureWarnings(True)
    if setup["brief_warnings"]:
        warnings.formatwarning = brief_warning
