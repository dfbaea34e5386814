"""Log lines the systemd journal files at their own priority.

Under systemd, the daemon's stderr is a stream to the journal, which stores every line at the
stream's default priority unless the line starts with a syslog priority prefix (``<3>``: error,
``<4>``: warning, ...; sd-daemon(3)). systemd names that stream in ``JOURNAL_STREAM``
(``device:inode``); only when stderr is that very stream do lines carry the prefix, so a terminal or
a redirected file reads as before, and ``journalctl -p warning`` finds cmcan's warnings and errors.
"""

from __future__ import annotations

import logging
import os
import sys
from typing import TextIO

# syslog priorities (RFC 5424) of Python's levels
_CRIT, _ERR, _WARNING, _INFO, _DEBUG = 2, 3, 4, 6, 7


def syslog_priority(levelno: int) -> int:
    if levelno >= logging.CRITICAL:
        return _CRIT
    if levelno >= logging.ERROR:
        return _ERR
    if levelno >= logging.WARNING:
        return _WARNING
    if levelno >= logging.INFO:
        return _INFO
    return _DEBUG


def is_journal(stream: TextIO) -> bool:
    """True when ``stream`` is the journal stream systemd named in ``JOURNAL_STREAM``."""
    try:
        dev, ino = (int(x) for x in os.environ.get("JOURNAL_STREAM", "").split(":"))
        st = os.fstat(stream.fileno())
    except (ValueError, OSError, AttributeError):  # not set, malformed, or no file behind the stream
        return False
    return (st.st_dev, st.st_ino) == (dev, ino)


class JournalFormatter(logging.Formatter):
    """A record's first line prefixed with its syslog priority (a traceback's further lines are
    entries of their own, at the stream's default priority)."""

    def format(self, record: logging.LogRecord) -> str:
        return f"<{syslog_priority(record.levelno)}>{super().format(record)}"


def error_line(text: str, stream: TextIO = sys.stderr) -> str:
    """A command's closing error line, prefixed as an error where the journal reads it."""
    return f"<{_ERR}>{text}" if is_journal(stream) else text


def stderr_handler(fmt: str, stream: TextIO | None = None) -> logging.Handler:
    """A handler writing to ``stream`` (stderr), with priority prefixes where that is the journal."""
    stream = stream or sys.stderr
    handler = logging.StreamHandler(stream)
    handler.setFormatter(JournalFormatter(fmt) if is_journal(stream) else logging.Formatter(fmt))
    return handler


def setup_logging(level: int, fmt: str) -> None:
    logging.basicConfig(level=level, handlers=[stderr_handler(fmt)])
