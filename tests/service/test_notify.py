"""systemd notify protocol: addresses, watchdog interval, datagrams, the cycle observer."""

from __future__ import annotations

import os
import socket

import pytest

from compd.service.notify import Notifier, WatchdogObserver, socket_address, watchdog_interval_s


@pytest.fixture
def listener(tmp_path):
    """A bound unix datagram socket standing in for systemd."""
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    path = tmp_path / "notify.sock"
    sock.bind(str(path))
    sock.settimeout(5)
    yield sock, str(path)
    sock.close()


def test_abstract_address():
    assert socket_address("@compd/notify") == "\0compd/notify"
    assert socket_address("/run/systemd/notify") == "/run/systemd/notify"


def test_watchdog_interval():
    assert watchdog_interval_s({}) is None
    assert watchdog_interval_s({"WATCHDOG_USEC": "5000000"}) == 5.0
    assert watchdog_interval_s({"WATCHDOG_USEC": "5000000", "WATCHDOG_PID": "1"}, pid=2) is None
    assert watchdog_interval_s({"WATCHDOG_USEC": "250000", "WATCHDOG_PID": "7"}, pid=7) == 0.25
    assert watchdog_interval_s({"WATCHDOG_USEC": "junk"}) is None
    assert watchdog_interval_s({"WATCHDOG_USEC": "0"}) is None


def test_send_to_path(listener):
    sock, path = listener
    n = Notifier.from_env({"NOTIFY_SOCKET": path})
    try:
        assert n.send(READY=1, STATUS="two\nlines")
        assert sock.recv(4096).decode() == "READY=1\nSTATUS=two lines"
    finally:
        n.close()
    assert not n.send(WATCHDOG=1)  # closed: nothing, no exception


def test_send_to_abstract_socket():
    name = f"@compd-test-{os.getpid()}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(socket_address(name))
    sock.settimeout(5)
    n = Notifier(name)
    try:
        assert n.send(STOPPING=1)
        assert sock.recv(4096) == b"STOPPING=1"
    finally:
        n.close()
        sock.close()


def test_no_socket_is_no_notifier_and_dead_socket_is_harmless(tmp_path):
    assert Notifier.from_env({}) is None
    n = Notifier(str(tmp_path / "nobody-listens"))
    try:
        assert not n.send(READY=1)
        assert n.errors == 1
    finally:
        n.close()


def test_observer_ready_once_then_pings_at_half_the_watchdog(listener):
    sock, path = listener
    t = [100.0]
    n = Notifier(path)
    obs = WatchdogObserver(n, 2.0, status="compensating", clock=lambda: t[0])
    try:
        obs(None, 0.0)  # the first cycle pings with READY: after a reload the interval starts here
        assert sock.recv(4096) == b"READY=1\nSTATUS=compensating\nWATCHDOG=1"
        for dt in (0.3, 0.3, 0.3):  # 0.9 s < 1.0 s: nothing
            t[0] += dt
            obs(None, 0.0)
        assert obs.pings == 1
        t[0] += 0.11
        obs(None, 0.0)
        assert sock.recv(4096) == b"WATCHDOG=1"
        assert obs.pings == 2
        obs.ping()  # a reload pauses the loop: the daemon pings as it starts building the new pipeline
        assert sock.recv(4096) == b"WATCHDOG=1" and obs.pings == 3
    finally:
        n.close()


def test_observer_without_watchdog_only_readies(listener):
    sock, path = listener
    t = [0.0]
    n = Notifier(path)
    obs = WatchdogObserver(n, None, clock=lambda: t[0])
    try:
        for _ in range(5):
            obs(None, 0.0)
            t[0] += 1000.0
        assert obs.ready and obs.pings == 0 and n.sent == 1
    finally:
        n.close()


def test_observer_sends_the_service_s_status_line_from_the_main_process_when_it_changes(listener):
    """The service composes STATUS= (in a process of its own); the cycle sends it, so every
    message comes from the main process (NotifyAccess=main)."""
    from compd.io.ring import SharedBlob

    sock, path = listener
    sock.settimeout(5)
    t = [0.0]
    n = Notifier(path)
    line = SharedBlob(64)
    obs = WatchdogObserver(n, None, status="compensating", clock=lambda: t[0], status_line=line)
    try:
        obs(None, 0.0)
        assert sock.recv(4096) == b"READY=1\nSTATUS=compensating"
        line.publish(b"compensating: word 0xC500, z=normal, 0 missed")
        for _ in range(3):  # checked once a second, sent once
            t[0] += 1.0
            obs(None, 0.0)
        assert sock.recv(4096) == b"STATUS=compensating: word 0xC500, z=normal, 0 missed"
        assert n.sent == 2
        line.publish(b"compensating: word 0xC600, z=normal, 0 missed")
        t[0] += 1.0
        obs(None, 0.0)
        assert sock.recv(4096).endswith(b"0xC600, z=normal, 0 missed") and n.sent == 3
    finally:
        n.close()


def test_the_watchdog_is_no_longer_fed_once_the_supervisor_gave_up(listener):
    """Too many lost child processes (compd.io.supervisor escalated): the cycle stops pinging,
    says why once in STATUS=, and systemd's watchdog restarts the daemon."""
    sock, path = listener
    n = Notifier(path)
    t = [0.0]
    healthy = [True]
    obs = WatchdogObserver(n, 2.0, status="compensating", clock=lambda: t[0], healthy=lambda: healthy[0])
    try:
        obs(None, 0.0)
        assert sock.recv(4096) == b"READY=1\nSTATUS=compensating\nWATCHDOG=1"
        t[0] += 1.1
        obs(None, 0.0)
        assert sock.recv(4096) == b"WATCHDOG=1"
        healthy[0] = False
        for _ in range(3):
            t[0] += 1.1
            obs(None, 0.0)
        assert sock.recv(4096).startswith(b"STATUS=I/O processes keep dying")
        assert obs.pings == 2 and obs.starved and n.sent == 3
        obs.ping()  # nor at a reload
        assert obs.pings == 2 and n.sent == 3
    finally:
        n.close()
