"""Model state that survives restarts and power loss: atomic JSON writes, checked loading."""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from compd.cycle.adapt import state_problem
from compd.service.threads import ServiceThread

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


def params_digest(params: Any) -> str:
    """A short hash of a model's params (a pydantic object or plain data): the adapter's
    estimate belongs to the model it was probed against, and a refit changes it."""
    data = params.model_dump(mode="json") if hasattr(params, "model_dump") else params
    text = json.dumps(data, sort_keys=True, default=str)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:16]


@dataclass
class Saved:
    """What a state file holds for the model it was checked against."""

    state: dict[str, Any]  # the model's state
    elapsed_s: float  # since it was saved
    adapt: dict[str, Any] | None  # the adapter's part: params_sha256, saved_unix_s, axes; None if none


def load_saved(path: Path, model_kind: str, inputs: list[str], outputs: list[str]) -> Saved | None:
    """The saved model state, the seconds elapsed since it was saved and the adapter's part, or None.

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
        log.warning(
            "state ignored: %s: %s", path, reason, extra={"event": "state_ignored", "path": str(path), "reason": reason}
        )
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
        adapt = raw.get("adapt")
        return Saved(dict(raw["state"]), max(elapsed, 0.0), adapt if isinstance(adapt, dict) else None)
    except (KeyError, TypeError, ValueError, OverflowError) as e:  # OverflowError: an int no float holds
        log.warning(
            "state ignored: %s: %s", path, e, extra={"event": "state_ignored", "path": str(path), "reason": str(e)}
        )
        return None


class StateWriter:
    """Persists model state from a background thread (the cycle never waits on fsync).

    `submit(state)` is called at a model step; only the newest pending state is
    written. `submit_adapt(state)` (after a probe) keeps the adapter's state, written
    with the model's in the same file: at once when a model state is known, else with
    the next one; a state with a number that is not finite or a covariance that is not
    one is never written (the last good one stays). Errors (full disk) are kept in
    `error` and logged, never raised.
    `close()` writes what is pending before it returns.
    """

    def __init__(
        self, path: Path, model_kind: str, inputs: list[str], outputs: list[str], params_sha256: str | None = None
    ) -> None:
        self.path = path
        self.header = {"format": FORMAT, "kind": model_kind, "inputs": inputs, "outputs": outputs}
        self.params_sha256 = params_sha256
        self.writes = 0
        self.error: str | None = None
        self._pending: dict[str, Any] | None = None
        self._last: dict[str, Any] | None = None  # the model state written last
        self._adapt: dict[str, Any] | None = None  # the adapter's newest state, with its time
        self._closing = False
        self._cv = threading.Condition()
        self._thread = ServiceThread("compd-state", self._run)
        self._thread.start()

    def submit(self, state: dict[str, Any]) -> None:
        with self._cv:
            self._pending = state
            self._cv.notify()

    def submit_adapt(self, axes: dict[str, Any]) -> None:
        """The adapter's state (Adapter.get_state()) after a probe; refused (an error event, the
        last good state kept) when an axis's part is not finite or its P not a covariance."""
        for axis, part in axes.items():
            why = state_problem(part)
            if why is not None:
                log.error(
                    "adaptation state not saved: %s: %s",
                    axis,
                    why,
                    extra={"event": "adapt_state_refused", "path": str(self.path), "reason": f"{axis}: {why}"},
                )
                return
        with self._cv:
            self._adapt = {"params_sha256": self.params_sha256, "saved_unix_s": time.time(), "axes": axes}
            if self._pending is None and self._last is not None:
                self._pending = self._last
            self._cv.notify()

    def write_now(self, state: dict[str, Any]) -> None:
        """Synchronous write."""
        data: dict[str, Any] = {**self.header, "saved_unix_s": time.time(), "state": state}
        with self._cv:
            adapt = self._adapt
            self._last = state
        if adapt is not None:
            data["adapt"] = adapt
        try:
            write_atomic(self.path, data)
            self.writes += 1
            self.error = None
        except OSError as e:
            self.error = f"state write failed: {e.strerror or e}"
            log.error(
                "%s: %s",
                self.error,
                self.path,
                extra={"event": "state_write_failed", "path": str(self.path), "reason": self.error},
            )

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
        self._thread.join(10.0)
