"""`compd status --watch`: the status file redrawn every interval, per axis and per signal (rich if installed)."""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable
from typing import Any, TextIO

from compd.core.errors import BadInput
from compd.service.status import liveness, read_status, render

CLEAR = "\x1b[H\x1b[2J"  # cursor home, clear the screen


def rich_available() -> bool:
    """Whether rich is installed (`pip install 'compd[watch]'`)."""
    try:
        import rich  # noqa: F401
    except ImportError:
        return False
    return True


def read_frame(path: str) -> tuple[dict[str, Any] | None, bool, str]:
    """(the snapshot or None, alive, why) of the status file at `path`; a missing or
    unreadable file is "not running", said the way `compd status` says it."""
    try:
        data = read_status(path)
        alive, why = liveness(data)
        render(data, alive, why)  # a field deeper down of the wrong type shows here, as in `compd status`
        return data, alive, why
    except BadInput as e:
        return None, False, f"not running: {e.message}"
    except (TypeError, ValueError, AttributeError, KeyError) as e:
        return None, False, f"not a compd status file: {type(e).__name__}: {e}"


def plain_frame(path: str, data: dict[str, Any] | None, alive: bool, why: str, interval_s: float) -> str:
    """The frame as text: `compd status`'s view, or why there is none."""
    stamp = time.strftime("%H:%M:%S")
    head = f"compd status --watch {path} — every {interval_s:g} s, {stamp} (Ctrl-C to stop)"
    if data is None:
        return f"{head}\n{why}; waiting for the daemon"
    body = render(data, alive, why)
    if not alive:
        body = f"NOT RUNNING: {why} (showing its last status)\n{body}"
    return f"{head}\n{body}"


def _cell(value: Any, fmt: str) -> str:
    return "nan" if value is None else format(value, fmt)


def rich_frame(path: str, data: dict[str, Any] | None, alive: bool, why: str, interval_s: float) -> Any:
    """The frame as rich renderables: the head, the model, a table per axis and per signal."""
    from rich.console import Group
    from rich.table import Table
    from rich.text import Text

    stamp = time.strftime("%H:%M:%S")
    head = Text(f"compd status --watch {path} — every {interval_s:g} s, {stamp} (Ctrl-C to stop)", style="dim")
    if data is None:
        return Group(head, Text(f"{why}; waiting for the daemon", style="bold yellow"))
    lines = render(data, alive, why).splitlines()
    # the text lines up to the axis table: head, config, loop, model, word
    cut = next((i for i, ln in enumerate(lines) if ln.startswith("axis ")), len(lines))
    top = Text("\n".join(lines[:cut]))
    parts: list[Any] = [head]
    if not alive:
        parts.append(Text(f"NOT RUNNING: {why} (showing its last status)", style="bold red"))
    parts.append(top)
    axes = Table(title="axes", title_justify="left")
    for col in ("axis", "predicted µm", "correction µm", "target µm", "byte", "enabled", "state", "policy", "sat"):
        axes.add_column(col, justify="right" if col.endswith("µm") else "left")
    for name, a in (data.get("axes") or {}).items():
        state = str(a.get("state", "?"))
        style = "red" if state in ("fault", "stale") else "yellow" if state in ("starting", "recovering") else ""
        axes.add_row(
            name,
            _cell(a.get("prediction_um"), ".2f"),
            _cell(a.get("correction_um"), ".2f"),
            _cell(a.get("target_um"), ".2f"),
            str(a.get("byte") or "-"),
            "yes" if a.get("enable") else "no",
            state,
            str(a.get("policy", "?")),
            "yes" if a.get("saturated") else "no",
            style=style,
        )
    sigs = Table(title="signals", title_justify="left")
    for col in ("signal", "value", "quality", "age s"):
        sigs.add_column(col, justify="right" if col in ("value", "age s") else "left")
    for name, sg in (data.get("signals") or {}).items():
        q = str(sg.get("quality", "?"))
        sigs.add_row(
            name, _cell(sg.get("value"), ".3f"), q, _cell(sg.get("age_s"), ".2f"), style="" if q == "good" else "red"
        )
    parts += [axes, sigs]
    tail = [ln for ln in lines[cut:] if ln.startswith(("source ", "faults:", "metrics:", "recent events", "  t="))]
    if tail:
        parts.append(Text("\n".join(tail)))
    return Group(*parts)


def watch(
    path: str,
    interval_s: float,
    *,
    out: TextIO | None = None,
    use_rich: bool | None = None,
    frames: int | None = None,
    sleep: Callable[[float], None] | None = None,
) -> int:
    """Redraw the status of the daemon at `path` every `interval_s` until Ctrl-C (or `frames`
    frames, for tests). While no daemon runs it says so and keeps waiting. Returns what
    `compd status` would for the last frame: 0 when the daemon was alive, 1 when not."""
    out = sys.stdout if out is None else out
    sleep = time.sleep if sleep is None else sleep
    if use_rich is None:
        use_rich = rich_available() and out.isatty()
    alive = False
    shown = 0
    if use_rich:
        from rich.console import Console
        from rich.live import Live

        console = Console(file=out)
        try:
            data, alive, why = read_frame(path)
            with Live(
                rich_frame(path, data, alive, why, interval_s), console=console, auto_refresh=False, transient=False
            ) as live:
                shown = 1
                while frames is None or shown < frames:
                    sleep(interval_s)
                    data, alive, why = read_frame(path)
                    live.update(rich_frame(path, data, alive, why, interval_s), refresh=True)
                    shown += 1
        except KeyboardInterrupt:
            pass
        return 0 if alive else 1
    clear = out.isatty() and os.environ.get("TERM") != "dumb"
    try:
        while frames is None or shown < frames:
            if shown:
                sleep(interval_s)
            data, alive, why = read_frame(path)
            text = plain_frame(path, data, alive, why, interval_s)
            out.write((CLEAR if clear else ("\n" if shown else "")) + text + "\n")
            out.flush()
            shown += 1
    except KeyboardInterrupt:
        pass
    return 0 if alive else 1
