"""Event log lines that journald shows well: one `key=value` line per event, level first.

    level=warning event=sensor_bad msg="T_xi bad: stale" sensor=T_xi quality=stale t_s=812.5

Under systemd (stderr is the journal stream named by $JOURNAL_STREAM) each line
starts with the syslog priority prefix `<N>` so `journalctl -p warning` filters by
level, and carries no time stamp (the journal has one). On a terminal it starts
with an ISO time stamp instead. Fields come from `extra={...}`; compd logs events
(start, ready, faults, recoveries, late cycles, stop), never a line per cycle.
"""

from __future__ import annotations

import logging
import os
import sys
import time
from typing import Any

LOGGER = "compd"
_PRIORITY = {logging.DEBUG: 7, logging.INFO: 6, logging.WARNING: 4, logging.ERROR: 3, logging.CRITICAL: 2}
# a library stays quiet until the CLI configures logging (no bare lastResort lines)
logging.getLogger(LOGGER).addHandler(logging.NullHandler())
_STANDARD = set(vars(logging.LogRecord("", 0, "", 0, "", None, None))) | {"message", "asctime", "event"}


def _quote(value: Any) -> str:
    text = f"{value:.6g}" if isinstance(value, float) else str(value)
    if text == "" or any(c in text for c in ' "=\\\n\t'):
        text = '"' + text.replace("\\", "\\\\").replace('"', '\\"').replace("\n", " ") + '"'
    return text


class KeyValueFormatter(logging.Formatter):
    """`level=… event=… msg="…" key=value …` on one line."""

    def __init__(self, journal: bool = False) -> None:
        super().__init__()
        self.journal = journal

    def format(self, record: logging.LogRecord) -> str:
        parts = []
        if self.journal:
            prefix = f"<{_PRIORITY.get(record.levelno, 6)}>"
        else:
            prefix = ""
            stamp = time.strftime("%Y-%m-%dT%H:%M:%S", time.localtime(record.created))
            parts.append(f"ts={stamp}.{int(record.msecs):03d}")
        parts.append(f"level={record.levelname.lower()}")
        parts.append(f"event={_quote(getattr(record, 'event', record.name.rsplit('.', 1)[-1]))}")
        parts.append(f"msg={_quote(record.getMessage())}")
        for key, value in record.__dict__.items():
            if key not in _STANDARD and not key.startswith("_"):
                parts.append(f"{key}={_quote(value)}")
        if record.exc_info:
            parts.append(f"exc={_quote(self.formatException(record.exc_info))}")
        return prefix + " ".join(parts)


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever sys.stderr is at the time of the call (tests swap it)."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property  # type: ignore[override]
    def stream(self) -> Any:
        return sys.stderr

    @stream.setter
    def stream(self, value: Any) -> None:
        pass


def stderr_is_journal(env: dict[str, str] | None = None) -> bool:
    """True when stderr is connected to the journal ($JOURNAL_STREAM = device:inode of stderr)."""
    env = dict(os.environ) if env is None else env
    value = env.get("JOURNAL_STREAM", "")
    try:
        dev, ino = (int(x) for x in value.split(":"))
        st = os.fstat(sys.stderr.fileno())
    except (ValueError, OSError, AttributeError):
        return False
    return st.st_dev == dev and st.st_ino == ino


def setup_logging(level: str = "info", *, journal: bool | None = None) -> logging.Logger:
    """Configure the `compd` logger once (idempotent): one stderr handler, key=value lines."""
    logger = logging.getLogger(LOGGER)
    for h in list(logger.handlers):
        if isinstance(h, _StderrHandler):
            logger.removeHandler(h)
    handler = _StderrHandler()
    handler.setFormatter(KeyValueFormatter(stderr_is_journal() if journal is None else journal))
    logger.addHandler(handler)
    logger.setLevel(level.upper())
    return logger
