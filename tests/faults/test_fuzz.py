"""Hypothesis fuzzing: mutated example configs are always a one-line BadInput (never a traceback);
random Modbus registers, DCON replies and CAN frames never raise out of a source's poll."""

from __future__ import annotations

import contextlib
import io
import math
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from compd.cli import main
from compd.config import load_config
from compd.core.errors import BadInput
from compd.core.frame import Quality
from compd.daemon.app import App
from compd.io.mailbox import Snapshot
from compd.sources.can import CanConfig, CanSource
from compd.sources.dcon import DconConfig, DconSource, parse_reply
from compd.sources.modbus import ModbusConfig, ModbusSource
from tests.conftest import ROOT

CONFIGS = sorted((ROOT / "configs").glob("*.yaml"))
FUZZ = settings(
    max_examples=int(__import__("os").environ.get("COMPD_FUZZ_EXAMPLES", "60")),
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
)

scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(2**40), 2**40),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=12),
)
values = st.recursive(
    scalars,
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner, max_size=3),
    max_leaves=6,
)


def _paths(node: Any, prefix: tuple = ()) -> list[tuple]:
    out = [prefix]
    if isinstance(node, dict):
        for k, v in node.items():
            out += _paths(v, (*prefix, k))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            out += _paths(v, (*prefix, i))
    return out


@st.composite
def mutated_config(draw: st.DrawFn) -> tuple[Path, str]:
    """An example config with one to three random edits: delete, replace, add a key, retype."""
    file = draw(st.sampled_from(CONFIGS))
    data = yaml.safe_load(file.read_text())
    for _ in range(draw(st.integers(1, 3))):
        paths = [p for p in _paths(data) if p]
        path = draw(st.sampled_from(paths))
        parent = data
        for part in path[:-1]:
            parent = parent[part]
        op = draw(st.sampled_from(["delete", "replace", "add", "replace"]))
        if op == "delete" and isinstance(parent, dict):
            del parent[path[-1]]
        elif op == "add" and isinstance(parent, dict):
            parent[draw(st.text(min_size=1, max_size=8))] = draw(values)
        else:
            parent[path[-1]] = draw(values)
    text = yaml.safe_dump(data, allow_unicode=True) if draw(st.booleans()) else _garble(draw, data)
    return file, text


def _garble(draw: st.DrawFn, data: Any) -> str:
    text = yaml.safe_dump(data)
    i = draw(st.integers(0, max(len(text) - 1, 0)))
    return (
        text[:i]
        + draw(st.sampled_from([":", "- ", "\t", "{", "]", "'", "&a", "*b", "!!python/object ", "\n  x"]))
        + text[i:]
    )


@FUZZ
@given(mutated_config())
def test_mutated_configs_are_one_line_bad_input(case: tuple[Path, str]) -> None:
    file, text = case
    try:
        cfg = load_config(file, text=text)  # relative paths resolve next to the example
        app = App(cfg, out=io.StringIO())  # what check-config builds (opens no device)
        if app.logger is not None:
            app.logger.close()
    except BadInput as e:
        msg = str(e)
        assert msg and "\n" not in msg and "Traceback" not in msg
        assert str(file) in msg  # names the file


def test_cli_exit_2_with_one_line(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text((ROOT / "configs" / "demo.yaml").read_text().replace("period_s: 0.2 ", "period_s: [1] "))
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = main(["check-config", str(bad)])
    lines = err.getvalue().strip().splitlines()
    assert code == 2 and len(lines) == 1 and "loop.period_s" in lines[0] and "bad.yaml" in lines[0]


# ---------------------------------------------------------------- replies


class _Reply:
    def __init__(self, registers: list[int] | None, function_code: int = 3) -> None:
        self.registers = registers or []
        self.exception_code = 4
        self.function_code = function_code
        self._error = registers is None

    def isError(self) -> bool:  # noqa: N802  (pymodbus's name)
        return self._error


class _FakeModbusClient:
    """Answers each read with what the test drew: registers, an exception reply or an error."""

    connected = True

    def __init__(self, replies: list[Any]) -> None:
        self.replies = list(replies)
        self.asked: list[tuple[int, int, Any]] = []

    def _read(self, address: int, count: int, device_id: int) -> _Reply:
        from pymodbus.exceptions import ModbusIOException

        r = self.replies.pop(0) if self.replies else None
        self.asked.append((address, count, r))
        if r == "io":
            raise ModbusIOException("timeout")
        if r == "os":
            raise OSError("connection reset")
        if isinstance(r, tuple):  # (registers, function code): a reply of another function
            return _Reply(r[0], r[1])
        return _Reply(r)

    def read_holding_registers(self, address: int, count: int = 1, device_id: int = 1) -> _Reply:
        return self._read(address, count, device_id)

    read_input_registers = read_holding_registers

    def close(self) -> None:
        pass


MODBUS = ModbusConfig.model_validate(
    {
        "kind": "modbus",
        "name": "m",
        "max_gap": 2,
        "channels": [
            {"name": "a", "address": 0, "status_address": 10},
            {"name": "b", "address": 2, "data_type": "float32", "word_order": "little"},
            {"name": "c", "address": 4, "data_type": "uint32", "byte_order": "little", "scale": 0.01},
            {"name": "d", "address": 20, "data_type": "uint16"},
        ],
    }
)
register_list = st.lists(st.integers(0, 0xFFFF), max_size=30)


def _check_frame(values: np.ndarray, quality: np.ndarray) -> None:
    for v, q in zip(values, quality, strict=True):
        assert int(q) in {x.value for x in Quality}
        if q == Quality.GOOD:
            assert math.isfinite(v)


@FUZZ
@given(
    st.lists(
        st.one_of(
            register_list,
            st.none(),
            st.sampled_from(["io", "os"]),
            st.tuples(register_list, st.sampled_from([4, 6, 16, 23])),
        ),
        max_size=4,
    )
)
def test_modbus_poll_never_raises(replies: list[Any]) -> None:
    src = ModbusSource(MODBUS)
    poller = src.make_poller(Snapshot(4))
    client = poller.client._client = _FakeModbusClient(replies)  # under compd's Modbus client
    values = np.full(4, np.nan)
    quality = np.full(4, Quality.NO_DATA, dtype=np.uint8)
    poller.poll(values, quality)
    _check_frame(values, quality)
    # a signal is GOOD only if the reply to its own request had exactly the registers asked
    shaped = {(a, c) for a, c, r in client.asked if isinstance(r, list) and len(r) == c}
    for i, ch in enumerate(poller._channels):
        if quality[i] == Quality.GOOD:
            assert any(a <= ch.address and ch.address + ch.width <= a + c for a, c in shaped), (ch.name, replies)


class _FakeSerial:
    def __init__(self, reply: bytes) -> None:
        self.reply = reply

    def reset_input_buffer(self) -> None:
        pass

    def write(self, data: bytes) -> None:
        pass

    def read_until(self, end: bytes) -> bytes:
        return self.reply

    def close(self) -> None:
        pass


DCON = DconConfig.model_validate(
    {"kind": "dcon", "name": "d", "serial_port": "/dev/null", "channels": ["a", None, "b"]}
)
field = st.one_of(
    st.sampled_from([b"+0021.50", b"-9999.9", b"+9999", b"-0000", b"+1.2.3", b"+.", b"+", b"-nan"]),
    st.from_regex(rb"\A[+-][0-9.]{1,8}\Z", fullmatch=True),
)
dcon_reply = st.one_of(
    st.binary(max_size=40),
    st.builds(
        lambda fs, end: b">" + b"".join(fs) + end, st.lists(field, max_size=5), st.sampled_from([b"\r", b"", b"XX\r"])
    ),
)


@FUZZ
@given(dcon_reply, st.booleans())
def test_dcon_poll_never_raises(reply: bytes, checksum: bool) -> None:
    poller = DconSource(DCON.model_copy(update={"checksum": checksum})).make_poller(Snapshot(2))
    poller._ser = _FakeSerial(reply)
    values = np.full(2, np.nan)
    quality = np.full(2, Quality.NO_DATA, dtype=np.uint8)
    poller.poll(values, quality)
    _check_frame(values, quality)
    with contextlib.suppress(ValueError):  # the parser's only complaint is ValueError
        parse_reply(reply, 1, checksum)


CAN = CanConfig.model_validate(
    {
        "kind": "can",
        "name": "c",
        "interface": "virtual",
        "signals": [
            {"name": "a", "id": 1, "offset": 0, "size": 2},
            {"name": "b", "id": 1, "offset": 4, "size": 4, "signed": False, "byte_order": "big"},
        ],
    }
)


@FUZZ
@given(st.binary(max_size=8))
def test_can_decode_never_raises(data: bytes) -> None:
    src = CanSource(CAN)
    for sig in CAN.signals:
        v, q = src.decode(data, sig)
        assert int(q) in {x.value for x in Quality}
        if q == Quality.GOOD:
            assert math.isfinite(v)
