"""The `probe` source: the CNC's probe-result block over Modbus TCP, each new result into its ring once (the
cycle takes them from there into the adapter's inbox)."""

from __future__ import annotations

import math
import time
from collections import deque

import numpy as np
import pytest

from compd.config import load_config
from compd.core.config import AdaptConfig
from compd.core.errors import ConfigError
from compd.cycle.adapt import Adapter
from compd.plc.fanuc_pmc import FanucPmc
from compd.plc.probe_block import encode_result
from compd.plc.siemens_nc import SiemensNc
from compd.sources.probe import ProbeConfig, ProbeSource
from hil_sim.devices.modbus_server import ModbusServerThread
from tests.sources.helpers import Harness
from tests.sources.rawmodbus import RawModbusServer


class RingInbox:
    """The probes the source's worker put in its ring, as the adapter's inbox would hold them."""

    def __init__(self) -> None:
        self._got: deque = deque()
        self._ring = None

    def attach(self, src: ProbeSource) -> None:
        src.bind_probes(deque())
        self._ring = src.probe_ring()

    def _drain(self) -> deque:
        if self._ring is not None:
            self._got.extend(self._ring.take())
        return self._got

    def __len__(self) -> int:
        return len(self._drain())

    def __iter__(self):  # noqa: ANN204
        return iter(list(self._drain()))

    def popleft(self):  # noqa: ANN201
        return self._drain().popleft()


def _source(port: int, cnc: str = "fanuc_pmc", axes=("x", "z")) -> ProbeSource:
    cfg = ProbeConfig.model_validate(
        {
            "kind": "probe",
            "name": "cnc_probe",
            "port": port,
            "cnc": cnc,
            "axes": list(axes),
            "poll_period_s": 0.01,
        }
    )
    return ProbeSource(cfg)


def _wait_polls(src: ProbeSource, n: int = 2, timeout_s: float = 10.0) -> None:
    want = src.polls + n
    deadline = time.monotonic() + timeout_s
    while src.polls < want:
        assert time.monotonic() < deadline, src.get_status()
        time.sleep(0.005)


@pytest.mark.parametrize("cnc", ["fanuc_pmc", "siemens_nc"])
def test_each_published_result_reaches_the_inbox_once(cnc):
    dev = FanucPmc() if cnc == "fanuc_pmc" else SiemensNc(axes=2)
    dev.publish_probe(0, 9.9)  # in the block before compd starts: of unknown age, not used
    inbox = RingInbox()
    with ModbusServerThread(dev, port=0) as srv:
        src = _source(srv.port, cnc)
        assert src.signal_names() == []
        inbox.attach(src)
        with Harness(src):
            _wait_polls(src)
            assert not inbox
            dev.publish_probe(1, -2.345, 123.456, 0.25)
            _wait_polls(src, 3)  # the same result polled again and again: one probe
            assert len(inbox) == 1
            p = inbox.popleft()
            assert (p.axis, p.error_um, p.position_mm, p.sigma_um) == ("z", -2.345, 123.456, 0.25)
            assert p.residual and p.source == "cnc_probe" and p.t_s > 0
            dev.publish_probe(0, 1.5)
            _wait_polls(src, 3)
            assert [(q.axis, q.error_um, q.position_mm, q.sigma_um) for q in inbox] == [("x", 1.5, None, None)]
            st = src.get_status()
            assert st["probes"] == 2 and st["missed"] == 0 and st["last_seq"] == 3


def test_a_wrapped_sequence_number_is_a_new_result():
    pmc = FanucPmc()
    pmc.write_registers(500, encode_result(0xFFFE, 0, 1.0))
    inbox = RingInbox()
    with ModbusServerThread(pmc, port=0) as srv:
        src = _source(srv.port)
        inbox.attach(src)
        with Harness(src):
            _wait_polls(src)
            assert pmc.publish_probe(0, 2.0) == 0xFFFF
            _wait_polls(src)
            assert pmc.publish_probe(0, 3.0) == 0  # wrapped
            _wait_polls(src)
            assert [p.error_um for p in inbox] == [2.0, 3.0]


def test_results_between_polls_count_as_missed_and_torn_blocks_wait():
    pmc = FanucPmc()
    inbox = RingInbox()
    with ModbusServerThread(pmc, port=0) as srv:
        src = _source(srv.port)
        inbox.attach(src)
        with Harness(src):
            _wait_polls(src)
            with pmc._lock:  # the cycle writes the block: first sequence number only so far
                pmc.probe.regs[:] = encode_result(1, 0, 4.0)
                pmc.probe.regs[7] = 0
            _wait_polls(src)
            assert not inbox and src.get_status()["torn"] >= 1
            pmc.write_registers(507, [1])  # done: the last register written
            _wait_polls(src)
            assert [p.error_um for p in inbox] == [4.0]
            with pmc._lock:  # three results between two polls: the newest is read, two missed
                for k in range(3):
                    pmc.probe.publish(1, 5.0 + k, None, None)
            _wait_polls(src)
            assert [p.error_um for p in inbox] == [4.0, 7.0]
            assert src.get_status()["missed"] == 2


def test_bad_axis_index_and_malformed_replies_are_faults_not_probes():
    inbox = RingInbox()
    with RawModbusServer({}) as srv:

        def put(regs: list[int]) -> None:
            srv.registers.update(zip(range(500, 508), regs, strict=True))

        src = _source(srv.port, axes=("x",))
        inbox.attach(src)
        with Harness(src):
            _wait_polls(src)
            put(encode_result(1, 3, 2.0))  # axis index 3, one axis configured
            _wait_polls(src)
            assert not inbox and src.get_status()["bad_axis"] == 1
            srv.set("fewer")  # 7 registers for 8 asked
            deadline = time.monotonic() + 10
            while src.get_status()["malformed_replies"] < 2:
                assert time.monotonic() < deadline
                time.sleep(0.01)
            put(encode_result(2, 0, 2.5))
            time.sleep(0.1)
            assert not inbox  # nothing trusted from a short reply
            srv.set("none")
            _wait_polls(src, 2)
            assert [p.error_um for p in inbox] == [2.5]


def test_bad_config_names_the_key(tmp_path):
    text = """\
loop: {period_s: 0.1}
sources:
  - kind: probe
    name: p
    cnc: heidenhain
    axes: [z]
model: {kind: mlr, inputs: [], outputs: [z], params: {}}
sink: {kind: pci1756}
"""
    p = tmp_path / "c.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError) as ei:
        load_config(p)
    assert "cnc" in str(ei.value) and "\n" not in str(ei.value)


def test_a_result_published_while_the_link_was_down_is_skipped_then_new_ones_count():
    pmc = FanucPmc()
    inbox = RingInbox()
    srv = ModbusServerThread(pmc, port=0).start()
    port = srv.port
    try:
        src = _source(port)
        inbox.attach(src)
        with Harness(src):
            _wait_polls(src)
            srv.stop()
            deadline = time.monotonic() + 10
            while src.get_status()["state"] != "down":
                assert time.monotonic() < deadline
                time.sleep(0.01)
            pmc.publish_probe(0, 1.0)  # while compd cannot read: of unknown age when it can
            srv = ModbusServerThread(pmc, port=port).start()
            _wait_polls(src, 2, timeout_s=20)
            assert not inbox
            pmc.publish_probe(0, 2.0)
            _wait_polls(src)
            assert [p.error_um for p in inbox] == [2.0]
    finally:
        srv.stop()


def test_a_reload_that_keeps_the_probe_source_hands_its_probes_to_the_new_adapter(tmp_path):
    from compd.daemon.app import App

    text = """\
loop: {{period_s: 0.1}}
sources:
  - {{kind: modbus, name: t, port: 5998, channels: [{{name: T_xi, address: 0}}]}}
  - {{kind: probe, name: p, port: 5999, cnc: siemens_nc, axes: [z]}}
model: {{kind: xi_spindle, inputs: [T_xi], outputs: [z], params: {{alpha_per_k: 13.6e-6, length_mm: 165.0}}}}
sink: {{kind: pci1756}}
adapt: {{sigma_um: {sigma}}}
"""
    paths = []
    for k, sigma in enumerate((0.3, 0.4)):
        p = tmp_path / f"c{k}.yaml"
        p.write_text(text.format(sigma=sigma))
        paths.append(p)
    from compd.core.probe import Probe

    old, new = App(load_config(paths[0])), App(load_config(paths[1]))
    src = old.sources[1]
    old.service.publisher.watch_probes(old.loop.sources)
    assert src.probe_ring() in old.service.publisher.probe_rings
    new.adopt(old)
    assert new.sources[1] is src  # unchanged section: taken over
    new.service.publisher.watch_probes(new.loop.sources)  # (what starting the new service does)
    src.probe_ring().put(Probe(t_s=1.0, axis="z", error_um=2.0, source="p", residual=True))
    new.service.publisher.after_cycle(float("inf"))  # the new pipeline's cycle takes it
    assert [p.error_um for p in new.loop.adapter.inbox] == [2.0] and not old.loop.adapter.inbox


def test_a_result_no_probe_measures_from_the_cnc_is_rejected_by_the_adapter_with_its_reason():
    """The block holds what a macro wrote: a deviation of 2 m fits its int32 of nm. The source hands
    it on as it reads it; the adapter, where every probe passes, rejects it and says why."""
    pmc = FanucPmc()
    inbox = RingInbox()
    ad = Adapter(AdaptConfig(), ["x", "z"])
    with ModbusServerThread(pmc, port=0) as srv:
        src = _source(srv.port)
        inbox.attach(src)
        with Harness(src):
            _wait_polls(src)
            pmc.publish_probe(1, 2_000_000.0, None, 65.535)  # 2 m, the block's largest σ
            _wait_polls(src, 3)
            pmc.publish_probe(1, 1.5, 200.0, 0.3)  # then a sound one
            _wait_polls(src, 3)
            probes = list(inbox)
    assert [p.error_um for p in probes] == [2_000_000.0, 1.5]
    out = np.zeros(2)
    for p in probes:
        ad.inbox.append(p)
        ad.apply(np.array([0.0, 8.0]), p.t_s, out, applied_um=np.array([0.0, -8.0]))
    verdicts = [e for e in ad.events if e["event"] in ("accepted", "rejected")]
    big, sound = verdicts
    assert big["event"] == "rejected" and big["reason"].startswith("error_um 2e+06 um is beyond"), big
    assert big["source"] == "cnc_probe" and math.isnan(big["innovation_um"])
    assert sound["event"] == "accepted" and ad.get_status()["z"]["accepted"] == 1
