import logging
import sys
from pathlib import Path

# tests import the shared synthetic-data helpers (tests/toydata.py) by module name
sys.path.insert(0, str(Path(__file__).parent))


class _ClosedSafeStream:
    """A log stream that drops what is written once the stream under it is closed."""

    def __init__(self, stream) -> None:
        self.stream = stream

    def write(self, text: str) -> None:
        try:
            self.stream.write(text)
        except ValueError:      # "I/O operation on closed file": pytest's capture has ended
            pass

    def flush(self) -> None:
        try:
            self.stream.flush()
        except ValueError:
            pass


def pytest_configure(config) -> None:
    """dask.distributed gives its loggers a StreamHandler bound to the ``sys.stderr`` of its
    import; when pytest closes that (capture) stream, a cluster shutting down afterwards
    (at interpreter exit) made every log record print a "--- Logging error ---" traceback
    ending in "ValueError: I/O operation on closed file" into the test output. Import it
    here, inside the session's capture, and let those handlers drop records written after
    the stream has closed; records before that are captured and shown as usual."""
    try:
        import distributed  # noqa: F401  (sets its handlers up now)
    except ImportError:
        return
    for name in list(logging.root.manager.loggerDict):
        if name.split(".")[0] not in ("distributed", "tornado", "bokeh"):
            continue
        for h in logging.getLogger(name).handlers:
            if type(h) is logging.StreamHandler and not isinstance(h.stream, _ClosedSafeStream):
                h.setStream(_ClosedSafeStream(h.stream))
