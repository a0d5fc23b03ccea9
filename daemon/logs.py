"""The daemon's log lines on stderr: one event a line, ``key=value`` fields, quiet by default.

Under systemd (``JOURNAL_STREAM`` set) each line starts with its syslog priority (``<4>``),
which journald turns into the entry's priority, and carries no timestamp (journald adds
it); elsewhere a line starts with a UTC timestamp. Fields passed as
``log.info("msg", extra={"fields": {...}})`` follow the message as ``key=value``, values
quoted when they hold spaces, so ``journalctl -u seamap | grep survey=`` works.
"""

from __future__ import annotations

import logging
import os
import sys
import time
from collections.abc import Mapping
from typing import Any, TextIO

_PRIORITY = {
    logging.DEBUG: 7,
    logging.INFO: 6,
    logging.WARNING: 4,
    logging.ERROR: 3,
    logging.CRITICAL: 2,
}


def format_fields(fields: Mapping[str, Any]) -> str:
    """``key=value`` pairs; strings with spaces, quotes or ``=`` are quoted."""
    parts = []
    for key, value in fields.items():
        if isinstance(value, float):
            text = f"{value:.3g}" if abs(value) < 1000 else f"{value:.0f}"
        elif value is None:
            text = "-"
        else:
            text = str(value)
        if not text or any(c in text for c in ' "=\n'):
            text = '"' + text.replace("\\", "\\\\").replace('"', '\\"').replace("\n", " ") + '"'
        parts.append(f"{key}={text}")
    return " ".join(parts)


class LineFormatter(logging.Formatter):
    """One line per record: [timestamp or <priority>] LEVEL logger: message key=value..."""

    def __init__(self, journald: bool) -> None:
        super().__init__()
        self.journald = journald

    def format(self, record: logging.LogRecord) -> str:
        message = record.getMessage().replace("\n", " ")
        fields = getattr(record, "fields", None)
        if fields:
            message = f"{message} {format_fields(fields)}"
        if record.exc_info and record.levelno <= logging.DEBUG:
            message = f"{message} | {self.formatException(record.exc_info)!r}"
        name = record.name.removeprefix("daemon.")
        if self.journald:
            priority = _PRIORITY.get(record.levelno, 6)
            return f"<{priority}>{record.levelname.lower()} {name}: {message}"
        stamp = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created))
        millis = int(record.msecs)
        return f"{stamp}.{millis:03d}Z {record.levelname.lower()} {name}: {message}"


def configure_logging(level: str, stream: TextIO | None = None) -> None:
    """Send every logger's records at ``level`` or above to ``stream`` (stderr)."""
    handler = logging.StreamHandler(stream if stream is not None else sys.stderr)
    handler.setFormatter(LineFormatter(journald="JOURNAL_STREAM" in os.environ))
    root = logging.getLogger()
    for old in list(root.handlers):
        root.removeHandler(old)
    root.addHandler(handler)
    root.setLevel(level.upper())
    # Libraries' chatter stays below the daemon's own lines unless debugging.
    if level != "debug":
        for name in ("asyncio", "zenoh", "drivers", "mapping", "tools"):
            logging.getLogger(name).setLevel(max(logging.WARNING, root.level))
