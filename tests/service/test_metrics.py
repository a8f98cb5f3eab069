"""Prometheus endpoint: bound to 127.0.0.1, families from the status snapshot, a consistent histogram."""

from __future__ import annotations

import urllib.request

import pytest

from compd.config import load_config
from compd.core.errors import BadInput
from compd.daemon.app import App
from compd.service.metrics import MetricsServer
from compd.service.status import snapshot
from tests.service_helpers import sim_config

pytest.importorskip("prometheus_client")  # the `metrics` extra; the `test` extra installs it


def _scrape(url: str) -> dict[str, float]:
    with urllib.request.urlopen(url, timeout=5) as r:
        text = r.read().decode()
    out = {}
    for line in text.splitlines():
        if line and not line.startswith("#"):
            name, value = line.rsplit(" ", 1)
            out[name] = float(value)
    return out


def _served(app: App, state: str) -> dict[str, float]:
    """The metrics of the loop's snapshot, scraped over HTTP from a server started for it."""
    server = MetricsServer("127.0.0.1", 0)
    url = server.start()
    try:
        server.update(snapshot(app.loop, state=state, observe=False), app.loop.stats)
        return _scrape(url)
    finally:
        server.stop()


def test_metrics_endpoint(tmp_path):
    app = App(load_config(sim_config(tmp_path, duration_s=1200)))
    app.run()
    server = MetricsServer("127.0.0.1", 0)
    url = server.start()
    try:
        assert url.startswith("http://127.0.0.1:")
        # nothing of compd's before the first snapshot (the service's own process_* are there)
        assert not [k for k in _scrape(url) if k.startswith("compd_")]
        snap = snapshot(app.loop, state="running", observe=False)
        server.update(snap, app.loop.stats)
        m = _scrape(url)
    finally:
        server.stop()
    cycles = app.loop.stats.cycles
    assert m["compd_cycles_total"] == cycles
    assert m['compd_cycle_lateness_seconds_bucket{le="+Inf"}'] == cycles
    assert m["compd_cycle_lateness_seconds_count"] == cycles
    buckets = [v for k, v in m.items() if k.startswith("compd_cycle_lateness_seconds_bucket")]
    assert buckets == sorted(buckets)
    assert m["compd_cycle_misses_total"] == app.loop.stats.misses
    assert m['compd_correction_meters{axis="z"}'] == pytest.approx(snap["axes"]["z"]["correction_um"] * 1e-6)
    assert m['compd_prediction_meters{axis="z"}'] == pytest.approx(float(app.loop.pred_um[0]) * 1e-6)
    assert m['compd_prediction_meters{axis="z"}'] > 1e-6
    assert m['compd_signal_celsius{signal="T_xi"}'] == pytest.approx(snap["signals"]["T_xi"]["value"])
    assert m['compd_axis_state{axis="z",state="normal"}'] == 1.0
    assert m['compd_signal_good{signal="T_xi"}'] == 1.0
    assert m['compd_signal_quality{quality="good",signal="T_xi"}'] == 1.0
    assert 'compd_stage_max_seconds{stage="model"}' in m
    assert m["compd_observe_mode"] == 0.0
    assert m['compd_axis_held{axis="z",reason="inhibited"}'] == 0.0


def test_an_axis_the_machine_holds_off(tmp_path):
    app = App(load_config(sim_config(tmp_path, duration_s=60)))
    app.run()
    app.loop.guard.hold[0] = 2  # compd.cycle.inhibit.WAITING: the axis waits for its reference
    m = _served(app, "running")
    assert m['compd_axis_held{axis="z",reason="waiting for reference"}'] == 1.0
    assert m['compd_axis_held{axis="z",reason="inhibited"}'] == 0.0


def test_faults_by_kind(tmp_path):
    from tests.service_helpers import fault_config

    app = App(load_config(fault_config(tmp_path)))
    app.run()
    m = _served(app, "stopped")
    assert m['compd_faults_total{kind="bad:out_of_range"}'] == 1
    assert m['compd_faults_total{kind="fault:input bad"}'] == 1


def test_port_in_use_is_bad_input():
    first = MetricsServer("127.0.0.1", 0)
    first.start()
    try:
        with pytest.raises(BadInput, match="cannot serve metrics"):
            MetricsServer("127.0.0.1", first.port).start()
    finally:
        first.stop()


def test_idle_connections_do_not_block_a_scrape():
    """100 idle TCP connections held open: a scrape is still answered within seconds."""
    import socket
    import time

    server = MetricsServer("127.0.0.1", 0)
    url = server.start()
    socks = []
    try:
        for _ in range(100):
            socks.append(socket.create_connection(("127.0.0.1", server.port), timeout=5))
        t0 = time.monotonic()
        # answered (nothing of compd's to show before the first snapshot)
        assert not [k for k in _scrape(url) if k.startswith("compd_")]
        assert time.monotonic() - t0 < 10.0
    finally:
        for s in socks:
            s.close()
        server.stop()


def test_an_idle_connection_is_closed_after_the_idle_timeout():
    """A client that connects and sends nothing does not hold a thread for ever."""
    import socket

    server = MetricsServer("127.0.0.1", 0)
    server.idle_timeout_s = 0.5
    server.start()
    try:
        with socket.create_connection(("127.0.0.1", server.port), timeout=15) as s:
            assert s.recv(1) == b""  # the server closed it (a timeout here raises instead)
    finally:
        server.stop()


def test_connections_beyond_the_cap_are_closed_not_queued():
    import socket
    import time

    server = MetricsServer("127.0.0.1", 0)
    server.max_connections = 2
    url = server.start()
    socks = []
    try:
        socks = [socket.create_connection(("127.0.0.1", server.port), timeout=15) for _ in range(2)]
        extra = socket.create_connection(("127.0.0.1", server.port), timeout=15)
        with extra:
            assert extra.recv(1) == b""  # turned away at once
        for s in socks:
            s.close()
        socks = []
        deadline = time.monotonic() + 20
        while True:  # the two slots come free once their threads see the close
            try:
                _scrape(url)
                break
            except OSError:
                assert time.monotonic() < deadline
    finally:
        for s in socks:
            s.close()
        server.stop()


def test_the_adaptation_estimate_and_probe_counts(tmp_path):
    from compd.core.probe import Probe

    app = App(load_config(sim_config(tmp_path, "adapt: {}", duration_s=600)))
    app.run()
    ad = app.loop.adapter
    ad.inbox.extend(
        [
            Probe(t_s=app.loop.now_s, axis="z", error_um=float(app.loop.pred_um[0]) + 2.0),
            Probe(t_s=app.loop.now_s, axis="z", error_um=1e4),
        ]
    )  # the second fails the gate
    app.loop.step(app.loop.now_s + 1.0)
    m = _served(app, "stopped")
    assert m['compd_probes_accepted_total{axis="z"}'] == 1
    assert m['compd_probes_rejected_total{axis="z"}'] == 1
    assert m['compd_adapt_offset_meters{axis="z"}'] == pytest.approx(float(ad.est[0].s[0]) * 1e-6)
    assert 0 < m['compd_adapt_offset_meters{axis="z"}'] <= 2e-6
    assert m['compd_adapt_offset_sigma_meters{axis="z"}'] > 0
