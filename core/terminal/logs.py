"""The log of a long-running command (``vservo serve``, ``controller``, ``virtual-cell``, ``run``):
its level and its format on standard error, text for a terminal or one JSON object a line
for the system's journal and a log shipper.

``--log-format json`` makes every line of standard error one JSON object: the log records,
the command's own announcements (``announce``), Python's warnings and an uncaught
exception's traceback alike, so a reader parses the stream line by line without exception.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import threading
import traceback
from datetime import datetime, timezone
from enum import StrEnum
from types import TracebackType
from typing import Any

TEXT_FORMAT = "%(asctime)s %(name)s %(levelname)s: %(message)s"


class LogFormat(StrEnum):
    TEXT = "text"
    JSON = "json"


class LogLevel(StrEnum):
    DEBUG = "debug"
    INFO = "info"
    WARNING = "warning"
    ERROR = "error"

    @property
    def number(self) -> int:
        return int(logging.getLevelName(self.name))


class JsonFormatter(logging.Formatter):
    """One JSON object per record: time (ISO 8601 UTC), level, logger, message, the process's
    role, and the traceback as one string when there is one."""

    def __init__(self, role: str) -> None:
        super().__init__()
        self.role = role

    def format(self, record: logging.LogRecord) -> str:
        entry: dict[str, Any] = {
            "time": datetime.fromtimestamp(record.created, timezone.utc).isoformat(timespec="milliseconds"),
            "level": record.levelname.lower(),
            "logger": record.name,
            "message": record.getMessage(),
            "process": self.role,
            "pid": record.process,
            "thread": record.threadName,
        }
        if record.exc_info:
            entry["traceback"] = self.formatException(record.exc_info)
        return json.dumps(entry, default=str)


_format = LogFormat.TEXT
_log = logging.getLogger("vservo")


def add_log_options(parser: argparse.ArgumentParser, default_level: LogLevel = LogLevel.WARNING) -> None:
    """--log-level and --log-format on a long-running command's parser."""
    parser.add_argument(
        "--log-level",
        choices=tuple(LogLevel),
        default=default_level.value,
        help=f"the least severe log records written to standard error (default {default_level.value})",
    )
    parser.add_argument(
        "--log-format",
        choices=tuple(LogFormat),
        default=LogFormat.TEXT.value,
        help="text for a terminal, or json: one JSON object a line, for the system's journal and log shippers (default text)",
    )


def configure_logging(args: argparse.Namespace, role: str) -> None:
    """Send the log to standard error at --log-level in --log-format; ``role`` names the process in JSON."""
    global _format
    _format = LogFormat(args.log_format)
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(JsonFormatter(role) if _format is LogFormat.JSON else logging.Formatter(TEXT_FORMAT))
    root = logging.getLogger()
    for old in list(root.handlers):
        root.removeHandler(old)
    root.addHandler(handler)
    root.setLevel(LogLevel(args.log_level).number)
    logging.captureWarnings(True)
    if _format is LogFormat.JSON:
        sys.excepthook = _log_uncaught
        threading.excepthook = lambda hook: _log_uncaught(hook.exc_type, hook.exc_value, hook.exc_traceback)


def _log_uncaught(kind: type[BaseException], value: BaseException | None, tb: TracebackType | None) -> None:
    _log.critical("uncaught %s: %s\n%s", kind.__name__, value, "".join(traceback.format_tb(tb)))


def announce(line: str) -> None:
    """A command's own line for its operator on standard error (where it listens, how to stop
    it): printed as it is, or as a JSON record whatever the level, so the stream stays JSON."""
    if _format is LogFormat.JSON:
        record = _log.makeRecord(_log.name, logging.INFO, __file__, 0, line, (), None)
        handler = logging.getLogger().handlers[0]
        print(handler.format(record), file=sys.stderr, flush=True)
    else:
        print(line, file=sys.stderr, flush=True)
