"""Messages and progress through standard ``logging``, in the driver and from Ray workers.

Every module logs to ``logging.getLogger(__name__)`` (all under ``anchordp3``); nothing prints.
Progress lines (items, rate, ETA) are INFO messages like any other.

- ``console(level)``: what a command line installs once: ``anchordp3``'s messages from ``level``
  on stderr as bare lines (warnings and errors prefixed), other libraries' only from ERROR (their
  warnings are for their developers, not something a user of this tool can act on).
- ``to_file(path)``: a context manager adding a timestamped log file with everything from INFO,
  other libraries' warnings included (``<run>/logs/driver.log`` for a data run).
- Worker output: ``Capture`` collects what is logged while a stage item runs in a Ray worker;
  the records travel back with the item's result and ``replay`` re-emits them in the driver,
  named after the stage and the item, so they reach the driver's console and log file.
"""

from __future__ import annotations

import logging
import sys
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

ROOT = "anchordp3"
FILE_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
_HANDLER_MARK = "_anchordp3_handler"


class _ConsoleFormat(logging.Formatter):
    """``message`` for INFO and below, ``warning: message`` / ``error: message`` above."""

    def format(self, record: logging.LogRecord) -> str:
        msg = record.getMessage()
        if record.exc_info and record.levelno >= logging.ERROR:
            msg += "\n" + self.formatException(record.exc_info)
        return msg if record.levelno < logging.WARNING else f"{record.levelname.lower()}: {msg}"


class _Levels(logging.Filter):
    """Passes ``anchordp3``'s records from level ``ours`` and other libraries' from ``others``."""

    def __init__(self, ours: int, others: int) -> None:
        super().__init__()
        self.ours, self.others = ours, others

    def filter(self, record: logging.LogRecord) -> bool:
        mine = record.name == ROOT or record.name.startswith(ROOT + ".")
        return record.levelno >= (self.ours if mine else self.others)


def _installed(logger: logging.Logger, kind: str) -> list[logging.Handler]:
    return [h for h in logger.handlers if getattr(h, _HANDLER_MARK, None) == kind]


class _CurrentStderr(logging.StreamHandler):
    """A stream handler that writes to whatever ``sys.stderr`` is when a record comes (test
    runners and in-process CLI invocations swap it, and close the one they swapped in)."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:  # StreamHandler sets it; the current one is always used
        pass


def console(level: int = logging.INFO, stream=None) -> None:
    """Show ``anchordp3``'s messages from ``level`` on ``stream`` (stderr); idempotent: a second
    call replaces the first's handler."""
    root = logging.getLogger()
    for h in _installed(root, "console"):
        root.removeHandler(h)
    handler = logging.StreamHandler(stream) if stream is not None else _CurrentStderr()
    handler.setFormatter(_ConsoleFormat())
    handler.addFilter(_Levels(level, logging.ERROR))
    setattr(handler, _HANDLER_MARK, "console")
    root.addHandler(handler)
    root.setLevel(min(root.level or logging.WARNING, logging.WARNING))
    logging.getLogger(ROOT).setLevel(min(level, logging.INFO))
    logging.captureWarnings(True)  # Python warnings become records of "py.warnings": kept from the console


class _LogFile(logging.FileHandler):
    """A log file that goes quiet once it cannot be written (a full disk): the command's own
    error says what happened, rather than a traceback per message on stderr."""

    broken = False

    def emit(self, record: logging.LogRecord) -> None:
        if not self.broken:
            super().emit(record)

    def handleError(self, record: logging.LogRecord) -> None:
        if isinstance(sys.exc_info()[1], OSError):
            self.broken = True
            return
        super().handleError(record)

    def close(self) -> None:
        try:
            super().close()
        except OSError:  # its last flush found the disk full
            self.broken = True


@contextmanager
def to_file(path: Path):
    """Append every ``anchordp3`` record from INFO, and other libraries' warnings, to ``path``
    (created with its folder) for the duration of the block."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    handler = _LogFile(path, encoding="utf-8")
    handler.setFormatter(logging.Formatter(FILE_FORMAT))
    handler.addFilter(_Levels(logging.INFO, logging.WARNING))
    setattr(handler, _HANDLER_MARK, "file")
    root, ours = logging.getLogger(), logging.getLogger(ROOT)
    old_root, old_ours = root.level, ours.level
    root.setLevel(min(root.level or logging.WARNING, logging.WARNING))
    if ours.getEffectiveLevel() > logging.INFO:
        ours.setLevel(logging.INFO)
    root.addHandler(handler)
    try:
        yield path
    finally:
        root.removeHandler(handler)
        handler.close()
        root.setLevel(old_root)
        ours.setLevel(old_ours)


# ------------------------------------------------------------------------------- worker output
@dataclass(frozen=True)
class WorkerRecord:
    """One message logged in a worker while it ran an item: enough to re-emit it in the driver."""

    name: str      # the logger's name in the worker
    level: int     # logging level number
    message: str   # the formatted message (exception text appended)
    created: float  # time.time() when it was logged, seconds


class Capture(logging.Handler):
    """While installed (``with Capture() as cap:``), collects the records of ``anchordp3`` from INFO
    and of other libraries from WARNING into ``cap.records`` (``WorkerRecord``s)."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.records: list[WorkerRecord] = []
        self.addFilter(_Levels(logging.INFO, logging.WARNING))
        self.setFormatter(logging.Formatter("%(message)s"))

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(WorkerRecord(record.name, record.levelno, self.format(record), record.created))

    def __enter__(self) -> Capture:
        root, ours = logging.getLogger(), logging.getLogger(ROOT)
        self._levels = (root.level, ours.level)
        if root.getEffectiveLevel() > logging.WARNING:
            root.setLevel(logging.WARNING)
        if ours.getEffectiveLevel() > logging.INFO:
            ours.setLevel(logging.INFO)
        logging.captureWarnings(True)
        root.addHandler(self)
        return self

    def __exit__(self, *exc) -> None:
        root, ours = logging.getLogger(), logging.getLogger(ROOT)
        root.removeHandler(self)
        root.setLevel(self._levels[0])
        ours.setLevel(self._levels[1])


def replay(records: list[WorkerRecord], where: str) -> None:
    """Re-emit worker ``records`` in this process, their messages prefixed with ``where``
    (``"render place_mouse/000003"``), through their own loggers: the driver's handlers show
    and file them as if they had been logged here."""
    for r in records:
        logger = logging.getLogger(r.name)
        if not logger.isEnabledFor(r.level):
            continue
        rec = logger.makeRecord(r.name, r.level, "(worker)", 0, f"{where}: {r.message}", None, None)
        rec.created, rec.msecs = r.created, (r.created - int(r.created)) * 1000
        rec.relativeCreated = (r.created - logging._startTime) * 1000  # noqa: SLF001 - as LogRecord computes it
        logger.handle(rec)
