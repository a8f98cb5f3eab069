"""Models in on purpose: a model from the command topic, validated like a reload, applied only when allowed and armed.

A refitted model reaches a machine as the text of a model file (the YAML `compd fit`
writes) in an NCMD `Node Control/Model` or DCMD `Model/apply` metric
(compd/plant/telemetry.py). `RemoteModels.handle` answers it:

1. `telemetry.remote_models.allow` must be true (else `refused`), the text at most
   `max_bytes`;
2. the machine must be armed: by `compd arm-model` (for `arm_window_s`, for one model)
   or while the `arm_signal` (a PMC/NC bit a source reads) is ≥ 0.5 with good quality;
3. the text is checked as a reload would check it: the config is read again with the
   model section pointing at the candidate; the kind must be the config's, the axes
   (outputs) the running model's, and the pipeline must build. A model file holds
   kind, inputs, outputs, params and fit only: nothing in it can touch the guard's
   limits, the codec or the sink, which stay the config's;
4. then the running model file is copied aside (`<file>.<UTC time>.bak`, kept), the
   candidate renamed over it, and the daemon sent SIGHUP: the reload that follows is
   the ordinary one (it validates again and, if anything fails, goes on with the old
   pipeline). The answer is `accepted`; the service of the reloaded pipeline answers
   `applied` when the model it runs is the one sent (the request waits in a small
   file next to the buffer meanwhile). If the reload did not take it (the old pipeline
   still runs `RELOAD_WAIT_S` later), the previous file is put back and the answer is
   `failed`.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import math
import os
import shutil
import signal
import time
from datetime import UTC, datetime
from glob import escape as glob_escape
from pathlib import Path
from typing import Any

from compd.errors import BadInput
from compd.plant.spec import RemoteSpec

log = logging.getLogger("compd.telemetry")

RELOAD_WAIT_S = 30.0  # a reload that has not replaced this service by then did not take the model
MAX_REJECTED_KEPT = 5  # rejected models kept beside the model file for the engineer; more are not kept


class RemoteModels:
    """The remote model handler of one pipeline's service (see the module)."""

    def __init__(self, spec: RemoteSpec) -> None:
        self.spec = spec
        self._armed_until = -math.inf  # monotonic time `compd arm-model` arms until
        self._signal_armed = False
        self._pending: dict[str, Any] | None = None  # a model this service sent into a reload
        self.applied = 0
        self.refused = 0

    # ---------------------------------------------------------------- arming
    def arm(self, window_s: float | None = None) -> dict[str, Any]:
        """`compd arm-model`: armed for `window_s` (default `arm_window_s`), for one model."""
        window = self.spec.arm_window_s if window_s is None else float(window_s)
        if not (math.isfinite(window) and 0 < window <= 86400):
            return {"ok": False, "error": f"window_s must be in (0, 86400], got {window_s!r}"}
        self._armed_until = time.monotonic() + window
        log.warning("remote model armed for %.0f s", window, extra={"event": "model_armed", "window_s": window})
        return {"ok": True, "armed_s": window, "pid": self.spec.daemon_pid}

    def observe(self, snap: dict[str, Any]) -> dict[str, Any] | None:
        """A status snapshot: the arming signal's value; a late answer for a reload that did not
        take the model (the request, or None)."""
        name = self.spec.arm_signal
        if name is not None:
            sig = (snap.get("signals") or {}).get(name) or {}
            value = sig.get("value")
            self._signal_armed = (sig.get("quality") == "good" and isinstance(value, int | float)
                                  and not isinstance(value, bool) and value >= 0.5)
        p = self._pending
        if p is not None and time.monotonic() > p["deadline"]:
            self._pending = None
            return self._undo(p)
        return None

    def armed(self) -> bool:
        return self._signal_armed or time.monotonic() < self._armed_until

    # ---------------------------------------------------------------- a model
    def handle(self, text: str, request: str) -> dict[str, Any]:
        """Validate and apply a model file's text (see the module); the answer."""
        spec = self.spec
        size = len(text.encode("utf-8"))
        if size > spec.max_bytes:
            return self._refuse(f"the model is {size} bytes, more than remote_models.max_bytes ({spec.max_bytes})")
        if not self.armed():
            return self._refuse("not armed: arm it at the machine (compd arm-model, or the arming signal)")
        if self._pending is not None:
            return self._refuse("a model sent before is still being applied")
        mfile = spec.model_file
        stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%S.%fZ")
        candidate = mfile.with_name(f".{mfile.name}.remote-{stamp}")
        try:
            candidate.write_text(text, encoding="utf-8")
        except OSError as e:
            return self._refuse(f"cannot write {candidate}: {e.strerror or e}")
        try:
            why = validate(spec, candidate)
        except Exception as e:  # a check that broke is a refusal, never a crash of the service
            why = f"{type(e).__name__}: {e}"
        if why is not None:
            if len(list(mfile.parent.glob(f"{glob_escape(mfile.name)}.rejected-*"))) >= MAX_REJECTED_KEPT:
                candidate.unlink(missing_ok=True)  # a peer cannot fill the disk with what it sends
                return self._refuse(f"invalid model: {why} (not kept: {MAX_REJECTED_KEPT} rejected models are"
                                    " kept already)")
            kept = candidate.with_name(f"{mfile.name}.rejected-{stamp}")
            os.replace(candidate, kept)  # kept for the engineer who wants to see what came
            return self._refuse(f"invalid model: {why} (kept as {kept.name})")
        backup = mfile.with_name(f"{mfile.name}.{stamp}.bak")
        try:
            shutil.copy2(mfile, backup)
            os.replace(candidate, mfile)
        except OSError as e:
            return self._refuse(f"cannot replace {mfile}: {e.strerror or e}")
        sha = hashlib.sha256(text.encode("utf-8")).hexdigest()
        self._armed_until = -math.inf  # one model per arming
        pending = {"request": request, "sha256": sha, "backup": str(backup), "t_unix_s": time.time()}
        try:
            spec.pending_path.write_text(json.dumps(pending), encoding="utf-8")
        except OSError as e:
            log.warning("cannot write %s: %s", spec.pending_path, e, extra={"event": "model_remote"})
        self._pending = {**pending, "deadline": time.monotonic() + RELOAD_WAIT_S}
        log.warning("remote model accepted (request %s, sha256 %s); reloading", request, sha[:12],
                    extra={"event": "model_remote", "result": "accepted", "request": request, "sha256": sha})
        os.kill(spec.daemon_pid, signal.SIGHUP)
        return {"result": "accepted", "reason": "validated; the daemon reloads", "sha256": sha,
                "backup": backup.name}

    def started(self) -> dict[str, Any] | None:
        """At the start of a pipeline's service: the answer to a model a reload has now applied
        (or not), if one was waiting for it."""
        path = self.spec.pending_path
        try:
            pending = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return None
        path.unlink(missing_ok=True)
        if not isinstance(pending, dict):
            return None
        request = str(pending.get("request", ""))
        if pending.get("sha256") == self.spec.model_sha256:
            self.applied += 1
            log.warning("remote model applied (request %s)", request,
                        extra={"event": "model_remote", "result": "applied", "request": request})
            return {"request": request, "result": "applied", "sha256": self.spec.model_sha256}
        return {"request": request, "result": "failed",
                "reason": "the reloaded pipeline does not run the model sent (it was replaced again)"}

    def _undo(self, p: dict[str, Any]) -> dict[str, Any]:
        """The reload did not take the model: the previous file back (the rejected one kept)."""
        mfile = self.spec.model_file
        stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%S.%fZ")
        try:
            shutil.copy2(mfile, mfile.with_name(f"{mfile.name}.rejected-{stamp}"))
            shutil.copy2(p["backup"], mfile)
        except OSError as e:
            log.error("cannot put %s back: %s", mfile, e, extra={"event": "model_remote"})
        self.spec.pending_path.unlink(missing_ok=True)
        log.error("remote model not applied: the reload did not take it; the previous model file is back",
                  extra={"event": "model_remote", "result": "failed", "request": p["request"]})
        return {"request": p["request"], "result": "failed",
                "reason": "the reload did not take it (see the daemon's reload_rejected line); previous model file back"}

    def _refuse(self, why: str) -> dict[str, Any]:
        self.refused += 1
        log.warning("remote model refused: %s", why, extra={"event": "model_remote", "result": "refused",
                                                             "reason": why})
        return {"result": "refused", "reason": why}


def validate(spec: RemoteSpec, candidate: Path) -> str | None:
    """Why the model file `candidate` cannot replace the running one (None: it can), checked as
    a reload would: the config read again with its model section pointing at `candidate`."""
    from compd.config import load_config, resolve_model
    from compd.cycle import pipeline

    try:
        cfg = load_config(spec.config)
        section = dict(cfg.top.model)
        section["file"] = str(candidate)
        model = resolve_model(section, cfg.doc, ("model",), Path(cfg.file).parent)
    except BadInput as e:
        return _private(str(e), spec, candidate)
    if list(model.outputs) != list(spec.outputs):
        return f"its axes {model.outputs} are not the running model's {spec.outputs}"
    try:
        pipeline.check(dataclasses.replace(cfg, model=model))  # wiring, signals (opens no device)
    except BadInput as e:
        return _private(str(e), spec, candidate)
    return None


def _private(text: str, spec: RemoteSpec, candidate: Path) -> str:
    """A refusal as the plant sees it: the model sent by that name, the machine's files by
    their names only (no folder of this host goes out over MQTT)."""
    text = text.replace(str(candidate), "the model sent")
    for path in (Path(spec.config).resolve(), Path(spec.config), spec.model_file):
        text = text.replace(str(path), path.name)
    return text


__all__ = ["RemoteModels", "validate"]
