"""`compd run` with telemetry and opcua: the service process publishes to mosquitto and serves OPC UA.

check-config finds what is wrong.
"""

from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path

from asyncua import Client, ua
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256

from compd.service.status import render

from .broker import SIM_SPINDLE, Listener, Mosquitto, compd, daemon, free_port, metric
from .test_opcua import PASSWORD, Pki

CONFIG = (
    SIM_SPINDLE
    + """\
model: {{kind: xi_spindle, inputs: [T_xi], outputs: [z], params: {{alpha_per_k: 13.6e-6, length_mm: 165.0}}}}
sink: {{kind: pci1756}}
status: {{path: status.json, period_s: 0.5}}
telemetry:
  port: {mqtt_port}
  group_id: hall2
  edge_node_id: cell7
  device_id: lathe
  period_s: 0.2
opcua:
  port: {ua_port}
  certificate: pki/server.pem
  private_key: pki/server.key
  trusted_clients: pki/trusted
  users: {{alice: {{password_file: pki/alice.password}}}}
  namespace_uri: urn:compd:test
"""
)


async def read_nodes(url: str, pki: Pki, names: list[str]) -> dict[str, object]:
    client = Client(url, timeout=30)
    cert, key, uri = pki.client("client")
    client.application_uri = uri
    await client.set_security(SecurityPolicyBasic256Sha256, cert, key, mode=ua.MessageSecurityMode.SignAndEncrypt)
    client.set_user("alice")
    client.set_password(PASSWORD)
    await client.connect()
    try:
        idx = await client.get_namespace_index("urn:compd:test")
        return {n: await client.get_node(ua.NodeId(n, idx)).read_value() for n in names}
    finally:
        await client.disconnect()


def test_the_daemon_publishes_and_serves(tmp_path: Path) -> None:
    (tmp_path / "pki").mkdir()
    pki = Pki(tmp_path / "pki")
    ua_port = free_port()
    with Mosquitto(tmp_path / "broker") as broker:
        cfg = tmp_path / "c.yaml"
        cfg.write_text(CONFIG.format(mqtt_port=broker.port, ua_port=ua_port))
        check = compd("check-config", str(cfg), cwd=tmp_path)
        assert check.stdout.strip() == "ok", check.stderr
        listener = Listener(broker.port)
        try:
            with daemon(cfg, tmp_path / "stderr.txt") as proc:
                listener.wait_for(lambda: len(listener.of("DDATA")) >= 5, timeout_s=60)
                deadline = time.monotonic() + 60
                while "OPC UA on" not in (tmp_path / "stderr.txt").read_text() and time.monotonic() < deadline:
                    time.sleep(0.1)
                url = f"opc.tcp://127.0.0.1:{ua_port}/compd/"
                values = asyncio.run(
                    read_nodes(
                        url,
                        pki,
                        ["compd.State", "compd.Axes.z.ModelKind", "compd.Loop.Cycles", "compd.Signals.T_xi.Quality"],
                    )
                )
                status = json.loads((tmp_path / "status.json").read_text())
        finally:
            listener.stop()
    text = (tmp_path / "stderr.txt").read_text()
    assert proc.returncode == 0, text
    assert values["compd.State"] == "running" and values["compd.Axes.z.ModelKind"] == "xi_spindle"
    assert values["compd.Loop.Cycles"] > 0 and values["compd.Signals.T_xi.Quality"] == "good"
    births = listener.of("DBIRTH")
    assert births and births[0].topic == "spBv1.0/hall2/DBIRTH/cell7/lathe"
    assert metric(births[0].payload, "Model/kind").value == "xi_spindle"
    kinds = [
        metric(m.payload, "Event/kind").value
        for m in listener.of("DDATA")
        if any(x.name == "Event/kind" for x in m.payload.metrics)
    ]
    assert kinds[0] == "started" and kinds[-1] == "stopping"
    assert len(listener.of("NDEATH")) == 1  # said on the way out
    assert status["telemetry"]["connected"] is True and status["telemetry"]["dropped"] == 0
    assert status["opcua"]["endpoint"] == f"opc.tcp://127.0.0.1:{ua_port}/compd/"
    shown = render(status, True, "")  # what `compd status` prints
    assert f"telemetry: 127.0.0.1:{broker.port} connected;" in shown
    assert f"opcua: opc.tcp://127.0.0.1:{ua_port}/compd/" in shown
    samples = [
        metric(m.payload, "Sample").value
        for m in listener.of("DDATA")
        if any(x.name == "Sample" for x in m.payload.metrics)
    ]
    assert samples == list(range(1, len(samples) + 1))  # every one, in order, once


def test_check_config_names_what_is_wrong(tmp_path: Path) -> None:
    (tmp_path / "pki").mkdir()
    Pki(tmp_path / "pki")
    cfg = tmp_path / "c.yaml"
    good = CONFIG.format(mqtt_port=1883, ua_port=4840)
    cases = [
        (good.replace("group_id: hall2", "group_id: hall/2"), "telemetry.group_id"),
        (
            good.replace("  period_s: 0.2\n", "  period_s: 0.2\n  password_file: nope.txt\n  username: u\n"),
            "telemetry.password_file",
        ),
        (
            good.replace("  period_s: 0.2\n", "  period_s: 0.2\n  remote_models: {allow: true}\n"),
            "telemetry.remote_models.allow",
        ),
        (
            good.replace("  period_s: 0.2\n", "  period_s: 0.2\n  remote_models: {arm_signal: nope}\n"),
            "telemetry.remote_models.arm_signal",
        ),
        (good.replace("pki/server.key", "pki/missing.key"), "opcua.private_key"),
        (good.replace("  users: {alice: {password_file: pki/alice.password}}\n", ""), "opcua.users"),
        (good.replace("  period_s: 0.2\n", "  period_s: 0.2\n  tls: {ca_file: ca.pem}\n"), "telemetry.tls.ca_file"),
        # a buffer too small for one sample would have stopped the service at start
        (good.replace("  period_s: 0.2\n", "  period_s: 0.2\n  buffer: {max_mb: 1.0e-7}\n"), "telemetry.buffer.max_mb"),
        # what would have left the daemon running without OPC UA
        (good.replace("  port: 4840\n", "  port: 4840\n  bind: 'not an addr'\n"), "opcua.bind"),
        (good.replace("private_key: pki/server.key", "private_key: pki/server.pem"), "opcua.private_key"),
    ]
    for text, key in cases:
        cfg.write_text(text)
        r = compd("check-config", str(cfg), cwd=tmp_path)
        assert r.returncode == 2, (key, r.stdout, r.stderr)
        line = r.stderr.strip()
        assert "\n" not in line and key in line and "Traceback" not in line, (key, line)
        assert f"{cfg}:" in line


def test_an_opcua_server_that_cannot_start_is_tried_again(tmp_path: Path) -> None:
    """The OPC UA port is taken when the daemon starts: the failure is said once, compensation and
    telemetry go on, and once the port is free the server comes up without a restart."""
    import socket

    (tmp_path / "pki").mkdir()
    Pki(tmp_path / "pki")
    blocker = socket.socket()
    blocker.bind(("127.0.0.1", 0))
    blocker.listen()
    ua_port = blocker.getsockname()[1]
    err = tmp_path / "stderr.txt"
    with Mosquitto(tmp_path / "broker") as broker:
        cfg = tmp_path / "c.yaml"
        cfg.write_text(CONFIG.format(mqtt_port=broker.port, ua_port=ua_port))
        try:
            with daemon(cfg, err) as proc:
                deadline = time.monotonic() + 90
                while "event=opcua_error" not in err.read_text():
                    assert time.monotonic() < deadline, err.read_text()[-2000:]
                    time.sleep(0.1)
                blocker.close()  # the port is free again
                while "OPC UA on" not in err.read_text():
                    assert time.monotonic() < deadline, err.read_text()[-2000:]
                    time.sleep(0.1)
                status = None
                while status is None or not (status.get("opcua") or {}).get("endpoint"):
                    assert time.monotonic() < deadline
                    time.sleep(0.1)
                    status = json.loads((tmp_path / "status.json").read_text())
        finally:
            blocker.close()
    text = err.read_text()
    assert proc.returncode == 0, text
    assert text.count("event=opcua_error") == 1  # said once, however many tries
    assert status["opcua"]["endpoint"] == f"opc.tcp://127.0.0.1:{ua_port}/compd/"
