"""compd's HAL components in agent processes: one per component, asked over a pipe by the I/O worker that owns it.

A HAL userspace component belongs to the process that made it: LinuxCNC's shutdown (`halcmd
unload all`) SIGTERMs that process, and a process whose HAL went away cannot join the next one
(its view of HAL is the old memory). So each of compd's components (the linuxcnc sink's, the hal
source's) lives in an agent (`python -m compd.io.hal_agent MODULE:CLASS ARGS…`), a process of its
own that the worker starts at connect (`Agent`) and asks one JSON line per request, one JSON line
back. When LinuxCNC stops, the agent ends; the worker's link goes down and its next connect
starts a fresh agent, which joins the new HAL. When compd is killed, its agent sees the pipe
close, takes its component out of HAL and ends.

The agent's work is a `Component` (the sink's pins, the source's pins): `make`, `net` and `ready`
(what `connect` does around them is the same for every component), `answer` (a request of its
own), `release`; `stale` when the HAL it was made in is gone (the agent then ends after its reply).
"""

from __future__ import annotations

import contextlib
import importlib
import json
import os
import signal
import subprocess
import sys
from abc import ABC, abstractmethod
from collections.abc import Sequence
from typing import Any, TextIO

from compd.core.errors import BadInput
from compd.io import hal_modules

HALCMD_TIMEOUT_S = 10.0
AGENT_WAIT_S = 10.0  # how long an agent is given to end when its pipe closes


def halcmd(*args: str) -> subprocess.CompletedProcess[str]:
    """Run LinuxCNC's halcmd (its script-friendly output), never for longer than HALCMD_TIMEOUT_S."""
    return subprocess.run(
        ["halcmd", "-s", *args],
        capture_output=True,
        text=True,
        timeout=HALCMD_TIMEOUT_S,
        check=False,
        env=os.environ.copy(),
    )


def linked_signal(pin: str) -> str | None:
    """The signal `pin` is linked to (halcmd's `show pin`), None when it is on none; LookupError when
    the pin does not exist (or HAL does not run: halcmd then shows nothing, and makes no HAL)."""
    done = halcmd("show", "pin", pin)
    for line in done.stdout.splitlines():
        words = line.split()
        if pin in words:
            k = words.index(pin)
            if k + 2 < len(words) and words[k + 1] in ("<==", "==>", "<=>"):
                return words[k + 2]
            return None
    raise LookupError(f"HAL has no pin {pin}" + (f" ({done.stderr.strip()})" if done.stderr.strip() else ""))


def net_input(hal: Any, ours: str, theirs: str, new_signal: str) -> str | None:
    """The float input pin `ours` on the signal the pin `theirs` is on (a new float signal `new_signal`,
    linked to `theirs`, when it is on none); why not, or None."""
    mine, sig = linked_signal(ours), linked_signal(theirs)
    if mine is not None:
        return None if mine == sig else f"{ours} is netted to {mine}, not to {theirs}'s signal ({sig or 'none'})"
    if sig is None:
        sig = new_signal
        hal.new_sig(sig, hal.HAL_FLOAT)
        hal.connect(theirs, sig)
    hal.connect(ours, sig)
    return None


def linuxcnc_runs() -> str | None:
    """None when LinuxCNC's motion controller is in HAL, else why not (compd never makes a HAL of its own)."""
    try:
        linked_signal("motion.motion-enabled")
    except (LookupError, OSError, subprocess.SubprocessError):
        return "LinuxCNC is not running (HAL has no motion.motion-enabled)"
    return None


class Component(ABC):
    """The agent's work: one HAL component of compd's. `connect` is the same for every component:
    LinuxCNC's modules loaded, LinuxCNC running (compd never makes a HAL of its own), the component
    made once (`make`), a component whose HAL is gone found `stale`, then its pins netted (`net`) and
    whatever else must hold (`ready`); each says why not in one line."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.last_error: str | None = None
        self.stale = False  # the HAL it was made in is gone: the agent ends
        self.hal: Any = None
        self.comp: Any = None

    def connect(self) -> bool:
        self.last_error = self._connect()
        return self.last_error is None

    def _connect(self) -> str | None:
        try:
            self.hal, _ = hal_modules.load()
        except BadInput as e:
            return str(e)
        why = linuxcnc_runs()
        if why is not None:
            return why
        if self.comp is not None:
            try:
                linked_signal(self.first_pin())
            except LookupError:  # made in a HAL that is gone (LinuxCNC restarted): this process cannot join the next
                self.stale = True
                return f"the HAL {self.name} was made in is gone (LinuxCNC restarted): a new agent joins the new one"
        if self.comp is None:
            try:
                self.comp = self.make(self.hal)
            except Exception as e:  # HAL says why in its own words (a name in use, no HAL)
                return f"cannot make the HAL component {self.name!r}: {e}"
        try:
            why = self.net(self.hal)
        except Exception as e:  # halcmd, or HAL in its own words
            return f"cannot net {self.name}'s pins: {e}"
        return why or self.ready()

    @abstractmethod
    def make(self, hal: Any) -> Any:
        """The component with its pins, ready."""

    @abstractmethod
    def first_pin(self) -> str:
        """A pin of the component (whether HAL still has it tells a HAL that went away)."""

    @abstractmethod
    def net(self, hal: Any) -> str | None:
        """The component's pins netted; why not, or None."""

    def ready(self) -> str | None:
        """What else must hold before the link is up; why not, or None."""
        return None

    @abstractmethod
    def answer(self, what: str, args: list[Any]) -> dict[str, Any]:
        """A request of the component's own (a read, a write)."""

    def release(self) -> None:
        """The component leaves HAL (LinuxCNC keeps what its pins left on their signals)."""
        if self.comp is not None:
            with contextlib.suppress(Exception):  # already gone with LinuxCNC
                self.comp.exit()
            self.comp = None


class Agent:
    """The worker's side: the agent process of `component_class` (a "module:Class" of compd's) and its pipe."""

    def __init__(self, component_class: str, args: Sequence[str]) -> None:
        self.argv = [sys.executable, "-m", "compd.io.hal_agent", component_class, *args]
        self._proc: subprocess.Popen[str] | None = None

    def alive(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    def start(self) -> str | None:
        """A fresh agent unless one runs; why not, or None."""
        if self.alive():
            return None
        self.end()
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}
        try:
            self._proc = subprocess.Popen(
                self.argv,
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=subprocess.DEVNULL,
                text=True,
                env=env,
                start_new_session=True,
            )
        except OSError as e:
            return f"cannot start compd's HAL agent: {e}"
        return None

    def ask(self, *request: Any) -> dict[str, Any] | None:
        """One request and its reply; None when the agent is gone (LinuxCNC's shutdown ends it)."""
        proc = self._proc
        if proc is None or proc.poll() is not None or proc.stdin is None or proc.stdout is None:
            return None
        try:
            proc.stdin.write(json.dumps(request) + "\n")
            proc.stdin.flush()
            line = proc.stdout.readline()
            got = json.loads(line) if line else None
        except (OSError, ValueError):
            return None
        return got if isinstance(got, dict) else None

    def connect(self) -> str | None:
        """A fresh agent unless one runs, its component connected; why not, or None."""
        why = self.start()
        if why is not None:
            return why
        got = self.ask("connect")
        if got is None:
            self.end()
            return "compd's HAL agent ended (LinuxCNC's shutdown ends it): a new one at the next try"
        return None if got.get("ok") else str(got.get("why"))

    def release(self) -> None:
        """For good: the agent's component leaves HAL, the agent ends."""
        self.ask("release")
        self.end()

    def end(self) -> None:
        """Close the pipe (the agent releases its component and ends) and wait for it."""
        proc, self._proc = self._proc, None
        if proc is None:
            return
        for f in (proc.stdin, proc.stdout):
            with contextlib.suppress(OSError, ValueError):
                if f is not None:
                    f.close()
        try:
            proc.wait(AGENT_WAIT_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(AGENT_WAIT_S)


def serve(component: Component, requests: TextIO, replies: TextIO) -> None:
    """The agent's loop: a JSON request per line, a JSON reply per line, until the pipe closes (or the
    component's HAL is gone); the component released at the end."""
    try:
        for line in requests:
            try:
                what, *args = json.loads(line)
            except (ValueError, TypeError):
                out: dict[str, Any] = {"fault": "reply", "why": "not a request"}
            else:
                if what == "connect":
                    out = {"ok": component.connect(), "why": component.last_error}
                elif what == "release":
                    component.release()
                    out = {"ok": True}
                else:
                    out = component.answer(str(what), args)
            replies.write(json.dumps(out) + "\n")
            replies.flush()
            if component.stale:
                return
    finally:
        component.release()


def main(argv: list[str] | None = None) -> int:
    """`python -m compd.io.hal_agent compd.MODULE:CLASS ARGS…`: the agent (see the module)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the daemon's Ctrl-C is the daemon's: it ends us
    args = sys.argv[1:] if argv is None else argv
    spec, *rest = args
    module, _, name = spec.partition(":")
    if not module.startswith("compd.") or not name:
        print(f"not a component of compd's: {spec}", file=sys.stderr)
        return 2
    cls = getattr(importlib.import_module(module), name)
    replies = os.fdopen(os.dup(1), "w")  # the replies' own descriptor: whatever HAL prints goes to stderr
    os.dup2(2, 1)
    serve(cls(*rest), sys.stdin, replies)
    return 0


if __name__ == "__main__":
    sys.exit(main())
