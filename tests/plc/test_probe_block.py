"""The probe-result block of the software PLC devices: layout, publish, sequence, the maps around it."""

from __future__ import annotations

import pytest

from compd.plc.fanuc_pmc import FanucPmc
from compd.plc.probe_block import NO_POSITION, decode_result, encode_result
from compd.plc.siemens_nc import SiemensNc


def test_encode_decode_round_trip_to_the_nanometre():
    regs = encode_result(7, 1, -12.345, 300.125, 0.3)
    assert regs[0] == regs[7] == 7 and regs[1] == 1
    r = decode_result(regs)
    assert r is not None
    assert (r.seq, r.axis, r.deviation_um, r.position_mm, r.sigma_um) == (7, 1, -12.345, 300.125, 0.3)
    none = decode_result(encode_result(8, 0, 0.004))
    assert none is not None and none.position_mm is None and none.sigma_um is None
    assert (encode_result(1, 0, 0.0)[4] << 16 | encode_result(1, 0, 0.0)[5]) == NO_POSITION


def test_a_block_being_written_is_not_a_result():
    regs = encode_result(5, 0, 1.0)
    regs[0] = 6  # the cycle started writing result 6
    assert decode_result(regs) is None
    with pytest.raises(ValueError):
        decode_result(regs[:7])


@pytest.mark.parametrize("make, base", [(FanucPmc, 500), (lambda: SiemensNc(axes=2), 1000)])
def test_publish_probe_writes_the_block_with_the_next_sequence_number(make, base):
    dev = make()
    assert dev.read_registers(base, 8) == [0] * 8
    assert dev.publish_probe(1, 3.21, 150.0, 0.25) == 1
    r = decode_result(dev.read_registers(base, 8))
    assert r is not None and (r.seq, r.axis, r.deviation_um, r.position_mm, r.sigma_um) == (1, 1, 3.21, 150.0, 0.25)
    assert dev.publish_probe(0, -0.5) == 2
    dev.write_registers(base, [0xFFFF] + [0] * 6 + [0xFFFF])  # a client may write the block too
    assert dev.publish_probe(0, 1.0) == 0  # mod 65536
    assert dev.read_registers(base + 8, 1) is None  # nothing past the block
    assert dev.read_registers(base - 1, 2) is None  # nor across its start


def test_existing_maps_unchanged():
    pmc = FanucPmc()
    assert pmc.read_registers(416, 1) is None and pmc.read_registers(316, 1) is None
    assert pmc.read_registers(400, 16) is not None
    nc = SiemensNc(axes=2)
    assert nc.read_registers(0, 32) is not None
    assert nc.read_registers(32, 1) is None and nc.read_registers(30, 4) is None
    assert not nc.write_registers(11, [0, 0])  # applied ΔK stays read only
    with pytest.raises(ValueError):
        SiemensNc(axes=63)
