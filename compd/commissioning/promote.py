"""`compd promote CONFIG`: the shadow model becomes the model, through the ordinary validated reload.

It is checked as a model sent from the plant is.

The config's text is edited, not rewritten: the `shadow` section's lines become the `model`
section (where `model` stood), and the old `model` section stays in the file as comment
lines under a header naming the date, so the file keeps its comments and order and the
previous model is one uncomment away.

Before anything is written it says what it is about to make the model (`describe`): the
shadow's kind, file and sha256, where it came from (its fit block; the plant's request that
sent it, when one did) and, from the running daemon's status, what it and the active model
predict now. Then the new text must pass what a model sent to be applied (Model/apply,
compd/plant/remote_model.py) must: it loads and builds as `compd check-config` checks it
(the kind's parameter bounds), its axes are the model's, and it keeps inside the guard's
clamp over the readings it was fitted on (`drive_check`). A shadow drives nothing, so it
arrives without arming: this is where it is checked as strictly as one that drives.

The score is the other check (`score_refusal`): every axis the shadow serves must have been
scored on at least `min_probes` probes by the daemon running this config, on this very
shadow (the status's `shadow.model.sha256` is the config's shadow's), and the shadow must
not have left the larger RMS. A shadow sent again from the plant reloads the daemon and
starts its score afresh, so a peer cannot promote a shadow by resetting its score. No
daemon, no status, or a score of another shadow is no score. `--force` promotes anyway
(never past the clamp).

The file as it was is kept beside it (`<config>.<UTC stamp>.bak`), then the new text
replaces it atomically and the daemon running this config (its status file names its pid)
is sent SIGHUP: its reload validates the file again and, if anything fails, goes on with
the old pipeline. `promote` waits until the status shows the promoted model. If it does not
within the wait, the file is put back as it was (byte for byte: a reboot must not start a
config the daemon refused), the promoted text is kept as
`<config>.promoted-rejected-<stamp>`, and the daemon is asked to reload once more, so that
what it runs is what the file says even if its reload was merely slow.
"""

from __future__ import annotations

import contextlib
import math
import os
import shutil
import signal
import time
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import yaml

from compd.config import Config, load_config, model_sha256
from compd.core.errors import BadInput
from compd.plant.remote_model import drive_check, read_shadow_record
from compd.plant.spec import check_config
from compd.service.status import daemon_status_path, liveness, read_status

MIN_PROBES = 3  # probes per axis the daemon must have scored the shadow on (`--min-probes`)


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
    shadow[0] = "model" + shadow[0][len("shadow") :]
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


def _real(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def _score_of(status: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """The status's `shadow.axes`: per axis its score (only mappings kept: the file's shape is checked)."""
    shadow = status.get("shadow")
    axes = shadow.get("axes") if isinstance(shadow, dict) else None
    if not isinstance(axes, dict):
        return {}
    return {str(a): sc for a, sc in axes.items() if isinstance(sc, dict)}


def scored_worse(status: dict[str, Any]) -> list[str]:
    """The axes on which a running daemon's shadow left a larger RMS than the active model on the probes."""
    worse = []
    for axis, sc in _score_of(status).items():
        a, s, n = sc.get("active_rms_um"), sc.get("shadow_rms_um"), sc.get("probes")
        if _real(n) and n > 0 and _real(a) and _real(s) and s > a:
            worse.append(f"{axis}: shadow {s:.2f} um vs active {a:.2f} um over {n} probes")
    return worse


def score_refusal(status: dict[str, Any] | None, shadow_sha256: str, axes: list[str], min_probes: int) -> str | None:
    """Why the daemon's score does not let the shadow be promoted (None: it does): no running daemon
    (no score), a daemon running no shadow or another one (the sha256 in its status is not
    `shadow_sha256`), fewer than `min_probes` scored probes on one of `axes`, or a larger RMS than
    the active model's on one."""
    if status is None:
        return "no daemon runs this config, so the shadow has no score on the probes"
    running = status.get("shadow")
    model = running.get("model") if isinstance(running, dict) else None
    if not isinstance(model, dict):
        return "the running daemon runs no shadow (it has not reloaded this config's shadow section): no score"
    if model.get("sha256") != shadow_sha256:
        got = model.get("sha256")
        return (
            f"the running daemon's score is of another shadow (sha256 {str(got)[:12] if got else 'not shown'},"
            f" the config's is {shadow_sha256[:12]}): a score of another shadow is no score"
        )
    scores = _score_of(status)
    few = []
    for axis in axes:
        n = scores.get(axis, {}).get("probes")
        n = int(n) if _real(n) else 0
        if n < min_probes:
            few.append(f"{axis} {n}")
    if few:
        return (
            f"the shadow was scored on too few probes ({', '.join(few)}; at least {min_probes} per axis,"
            " --min-probes): a shadow sent again from the plant starts its score afresh"
        )
    worse = scored_worse(status)
    if worse:
        return (
            "the running daemon scored the shadow worse than the active model on the probes (" + "; ".join(worse) + ")"
        )
    return None


def _daemon_status(cfg: Config) -> tuple[Path | None, dict[str, Any] | None]:
    """The status file of the daemon running `cfg`, and its record when that daemon runs (else None)."""
    status_path = daemon_status_path(cfg)
    if status_path is None or not Path(status_path).exists():
        return status_path, None
    try:
        data = read_status(str(status_path))
    except BadInput:
        return status_path, None
    alive, _ = liveness(data)
    return status_path, data if alive else None


def _origin(fit: Any) -> str:
    """Where a model file came from, by its fit block: when and on what log it was fitted."""
    fit = fit if isinstance(fit, dict) else {}
    when, log = fit.get("fitted_at"), fit.get("log")
    if not when and not log:
        return "its file has no fit block (fitted_at, log)"
    return "fitted" + (f" {str(when)[:40]}" if when else "") + (f" on {str(log)[:120]}" if log else "")


def describe(cfg: Config, status: dict[str, Any] | None, shadow_sha256: str) -> list[str]:
    """What `promote` is about to make the model, a line each: the shadow's kind, file and sha256,
    where it came from, and what it and the active model predict now (the running daemon's status)."""
    spec = cfg.shadow
    assert spec is not None  # `promote` refuses a config without a shadow before it describes one
    kind = spec.kind
    parts = getattr(spec.params, "contributions", None)
    if spec.file is not None:
        what = f"{kind}, file {spec.file}, sha256 {shadow_sha256}"
    elif parts is not None:
        what = (
            f"{kind} "
            + ", ".join(f"{p.name} ({p.kind}{', ' + p.file if p.file else ''})" for p in parts)
            + f", sha256 {shadow_sha256} (of its definition)"
        )
    else:
        what = f"{kind}, inline params in the config, sha256 {shadow_sha256} (of its definition)"
    lines = [f"about to make the shadow the model: {what}"]
    if spec.file is not None:
        lines.append(f"the shadow came from: {_origin(spec.fit)}")
        record = read_shadow_record(spec.file)
        if record is not None and record.get("sha256") == shadow_sha256:
            lines.append(
                f"the shadow came from: the plant (Model/shadow, request {str(record.get('request'))[:40]},"
                f" accepted {str(record.get('accepted_utc'))[:40]})"
            )
    for p in parts or ():
        if p.file is not None:
            lines.append(f"contribution {p.name} came from: {_origin(p.fit)}")
    if status is None:
        lines.append("no daemon runs this config: no prediction now, no score on the probes")
        return lines
    axes = status.get("axes") if isinstance(status.get("axes"), dict) else {}
    now = []
    for axis in spec.outputs:
        ax = axes.get(axis) if isinstance(axes.get(axis), dict) else {}
        sh, act = ax.get("shadow_um"), ax.get("prediction_um")
        now.append(
            f"{axis}: the shadow predicts {f'{sh:.2f} um' if _real(sh) else 'nothing'}, the active model"
            f" {f'{act:.2f} um' if _real(act) else 'nothing'}"
        )
    lines.append(f"now (daemon pid {status.get('pid')}): " + "; ".join(now))
    scores = _score_of(status)
    scored = []
    for axis in spec.outputs:
        sc = scores.get(axis, {})
        n, a, s = sc.get("probes"), sc.get("active_rms_um"), sc.get("shadow_rms_um")
        if _real(n) and n > 0 and _real(a) and _real(s):
            scored.append(f"{axis}: {int(n)} probes, shadow RMS {s:.2f} um, active {a:.2f} um")
        else:
            scored.append(f"{axis}: no probe")
    lines.append("its score on the probes: " + "; ".join(scored))
    return lines


def promote(
    config: str | Path,
    *,
    force: bool = False,
    reload: bool = True,
    wait_s: float = 60.0,
    dry_run: bool = False,
    min_probes: int = MIN_PROBES,
    say: Callable[[str], None] = lambda line: None,
) -> dict[str, Any]:
    """Promote the config's shadow (see the module): `say` is given what it is about to do, line by line,
    before anything is checked against it or written; what was done, for the command to print. A
    refusal is BadInput (exit 2)."""
    path = Path(config)
    cfg = load_config(path)  # the file as it is must be valid, with a shadow
    if cfg.shadow is None:
        raise BadInput("the config has no shadow section: nothing to promote", file=str(path), path="shadow")
    status_path, status = _daemon_status(cfg)
    sha = model_sha256(cfg.shadow)
    for line in describe(cfg, status, sha):
        say(line)
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
    text = path.read_bytes()
    new = promoted_text(text.decode("utf-8"), str(path), stamp)
    new_cfg = load_config(path, text=new)  # what check-config checks (the kind's parameter bounds), on the new text
    check_config(new_cfg)
    why = drive_check(new_cfg, new_cfg.model, list(cfg.model.outputs))  # as a model sent to be applied
    if why is not None:
        raise cfg.doc.error(f"the shadow cannot be made the model: {why}", ("shadow",))
    if not force:
        why = score_refusal(status, sha, list(cfg.shadow.outputs), min_probes)
        if why is not None:
            raise cfg.doc.error(f"not promoted: {why} (give --force to promote it anyway)", ("shadow",))
    result: dict[str, Any] = {
        "config": str(path),
        "model": new_cfg.model.kind,
        "model_file": new_cfg.model.file,
        "text": new,
        "sha256": sha,
    }
    if dry_run:
        return result
    backup = path.with_name(f"{path.name}.{stamp}.bak")
    shutil.copy2(path, backup)
    _replace(path, new.encode("utf-8"), stamp)
    result["backup"] = str(backup)
    result["reloaded"] = None
    if reload and status is not None:
        pid = int(status.get("pid") or 0)
        before = status.get("written_unix_s")
        os.kill(pid, signal.SIGHUP)
        result["pid"] = pid
        result["reloaded"] = _wait_reloaded(str(status_path), new_cfg, before, wait_s)
        if not result["reloaded"]:
            result["restored"] = _put_back(path, text, new, stamp, pid)
    return result


def _replace(path: Path, data: bytes, stamp: str) -> None:
    """`path`'s content made `data` atomically (its mode kept)."""
    tmp = path.with_name(f".{path.name}.promote-{stamp}")
    tmp.write_bytes(data)
    shutil.copymode(path, tmp)
    os.replace(tmp, path)


def _put_back(path: Path, before: bytes, new: str, stamp: str, pid: int) -> str:
    """The reload did not take the promoted config: the file as it was, byte for byte, the promoted
    text kept beside it, and the daemon asked to reload what the file says now (were its reload only
    slow, it would otherwise run a config no file holds); where the promoted text is."""
    kept = path.with_name(f"{path.name}.promoted-rejected-{stamp}")
    kept.write_text(new, encoding="utf-8")
    _replace(path, before, stamp)
    with contextlib.suppress(OSError):  # gone: it reads the file as it was at its next start
        os.kill(pid, signal.SIGHUP)
    return str(kept)


def _wait_reloaded(status_path: str, cfg: Config, before: Any, wait_s: float) -> bool:
    """Whether the daemon's status shows the promoted model (its kind and file, and no shadow) within `wait_s`."""
    want_kind, want_file = cfg.model.kind, cfg.model.file
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline:
        try:
            data = read_status(status_path)
        except BadInput:
            data = {}
        model = data.get("model") or {}
        if (
            data.get("written_unix_s") != before
            and model.get("kind") == want_kind
            and model.get("file") == want_file
            and data.get("shadow") is None
        ):
            return True
        time.sleep(0.2)
    return False
