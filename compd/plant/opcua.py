"""A read-only OPC UA server (asyncua) that shows compd's live status to the plant, secured with Basic256Sha256.

The service process (compd/service/host.py) starts an `OpcUaServer` on its first status
snapshot (compd/service/status.py) and hands it each later one; the server runs on a thread of
its own ("compd-opcua") with its own asyncio loop, never on the cycle.

The address space (docs/plant.md, "OPC UA"): under Objects, a folder `compd` in the
namespace `opcua.namespace_uri`. Every node id is a string that is also the node's
browse path: `ns=<idx>;s=compd.Axes.z.CorrectionUm` is the variable `CorrectionUm` in
the folder `z` in the folder `Axes` in `compd`.

* `compd.State` (String), `compd.Observe` (Boolean): the daemon's state, observe mode;
* `compd.Axes.<axis>.` CorrectionUm, TargetUm, PredictionUm, AppliedUm (Double, µm: what
  the device acknowledged or reads back), Word (UInt16: the 16-bit word that carries the
  axis), Enable (Boolean: on at the machine, so false in observe mode; Bad, not confirmed,
  while the sink's link is not up), State (String), ModelKind
  (String), FitDate (String: the model's `fit.fitted_at`, or empty);
* `compd.Signals.<signal>.` Value (Double, its StatusCode from the signal's quality,
  see `QUALITY_STATUS`), Quality (String);
* `compd.Loop.` PeriodMs (Double, ms), Cycles and Misses (UInt64), LatenessP99Us,
  LatenessMaxUs, ComputeP99Us (Double, µs; a p99 over the histogram's range is its limit,
  20000 µs, with Uncertain_EngineeringUnitsExceeded: `OVER_RANGE_STATUS`).

A Double with a unit has an `EngineeringUnits` property (EUInformation, UNECE code).
The axes and signals are those of the first snapshot: a reload builds a new server.
A value compd does not have (None, NaN) is written with a Bad StatusCode, never as a
number; a snapshot of another shape writes what it can and counts an error.

Every variable is CurrentRead only and no client is ever an admin, so a write is
refused (Bad_UserAccessDenied). Security: endpoints for the `opcua.security` policies
only; a client whose channel is not secured is refused at login unless "None" is
offered; with `trusted_clients`, only the certificates in that folder (exact match)
may open a session; user names and passwords from the password files (compared in
constant time); anonymous clients only with `anonymous: true`.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import hmac
import ipaddress
import logging
import math
import os
import threading
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import rsa
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from compd import version
from compd.errors import BadInput
from compd.plant.spec import MAX_SECRET_BYTES
from compd.service.threads import ServiceThread

if TYPE_CHECKING:
    from compd.config import OpcUaConfig

log = logging.getLogger("compd.opcua")

START_TIMEOUT_S = 60.0  # init (≈ 1.5 s: asyncua builds the standard address space; 28 s on a loaded box) + bind
STOP_TIMEOUT_S = 10.0
MAX_CERT_BYTES = 1 << 20
CERT_SUFFIXES = (".der", ".pem", ".crt", ".cer")  # files of `trusted_clients` that are read


# ------------------------------------------------------------------ the address space


@dataclass(frozen=True)
class Unit:
    """An engineering unit as OPC UA names it: a UNECE Recommendation 20 code."""

    symbol: str
    unece: str
    description: str

    def eu_information(self) -> Any:
        from asyncua import ua

        return ua.EUInformation(
            NamespaceUri="http://www.opcfoundation.org/UA/units/un/cefact",
            UnitId=int.from_bytes(self.unece.encode("ascii"), "big"),  # Part 8 §5.6.3: the code's bytes
            DisplayName=ua.LocalizedText(self.symbol),
            Description=ua.LocalizedText(self.description),
        )


MICROMETRE = Unit("µm", "4H", "micrometre (micron)")
MILLISECOND = Unit("ms", "C26", "millisecond")
MICROSECOND = Unit("µs", "B98", "microsecond")

# a signal's quality (compd/cycle/frame.py) → the StatusCode of its Value; any other → BadSensorFailure
QUALITY_STATUS = {
    "good": "Good",
    "stale": "UncertainLastUsableValue",
    "comms_lost": "BadNoCommunication",
    "no_data": "BadWaitingForInitialData",
    "out_of_range": "BadOutOfRange",
}
OTHER_QUALITY_STATUS = "BadSensorFailure"  # burnout, implausible, frozen, and any quality not above
NO_VALUE_STATUS = "BadNoData"  # compd has no value (None, NaN) or the snapshot lacks it
# a percentile whose quantile fell in the histogram's overflow bin: the value is the range limit
OVER_RANGE_STATUS = "UncertainEngineeringUnitsExceeded"

Reader = Callable[[dict[str, Any]], tuple[Any, str]]  # snapshot → (raw value, StatusCode name)


@dataclass(frozen=True)
class Variable:
    """One variable: its node id (= browse path), type, unit and where its value comes from."""

    node_id: str
    data_type: str  # a ua.VariantType name: Double, UInt16, UInt64, Boolean, String
    unit: Unit | None
    read: Reader


def _good(get: Callable[[dict[str, Any]], Any]) -> Reader:
    return lambda snap: (get(snap), "Good")


def _fit_date(snap: dict[str, Any]) -> Any:
    return (snap["model"].get("fit") or {}).get("fitted_at") or ""


def _percentile(group: str, key: str) -> Reader:
    """A loop percentile (`group`: lateness_us, cycle_compute_us); one over the histogram's range
    (the loop's `over_range`) is its range limit with Uncertain_EngineeringUnitsExceeded."""
    def read(snap: dict[str, Any]) -> tuple[Any, str]:
        lp = snap["loop"]
        over = lp.get("over_range")
        flagged = isinstance(over, dict) and key in (over.get(group) or ())
        return lp[group][key], OVER_RANGE_STATUS if flagged else "Good"

    return read


def _signal_value(name: str) -> Reader:
    def read(snap: dict[str, Any]) -> tuple[Any, str]:
        s = snap["signals"][name]
        return s["value"], QUALITY_STATUS.get(s["quality"], OTHER_QUALITY_STATUS)

    return read


def address_space(snap: dict[str, Any]) -> list[Variable]:
    """The variables for the axes and signals of this (first) snapshot, in browse order."""
    um = MICROMETRE
    out = [
        Variable("compd.State", "String", None, _good(lambda s: s["state"])),
        Variable("compd.Observe", "Boolean", None, _good(lambda s: s["observe"])),
    ]
    axes = snap.get("axes")
    for axis in sorted(axes) if isinstance(axes, dict) else []:
        p = f"compd.Axes.{axis}."

        def field(key: str, axis: str = axis) -> Reader:
            return _good(lambda s: s["axes"][axis][key])

        out += [
            Variable(p + "CorrectionUm", "Double", um, field("correction_um")),
            Variable(p + "TargetUm", "Double", um, field("target_um")),
            Variable(p + "PredictionUm", "Double", um, field("prediction_um")),
            # what the device acknowledged or reads back (Bad: not known, e.g. the sink's link not up)
            Variable(p + "AppliedUm", "Double", um, field("applied_um")),
            Variable(p + "Word", "UInt16", None, _good(lambda s: int(s["word"], 16))),
            # on at the machine (compd/service/status.py): never in observe mode, whose word is 0
            Variable(p + "Enable", "Boolean", None,  # None (Bad): not confirmed while the link is not up
                     _good(lambda s, axis=axis: False if s.get("observe") else s["axes"][axis]["enable"])),
            Variable(p + "State", "String", None, field("state")),
            Variable(p + "ModelKind", "String", None, _good(lambda s: s["model"]["kind"])),
            Variable(p + "FitDate", "String", None, _good(_fit_date)),
        ]
    signals = snap.get("signals")
    for name in sorted(signals) if isinstance(signals, dict) else []:
        p = f"compd.Signals.{name}."
        out += [
            Variable(p + "Value", "Double", None, _signal_value(name)),
            Variable(p + "Quality", "String", None, _good(lambda s, n=name: s["signals"][n]["quality"])),
        ]
    out += [
        Variable("compd.Loop.PeriodMs", "Double", MILLISECOND, _good(lambda s: s["loop"]["period_ms"])),
        Variable("compd.Loop.Cycles", "UInt64", None, _good(lambda s: s["loop"]["cycles"])),
        Variable("compd.Loop.Misses", "UInt64", None, _good(lambda s: s["loop"]["misses"])),
        Variable("compd.Loop.LatenessP99Us", "Double", MICROSECOND, _percentile("lateness_us", "p99")),
        Variable("compd.Loop.LatenessMaxUs", "Double", MICROSECOND,
                 _good(lambda s: s["loop"]["lateness_us"]["max"])),
        Variable("compd.Loop.ComputeP99Us", "Double", MICROSECOND, _percentile("cycle_compute_us", "p99")),
    ]
    return out


def _coerce(data_type: str, raw: Any) -> Any:
    """`raw` as a value of `data_type`, None for a missing number (None, NaN, ±inf);
    TypeError or ValueError when it is not of that type."""
    if raw is None:
        return None
    if data_type == "Boolean":
        if not isinstance(raw, bool):
            raise TypeError(f"{raw!r} is not a boolean")
        return raw
    if data_type == "String":
        if not isinstance(raw, str):
            raise TypeError(f"{raw!r} is not a string")
        return raw
    if isinstance(raw, bool) or not isinstance(raw, int | float):
        raise TypeError(f"{raw!r} is not a number")
    if data_type == "Double":
        return float(raw) if math.isfinite(raw) else None
    top = 0xFFFF if data_type == "UInt16" else (1 << 64) - 1
    if not isinstance(raw, int) or not 0 <= raw <= top:
        raise ValueError(f"{raw!r} is not a {data_type}")
    return raw


def data_values(variables: list[Variable], snap: dict[str, Any]) -> tuple[list[Any], list[str]]:
    """A ua.DataValue per variable from one snapshot, and a line per value the snapshot lacked
    or had of the wrong type (that variable: Bad_NoData). Never raises for the snapshot's shape."""
    from asyncua import ua

    now = datetime.now(UTC)
    written = snap.get("written_unix_s")
    source = now
    if isinstance(written, int | float) and not isinstance(written, bool) and math.isfinite(written):
        source = datetime.fromtimestamp(written, UTC)
    out, problems = [], []
    for var in variables:
        vtype = getattr(ua.VariantType, var.data_type)
        try:
            raw, code = var.read(snap)
            value = _coerce(var.data_type, raw)
        except (KeyError, IndexError, TypeError, ValueError, AttributeError) as e:
            problems.append(f"{var.node_id}: {type(e).__name__}: {e}")
            value, code = None, NO_VALUE_STATUS
        status = ua.StatusCode(getattr(ua.StatusCodes, code))
        if value is None and not status.is_bad():
            status = ua.StatusCode(getattr(ua.StatusCodes, NO_VALUE_STATUS))
        variant = ua.Variant() if status.is_bad() else ua.Variant(value, vtype)
        out.append(ua.DataValue(Value=variant, StatusCode=status, SourceTimestamp=source, ServerTimestamp=now))
    return out, problems


# ------------------------------------------------------------------ files


def _read_file(path: Path, what: str, max_bytes: int) -> bytes:
    try:
        with open(path, "rb") as fh:
            data = fh.read(max_bytes + 1)
    except OSError as e:
        raise BadInput(f"cannot read the {what}: {e.strerror or e}", file=str(path)) from None
    if len(data) > max_bytes:
        raise BadInput(f"the {what} is longer than {max_bytes} bytes", file=str(path))
    return data


def _load_certificates(path: Path, what: str) -> list[x509.Certificate]:
    """The certificate(s) of a PEM (one or more) or DER file."""
    data = _read_file(path, what, MAX_CERT_BYTES)
    try:
        if data.lstrip().startswith(b"-----BEGIN"):
            return x509.load_pem_x509_certificates(data)
        return [x509.load_der_x509_certificate(data)]
    except ValueError:
        raise BadInput(f"the {what} is not a PEM or DER X.509 certificate", file=str(path)) from None


@dataclass
class _Material:
    """Everything read from files at start, before the thread starts."""

    certificate: x509.Certificate
    private_key: rsa.RSAPrivateKey
    application_uri: str
    passwords: dict[str, bytes]
    trusted: frozenset[bytes] | None  # DER of each trusted client certificate; None = trust any


def check_material(cfg: OpcUaConfig, base_dir: Path) -> None:
    """BadInput (naming the file) unless the certificate, its key, the users' password files and
    the trusted clients' folder are what the server needs to start (check-config)."""
    _read_material(cfg, base_dir)


def _read_material(cfg: OpcUaConfig, base_dir: Path) -> _Material:
    cert_path = base_dir / cfg.certificate
    cert = _load_certificates(cert_path, "server certificate (opcua.certificate)")[0]
    try:
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        uris = san.get_values_for_type(x509.UniformResourceIdentifier)
    except x509.ExtensionNotFound:
        uris = []
    if not uris:
        raise BadInput("the server certificate has no SubjectAltName URI (OPC UA's application URI)",
                       file=str(cert_path))
    key_path = base_dir / cfg.private_key
    key_data = _read_file(key_path, "private key (opcua.private_key)", MAX_CERT_BYTES)
    try:
        key = serialization.load_pem_private_key(key_data, password=None)
    except TypeError:
        raise BadInput("the private key is encrypted: compd needs it unencrypted (mode 0600)",
                       file=str(key_path)) from None
    except ValueError:
        raise BadInput("not a PEM private key", file=str(key_path)) from None
    if not isinstance(key, rsa.RSAPrivateKey):
        raise BadInput("Basic256Sha256 needs an RSA private key", file=str(key_path))
    if key.public_key().public_numbers() != cert.public_key().public_numbers():
        raise BadInput(f"the private key does not belong to the certificate {cert_path}", file=str(key_path))
    if os.stat(key_path).st_mode & 0o077:
        log.warning("the OPC UA private key %s can be read by other users (chmod 600 it)", key_path)
    passwords = {}
    for name, user in cfg.users.items():
        pw_path = base_dir / user.password_file
        data = _read_file(pw_path, f"password file of user {name!r}", MAX_SECRET_BYTES)
        try:
            text = data.decode("utf-8").rstrip("\r\n")
        except UnicodeDecodeError:
            raise BadInput("the password file is not UTF-8 text", file=str(pw_path)) from None
        if not text:
            raise BadInput("the password file is empty", file=str(pw_path))
        passwords[name] = text.encode("utf-8")
    if not passwords and not cfg.anonymous:
        raise BadInput("opcua: no users and anonymous is false: no client could log in")
    trusted = None
    if cfg.trusted_clients is not None:
        folder = base_dir / cfg.trusted_clients
        try:
            files = sorted(folder.iterdir())
        except OSError as e:
            raise BadInput(f"cannot read the trusted_clients folder: {e.strerror or e}", file=str(folder)) from None
        ders = set()
        for f in files:
            if f.suffix.lower() in CERT_SUFFIXES and not f.name.startswith(".") and f.is_file():
                for c in _load_certificates(f, "trusted client certificate"):
                    ders.add(c.public_bytes(serialization.Encoding.DER))
        if not ders:
            log.warning("no certificate (%s) in trusted_clients %s: every client is refused",
                        ", ".join(CERT_SUFFIXES), folder)
        trusted = frozenset(ders)
    return _Material(cert, key, uris[0], passwords, trusted)


def generate_certificate(
    cert_path: Path,
    key_path: Path,
    *,
    common_name: str,
    application_uri: str,
    hosts: list[str],
    days: int = 3650,
) -> None:
    """Write a self-signed OPC UA application instance certificate (PEM) and its RSA 2048 key
    (PEM, PKCS#8, mode 0600), signed with SHA-256, as Basic256Sha256 needs.

    As OPC UA Part 6 §6.2.2 asks: the application URI and each host (a DNS name, or an IP
    address) in the SubjectAltName; digital signature, non-repudiation, key and data
    encipherment in the key usage, and, being self-signed, cA and keyCertSign (so that
    validators that follow chains accept it as its own trust anchor); server and client
    authentication in the extended key usage, so one generator serves both ends.
    """
    key = rsa.generate_private_key(public_exponent=65537, key_size=2048)
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)])
    alt: list[x509.GeneralName] = [x509.UniformResourceIdentifier(application_uri)]
    for host in hosts:
        try:
            alt.append(x509.IPAddress(ipaddress.ip_address(host)))
        except ValueError:
            alt.append(x509.DNSName(host))
    now = datetime.now(UTC)
    public = key.public_key()
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(public)
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - timedelta(hours=1))  # a peer whose clock is a little behind
        .not_valid_after(now + timedelta(days=days))
        .add_extension(x509.SubjectAlternativeName(alt), critical=False)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True, content_commitment=True, key_encipherment=True,
                data_encipherment=True, key_agreement=False, key_cert_sign=True, crl_sign=False,
                encipher_only=False, decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(
            x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
            critical=False,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(public), critical=False)
        .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(public), critical=False)
        .sign(key, hashes.SHA256())
    )
    key_pem = key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )
    fd = os.open(key_path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as fh:
        os.fchmod(fh.fileno(), 0o600)  # the file may have existed with a wider mode
        fh.write(key_pem)
    Path(cert_path).write_bytes(cert.public_bytes(serialization.Encoding.PEM))


# ------------------------------------------------------------------ the server


class _Users:
    """asyncua's user manager: who may open a session. Nobody is ever an admin (who could write)."""

    def __init__(self, passwords: dict[str, bytes], anonymous: bool, plain_ok: bool) -> None:
        self._passwords = passwords
        self._anonymous = anonymous
        self._plain_ok = plain_ok

    def get_user(self, iserver: Any, username: str | None = None, password: str | None = None,
                 certificate: Any = None) -> Any:
        from asyncua.crypto.permission_rules import User, UserRole

        # asyncua keeps a channel with SecurityPolicy None open to every client (for
        # GetEndpoints) even when no None endpoint is offered: such a channel has no peer
        # certificate, and its sessions are refused here.
        if not certificate and not self._plain_ok:
            log.info("OPC UA login refused: the channel is not secured")
            return None
        if username is None:
            if self._anonymous:
                return User(role=UserRole.User, name="anonymous")
            log.info("OPC UA login refused: anonymous")
            return None
        expected = self._passwords.get(username)
        ok = hmac.compare_digest((password or "").encode("utf-8"), expected or b"")
        if ok and expected is not None:
            return User(role=UserRole.User, name=username)
        log.info("OPC UA login refused: user %r", username)
        return None


class _TrustedClients:
    """asyncua's certificate validator: a client certificate must be one of those given, valid
    now, and name the client's application URI."""

    def __init__(self, trusted: frozenset[bytes]) -> None:
        from asyncua.crypto.validator import CertificateValidator
        from asyncua.crypto.validator import CertificateValidatorOptions as Opt

        self._trusted = trusted
        self._basic = CertificateValidator(Opt.TIME_RANGE | Opt.URI | Opt.PEER_CLIENT)

    async def __call__(self, cert: x509.Certificate, app_description: Any) -> None:
        from asyncua import ua
        from asyncua.common.utils import ServiceError

        if cert.public_bytes(serialization.Encoding.DER) not in self._trusted:
            log.warning("OPC UA client refused: its certificate (%s) is not in trusted_clients",
                        cert.subject.rfc4514_string())
            raise ServiceError(ua.StatusCodes.BadCertificateUntrusted)
        await self._basic.validate(cert, app_description)


class OpcUaServer:
    """The OPC UA server of one config: `start` on the first snapshot, `update` with each later one, `stop`."""

    def __init__(self, cfg: OpcUaConfig, base_dir: Path) -> None:
        self.cfg = cfg
        self.base_dir = Path(base_dir)
        self._lock = threading.Lock()
        self._thread: ServiceThread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None  # the server thread's, while it runs
        self._wake: asyncio.Event | None = None
        self._pending: list[Any] | None = None  # the newest values not yet written
        self._stopping = False
        self._variables: list[Variable] = []
        self._endpoint: str | None = None
        self._updates = 0
        self._errors = 0
        self._last_error: str | None = None

    # ------------------------------------------------------------ the caller's side
    def start(self, snap: dict[str, Any]) -> str:
        """Build the address space from this first status snapshot, start serving on a thread of
        its own (its own asyncio loop), return the endpoint URL (opc.tcp://HOST:PORT/compd/, the
        real port when `port` is 0). BadInput (one line naming the file) for a certificate, key or
        password file that is missing or unreadable, or a port that is taken. Returns once the
        server accepts connections."""
        if self._thread is not None:
            raise RuntimeError("OpcUaServer.start called twice")
        if logging.getLogger("asyncua").level == logging.NOTSET:
            logging.getLogger("asyncua").setLevel(logging.WARNING)  # it logs every request at INFO
        material = _read_material(self.cfg, self.base_dir)
        if "None" in self.cfg.security:
            log.warning("OPC UA security 'None' is offered: that traffic is not encrypted")
        self._variables = address_space(snap)
        values, problems = data_values(self._variables, snap)
        self._count(problems)
        ready: concurrent.futures.Future[str] = concurrent.futures.Future()
        self._thread = ServiceThread("compd-opcua", self._run, material, values, ready)
        self._thread.start()
        try:
            self._endpoint = ready.result(timeout=START_TIMEOUT_S)
        except concurrent.futures.TimeoutError:
            self.stop()
            raise BadInput(f"the OPC UA server did not start within {START_TIMEOUT_S:g} s") from None
        except BaseException:
            self.stop()
            raise
        return self._endpoint

    def update(self, snap: dict[str, Any]) -> None:
        """Write this snapshot's values. Thread-safe and quick: the values are computed here and
        handed to the server's loop, which writes the newest it has (never waits for a client).
        Axes and signals not in the first snapshot are ignored (a reload builds a new server)."""
        values, problems = data_values(self._variables, snap)
        self._count(problems)
        with self._lock:
            if self._loop is None or self._stopping:
                return
            wake = self._pending is None  # else a wake-up is already on its way
            self._pending = values
            if wake:
                self._loop.call_soon_threadsafe(self._wake.set)  # type: ignore[union-attr]

    def stop(self) -> None:
        """Stop serving, join the thread, close the sockets. Idempotent."""
        with self._lock:
            self._stopping = True
            if self._loop is not None:
                self._loop.call_soon_threadsafe(self._wake.set)  # type: ignore[union-attr]
        thread = self._thread
        if thread is not None and not thread.is_current():
            thread.join(STOP_TIMEOUT_S)

    def get_status(self) -> dict[str, Any]:
        """The endpoint, the snapshots written, the snapshots that had a problem and the last one."""
        with self._lock:
            return {"endpoint": self._endpoint, "updates": self._updates, "errors": self._errors,
                    "last_error": self._last_error}

    def _count(self, problems: list[str]) -> None:
        if not problems:
            return
        line = f"{len(problems)} value(s) missing or of the wrong type: " + "; ".join(problems[:3])
        with self._lock:
            self._errors += 1
            new = line != self._last_error
            self._last_error = line
        if new:  # once per kind of problem, not once a second
            log.warning("OPC UA: %s", line)

    # ------------------------------------------------------------ the server thread
    def _run(self, material: _Material, values: list[Any], ready: concurrent.futures.Future[str]) -> None:
        try:
            asyncio.run(self._serve(material, values, ready))
        except Exception as e:
            if not ready.done():
                ready.set_exception(e)
            else:
                log.exception("the OPC UA server failed")
        finally:
            with self._lock:
                self._loop = None

    async def _serve(self, material: _Material, values: list[Any], ready: concurrent.futures.Future[str]) -> None:
        from asyncua import Server, ua

        cfg = self.cfg
        server = Server(user_manager=_Users(material.passwords, cfg.anonymous, "None" in cfg.security))
        await server.init()
        host = f"[{cfg.bind}]" if ":" in cfg.bind else cfg.bind
        server.set_endpoint(f"opc.tcp://{host}:{cfg.port}/compd/")
        server.set_server_name("compd")
        server.product_uri = "urn:compd"
        await server.set_application_uri(material.application_uri)
        await server.set_build_info("urn:compd", "compd", "compd", version(), version(), datetime.now(UTC))
        server.set_security_policy([getattr(ua.SecurityPolicyType, _POLICIES[p]) for p in cfg.security])
        server.set_identity_tokens(
            ([ua.UserNameIdentityToken] if material.passwords else [])
            + ([ua.AnonymousIdentityToken] if cfg.anonymous else [])
        )
        await server.load_certificate(material.certificate.public_bytes(serialization.Encoding.DER), format="der")
        await server.load_private_key(
            material.private_key.private_bytes(
                serialization.Encoding.DER, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
            ),
            format="der",
        )
        if material.trusted is not None:
            server.set_certificate_validator(_TrustedClients(material.trusted))
        node_ids = await self._build(server, await server.register_namespace(cfg.namespace_uri))
        await self._write(server, node_ids, values)
        try:
            await server.start()
        except OSError as e:
            raise BadInput(f"opcua: cannot listen on {cfg.bind}:{cfg.port}: {e.strerror or e}") from None
        try:
            url = f"opc.tcp://{host}:{server.bserver.port}/compd/"  # type: ignore[union-attr]
            server.set_endpoint(url)
            for edp in server.iserver.endpoints:  # they were made before the port was known
                edp.EndpointUrl = url
                edp.Server.DiscoveryUrls = [url]
            self._wake = asyncio.Event()
            with self._lock:
                self._loop = asyncio.get_running_loop()
                if self._stopping:  # stop() came while starting (start timed out)
                    self._wake.set()
            ready.set_result(url)
            await self._pump(server, node_ids)
        finally:
            await server.stop()

    async def _pump(self, server: Any, node_ids: list[Any]) -> None:
        """Write the newest values handed over by `update` until `stop`."""
        assert self._wake is not None
        while True:
            await self._wake.wait()
            self._wake.clear()
            with self._lock:
                values, self._pending = self._pending, None
                if self._stopping:
                    return
            if values is None:
                continue
            try:
                await self._write(server, node_ids, values)
            except Exception as e:  # asyncua's: keep serving, count it
                log.exception("OPC UA: writing the values failed")
                self._count([f"write: {type(e).__name__}: {e}"])
                continue
            with self._lock:
                self._updates += 1

    async def _build(self, server: Any, idx: int) -> list[Any]:
        """The folders and variables under Objects/compd; the variables' NodeIds, in order."""
        from asyncua import ua

        folders = {"": server.nodes.objects}
        node_ids = []
        for var in self._variables:
            *path, name = var.node_id.split(".")
            for depth in range(1, len(path) + 1):
                key = ".".join(path[:depth])
                if key not in folders:
                    parent = folders[".".join(path[: depth - 1])]
                    folders[key] = await parent.add_folder(ua.NodeId(key, idx), ua.QualifiedName(path[depth - 1], idx))
            vtype = getattr(ua.VariantType, var.data_type)
            node = await folders[".".join(path)].add_variable(
                ua.NodeId(var.node_id, idx), ua.QualifiedName(name, idx), _ZERO[var.data_type], vtype
            )
            if var.unit is not None:
                await node.add_property(
                    ua.NodeId(var.node_id + ".EngineeringUnits", idx), ua.QualifiedName("EngineeringUnits", 0),
                    var.unit.eu_information(), datatype=ua.NodeId(ua.ObjectIds.EUInformation),
                )
            node_ids.append(node.nodeid)
        return node_ids

    async def _write(self, server: Any, node_ids: list[Any], values: list[Any]) -> None:
        for node_id, dv in zip(node_ids, values, strict=True):
            await server.write_attribute_value(node_id, dv)


_POLICIES = {
    "Basic256Sha256_SignAndEncrypt": "Basic256Sha256_SignAndEncrypt",
    "Basic256Sha256_Sign": "Basic256Sha256_Sign",
    "None": "NoSecurity",
}
_ZERO = {"Double": 0.0, "UInt16": 0, "UInt64": 0, "Boolean": False, "String": ""}  # before the first write
