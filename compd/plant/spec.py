"""`telemetry` and `opcua` resolved to plain specs: files read, paths made absolute, every problem a config error.

Built when the pipeline is built (so `compd check-config` finds a missing password
file or an unknown arming signal), used by the service process. Imports nothing
heavy: paho-mqtt, protobuf and asyncua load in the service process only.
"""

from __future__ import annotations

import dataclasses
import hashlib
import ipaddress
import os
import re
import socket
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from compd import version
from compd.config import Config
from compd.core.config import MAX_SECRET_BYTES
from compd.core.errors import BadInput
from compd.cycle import pipeline


def read_secret(cfg: Any, rel: str, key: tuple[str | int, ...]) -> str:
    """A password from its file (relative to the config), the trailing newline stripped; a config error naming `key`."""
    path = cfg.resolve_path(rel)
    try:
        data = path.read_bytes()[: MAX_SECRET_BYTES + 1]
    except OSError as e:
        raise cfg.doc.error(f"cannot read {path}: {e.strerror or e}", key) from None
    if len(data) > MAX_SECRET_BYTES:
        raise cfg.doc.error(f"{path} is longer than a password ({MAX_SECRET_BYTES} bytes)", key)
    try:
        text = data.decode("utf-8").rstrip("\r\n")
    except UnicodeDecodeError:
        raise cfg.doc.error(f"{path} is not UTF-8 text", key) from None
    if not text:
        raise cfg.doc.error(f"{path} is empty", key)
    return text


def readable_file(cfg: Any, rel: str, key: tuple[str | int, ...]) -> str:
    """The absolute path of a file the config names, which must be readable now."""
    path = cfg.resolve_path(rel)
    try:
        with open(path, "rb"):
            pass
    except OSError as e:
        raise cfg.doc.error(f"cannot read {path}: {e.strerror or e}", key) from None
    return str(path)


def buffer_path(cfg: Any, env: dict[str, str] | None = None) -> Path:
    """`telemetry.buffer.path`, else $STATE_DIRECTORY/<config name>.telemetry.sqlite, else next to the config."""
    env = dict(os.environ) if env is None else env
    tel = cfg.top.telemetry
    if tel.buffer.path:
        return cfg.resolve_path(tel.buffer.path)
    stem = Path(cfg.file).stem
    state_dir = env.get("STATE_DIRECTORY", "").split(":")[0]
    return (Path(state_dir) if state_dir else Path(cfg.file).parent) / f"{stem}.telemetry.sqlite"


@dataclass
class RemoteSpec:
    """What the remote model handler needs (`telemetry.remote_models` with `allow: true`): the
    files a model sent may replace (the model's, the shadow's; None where that section names
    none), what they hold now, and how the arming works."""

    config: str
    model_file: Path | None  # None: the model is inline params or contributions (Model/apply refused)
    model_sha256: str | None
    outputs: list[str]
    arm_signal: str | None
    arm_window_s: float
    max_bytes: int
    daemon_pid: int
    pending_path: Path
    shadow_file: Path | None = None  # the shadow section's model file: what Model/shadow replaces
    shadow_sha256: str | None = None
    model_form: str = "file"  # how the model section gives it: file, params or contributions
    shadow_form: str | None = None  # ... and the shadow section (None: there is none)
    shadow_min_interval_s: float = 60.0  # a shadow sent sooner after the last one accepted is refused


@dataclass(kw_only=True)
class BrokerSpec:
    """Where the plant's MQTT broker is and how to log in to it: the telemetry section's connection
    keys, its files read (`broker_spec`); a Telemetry's and `compd sparkplug-watch`'s."""

    host: str
    port: int
    username: str | None = None
    password: str | None = None
    ca_file: str | None = None
    cert_file: str | None = None
    key_file: str | None = None
    check_hostname: bool = True


@dataclass(kw_only=True)
class TelemetrySpec(BrokerSpec):
    """Everything a Telemetry needs, resolved from the config (plain data: it crosses a fork)."""

    client_id: str
    group_id: str
    edge_node_id: str
    device_id: str
    buffer_path: Path
    buffer_max_bytes: int
    period_s: float = 1.0
    full_refresh_s: float = 60.0  # a DDATA with every metric at least this often (sample time); 0 = always
    keepalive_s: int = 30
    reconnect_max_s: float = 30.0
    properties: dict[str, str] = field(default_factory=dict)  # NBIRTH's Properties/… (version, config)
    poll_s: float = 0.05  # the thread's wait for the network between two looks at its inbox
    slack_s: float = 0.0  # a snapshot this much before a sample is due is taken for it (half the snapshots' period)
    remote: RemoteSpec | None = None  # remote models allowed: what applying one needs
    primary_host_id: str | None = None  # data flows only while this Sparkplug host is online


def _model_form(section: Any, spec: Any) -> str:
    """How a model section (raw) gives its model, resolved as `spec`: "contributions", "file" or "params"."""
    if isinstance(section, dict) and "contributions" in section:
        return "contributions"
    return "file" if spec.file is not None else "params"


def file_sha256(path: Path) -> str:
    try:
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()
    except OSError:
        return ""


def broker_spec(cfg: Any) -> BrokerSpec:
    """The telemetry section's broker: address, user and password (its file read), TLS files
    (readable); a config error naming the key of a file that cannot be read."""
    tel = cfg.top.telemetry
    key = ("telemetry",)
    b = BrokerSpec(host=tel.host, port=tel.port or (8883 if tel.tls is not None else 1883), username=tel.username)
    if tel.password_file is not None:
        if tel.username is None:
            raise cfg.doc.error("a password needs a username", (*key, "password_file"))
        b.password = read_secret(cfg, tel.password_file, (*key, "password_file"))
    if tel.tls is not None:
        b.ca_file = readable_file(cfg, tel.tls.ca_file, (*key, "tls", "ca_file"))
        if tel.tls.cert_file is not None and tel.tls.key_file is not None:
            b.cert_file = readable_file(cfg, tel.tls.cert_file, (*key, "tls", "cert_file"))
            b.key_file = readable_file(cfg, tel.tls.key_file, (*key, "tls", "key_file"))
        b.check_hostname = tel.tls.check_hostname
    return b


def telemetry_spec(cfg: Any, signals: list[str], outputs: list[str], snapshot_period_s: float) -> TelemetrySpec:
    """The telemetry section as a TelemetrySpec; a config error for a file that cannot be read,
    an arming signal no source gives, or remote models without a model file to replace (the
    model's or the shadow's) or with one in a folder that is not writable."""
    tel = cfg.top.telemetry
    key = ("telemetry",)
    broker = broker_spec(cfg)
    bpath = buffer_path(cfg)
    if not bpath.parent.is_dir():
        raise cfg.doc.error(f"folder {bpath.parent} does not exist", (*key, "buffer", "path"))
    remote = None
    rm = tel.remote_models
    if rm.arm_signal is not None and rm.arm_signal not in signals:
        raise cfg.doc.error(f"no source gives a signal {rm.arm_signal!r}", (*key, "remote_models", "arm_signal"))
    if rm.allow:
        # a model sent replaces a model file: the model section's (Model/apply, armed) or the
        # shadow section's (Model/shadow); at least one of them must name one
        mform = _model_form(cfg.top.model, cfg.model)
        sform = _model_form(cfg.top.shadow, cfg.shadow) if cfg.shadow is not None else None
        mfile = Path(cfg.model.file) if mform == "file" else None
        sfile = Path(cfg.shadow.file) if sform == "file" else None
        if mfile is None and sfile is None:
            raise cfg.doc.error(
                "remote models replace a model file: give model.file (or a shadow section with a"
                " file), not inline params or contributions",
                (*key, "remote_models", "allow"),
            )
        for f in (mfile, sfile):
            if f is not None and not os.access(f.parent, os.W_OK):
                raise cfg.doc.error(
                    f"remote models replace {f}, but its folder is not writable", (*key, "remote_models", "allow")
                )
        remote = RemoteSpec(
            config=str(Path(cfg.file).resolve()),
            model_file=mfile,
            model_sha256=file_sha256(mfile) if mfile is not None else None,
            outputs=list(outputs),
            arm_signal=rm.arm_signal,
            arm_window_s=rm.arm_window_s,
            max_bytes=rm.max_bytes,
            daemon_pid=os.getpid(),
            pending_path=Path(f"{bpath}.model-pending.json"),
            shadow_file=sfile,
            shadow_sha256=file_sha256(sfile) if sfile is not None else None,
            model_form=mform,
            shadow_form=sform,
            shadow_min_interval_s=rm.shadow_min_interval_s,
        )
    return TelemetrySpec(
        **dataclasses.asdict(broker),
        client_id=tel.client_id or f"{tel.group_id}-{tel.edge_node_id}",
        group_id=tel.group_id,
        edge_node_id=tel.edge_node_id,
        device_id=tel.device_id,
        buffer_path=bpath,
        buffer_max_bytes=int(tel.buffer.max_mb * 1e6),
        period_s=tel.period_s,
        full_refresh_s=tel.full_refresh_s,
        keepalive_s=tel.keepalive_s,
        reconnect_max_s=tel.reconnect_max_s,
        properties={"compd version": version(), "config": str(Path(cfg.file).resolve())},
        slack_s=snapshot_period_s / 2,
        remote=remote,
        primary_host_id=tel.primary_host_id,
    )


@dataclass
class OpcUaSpec:
    """The opcua section and the folder its paths are relative to."""

    cfg: Any
    base_dir: Path
    guard: Any = None  # the config's guard section: the EURange of each axis and signal


def opcua_spec(cfg: Any) -> OpcUaSpec:
    """The opcua section, its files checked readable (a config error naming the key)."""
    ua = cfg.top.opcua
    if not ua.anonymous and not ua.users:
        raise cfg.doc.error("no one could log in: give users, or anonymous: true", ("opcua", "users"))
    readable_file(cfg, ua.certificate, ("opcua", "certificate"))
    readable_file(cfg, ua.private_key, ("opcua", "private_key"))
    for name, user in ua.users.items():
        read_secret(cfg, user.password_file, ("opcua", "users", name, "password_file"))
    if ua.trusted_clients is not None and not cfg.resolve_path(ua.trusted_clients).is_dir():
        raise cfg.doc.error(f"{cfg.resolve_path(ua.trusted_clients)} is not a folder", ("opcua", "trusted_clients"))
    _check_bind(cfg, ua.bind)
    base = Path(cfg.file).parent
    from compd.plant.material import (
        check_material,  # what the server reads at start, read now (cryptography)
    )

    try:
        check_material(ua, base)
    except BadInput as e:  # named by the key whose file it is
        key: tuple[str, ...] = ("opcua",)
        if e.file == str(base / ua.private_key):
            key = ("opcua", "private_key")
        elif e.file == str(base / ua.certificate):
            key = ("opcua", "certificate")
        raise cfg.doc.error(e.message + (f" ({Path(e.file).name})" if e.file else ""), key) from None
    return OpcUaSpec(ua, base, cfg.top.guard)


_HOSTNAME = re.compile(
    r"^(?=.{1,253}$)([A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?)(\.[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?)*$"
)


def _check_bind(cfg: Any, bind: str) -> None:
    """`opcua.bind` is an address of this host the server can listen on (a config error
    naming the key, at check-config, not an OPC UA server silently off at run time)."""
    try:
        ipaddress.ip_address(bind)
    except ValueError:
        if not _HOSTNAME.match(bind):
            raise cfg.doc.error(f"{bind!r} is neither an IP address nor a host name", ("opcua", "bind")) from None
    try:
        infos = socket.getaddrinfo(bind, None, type=socket.SOCK_STREAM)
    except socket.gaierror as e:
        raise cfg.doc.error(f"{bind!r} does not resolve: {e.strerror}", ("opcua", "bind")) from None
    family, _, _, _, addr = infos[0]
    try:
        with socket.socket(family, socket.SOCK_STREAM) as s:
            s.bind((addr[0], 0))
    except OSError as e:
        raise cfg.doc.error(f"cannot listen on {bind}: {e.strerror or e}", ("opcua", "bind")) from None


def check_config(cfg: Config) -> None:
    """Validate a config as far as it can be without running it (`compd check-config`, a model
    the plant sends): every stage built and wired (`from_config`), the plant's telemetry and
    OPC UA sections read and checked against the signals and axes. Opens nothing; BadInput
    names the file, line and key of the first problem."""
    p, _ = pipeline.from_config(cfg)
    top = cfg.top
    if top.telemetry is not None or top.opcua is not None:
        period_s = min(top.status.period_s, *(sec.period_s for sec in (top.telemetry, top.opcua) if sec is not None))
        if top.telemetry is not None:
            telemetry_spec(cfg, list(p.frame.names), list(p.model.outputs), period_s)
        if top.opcua is not None:
            opcua_spec(cfg)
