"""The daemon's log lines as a test sees them, from every process of it: the service and the device I/O write
their own lines (compd/daemon/host.py, compd/io/child.py), so a test reads stderr at the descriptor, as the journal
would, and parses the key=value lines back into records."""

from __future__ import annotations

import contextlib
import logging
import os
import re
import tempfile
from collections.abc import Iterator
from types import SimpleNamespace

from compd.service.logsetup import KeyValueFormatter

_PAIR = re.compile(r'(\w+)=("(?:[^"\\]|\\.)*"|\S*)')


def parse_line(line: str) -> SimpleNamespace | None:
    """One `level=… event=… msg="…" key=value` line as a record (values as text); None for another line."""
    fields = {}
    for key, value in _PAIR.findall(line):
        if value.startswith('"'):
            value = value[1:-1].replace('\\"', '"').replace("\\\\", "\\")
        fields[key] = value
    if "level" not in fields or "event" not in fields:
        return None
    fields["levelno"] = logging.getLevelName(fields["level"].upper())
    return SimpleNamespace(**fields, getMessage=lambda: fields.get("msg", ""))


@contextlib.contextmanager
def log_lines(level: int = logging.DEBUG) -> Iterator[list[SimpleNamespace]]:
    """Inside: the `compd` logger writes key=value lines to stderr, and stderr (descriptor 2,
    which child processes inherit) goes to a file; at the end, the list holds its lines as records."""
    records: list[SimpleNamespace] = []
    logger = logging.getLogger("compd")
    old_level = logger.level
    with tempfile.TemporaryFile(mode="w+", encoding="utf-8") as out:
        saved = os.dup(2)
        os.dup2(out.fileno(), 2)
        stream = open(2, "w", buffering=1, encoding="utf-8", closefd=False)  # noqa: SIM115  (a child keeps fd 2)
        handler = logging.StreamHandler(stream)
        handler.setFormatter(KeyValueFormatter())
        handler.setLevel(level)
        # the only handler while it reads, as the daemon has one: a handler an earlier test of this process
        # left on the logger (a `compd` command run in process) would write every line a second time
        others = logger.handlers[:]
        logger.handlers = [handler]
        logger.setLevel(level)
        try:
            yield records
        finally:
            logger.handlers = others
            logger.setLevel(old_level)
            handler.flush()
            stream.close()
            os.dup2(saved, 2)
            os.close(saved)
            out.seek(0)
            records.extend(r for r in map(parse_line, out.read().splitlines()) if r is not None)
