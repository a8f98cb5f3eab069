"""`compd promote CONFIG`: the shadow model becomes the model, through the ordinary validated reload.

The config's text is edited, not rewritten: the `shadow` section's lines become the `model`
section (where `model` stood), and the old `model` section stays in the file as comment
lines under a header naming the date, so the file keeps its comments and order and the
previous model is one uncomment away. The new text must load and build as `compd
check-config` would check it before anything is written; the file as it was is kept beside
it (`<config>.<UTC stamp>.bak`), then the new text replaces it atomically. A daemon running
this config (its status file names its pid) is sent SIGHUP: its reload validates the file
again and, if anything fails, goes on with the old pipeline; `promote` waits until the
status shows the promoted model, and says so, or that the reload did not take it.

A shadow the running daemon has scored worse than the active model on the probes is not
promoted without `--force`.
"""

from __future__ import annotations

import os
import shutil
import signal
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import yaml

from compd.errors import BadInput


def _top_blocks(text: str, file: str) -> dict[str, tuple[int, int]]:
    """Each top-level key's line span [first, end) in `text` (0-based): from its key's line to the
    next top-level key's (comment lines just above that key go with it)."""
    try:
        node = yaml.compose(text)
    except yaml.YAMLError as e:
        raise BadInput(f"not YAML: {e}", file=file) from None
    if not isinstance(node, yaml.MappingNode) or node.flow_style:
        raise BadInput("promote edits a config written as a block mapping (one top-level key per line)", file=file)
    lines = text.splitlines(keepends=True)
    starts = [(k.value, k.start_mark.line) for k, _ in node.value]
    out: dict[str, tuple[int, int]] = {}
    for i, (key, first) in enumerate(starts):
        if lines[first][:1] in (" ", "\t") or not lines[first].startswith(str(key)):
            raise BadInput(f"top-level key {key!r} does not start its line", file=file, path=(str(key),))
        end = starts[i + 1][1] if i + 1 < len(starts) else len(lines)
        while end - 1 > first and lines[end - 1].lstrip().startswith("#"):
            end -= 1  # a comment above the next key belongs to it
        out[str(key)] = (first, end)
    return out


def promoted_text(text: str, file: str, stamp: str) -> str:
    """The config's text with its shadow section made the model (see the module)."""
    blocks = _top_blocks(text, file)
    if "shadow" not in blocks:
        raise BadInput("the config has no shadow section: nothing to promote", file=file, path="shadow")
    if "model" not in blocks:
        raise BadInput("the config has no model section", file=file, path="model")
    lines = text.splitlines(keepends=True)
    if lines and not lines[-1].endswith("\n"):
        lines[-1] += "\n"
    m0, m1 = blocks["model"]
    s0, s1 = blocks["shadow"]
    shadow = list(lines[s0:s1])
    shadow[0] = "model" + shadow[0][len("shadow"):]
    old = [f"# model before `compd promote` of {stamp} (the shadow became the model):\n"]
    old += [f"# {ln}" if ln.strip() else "#\n" for ln in lines[m0:m1]]
    new_model = old + shadow
    out: list[str] = []
    for i, ln in enumerate(lines):
        if i == m0:
            out += new_model
        if m0 <= i < m1 or s0 <= i < s1:
            continue
        out.append(ln)
    return "".join(out)


def scored_worse(status: dict[str, Any]) -> list[str]:
    """The axes on which a running daemon's shadow left a larger RMS than the active model on the probes."""
    axes = ((status.get("shadow") or {}).get("axes")) or {}
    worse = []
    for axis, sc in axes.items():
        a, s = sc.get("active_rms_um"), sc.get("shadow_rms_um")
        if sc.get("probes") and isinstance(a, int | float) and isinstance(s, int | float) and s > a:
            worse.append(f"{axis}: shadow {s:.2f} um vs active {a:.2f} um over {sc['probes']} probes")
    return worse


def promote(config: str | Path, *, force: bool = False, reload: bool = True, wait_s: float = 60.0,
            dry_run: bool = False) -> dict[str, Any]:
    """Promote the config's shadow (see the module); what was done, for the command to print."""
    from compd.config import load_config
    from compd.cycle import pipeline
    from compd.service.host import daemon_status_path
    from compd.service.status import liveness, read_status

    path = Path(config)
    cfg = load_config(path)  # the file as it is must be valid, with a shadow
    if cfg.shadow is None:
        raise BadInput("the config has no shadow section: nothing to promote", file=str(path), path="shadow")
    status_path = daemon_status_path(cfg)
    status: dict[str, Any] | None = None
    if status_path is not None and Path(status_path).exists():
        try:
            data = read_status(str(status_path))
            alive, _ = liveness(data)
            status = data if alive else None
        except BadInput:
            status = None
    if status is not None and not force:
        worse = scored_worse(status)
        if worse:
            raise BadInput("the running daemon scored the shadow worse than the active model on the probes ("
                           + "; ".join(worse) + "): give --force to promote it anyway", file=str(path), path="shadow")
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
    text = path.read_text(encoding="utf-8")
    new = promoted_text(text, str(path), stamp)
    new_cfg = load_config(path, text=new)  # what check-config checks, on the new text
    pipeline.check(new_cfg)
    result: dict[str, Any] = {"config": str(path), "model": new_cfg.model.cls.kind,
                              "model_file": new_cfg.model.file, "text": new}
    if dry_run:
        return result
    backup = path.with_name(f"{path.name}.{stamp}.bak")
    shutil.copy2(path, backup)
    tmp = path.with_name(f".{path.name}.promote-{stamp}")
    tmp.write_text(new, encoding="utf-8")
    shutil.copymode(path, tmp)
    os.replace(tmp, path)
    result["backup"] = str(backup)
    result["reloaded"] = None
    if reload and status is not None:
        pid = int(status.get("pid") or 0)
        before = status.get("written_unix_s")
        os.kill(pid, signal.SIGHUP)
        result["pid"] = pid
        result["reloaded"] = _wait_reloaded(str(status_path), new_cfg, before, wait_s)
    return result


def _wait_reloaded(status_path: str, cfg: Any, before: Any, wait_s: float) -> bool:
    """Whether the daemon's status shows the promoted model (its kind and file, and no shadow) within `wait_s`."""
    from compd.service.status import read_status

    want_kind, want_file = cfg.model.cls.kind, cfg.model.file
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline:
        try:
            data = read_status(status_path)
        except BadInput:
            data = {}
        model = data.get("model") or {}
        if (data.get("written_unix_s") != before and model.get("kind") == want_kind
                and model.get("file") == want_file and data.get("shadow") is None):
            return True
        time.sleep(0.2)
    return False
