"""The packaged unit's IP sandbox said where it bites: a broker connect() refused with EPERM names the
sandbox and the drop-in; an OPC UA server on an address other than loopback, started by systemd, says
that only localhost reaches it unless the drop-in allows more."""

from __future__ import annotations

import errno
import logging
import socket
import time
from pathlib import Path
from typing import Any

import pytest

from compd.plant.sandbox import is_loopback, listening_hint
from compd.plant.telemetry import Telemetry

from .broker import free_port
from .test_telemetry import feed, spec


def test_a_broker_connect_refused_by_this_host_names_the_sandbox_and_the_drop_in(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: Any
) -> None:
    """Under IPAddressDeny the kernel fails connect() with EPERM: the telemetry's real connect path
    (paho's socket) meets it here from a connect() that raises what the kernel returns."""
    caplog.set_level(logging.INFO, logger="compd.telemetry")
    port = free_port()
    real_connect = socket.socket.connect

    def connect(self: socket.socket, address: Any) -> None:
        if isinstance(address, tuple) and address[1] == port:
            raise PermissionError(errno.EPERM, "Operation not permitted")
        real_connect(self, address)

    monkeypatch.setattr(socket.socket, "connect", connect)
    tel = Telemetry(spec(tmp_path, port, reconnect_max_s=0.5))
    try:
        tel.start()
        feed(tel, 0, 1, time.time())  # the first sample: it connects
        deadline = time.monotonic() + 30
        while "sandbox" not in (tel.get_status()["last_error"] or "") and time.monotonic() < deadline:
            time.sleep(0.05)
        st = tel.get_status()
    finally:
        tel.stop()
    assert not st["connected"]
    assert st["last_error"].startswith(
        f"cannot connect to 127.0.0.1:{port}: Operation not permitted (refused by this"
        " host, not by 127.0.0.1: the service's IP sandbox"
    ), st["last_error"]
    assert "install the network drop-in with IPAddressAllow=127.0.0.1" in st["last_error"]
    said = [r for r in caplog.records if getattr(r, "event", None) == "telemetry_down"]
    assert len(said) == 1 and "IPAddressDeny=any" in said[0].getMessage()


def test_a_refusal_elsewhere_is_not_blamed_on_the_sandbox(tmp_path: Path) -> None:
    """Nothing listening: ECONNREFUSED, from the other end, says nothing of a sandbox."""
    tel = Telemetry(spec(tmp_path, free_port(), reconnect_max_s=0.5))
    try:
        tel.start()
        feed(tel, 0, 1, time.time())
        deadline = time.monotonic() + 30
        while tel.get_status()["last_error"] is None and time.monotonic() < deadline:
            time.sleep(0.05)
        err = tel.get_status()["last_error"]
    finally:
        tel.stop()
    assert "Connection refused" in err and "sandbox" not in err


def test_an_opcua_server_beyond_loopback_under_systemd_says_what_reaches_it() -> None:
    systemd = {"INVOCATION_ID": "0123456789abcdef0123456789abcdef"}
    hint = listening_hint("the OPC UA server", "0.0.0.0", env=systemd)
    assert hint is not None
    assert "only localhost reaches it" in hint and "IPAddressAllow=" in hint and "network drop-in" in hint
    assert listening_hint("the OPC UA server", "192.0.2.10", env=systemd) is not None
    assert listening_hint("the OPC UA server", "127.0.0.1", env=systemd) is None  # what the sandbox lets in
    assert listening_hint("the OPC UA server", "0.0.0.0", env={}) is None  # not systemd's: no sandbox known
    assert [
        is_loopback(a) for a in ("127.0.0.1", "127.1.2.3", "::1", "[::1]", "localhost", "0.0.0.0", "::", "machine1")
    ] == [True, True, True, True, True, False, False, False]
