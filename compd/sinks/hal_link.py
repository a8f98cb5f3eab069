"""LinuxCNC's HAL as the device behind a sink's link: compd's HAL component, its pins shown as registers.

The linuxcnc sink speaks the register map of compd.plc.eoffsets through the same link as every
sink (compd.io.modbus_link: its worker, epochs, read-back before the first write, back-off).
`HalRegisters` is that link's device: it runs on the link's worker (a thread, or the I/O child
process), never in the cycle.

At connect it makes compd's HAL userspace component (`sink.component`, default `compd`) with,
per axis L, `<comp>.L.eoffset-counts` (s32 out), `.L.eoffset-enable` (bit out), `.L.eoffset-scale`
(float out: machine units per count) and `.L.eoffset` (float in: what LinuxCNC applies), and
nets them to LinuxCNC's `axis.L.eoffset-counts`/`-enable`/`-scale` and from `axis.L.eoffset`:
to the signals those pins are on (the HAL file's nets; found with halcmd), or to new signals
`<comp>-L-eoffset-counts` … when they are on none. Each output pin takes its signal's value
before it is linked, so linking moves nothing: a compd started again (its counts pin back at 0)
joins the counts where the last one left them and the axis does not move. A signal another
component writes is never fought: the link stays down and says which.

The link is up only while LinuxCNC runs, the machine is on (`motion.motion-enabled`) and homed
(`motion.is-all-homed`): counts act only then (LinuxCNC ignores them otherwise and moves the
baseline). Whenever one of these ends the link goes down (its last error says why) and, when
they hold again, a new epoch reads back what LinuxCNC applies before anything is written.

The component lives in an agent process of its own (compd.io.hal_agent: `HalPins` there,
`HalRegisters` on the link's worker): LinuxCNC's shutdown ends the agent, the link goes down,
and the next connect starts a fresh one in the new HAL; compd's daemon and its I/O process run on.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from compd.io.hal_agent import Agent, Component, halcmd, linked_signal, net_input
from compd.io.modbus_client import BadReply, LinkFault, ModbusFault
from compd.plc.eoffsets import (
    BLOCK,
    COUNTS,
    ENABLE,
    HOMED,
    LIMITED,
    NETTED,
    ON,
    S32_MAX,
    S32_MIN,
    regs_s32,
    s32_regs,
)
from compd.plc.siemens_nc import f32_regs

MM_PER_UNIT = {"mm": 1.0, "inch": 25.4}


class HalPins(Component):
    """compd's HAL component as a register device (compd.plc.eoffsets' map), in its agent's process
    (arguments as the agent's command line gives them)."""

    def __init__(self, component: str, units: str, count_um: str | float, *axes: str) -> None:
        super().__init__(component)
        self.axes = list(axes)
        self.count_um = count_um = float(count_um)
        self.scale = count_um / 1000.0 / MM_PER_UNIT[units]  # machine units per count
        self.unit_um = 1000.0 * MM_PER_UNIT[units]
        self.limited = False

    def make(self, hal: Any) -> Any:
        c = hal.component(self.name)
        for a in self.axes:
            c.newpin(f"{a}.eoffset-counts", hal.HAL_S32, hal.HAL_OUT)
            c.newpin(f"{a}.eoffset-enable", hal.HAL_BIT, hal.HAL_OUT)
            c.newpin(f"{a}.eoffset-scale", hal.HAL_FLOAT, hal.HAL_OUT)
            c.newpin(f"{a}.eoffset", hal.HAL_FLOAT, hal.HAL_IN)
        c.ready()
        return c

    def first_pin(self) -> str:
        return f"{self.name}.{self.axes[0]}.eoffset-counts"

    def net(self, hal: Any) -> str | None:
        """Each pin of compd's on LinuxCNC's signal (see the module); why not, or None."""
        comp = self.name
        for a in self.axes:
            for part, kind in (("counts", hal.HAL_S32), ("enable", hal.HAL_BIT), ("scale", hal.HAL_FLOAT)):
                ours, theirs = f"{comp}.{a}.eoffset-{part}", f"axis.{a}.eoffset-{part}"
                mine, sig = linked_signal(ours), linked_signal(theirs)
                if mine is not None:
                    if mine != sig:
                        return f"{ours} is netted to {mine}, not to {theirs}'s signal ({sig or 'none'})"
                    continue
                if sig is None:
                    sig = f"{comp}-{a}-eoffset-{part}"
                    hal.new_sig(sig, kind)
                    halcmd("sets", sig, str(hal.get_value(theirs)))
                    hal.connect(theirs, sig)
                elif hal.pin_has_writer(theirs):
                    return f"{theirs} is driven through signal {sig} by another component: compd will not fight it"
                self.comp[f"{a}.eoffset-{part}"] = hal.get_value(sig)  # linking moves nothing
                hal.connect(ours, sig)
            why = net_input(hal, f"{comp}.{a}.eoffset", f"axis.{a}.eoffset", f"{comp}-{a}-eoffset")
            if why is not None:
                return why
        for a in self.axes:  # the scale compd counts in (counts are reckoned from what is applied)
            if not math.isclose(float(self.comp[f"{a}.eoffset-scale"]), self.scale, rel_tol=1e-12):
                if self.comp[f"{a}.eoffset-enable"] and int(self.comp[f"{a}.eoffset-counts"]) != 0:
                    return (
                        f"axis.{a}.eoffset-scale is {self.comp[f'{a}.eoffset-scale']} with the offset enabled:"
                        f" compd counts in {self.scale:g} (sink.count_um); clear the offset first"
                    )
                self.comp[f"{a}.eoffset-scale"] = self.scale
        return None

    def ready(self) -> str | None:
        """Why counts would not act now (machine off, not homed), or None."""
        hal = self.hal
        try:
            on, homed = bool(hal.get_value("motion.motion-enabled")), bool(hal.get_value("motion.is-all-homed"))
        except Exception as e:
            return f"LinuxCNC does not answer ({e})"
        if not on:
            return "LinuxCNC: the machine is off (estop or not on): the offset is held, compd waits"
        if not homed:
            return "LinuxCNC: the machine is not homed: the offset is held, compd waits"
        return None

    def answer(self, what: str, args: list[Any]) -> dict[str, Any]:
        """`read ADDRESS COUNT` and `write ADDRESS VALUES` (compd.plc.eoffsets' map)."""
        if what == "read":
            got = self.read_registers(int(args[0]), int(args[1]))
            return {"regs": got} if isinstance(got, list) else _fault(got)
        if what == "write":
            done = self.write_registers(int(args[0]), [int(v) for v in args[1]])
            return {"regs": []} if done is None else _fault(done)
        return {"fault": "reply", "why": f"unknown request {what!r}"}

    # ------------------------------------------------------------ registers
    def read_registers(self, address: int, count: int, **_: Any) -> list[int] | ModbusFault:
        """The map's registers now; a LinkFault when counts would no longer act (see the module)."""
        if self.comp is None:
            return LinkFault("the HAL component is not made")
        why = self.ready()
        if why is not None:
            self.last_error = why
            return LinkFault(why)
        try:
            self.limited = bool(self.hal.get_value("motion.eoffset-limited"))
        except Exception as e:
            return LinkFault(f"LinuxCNC does not answer ({e})")
        regs: list[int] = []
        flags = NETTED | ON | HOMED | (LIMITED if self.limited else 0)
        for a in self.axes:
            applied = float(self.comp[f"{a}.eoffset"]) * self.unit_um
            regs += [
                *s32_regs(int(self.comp[f"{a}.eoffset-counts"])),
                int(bool(self.comp[f"{a}.eoffset-enable"])),
                *f32_regs(applied if math.isfinite(applied) else math.nan),
                flags,
                0,
                0,
            ]
        if address < 0 or address + count > len(regs):
            return BadReply(f"registers {address}+{count} are not in the map", "range")
        return regs[address : address + count]

    def write_registers(self, address: int, values: Sequence[int]) -> None | ModbusFault:
        """COUNTS of one axis (two registers), or its ENABLE (one)."""
        i, off = divmod(address, BLOCK)
        ok = (off == COUNTS and len(values) == 2) or (off == ENABLE and len(values) == 1 and values[0] in (0, 1))
        if self.comp is None or not 0 <= i < len(self.axes) or not ok:
            return BadReply(f"registers {address}+{len(values)} are not writable", "range")
        why = self.ready()
        if why is not None:
            return LinkFault(why)
        a = self.axes[i]
        if off == ENABLE:
            self.comp[f"{a}.eoffset-enable"] = bool(values[0])
            return None
        counts = regs_s32(values[0], values[1])
        if not S32_MIN <= counts <= S32_MAX:
            return BadReply(f"counts {counts} out of range", "range")
        self.comp[f"{a}.eoffset-counts"] = counts
        return None


def _fault(f: ModbusFault) -> dict[str, Any]:
    return {"fault": "link" if isinstance(f, LinkFault) else "reply", "why": f.detail}


class HalRegisters:
    """The linuxcnc sink's register device on the link's worker: `HalPins` in an agent (compd.io.hal_agent)."""

    def __init__(self, component: str, axes: Sequence[str], units: str, count_um: float) -> None:
        self.agent = Agent("compd.sinks.hal_link:HalPins", [component, units, repr(count_um), *axes])
        self.last_error: str | None = None

    def connect(self) -> bool:
        """A fresh agent unless the running one still answers; ready as `HalPins` says."""
        self.last_error = self.agent.connect()
        return self.last_error is None

    def close(self) -> None:
        """The link's disconnect: the agent stays (its component's pins keep what they carry)."""

    def release(self) -> None:
        """For good (after the safe output): the agent's component leaves HAL, the agent ends."""
        self.agent.release()

    def read_registers(self, address: int, count: int, **_: Any) -> list[int] | ModbusFault:
        return self._answer(self.agent.ask("read", address, count))

    def write_registers(self, address: int, values: Sequence[int]) -> None | ModbusFault:
        got = self._answer(self.agent.ask("write", address, [int(v) for v in values]))
        return None if isinstance(got, list) else got

    def _answer(self, got: dict[str, Any] | None) -> list[int] | ModbusFault:
        if got is None:
            return LinkFault("compd's HAL agent ended (LinuxCNC's shutdown ends it)")
        regs = got.get("regs")
        if isinstance(regs, list) and all(isinstance(v, int) for v in regs):
            return list(regs)
        if got.get("fault") == "reply":
            return BadReply(str(got.get("why")), "range")
        return LinkFault(str(got.get("why", "compd's HAL agent gave no answer")))
