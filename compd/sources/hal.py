"""HAL source: signals read from LinuxCNC's HAL, through compd's input component (`compd.in.<signal>`), polled.

A LinuxCNC machine already has its spindle speed (`spindle.0.speed-out`) and, often, temperatures
read by its own I/O boards on HAL pins. This source is a HAL userspace component (default name
`compd.in`) with one float input pin per signal, `compd.in.<signal>`; a signal that names a `pin`
is netted by compd to the signal that pin is on (or to a new one, `compd.in-<signal>`), the others
are netted by the machine's HAL file. The component lives in an agent process of its own
(compd.io.hal_agent), polled every `poll_period_s` by the source's I/O worker.

The same rules as every source: a value that is not finite is COMMS_LOST for that signal; while
LinuxCNC does not run, or a signal's pin has no writer (not netted), the signals are COMMS_LOST
(the worker reconnects with back-off, a fresh agent after LinuxCNC's restart); `stale_after_s`
marks an old sample STALE; the guard's `signals` limits judge plausibility.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from pydantic import Field, model_validator

from compd.core.config import SourceConfig, Strict
from compd.core.frame import Quality
from compd.io import hal_modules
from compd.io.hal_agent import Agent, Component, net_input
from compd.io.mailbox import Snapshot
from compd.io.worker import LinkDown
from compd.sources.base import PolledSource, Poller

HAL_NAME = r"^[A-Za-z][A-Za-z0-9_.-]*$"


class HalSignal(Strict):
    """One signal: its name (the pin `<component>.<name>`) and the HAL pin it is read from."""

    name: str = Field(pattern=r"^[A-Za-z][A-Za-z0-9_-]*$", description="the signal's name (a model input)")
    pin: str | None = Field(
        None,
        pattern=HAL_NAME,
        description="the HAL pin that carries it (e.g."
        " spindle.0.speed-out): compd nets its input to it; none: the HAL file nets it",
    )


class HalConfig(SourceConfig):
    """Float input pins of compd's HAL component in LinuxCNC (docs/linuxcnc.md)."""

    component: str = Field("compd.in", pattern=HAL_NAME, description="the input component's name (its pins' prefix)")
    signals: list[HalSignal] = Field(min_length=1, description="the signals, each a float input pin")
    poll_period_s: float = Field(0.05, ge=0.001, le=60)
    stale_after_s: float | None = Field(None, gt=0, le=86400, description="longer than poll_period_s")

    @model_validator(mode="after")
    def _check(self) -> HalConfig:
        names = [s.name for s in self.signals]
        if len(set(names)) != len(names):
            raise ValueError("a signal name is used twice")
        if self.stale_after_s is not None and not self.stale_after_s > self.poll_period_s:
            raise ValueError("stale_after_s must be longer than poll_period_s (else every sample is stale)")
        why = hal_modules.available()
        if why is not None:
            raise ValueError(why)
        return self


class HalInputs(Component):
    """The input component in its agent: `COMPONENT NAME[=PIN]…` from the agent's command line."""

    def __init__(self, component: str, *specs: str) -> None:
        super().__init__(component)
        self.signals = [(name, pin or None) for name, _, pin in (s.partition("=") for s in specs)]

    def make(self, hal: Any) -> Any:
        c = hal.component(self.name)
        for name, _ in self.signals:
            c.newpin(name, hal.HAL_FLOAT, hal.HAL_IN)
        c.ready()
        return c

    def first_pin(self) -> str:
        return f"{self.name}.{self.signals[0][0]}"

    def net(self, hal: Any) -> str | None:
        """Each signal that names a pin on that pin's signal; every input written by something."""
        for name, pin in self.signals:
            why = None if pin is None else net_input(hal, f"{self.name}.{name}", pin, f"{self.name}-{name}")
            if why is not None:
                return why
        loose = [f"{self.name}.{n}" for n, _ in self.signals if not hal.pin_has_writer(f"{self.name}.{n}")]
        if loose:
            return (
                f"not netted to anything that writes it: {', '.join(loose)} (net it in the HAL file, or give its pin)"
            )
        return None

    def answer(self, what: str, args: list[Any]) -> dict[str, Any]:
        """`values`: each signal's pin now."""
        if what != "values" or self.comp is None:
            return {"fault": "reply", "why": f"unknown request {what!r}"}
        try:
            return {"values": [float(self.comp[name]) for name, _ in self.signals]}
        except Exception as e:
            return {"fault": "link", "why": f"LinuxCNC does not answer ({e})"}


class HalSource(PolledSource):
    """compd's input component in LinuxCNC, polled by its I/O worker; `read` never blocks."""

    Config = HalConfig

    def __init__(self, cfg: HalConfig, base_dir: str = ".") -> None:
        super().__init__(cfg, base_dir)
        self.cfg: HalConfig = cfg
        self.poll_period_s = cfg.poll_period_s
        self.stale_after_s = cfg.stale_after_s

    def signal_names(self) -> list[str]:
        return [s.name for s in self.cfg.signals]

    def make_poller(self, snapshot: Snapshot) -> HalPoller:
        return HalPoller(self.cfg, snapshot)

    def get_status(self) -> dict[str, Any]:
        io = self.io_status()
        return {**super().get_status(), "polls": self.polls, "last_error": io["last_error"], "link": io["state"]}


class HalPoller(Poller):
    """The device half: the agent's pins read each round."""

    def __init__(self, cfg: HalConfig, snapshot: Snapshot) -> None:
        super().__init__(len(cfg.signals), snapshot)
        specs = [s.name + (f"={s.pin}" if s.pin else "") for s in cfg.signals]
        self.agent = Agent("compd.sources.hal:HalInputs", [cfg.component, *specs])

    def connect(self) -> None:
        why = self.agent.connect()
        if why is not None:
            raise LinkDown(why)

    def poll(self, values: np.ndarray, quality: np.ndarray) -> None:
        got = self.agent.ask("values")
        vals = got.get("values") if got is not None else None
        if not isinstance(vals, list) or len(vals) != len(values):
            quality[:] = Quality.COMMS_LOST
            raise LinkDown(str(got.get("why")) if got else "compd's HAL agent ended (LinuxCNC's shutdown ends it)")
        for k, v in enumerate(vals):
            if isinstance(v, (int, float)) and math.isfinite(v):
                values[k] = float(v)
                quality[k] = Quality.GOOD
            else:
                quality[k] = Quality.COMMS_LOST

    def close(self) -> None:
        """For good: the agent's component leaves HAL, the agent ends."""
        self.agent.release()
