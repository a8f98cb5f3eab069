"""A Modbus TCP link for sinks: writes from the cycle are queued, an I/O worker does the I/O.

The cycle never waits on the network: `submit` puts the newest values per register
range in a `WriteQueue` and wakes the link's worker, which writes them (in order of
first submission) and reads a status block every `status_period_s`. A lost connection
is retried with exponential back-off (`compd.io.worker`); what the sink knows of the
device is the last status read (`status`, published by the worker). Every reply is
shape-checked by the Modbus client (`compd.io.modbus_client`: function code, register
count, frame length, unit): a reply of the wrong shape is a link error (`errors`,
`bad_replies`, `last_error`), never taken as the device's status or applied value.
`state` is the link as the worker last found it: connecting (started, no answer
yet), up, down (connect or I/O failed), closed.

What the device holds, before anything is written (`sync` ranges): a sink never knows what
a device applies when it connects — its own earlier run may have been killed while the
device held a correction, another process may have written it, the device may have been
restarted and hold 0. So at every connect (the first, and every one after the link was
lost) the worker, before it sends anything, starts a new *epoch*, reads the sync ranges and
publishes them as the epoch's `held` block. It sends nothing more until the sink has taken
that block (`accept`, which also drops the writes still queued: they were reckoned from what
the device held before): the sink then knows what the device applies and steps from there,
so the first write of every connection is within one step of what the machine applies.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from typing import Any, Protocol

from compd.io.child import hosting_now
from compd.io.histogram import DurationHist
from compd.io.mailbox import SharedRegisters, Sync, WriteQueue
from compd.io.modbus_client import (
    BadReply,
    Connectable,
    LinkFault,
    ModbusClient,
    ModbusFault,
    OverModbus,
)
from compd.io.worker import DeviceWork, IoWorker, LinkDown, stall_after

log = logging.getLogger("compd.io")


class RegisterDevice(Connectable, Protocol):
    """What a link's worker talks to: a Modbus client (`ModbusClient`), or a device that shows
    itself as registers the same way (compd.sinks.hal_link: LinuxCNC's HAL)."""

    def release(self) -> None: ...
    def read_registers(self, address: int, count: int) -> list[int] | ModbusFault: ...
    def write_registers(self, address: int, values: Sequence[int]) -> None | ModbusFault: ...


class LinkWork(OverModbus, DeviceWork):
    """The device half of a link (the worker's thread): send what is queued, read the status."""

    client: RegisterDevice

    def __init__(
        self,
        client: RegisterDevice,
        queue: WriteQueue,
        status_out: SharedRegisters,
        status_range: tuple[int, int] | None,
        status_period_s: float,
        sync: Sync | None = None,
    ) -> None:
        super().__init__()
        self.client = client
        self.queue = queue
        self.status_out = status_out
        self.status_range = status_range
        self.status_period_s = status_period_s
        self.sync = sync
        self._synced = False  # this connection's held block has been read
        self.writes = 0
        self.reply_errors = 0  # exception replies and malformed replies
        self.bad_replies = 0
        self.write_hist = DurationHist()  # request to reply of each write, µs
        self.latency_hist = DurationHist()  # queued by the cycle to acknowledged by the device, µs
        self._next_status_s = 0.0

    def counters(self) -> dict[str, Any]:
        return {"writes": self.writes, "reply_errors": self.reply_errors, "bad_replies": self.bad_replies}

    def close(self) -> None:
        """The worker stops: the device released for good."""
        self.client.release()

    max_writes_per_round = 64  # a round ends, so requests and stop are seen, however busy the queue

    def connect(self) -> None:
        super().connect()
        self._synced = False
        if self.sync is not None:  # a new epoch: nothing is sent until the sink has taken its held block
            self.sync.begin()

    def round(self, request: Any) -> list[int] | None:
        """A new connection's held block first (see the module); then send the queued writes
        (once the sink has taken it), reading the status block whenever it is due; then the
        registers `request` asks for (address, count)."""
        sync = self.sync
        if sync is not None and not self._synced:
            self._read_held(sync)
        if sync is None or sync.accepted():
            self._send_queued()
        self._status_if_due()
        return None if request is None else self._read(*request)

    def _read_held(self, sync: Sync) -> None:
        """This connection's held block: the sync ranges read and published (the sink takes it
        and drops what it had queued before: `ModbusLink.accept`). A range the device refuses
        leaves it unread (tried again next round): nothing is written meanwhile."""
        regs: list[int] = []
        for address, count in sync.ranges:
            r = self._read(address, count)
            if r is None:
                self.last_error = f"cannot read what the device holds (registers {address}+{count}): {self.last_error}"
                return
            regs += r
        sync.publish(regs)
        self._synced = True

    def _status_if_due(self) -> None:
        now = time.monotonic()
        if self.status_range is not None and now >= self._next_status_s:
            regs = self._read(*self.status_range)
            if regs is not None:
                self.status_out.publish((regs, now))
            self._next_status_s = now + self.status_period_s

    def _send_queued(self) -> None:
        perf = time.perf_counter_ns
        for _ in range(self.max_writes_per_round):
            w = self.queue.take()
            if w is None:
                return
            address, values, queued_ns = w[0], w[1], w[2]
            w0 = perf()
            r = self.client.write_registers(address, values)
            w1 = perf()
            if isinstance(r, LinkFault):
                self.queue.done(w, sent=False)  # sent again once the link is back
                raise LinkDown(r.detail)
            self.write_hist.add_ns(w1 - w0)
            self.latency_hist.add_ns(w1 - queued_ns)
            if r is None:
                self.writes += 1
            else:
                self._reply_error(r)
            self.queue.done(w, sent=True)
            self._status_if_due()

    def _read(self, address: int, count: int) -> list[int] | None:
        r = self.client.read_registers(address, count)
        if isinstance(r, LinkFault):
            raise LinkDown(r.detail)
        if isinstance(r, ModbusFault):
            self._reply_error(r)
            return None
        return r

    def _reply_error(self, fault: ModbusFault) -> None:
        self.reply_errors += 1
        if isinstance(fault, BadReply):
            self.bad_replies += 1
        self.last_error = fault.detail


class ModbusLink:
    """Holding-register writes and a status read, by an I/O worker (see the module)."""

    def __init__(
        self,
        host: str,
        port: int,
        *,
        device_id: int = 1,
        timeout_s: float = 0.25,
        status: tuple[int, int] | None = None,
        status_period_s: float = 0.05,
        reconnect_min_s: float = 0.1,
        reconnect_max_s: float = 5.0,
        name: str = "sink",
        sync: list[tuple[int, int]] | None = None,
        device: RegisterDevice | None = None,
    ) -> None:
        """`device`: what the registers are, when not a Modbus TCP device at host:port."""
        self.host, self.port, self.device_id = host, port, device_id
        self.timeout_s = timeout_s
        self.status_range = status
        self.status_period_s = status_period_s
        self.reconnect_min_s, self.reconnect_max_s = reconnect_min_s, reconnect_max_s
        self.name = name
        self._status = SharedRegisters(status[1] if status is not None else 0)
        self._queue = WriteQueue()
        # what the device holds at each connect, before anything is written (None: no such read)
        self.sync = Sync(sync) if sync is not None else None
        self._work = LinkWork(
            device if device is not None else ModbusClient.tcp(host, port, device_id=device_id, timeout_s=timeout_s),
            self._queue,
            self._status,
            status,
            status_period_s,
            self.sync,
        )
        self._worker = IoWorker(
            self._work,
            name=f"modbus-link-{name}",
            period_s=status_period_s,
            reconnect_min_s=reconnect_min_s,
            reconnect_max_s=reconnect_max_s,
            stall_after_s=stall_after(timeout_s),
        )
        self._queue.wake = self._worker.wake
        self.write_hist = self._work.write_hist
        self.latency_hist = self._work.latency_hist

    def start(self) -> None:
        """Start the link's worker (in a process of its own when the loop hosts I/O so)."""
        host = hosting_now()
        self._worker.start(process=host.process, avoid_cpus=host.cpus)

    # ------------------------------------------------------------ the cycle's side
    def submit(self, address: int, values: list[int]) -> None:
        """Queue a write; a newer write to the same address replaces an unsent one. Never waits."""
        self._queue.submit(address, values)

    def pending(self) -> bool:
        """Whether a write is queued or on its way (not yet acknowledged by the device)."""
        return self._queue.pending()

    @property
    def status(self) -> list[int] | None:
        """The status registers as last read (None before the first good read)."""
        return self._status.value[0]

    @status.setter
    def status(self, regs: list[int] | None) -> None:
        """A status read elsewhere (a settle's `read_now`) is the newest one."""
        self._status.publish((regs, time.monotonic()))

    @property
    def status_stamp(self) -> float:
        """When (monotonic s) `status` was read; -1 before the first read."""
        return self._status.value[1]

    @property
    def state(self) -> str:
        return self._worker.state

    @property
    def writes(self) -> int:
        return int(self._worker.get_status().get("writes", 0))

    @property
    def errors(self) -> int:
        """Failed connects and I/O, exception replies, malformed replies."""
        io = self._worker.get_status()
        return int(io["errors"]) + int(io.get("reply_errors", 0))

    @property
    def bad_replies(self) -> int:
        return int(self._worker.get_status().get("bad_replies", 0))

    @property
    def last_error(self) -> str | None:
        return self._worker.get_status().get("last_error")

    @property
    def in_process(self) -> bool:
        """Whether the link's worker runs in a process of its own."""
        return self._worker.in_process

    def get_status(self) -> dict[str, Any]:
        io = self._worker.get_status()
        return {
            "state": io["state"],
            "writes": io.get("writes", 0),
            "errors": io["errors"] + io.get("reply_errors", 0),
            "bad_replies": io.get("bad_replies", 0),
            "last_error": io["last_error"],
            "pid": io.get("pid"),
        }

    def held(self) -> tuple[int, list[int]] | None:
        """The held block of the link's current connection, with its epoch, when the worker has
        read it and the sink has not yet taken it (`accept`); None otherwise. Never waits."""
        return self.sync.pending() if self.sync is not None else None

    def accept(self, epoch: int) -> None:
        """The sink has taken the held block of `epoch` (and reckons from it): what it submits
        from now on is sent. Drops what was submitted before (reckoned from an older state)."""
        assert self.sync is not None
        self._queue.clear()
        self.sync.accept(epoch)

    def synced(self) -> bool:
        """Whether what is submitted now is sent: the sink has taken the current connection's
        held block (always, for a link without sync ranges)."""
        return self.sync is None or self.sync.accepted()

    # ------------------------------------------------------------ between cycles
    def await_held(self, timeout_s: float) -> bool:
        """Between cycles (a lockstep clock's release, the safe output): wait until the link is
        synced or has a held block for the sink to take; False after `timeout_s`."""
        deadline = time.monotonic() + timeout_s
        while not self.synced() and self.held() is None:
            if time.monotonic() >= deadline:
                return False
            self._worker.wake()
            time.sleep(0.002)
        return True

    def flush(self, timeout_s: float = 2.0) -> bool:
        """Wait until every queued write has been acknowledged by the device (or `timeout_s`);
        a write that failed on the way is queued again and retried once the link is back."""
        return self._queue.wait_empty(timeout_s)

    def drain(self, timeout_s: float) -> bool:
        """Every write so far acknowledged by the device before this returns (lockstep runs,
        between two cycles); False after `timeout_s`."""
        self._worker.wake()
        return self._queue.wait_empty(timeout_s)

    def ensure_serving(self, timeout_s: float = 0.5) -> bool:
        """Before the safe output: make sure a live worker will send it. A worker whose
        process has died, or that does not beat within `timeout_s` (stopped, hung), is
        abandoned and replaced by a fresh link on a thread of this process (the daemon is
        stopping: nothing is left to keep off the cycle). True when the old one served."""
        w = self._worker
        if w.running:
            beat = w.beats
            if w.wait_for(lambda: w.beats != beat, timeout_s):
                return True
            reason = f"stopped beating for {timeout_s:.1f} s"
        else:
            reason = w.lost or "its process has ended"
        if self.sync is not None:  # a fresh link: what the device holds is read again before anything is sent
            self.sync.begin()
        if w.wanted or w.lost is not None:
            log.error(
                "%s (pid %s) %s: the safe output goes through a fresh link",
                w.name,
                w.pid or w.lost_pid,
                reason,
                extra={"event": "io_process_lost", "worker": w.name, "pid": w.pid or w.lost_pid, "reason": reason},
            )
            w.abandon(reason)
        w.start(process=False)
        w.lost = None
        return False

    def read_now(self, address: int, count: int) -> list[int] | None:
        """Registers read now (after what is queued is sent), waiting for them (tests, settle);
        None on error or when the link is down."""
        return self._worker.request((address, count), timeout_s=4 * self.timeout_s + 1.0)

    def stop(self, timeout_s: float = 2.0) -> None:
        """Send what is queued (up to `timeout_s`), then close."""
        if self._worker.running:
            self.flush(timeout_s)
        self._worker.stop()
        self._queue.clear()
