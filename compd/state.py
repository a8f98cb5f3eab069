"""Model state that survives restarts and power loss: atomic JSON writes, checked loading."""

from __future__ import annotations

import json
import logging
import math
import os
import threading
import time
from pathlib import Path
from typing import Any

log = logging.getLogger("compd.state")

FORMAT = 1


def write_atomic(path: Path, data: dict[str, Any]) -> None:
    """Write JSON to `path` so that a crash leaves either the old or the new file.

    Temp file in the same folder, fsync, rename over the old file, fsync the folder.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "w", encoding="utf-8") as fh:
        json.dump(data, fh)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)
    fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def load_state(path: Path, model_kind: str, inputs: list[str], outputs: list[str]) -> tuple[dict[str, Any], float] | None:
    """The saved model state and the seconds elapsed since it was saved, or None.

    A file for another model (kind, inputs or outputs differ), a corrupt file, or
    one saved "in the future" (clock jumped back) is ignored with a warning: the
    model then starts fresh, which is safe (it starts from zero correction).
    """
    try:
        raw = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as e:
        reason = f"unreadable: {e}"
        log.warning("state ignored: %s: %s", path, reason,
                    extra={"event": "state_ignored", "path": str(path), "reason": reason})
        return None
    try:
        if raw.get("format") != FORMAT:
            raise ValueError(f"format {raw.get('format')!r}")
        if raw["kind"] != model_kind or raw["inputs"] != inputs or raw["outputs"] != outputs:
            raise ValueError("saved for another model")
        saved = float(raw["saved_unix_s"])
        if not math.isfinite(saved):
            raise ValueError("bad time stamp")
        elapsed = time.time() - saved
        if elapsed < -5.0:
            raise ValueError(f"saved {-elapsed:.0f} s in the future (clock jumped?)")
        return dict(raw["state"]), max(elapsed, 0.0)
    except (KeyError, TypeError, ValueError) as e:
        log.warning("state ignored: %s: %s", path, e,
                    extra={"event": "state_ignored", "path": str(path), "reason": str(e)})
        return None


class StateWriter:
    """Persists model state from a background thread (the cycle never waits on fsync).

    `submit(state)` is called at a model step; only the newest pending state is
    written. Errors (full disk) are kept in `error` and logged, never raised.
    `close()` writes what is pending before it returns.
    """

    def __init__(self, path: Path, model_kind: str, inputs: list[str], outputs: list[str]) -> None:
        self.path = path
        self.header = {"format": FORMAT, "kind": model_kind, "inputs": inputs, "outputs": outputs}
        self.writes = 0
        self.error: str | None = None
        self._pending: dict[str, Any] | None = None
        self._closing = False
        self._cv = threading.Condition()
        self._thread = threading.Thread(target=self._run, name="compd-state", daemon=True)
        self._thread.start()

    def submit(self, state: dict[str, Any]) -> None:
        with self._cv:
            self._pending = state
            self._cv.notify()

    def write_now(self, state: dict[str, Any]) -> None:
        """Synchronous write."""
        data = {**self.header, "saved_unix_s": time.time(), "state": state}
        try:
            write_atomic(self.path, data)
            self.writes += 1
            self.error = None
        except OSError as e:
            self.error = f"state write failed: {e.strerror or e}"
            log.error("%s: %s", self.error, self.path,
                      extra={"event": "state_write_failed", "path": str(self.path), "reason": self.error})

    def _run(self) -> None:
        while True:
            with self._cv:
                while self._pending is None and not self._closing:
                    self._cv.wait()
                state, self._pending = self._pending, None
                closing = self._closing
            if state is not None:
                self.write_now(state)
            elif closing:
                return

    def close(self) -> None:
        with self._cv:
            self._closing = True
            self._cv.notify()
        self._thread.join(timeout=10)
