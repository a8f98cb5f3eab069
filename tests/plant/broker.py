"""Test helpers for the plant: Debian's mosquitto on 127.0.0.1 with a config the test writes, a
Sparkplug subscriber of its own (paho-mqtt + compd.plant.sparkplug.decode), certificates."""

from __future__ import annotations

import contextlib
import datetime as dt
import getpass
import ipaddress
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import paho.mqtt.client as mqtt
import pytest
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import rsa
from cryptography.x509.oid import NameOID

from compd.plant.sparkplug import AliasResolver, Payload, decode

# the start of a daemon's config (str.format-escaped): the sim spindle at wall-clock pace
SIM_SPINDLE = """\
loop: {{clock: sim, period_s: 0.05, speedup: 1}}
sources:
  - kind: sim
    name: spindle
    plant: spindle
    scenario: {{seed: 3, segments: [{{duration_s: 86400, speed_rpm: 10000}}]}}
"""

MOSQUITTO = shutil.which("mosquitto") or ("/usr/sbin/mosquitto" if Path("/usr/sbin/mosquitto").exists() else None)
MOSQUITTO_PASSWD = shutil.which("mosquitto_passwd") or (
    "/usr/bin/mosquitto_passwd" if Path("/usr/bin/mosquitto_passwd").exists() else None
)


def need_mosquitto() -> str:
    if MOSQUITTO is None:
        pytest.fail("mosquitto is not installed: `make sysdeps` installs it")
    return MOSQUITTO


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_port(port: int, timeout_s: float = 20.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                return
        except OSError:
            time.sleep(0.05)
    raise TimeoutError(f"nothing listens on 127.0.0.1:{port}")


@dataclass
class Tls:
    """A CA, the broker's certificate and a client's, in `folder`."""

    folder: Path
    ca: Path = field(init=False)
    server_cert: Path = field(init=False)
    server_key: Path = field(init=False)
    client_cert: Path = field(init=False)
    client_key: Path = field(init=False)

    def __post_init__(self) -> None:
        f = self.folder
        f.mkdir(parents=True, exist_ok=True)
        ca_key = _key()
        ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "compd test CA")])
        now = dt.datetime.now(dt.UTC)
        ca_cert = (
            x509.CertificateBuilder()
            .subject_name(ca_name)
            .issuer_name(ca_name)
            .public_key(ca_key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - dt.timedelta(days=1))
            .not_valid_after(now + dt.timedelta(days=30))
            .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
            .sign(ca_key, hashes.SHA256())
        )
        self.ca = _write_cert(f / "ca.pem", ca_cert)
        self.server_cert, self.server_key = self._leaf("server", ca_key, ca_cert, server=True)
        self.client_cert, self.client_key = self._leaf("client", ca_key, ca_cert, server=False)

    def _leaf(self, name: str, ca_key: Any, ca_cert: Any, server: bool) -> tuple[Path, Path]:
        key = _key()
        now = dt.datetime.now(dt.UTC)
        b = (
            x509.CertificateBuilder()
            .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "127.0.0.1" if server else name)]))
            .issuer_name(ca_cert.subject)
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - dt.timedelta(days=1))
            .not_valid_after(now + dt.timedelta(days=30))
        )
        if server:
            b = b.add_extension(
                x509.SubjectAlternativeName(
                    [x509.IPAddress(ipaddress.ip_address("127.0.0.1")), x509.DNSName("localhost")]
                ),
                critical=False,
            )
        cert = b.sign(ca_key, hashes.SHA256())
        kpath = self.folder / f"{name}.key"
        kpath.write_bytes(
            key.private_bytes(
                serialization.Encoding.PEM, serialization.PrivateFormat.TraditionalOpenSSL, serialization.NoEncryption()
            )
        )
        kpath.chmod(0o600)
        return _write_cert(self.folder / f"{name}.pem", cert), kpath


def _key() -> Any:
    return rsa.generate_private_key(public_exponent=65537, key_size=2048)


def _write_cert(path: Path, cert: Any) -> Path:
    path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    return path


class Mosquitto:
    """mosquitto on 127.0.0.1:`port` with a config written here; `kill` and `start` again for an outage."""

    def __init__(
        self,
        folder: Path,
        *,
        users: dict[str, str] | None = None,
        tls: Tls | None = None,
        require_certificate: bool = False,
    ) -> None:
        self.exe = need_mosquitto()
        self.folder = folder
        folder.mkdir(parents=True, exist_ok=True)
        self.port = free_port()
        lines = [
            f"listener {self.port} 127.0.0.1",
            f"user {getpass.getuser()}",
            "persistence false",
            f"log_dest file {folder / 'mosquitto.log'}",
            "log_type error",
            "log_type warning",
            "max_queued_messages 100000",
            "max_inflight_messages 0",
        ]
        if users:
            pw = folder / "passwd"
            pw.write_text("")
            for user, password in users.items():
                subprocess.run(
                    [MOSQUITTO_PASSWD or "mosquitto_passwd", "-b", str(pw), user, password],
                    check=True,
                    capture_output=True,
                )
            pw.chmod(0o600)
            lines += ["allow_anonymous false", f"password_file {pw}"]
        else:
            lines.append("allow_anonymous true")
        if tls is not None:
            lines += [
                f"cafile {tls.ca}",
                f"certfile {tls.server_cert}",
                f"keyfile {tls.server_key}",
                f"require_certificate {'true' if require_certificate else 'false'}",
            ]
        self.conf = folder / "mosquitto.conf"
        self.conf.write_text("\n".join(lines) + "\n")
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> Mosquitto:
        self.proc = subprocess.Popen(
            [self.exe, "-c", str(self.conf)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
        )
        try:
            wait_port(self.port)
        except TimeoutError:
            self.kill()
            raise
        return self

    def kill(self) -> None:
        if self.proc is not None:
            self.proc.kill()
            self.proc.wait(10)
            if self.proc.stderr is not None:
                self.proc.stderr.close()
            self.proc = None

    def __enter__(self) -> Mosquitto:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.kill()


@dataclass
class Message:
    topic: str
    kind: str  # NBIRTH, DDATA, …
    payload: Payload
    t_recv_s: float


class Listener:
    """A Sparkplug host of the test's own: subscribes to spBv1.0/#, decodes every message."""

    def __init__(
        self,
        port: int,
        *,
        username: str | None = None,
        password: str | None = None,
        tls: Tls | None = None,
        client_id: str = "test-listener",
        host_id: str | None = None,
    ) -> None:
        self.messages: list[Message] = []
        self.errors: list[str] = []
        self.aliases = AliasResolver()  # data comes by alias: named from the births, as a host does
        self._lock = threading.Lock()
        self._subscribed = threading.Event()
        c = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=client_id, clean_session=True)
        if username is not None:
            c.username_pw_set(username, password)
        if tls is not None:
            c.tls_set(ca_certs=str(tls.ca), certfile=str(tls.client_cert), keyfile=str(tls.client_key))
        self.host_id = host_id
        if host_id is not None:  # a Sparkplug primary host: its STATE, offline as its will
            c.will_set(f"spBv1.0/STATE/{host_id}", json.dumps({"online": False, "timestamp": 0}), qos=1, retain=True)
        c.on_connect = lambda cl, u, f, rc, p: cl.subscribe("spBv1.0/#", qos=1)
        c.on_subscribe = self._on_subscribe
        c.on_message = self._on_message
        c.reconnect_delay_set(0.05, 0.2)
        self.client = c
        c.connect("127.0.0.1", port, keepalive=10)
        c.loop_start()
        if not self._subscribed.wait(20):
            self.stop()
            raise TimeoutError("the listener did not subscribe")

    def _on_subscribe(self, client: Any, *args: Any) -> None:
        if self.host_id is not None:  # online once it receives what the edge nodes send
            client.publish(
                f"spBv1.0/STATE/{self.host_id}",
                json.dumps({"online": True, "timestamp": int(time.time() * 1000)}),
                qos=1,
                retain=True,
            )
        self._subscribed.set()

    def _on_message(self, client: Any, userdata: Any, msg: Any) -> None:
        t = time.time()
        if msg.topic.startswith("spBv1.0/STATE/"):
            return
        kind = msg.topic.split("/")[2]
        try:
            payload = decode(msg.payload)
        except Exception as e:
            with self._lock:
                self.errors.append(f"{msg.topic}: {e}")
            return
        with self._lock:
            self.aliases.resolve(msg.topic, payload)
            self.messages.append(Message(msg.topic, kind, payload, t))

    def of(self, kind: str) -> list[Message]:
        with self._lock:
            return [m for m in self.messages if m.kind == kind]

    def wait_for(self, cond: Any, timeout_s: float = 30.0) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if cond():
                return
            time.sleep(0.05)
        raise TimeoutError(f"not seen in {timeout_s} s; {len(self.messages)} messages")

    def stop(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()
        self.client._reset_sockets()  # paho's wake-up socket pair, else closed only by the garbage collector


def metric(payload: Payload, name: str) -> Any:
    for m in payload.metrics:
        if m.name == name:
            return m
    raise KeyError(name)


@contextlib.contextmanager
def daemon(cfg: Path, err_path: Path) -> Iterator[subprocess.Popen[bytes]]:
    """`compd run CFG` (stderr to `err_path`) for the block; SIGTERM at the end, its exit awaited."""
    with open(err_path, "w") as err:
        proc = subprocess.Popen(
            [sys.executable, "-m", "compd", "run", str(cfg)],
            cwd=cfg.parent,
            stdout=subprocess.DEVNULL,
            stderr=err,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
        try:
            yield proc
        finally:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=60)
            finally:
                if proc.poll() is None:
                    proc.kill()
                    proc.wait()


def compd(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    """`compd ARGS` in `cwd`, its output captured."""
    return subprocess.run([sys.executable, "-m", "compd", *args], cwd=cwd, capture_output=True, text=True, timeout=60)
