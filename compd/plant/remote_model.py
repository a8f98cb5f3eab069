"""Models in on purpose: a model from the command topic, validated like a reload, applied only when allowed and armed.

A shadow is installed without arming.

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
   limits, the codec or the sink, which stay the config's. Then the model must keep
   inside the guard's clamp over the readings it was fitted on (`clamp_check`): a model
   whose parameters are each within their bounds may still predict a correction no
   machine has (α and L at their limits), and the axis would sit at the clamp;
4. then the running model file is copied aside (`<file>.<UTC time>.bak`, kept), the
   candidate renamed over it, and the daemon sent SIGHUP: the reload that follows is
   the ordinary one (it validates again and, if anything fails, goes on with the old
   pipeline). The answer is `accepted`; the service of the reloaded pipeline answers
   `applied` when the model it runs is the one sent (the request waits in a small
   file next to the buffer meanwhile). If the reload did not take it (the old pipeline
   still runs `RELOAD_WAIT_S` later), the previous file is put back and the answer is
   `failed`.

A model may come as the **shadow** instead: NCMD `Node Control/Shadow` or DCMD
`Model/shadow`, the same text. A shadow drives nothing (compd/cycle/shadow.py), so it is
not armed for; what makes it the model later is `compd promote`, at the machine.
`RemoteModels.handle(text, request, "shadow")` answers it:

1. `telemetry.remote_models.allow` must be true, the text at most `max_bytes`, and the
   config's `shadow` section must name one model file (`shadow: {kind, file}`): a config
   without one, or a shadow given as inline params or as contributions, is `refused`
   (nothing to replace). The machine need not be armed. Refused before anything is
   written (`_shadow_gate`): the text the shadow file holds already, a shadow less than
   `shadow_min_interval_s` after the last one accepted (each reloads the daemon and starts
   the shadow's score on the probes afresh, the score `compd promote` wants; the last one
   is recorded beside the shadow file, `<file>.remote.json`, so the limit holds across the
   reload), and one when MAX_SHADOW_BACKUPS backups of the shadow file are kept (none is
   deleted: a backup is what a failed reload puts back);
2. checked as a reload would check it, against the shadow section: the config read again
   with the shadow pointing at the candidate; the kind must be the shadow section's, its
   axes among the running model's, the pipeline must build with it as the shadow (its
   inputs signals a source gives), and its file must not be one the active model reads
   (else sending a shadow would change what drives the machine). No clamp check: it
   drives no axis (`compd promote`, which makes it the model, applies `drive_check`, the
   model's checks, at the machine);
3. then as for a model: the shadow file copied aside (`<file>.<UTC time>.bak`), the
   candidate renamed over it, SIGHUP; `accepted`, then `applied` when the reloaded
   pipeline's shadow is the file sent, or `failed` (and the previous shadow file back).

`Model/apply` needs the config's model to be one model file too: a model given as inline
params or as contributions is `refused` (a config may allow remote models for its shadow
alone). One model (or shadow) is applied at a time; the request waiting for its reload
records which file it replaced.
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import json
import logging
import math
import numbers
import os
import shutil
import signal
import time
from collections.abc import Callable
from datetime import UTC, datetime
from glob import escape as glob_escape
from pathlib import Path
from typing import Any

import numpy as np

from compd.config import ModelSpec, load_config, resolve_model
from compd.core.errors import BadInput
from compd.cycle.pipeline import build_model
from compd.models import MODELS
from compd.plant.spec import RemoteSpec, check_config, file_sha256

log = logging.getLogger("compd.telemetry")

TARGETS = ("model", "shadow")  # what a model sent replaces: the model section's file, or the shadow section's
FORMS = {"params": "given as inline params", "contributions": "a set of contributions"}
RELOAD_WAIT_S = 30.0  # a reload that has not replaced this service by then did not take the model
MAX_REJECTED_KEPT = 5  # rejected models kept beside the model file for the engineer; more are not kept
MAX_SHADOW_BACKUPS = 10  # backups of the shadow file beside it: with this many, a shadow sent is refused


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
            self._signal_armed = (
                sig.get("quality") == "good"
                and isinstance(value, int | float)
                and not isinstance(value, bool)
                and value >= 0.5
            )
        p = self._pending
        if p is not None and time.monotonic() > p["deadline"]:
            self._pending = None
            return self._undo(p)
        return None

    def armed(self) -> bool:
        return self._signal_armed or time.monotonic() < self._armed_until

    # ---------------------------------------------------------------- a model
    def handle(self, text: str, request: str, target: str = "model") -> dict[str, Any]:
        """Validate and apply a model file's text as the model or as the shadow (`target`, see
        the module); the answer."""
        spec = self.spec
        if target not in TARGETS:
            return self._refuse(f"unknown target {target[:40]!r} (known: {', '.join(TARGETS)})", "model")
        shadow = target == "shadow"
        size = len(text.encode("utf-8"))
        if size > spec.max_bytes:
            return self._refuse(
                f"the {target} is {size} bytes, more than remote_models.max_bytes ({spec.max_bytes})", target
            )
        mfile = self._file(target)
        if isinstance(mfile, str):
            return self._refuse(mfile, target)
        if shadow and (why := _shadow_read_by_model(spec)) is not None:
            return self._refuse(why, target)  # the config's doing, not the text's: nothing written
        if not shadow and not self.armed():
            return self._refuse("not armed: arm it at the machine (compd arm-model, or the arming signal)", target)
        if self._pending is not None:
            return self._refuse("a model sent before is still being applied", target)
        if shadow and (why := self._shadow_gate(mfile, text)) is not None:
            return self._refuse(why, target)  # nothing written, nothing reloaded
        stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%S.%fZ")
        candidate = mfile.with_name(f".{mfile.name}.remote-{stamp}")
        try:
            candidate.write_text(text, encoding="utf-8")
        except OSError as e:
            return self._refuse(f"cannot write {candidate}: {e.strerror or e}", target)
        try:
            why = validate(spec, candidate, target)
        except Exception as e:  # a check that broke is a refusal, never a crash of the service
            why = f"{type(e).__name__}: {e}"
        if why is not None:
            if len(list(mfile.parent.glob(f"{glob_escape(mfile.name)}.rejected-*"))) >= MAX_REJECTED_KEPT:
                candidate.unlink(missing_ok=True)  # a peer cannot fill the disk with what it sends
                return self._refuse(
                    f"invalid {target}: {why} (not kept: {MAX_REJECTED_KEPT} rejected models are kept already)", target
                )
            kept = candidate.with_name(f"{mfile.name}.rejected-{stamp}")
            os.replace(candidate, kept)  # kept for the engineer who wants to see what came
            return self._refuse(f"invalid {target}: {why} (kept as {kept.name})", target)
        backup = mfile.with_name(f"{mfile.name}.{stamp}.bak")
        try:
            shutil.copy2(mfile, backup)
            os.replace(candidate, mfile)
        except OSError as e:
            candidate.unlink(missing_ok=True)
            return self._refuse(f"cannot replace {mfile.name}: {e.strerror or e}", target)
        sha = hashlib.sha256(text.encode("utf-8")).hexdigest()
        if not shadow:
            self._armed_until = -math.inf  # one model per arming (a shadow is not armed for)
        else:
            _write_shadow_record(mfile, request, sha)  # the next one waits for it; `compd promote` shows it
        pending = {
            "request": request,
            "target": target,
            "file": str(mfile),
            "sha256": sha,
            "backup": str(backup),
            "t_unix_s": time.time(),
        }
        try:
            spec.pending_path.write_text(json.dumps(pending), encoding="utf-8")
        except OSError as e:
            log.warning("cannot write %s: %s", spec.pending_path, e, extra={"event": "model_remote"})
        self._pending = {**pending, "deadline": time.monotonic() + RELOAD_WAIT_S}
        log.warning(
            "remote %s accepted (request %s, sha256 %s); reloading",
            target,
            request,
            sha[:12],
            extra={"event": "model_remote", "result": "accepted", "target": target, "request": request, "sha256": sha},
        )
        os.kill(spec.daemon_pid, signal.SIGHUP)
        return {
            "result": "accepted",
            "target": target,
            "reason": "validated; the daemon reloads",
            "sha256": sha,
            "backup": backup.name,
        }

    def _shadow_gate(self, mfile: Path, text: str) -> str | None:
        """Why a shadow sent is refused before it is checked (None: it is checked): the shadow file
        holds this text already (nothing would change but the score, started afresh by the reload),
        one was accepted less than `shadow_min_interval_s` ago (each reloads the daemon and starts
        the shadow's score on the probes afresh), or MAX_SHADOW_BACKUPS backups of the shadow file
        are kept already (none is deleted: a backup is what a reload that fails puts back)."""
        sha = hashlib.sha256(text.encode("utf-8")).hexdigest()
        if file_sha256(mfile) == sha:
            return (
                f"the shadow file {mfile.name} holds this text already (sha256 {sha[:12]}): nothing to reload"
                " (its score on the probes goes on)"
            )
        interval = self.spec.shadow_min_interval_s
        record = read_shadow_record(mfile)
        since = since_recorded_s(record) if record is not None and interval > 0 else None
        if record is not None and since is not None and since < interval:
            return (
                f"a shadow was accepted {since:.0f} s ago (request {str(record.get('request'))[:40]}): at most one"
                f" per remote_models.shadow_min_interval_s ({interval:g} s), since each reloads the daemon and"
                " starts the shadow's score on the probes afresh"
            )
        kept = len(list(mfile.parent.glob(f"{glob_escape(mfile.name)}.*.bak")))
        if kept >= MAX_SHADOW_BACKUPS:
            return (
                f"{kept} backups of {mfile.name} are kept beside it already (at most {MAX_SHADOW_BACKUPS}, none"
                " deleted): move them away at the machine to take another shadow"
            )
        return None

    def _file(self, target: str) -> Path | str:
        """The file a `target` sent replaces, or why there is none (a refusal)."""
        spec = self.spec
        if target == "shadow":
            if spec.shadow_form is None:
                return (
                    "the config has no shadow section: a shadow sent replaces the model file its shadow section"
                    " names (shadow: {kind, file})"
                )
            if spec.shadow_file is None:
                return (
                    f"the config's shadow is {FORMS.get(spec.shadow_form, spec.shadow_form)}: only a shadow"
                    " that is one model file (shadow: {kind, file}) can be replaced remotely"
                )
            return spec.shadow_file
        if spec.model_file is None:
            return (
                f"the config's model is {FORMS.get(spec.model_form, spec.model_form)}: Model/apply replaces"
                " a model that is one model file (model: {kind, file})"
            )
        return spec.model_file

    def started(self) -> dict[str, Any] | None:
        """At the start of a pipeline's service: the answer to a model (or shadow) a reload has now
        applied (or not), if one was waiting for it."""
        path = self.spec.pending_path
        try:
            pending = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return None
        path.unlink(missing_ok=True)
        if not isinstance(pending, dict):
            return None
        request = str(pending.get("request", ""))
        target = "shadow" if pending.get("target") == "shadow" else "model"
        running = self.spec.shadow_sha256 if target == "shadow" else self.spec.model_sha256
        if running is not None and pending.get("sha256") == running:
            self.applied += 1
            log.warning(
                "remote %s applied (request %s)",
                target,
                request,
                extra={"event": "model_remote", "result": "applied", "target": target, "request": request},
            )
            return {"request": request, "result": "applied", "target": target, "sha256": running}
        return {
            "request": request,
            "result": "failed",
            "target": target,
            "reason": f"the reloaded pipeline does not run the {target} sent (it was replaced again)",
        }

    def _undo(self, p: dict[str, Any]) -> dict[str, Any]:
        """The reload did not take the model: the previous file back (the rejected one kept)."""
        target = p.get("target", "model")
        mfile = Path(p["file"])
        stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%S.%fZ")
        try:
            shutil.copy2(mfile, mfile.with_name(f"{mfile.name}.rejected-{stamp}"))
            shutil.copy2(p["backup"], mfile)
        except OSError as e:
            log.error("cannot put %s back: %s", mfile, e, extra={"event": "model_remote"})
        self.spec.pending_path.unlink(missing_ok=True)
        log.error(
            "remote %s not applied: the reload did not take it; the previous %s file is back",
            target,
            target,
            extra={"event": "model_remote", "result": "failed", "target": target, "request": p["request"]},
        )
        return {
            "request": p["request"],
            "result": "failed",
            "target": target,
            "reason": f"the reload did not take it (see the daemon's reload_rejected line); previous {target} file"
            " back",
        }

    def _refuse(self, why: str, target: str) -> dict[str, Any]:
        self.refused += 1
        log.warning(
            "remote %s refused: %s",
            target,
            why,
            extra={"event": "model_remote", "result": "refused", "target": target, "reason": why},
        )
        return {"result": "refused", "target": target, "reason": why}


def validate(spec: RemoteSpec, candidate: Path, target: str = "model") -> str | None:
    """Why the model file `candidate` cannot replace the running model's (`target` "model") or
    the shadow's ("shadow") file (None: it can), checked as a reload would: the config read
    again with its model (or shadow) section pointing at `candidate`."""
    shadow = target == "shadow"
    try:
        cfg = load_config(spec.config)
        raw = cfg.top.shadow if shadow else cfg.top.model
        if not isinstance(raw, dict) or "contributions" in raw or raw.get("file") is None:
            return f"the config's {target} section names no model file now (it was edited since the daemon read it)"
        section = dict(raw)
        section["file"] = str(candidate)
        model = resolve_model(section, cfg.doc, (target,), Path(cfg.file).parent)
    except BadInput as e:
        return _private(str(e), spec, candidate)
    if not shadow:
        why = drive_check(cfg, model, spec.outputs)
        return None if why is None else _private(why, spec, candidate)
    lacking = [a for a in model.outputs if a not in spec.outputs]
    if lacking:
        return (
            f"its axes {model.outputs} are not among the running model's {spec.outputs} (a shadow stands"
            f" beside the model on its axes: {lacking[0]!r} is none of them)"
        )
    if (why := _shadow_read_by_model(spec, cfg)) is not None:
        return why
    try:
        check_config(dataclasses.replace(cfg, shadow=model))  # wiring, signals (opens no device)
    except BadInput as e:
        return _private(str(e), spec, candidate)
    return None  # it drives nothing: no clamp to keep inside


def drive_check(cfg: Any, model: Any, outputs: list[str]) -> str | None:
    """Why the resolved `model` (a compd.config.ModelSpec, its kind's parameter bounds checked when
    it was read) cannot drive the machine of `cfg` (None: it can): what a model sent to be applied
    (Model/apply) and a shadow made the model (`compd promote`) must both pass. Its axes must be
    `outputs` (the running model's, in order: the word's bytes follow them), the pipeline must
    build with it as the model (wiring, signals; opens no device), and it must keep inside the
    guard's clamp over the readings it was fitted on (`clamp_check`)."""
    if list(model.outputs) != list(outputs):
        return f"its axes {model.outputs} are not the running model's {list(outputs)}"
    try:
        check_config(dataclasses.replace(cfg, model=model))
    except BadInput as e:
        return str(e)
    return clamp_check(model, cfg.top.guard)


# --- a shadow sent from the plant: when it was accepted, and which one ----------------------------


def shadow_record_path(shadow_file: str | Path) -> Path:
    """The record of the last shadow the plant sent for `shadow_file`, beside it (one file, replaced
    by the next): its request, sha256 and when it was accepted."""
    path = Path(shadow_file)
    return path.with_name(f"{path.name}.remote.json")


def read_shadow_record(shadow_file: str | Path) -> dict[str, Any] | None:
    """The record of the last shadow sent for `shadow_file` (None: none, or not a record)."""
    try:
        data = json.loads(shadow_record_path(shadow_file).read_text(encoding="utf-8")[:4096])
    except (OSError, ValueError):
        return None
    if not isinstance(data, dict) or not isinstance(data.get("sha256"), str):
        return None
    return data


def since_recorded_s(record: dict[str, Any]) -> float | None:
    """How long ago a record was written (s): on the monotonic clock while the machine has not
    restarted since (its boot id), else on the wall clock; None when unknown (a wall clock that went
    back, a record without a time)."""
    boot, mono = _boot_id(), record.get("monotonic_s")
    if boot and record.get("boot_id") == boot and _real(mono):
        return max(time.monotonic() - float(mono), 0.0)
    t = record.get("t_unix_s")
    if not _real(t):
        return None
    since = time.time() - float(t)
    return since if since >= 0 else None


def _real(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def _boot_id() -> str:
    try:
        return Path("/proc/sys/kernel/random/boot_id").read_text(encoding="ascii").strip()
    except OSError:
        return ""


def _write_shadow_record(shadow_file: Path, request: str, sha256: str) -> None:
    now = time.time()
    record = {
        "request": request,
        "sha256": sha256,
        "file": shadow_file.name,
        "accepted_utc": datetime.fromtimestamp(now, UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "t_unix_s": now,
        "monotonic_s": time.monotonic(),
        "boot_id": _boot_id(),
    }
    path = shadow_record_path(shadow_file)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        tmp.write_text(json.dumps(record), encoding="utf-8")
        os.replace(tmp, path)
    except OSError as e:
        log.warning("cannot write %s: %s", path, e.strerror or e, extra={"event": "model_remote"})


def model_files(spec: Any) -> list[str]:
    """The model files a resolved model (compd.config.ModelSpec) reads: its own, or its contributions'."""
    files = [spec.file] if spec.file else []
    files += [p.file for p in getattr(spec.params, "contributions", None) or () if getattr(p, "file", None)]
    return files


def _shadow_read_by_model(spec: RemoteSpec, cfg: Any = None) -> str | None:
    """Why the shadow's file cannot be replaced without arming: the active model (of `cfg`, else of
    the config read now) reads it too; None when it does not (or the config cannot be read: the
    check as a reload would check it says why)."""
    if spec.shadow_file is None:
        return None
    if cfg is None:
        try:
            cfg = load_config(spec.config)
        except BadInput:
            return None
    if not any(_same_file(spec.shadow_file, f) for f in model_files(cfg.model)):
        return None
    return (
        f"the shadow's file {spec.shadow_file.name} is one the active model reads: replacing it would change what"
        " drives the machine (give the shadow a file of its own, or send the model with Model/apply, armed)"
    )


def _same_file(a: Path, b: str | Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return Path(a).resolve() == Path(b).resolve()


# --- the model against the guard's clamp, over the readings it was fitted on ---------------------

FIT_RANGE_KEY = "input_range"  # fit.input_range: {input: [min, max]}, the readings of the fit's log
HORIZON_S = 8 * 3600.0  # a model that evolves in time holds its readings this long: a shift
MAX_STEPS = 2000  # ... in at most this many steps (its update period, else a minute, apart)
MAX_COMBINATIONS = 4096  # more (reference, reading) combinations than this: a coordinate search
MAX_ROWS = 1_000_000  # ... or more model rows than this in all (a second or two on the service's thread)
POSITION_POINTS = 11  # a position input is tried at this many points along its range


def input_ranges(model: Any, guard: Any) -> tuple[dict[str, tuple[float, float]], str] | str:
    """Per model input the (min, max) its predictions are checked over, and where they come from;
    or why there are none (a refusal).

    The model file's `fit.input_range` (the range of each input in the log it was fitted on),
    checked: a mapping of every input to [min, max], finite, min ≤ max. Without it, each input's
    plausibility limits (`guard.signals.<input>` min and max: the readings the guard lets through);
    an input without either cannot be bounded, and the model is refused rather than applied
    unchecked."""
    fit = model.fit if isinstance(model.fit, dict) else {}
    raw = fit.get(FIT_RANGE_KEY)
    inputs = list(model.inputs)
    if raw is not None:
        where = f"its fit.{FIT_RANGE_KEY}"
        if not isinstance(raw, dict):
            return f"{where} is not a mapping of each input to [min, max]"
        extra = sorted(str(k) for k in raw if k not in inputs)
        if extra:
            return f"{where} names {extra[0][:60]!r}, which is not one of its inputs"
        out: dict[str, tuple[float, float]] = {}
        for name in inputs:
            pair = raw.get(name)
            if (
                not isinstance(pair, list | tuple)
                or len(pair) != 2
                or not all(isinstance(v, numbers.Real) and not isinstance(v, bool) for v in pair)
                or not all(math.isfinite(float(v)) for v in pair)
            ):
                return f"{where}.{name} is not [min, max] (two finite numbers)"
            lo, hi = float(pair[0]), float(pair[1])
            if lo > hi:
                return f"{where}.{name}: min {lo:g} is above max {hi:g}"
            out[name] = (lo, hi)
        return out, f"fit.{FIT_RANGE_KEY}"
    missing = [name for name in inputs if name not in guard.signals]
    if missing:
        return (
            f"the model file records no fit range (fit.{FIT_RANGE_KEY}) and guard.signals gives no limits for"
            f" {missing[0]}: what it predicts there is unbounded, so it is not applied unchecked (give the"
            f" model file fit.{FIT_RANGE_KEY}, or guard.signals.{missing[0]} min and max)"
        )
    return {name: (float(guard.signals[name].min), float(guard.signals[name].max)) for name in inputs}, "guard.signals"


def clamp_check(model: Any, guard: Any) -> str | None:
    """Why the model (a compd.config.ModelSpec) would drive an axis into the guard's clamp (None: it
    would not): anywhere over its input ranges (`input_ranges`), with the reference readings at
    start anywhere in them too, a predicted |correction| above that axis's clamp
    (`guard.axes.<axis>.max_abs_um`, else `guard.max_abs_um`), or one that is not finite.

    Tried: every input's (reference, reading) at the ends of its range — (min, max), (max, min),
    (min, min), (max, max) —, a position input at POSITION_POINTS points along it, in every
    combination (up to MAX_COMBINATIONS and MAX_ROWS model rows; beyond, a coordinate search per
    axis and sign, which is exact for the kinds linear in their inputs: lvr, mlr). A model that
    evolves in time (ar1, the analytic feed_axis) holds the readings for HORIZON_S; the others are
    evaluated once. The model is evaluated as the loop runs it (Model.predict_rows: the input
    lead's transient left out).

    A sum of contributions: each contribution on its own, over its own file's fit.input_range
    (else the guard's signal limits), against its own clamp (its `max_abs_um`, which defaults to
    its axis's): a contribution that sits at its clamp is as absurd as a model at the guard's."""
    parts = getattr(model.params, "contributions", None)
    if parts is None:
        return _clamp_check(model, guard, guard.clamp_um, "", "the guard's")
    for p in parts:
        cls = MODELS.get(p.kind)
        spec = ModelSpec(
            cls,
            cls.Params.model_validate(p.params),
            list(p.inputs),
            list(p.outputs),
            p.update_period_s,
            dict(p.fit),
            None,
            (),
            p.file,
        )  # type: ignore[arg-type]
        lims = dict(zip(p.outputs, p.max_abs_um, strict=True))
        why = _clamp_check(
            spec,
            guard,
            lambda axis, lims=lims, p=p: (lims[axis], f"contribution {p.name}'s max_abs_um"),
            f"contribution {p.name!r}: ",
            "its",
        )
        if why is not None:
            return why
    return None


def _clamp_check(
    model: Any, guard: Any, clamp_um: Callable[[str], tuple[float, str]], who: str, whose: str
) -> str | None:
    """`clamp_check` of one model against the clamp `clamp_um(axis)` gives (the limit, its key)."""
    got = input_ranges(model, guard)
    if isinstance(got, str):
        return who + got
    ranges, source = got
    peaks = largest_predictions(model, ranges)
    for axis, (peak_um, reference, reading) in zip(model.outputs, peaks, strict=True):
        lim, key = clamp_um(axis)
        at = _where(model.inputs, reference, reading)
        if not math.isfinite(peak_um):
            return (
                f"{who}axis {axis}: over its input range ({source}) the model predicts a value that is not finite"
                f" ({at})"
            )
        if abs(peak_um) > lim:
            return (
                f"{who}axis {axis} would sit at {whose} clamp: over its input range ({source}) the model predicts"
                f" a |correction| of {abs(peak_um):.1f} µm ({at}), beyond {key} {lim:g} µm"
            )
    return None


def _where(inputs: list[str], reference: np.ndarray, reading: np.ndarray) -> str:
    parts = []
    for name, r0, r in zip(inputs, reference, reading, strict=True):
        parts.append(f"{name} {r:.6g}" + (f" from {r0:.6g} at start" if r0 != r else ""))
    return "at " + ", ".join(parts)


def _dynamic(model: Any) -> bool:
    """Whether the model's prediction moves while its readings hold (an ar1 recursion, the analytic
    feed-axis heating), so that a step of readings must be held to see where it goes."""
    return model.update_period_s > 0 or (model.kind == "feed_axis" and not model.field_form)


def largest_predictions(
    spec: Any, ranges: dict[str, tuple[float, float]]
) -> list[tuple[float, np.ndarray, np.ndarray]]:
    """Per output axis the prediction (µm) of largest magnitude over the ranges (`clamp_check`),
    with the reference readings and the readings it comes at; NaN or ±inf wins over any number."""

    def fresh() -> Any:
        return build_model(spec)  # a model as the loop builds it, fresh for each combination

    probe = fresh()
    roles = list(getattr(spec.params, "input_roles", None) or [])
    cands: list[list[tuple[float, float]]] = []
    for i, name in enumerate(spec.inputs):
        lo, hi = ranges[name]
        if i < len(roles) and roles[i] == "position":
            cands.append([(float(v), float(v)) for v in np.linspace(lo, hi, POSITION_POINTS)])
        elif lo == hi:
            cands.append([(lo, lo)])
        else:
            cands.append([(lo, hi), (hi, lo), (lo, lo), (hi, hi)])
    if _dynamic(probe):
        step_s = probe.update_period_s if probe.update_period_s > 0 else 60.0
        n = int(min(MAX_STEPS, math.ceil(HORIZON_S / step_s)))
        t_s = np.arange(n + 1, dtype=float) * step_s
    else:
        n, t_s = 1, np.array([0.0, 1.0])
    seen: dict[tuple[int, ...], np.ndarray] = {}

    def run(choice: tuple[int, ...]) -> np.ndarray:
        """The predictions (rows × axes) of one combination: started on the references, then the readings."""
        if choice not in seen:
            pairs = [c[k] for c, k in zip(cands, choice, strict=True)]
            X = np.empty((n + 1, len(pairs)))
            X[0] = [a for a, _ in pairs]
            X[1:] = [b for _, b in pairs]
            with np.errstate(all="ignore"):
                seen[choice] = np.asarray(fresh().predict_rows(X, t_s), dtype=float)
        return seen[choice]

    def score(choice: tuple[int, ...], axis: int, sign: float) -> float:
        col = run(choice)[:, axis]
        return math.inf if not np.isfinite(col).all() else float(np.max(sign * col))

    total = math.prod(len(c) for c in cands)
    best: list[tuple[float, tuple[int, ...]]] = [(-math.inf, ())] * len(spec.outputs)
    if total <= MAX_COMBINATIONS and total * (n + 1) <= MAX_ROWS:
        for choice in itertools.product(*(range(len(c)) for c in cands)):
            for a in range(len(spec.outputs)):
                v = max(score(choice, a, 1.0), score(choice, a, -1.0))
                if v > best[a][0]:
                    best[a] = (v, choice)
    else:
        for a in range(len(spec.outputs)):
            for sign in (1.0, -1.0):
                v, choice = _coordinate_search(lambda c, a=a, sign=sign: score(c, a, sign), [len(c) for c in cands])
                if v > best[a][0]:
                    best[a] = (v, choice)
    out = []
    for a, (_, choice) in enumerate(best):
        col = run(choice)[:, a]
        bad = ~np.isfinite(col)
        row = int(np.argmax(bad)) if bad.any() else int(np.argmax(np.abs(col)))
        pairs = [c[k] for c, k in zip(cands, choice, strict=True)]
        reference = np.array([p for p, _ in pairs])
        # the first row is the start itself: its readings are the references
        out.append((float(col[row]), reference, reference.copy() if row == 0 else np.array([r for _, r in pairs])))
    return out


def _coordinate_search(score: Callable[[tuple[int, ...]], float], sizes: list[int]) -> tuple[float, tuple[int, ...]]:
    """The largest `score` over the combinations of one choice per input (sizes[i] each), by changing
    one input's choice at a time while that raises it, from every input at its first and at its
    second choice: exact when the score is a sum of one term per input (a linear model)."""
    best_v, best_c = -math.inf, tuple(0 for _ in sizes)
    for start in {tuple(0 for _ in sizes), tuple(min(1, n - 1) for n in sizes)}:
        choice, v = start, score(start)
        for _ in range(50):  # sweeps; each one raises the score or ends the search
            better = False
            for i, n in enumerate(sizes):
                for k in range(n):
                    if k != choice[i]:
                        trial = (*choice[:i], k, *choice[i + 1 :])
                        tv = score(trial)
                        if tv > v:
                            choice, v, better = trial, tv, True
            if not better:
                break
        if v > best_v:
            best_v, best_c = v, choice
    return best_v, best_c


def _private(text: str, spec: RemoteSpec, candidate: Path) -> str:
    """A refusal as the plant sees it: the model sent by that name, the machine's files by
    their names only (no folder of this host goes out over MQTT)."""
    text = text.replace(str(candidate), "the model sent")
    for path in (Path(spec.config).resolve(), Path(spec.config), spec.model_file, spec.shadow_file):
        if path is not None:
            text = text.replace(str(path), path.name)
    return text


__all__ = [
    "TARGETS",
    "RemoteModels",
    "clamp_check",
    "drive_check",
    "input_ranges",
    "largest_predictions",
    "model_files",
    "read_shadow_record",
    "shadow_record_path",
    "since_recorded_s",
    "validate",
]
