"""The OPC UA server's files: its certificate and key, the users' password files, the trusted clients.

Also a generator of the certificate and key.
"""

from __future__ import annotations

import ipaddress
import logging
import os
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import TYPE_CHECKING

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import rsa
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from compd.core.config import MAX_SECRET_BYTES
from compd.core.errors import BadInput

if TYPE_CHECKING:
    from compd.core.config import OpcUaConfig

log = logging.getLogger("compd.opcua")

MAX_CERT_BYTES = 1 << 20
CERT_SUFFIXES = (".der", ".pem", ".crt", ".cer")  # files of `trusted_clients` that are read


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
class Material:
    """Everything read from files at start, before the thread starts."""

    certificate: x509.Certificate
    private_key: rsa.RSAPrivateKey
    application_uri: str
    passwords: dict[str, bytes]
    trusted: frozenset[bytes] | None  # DER of each trusted client certificate; None = trust any


def check_material(cfg: OpcUaConfig, base_dir: Path) -> None:
    """BadInput (naming the file) unless the certificate, its key, the users' password files and
    the trusted clients' folder are what the server needs to start (check-config)."""
    read_material(cfg, base_dir)


def read_material(cfg: OpcUaConfig, base_dir: Path) -> Material:
    cert_path = base_dir / cfg.certificate
    cert = _load_certificates(cert_path, "server certificate (opcua.certificate)")[0]
    try:
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        uris = san.get_values_for_type(x509.UniformResourceIdentifier)
    except x509.ExtensionNotFound:
        uris = []
    if not uris:
        raise BadInput(
            "the server certificate has no SubjectAltName URI (OPC UA's application URI)", file=str(cert_path)
        )
    key_path = base_dir / cfg.private_key
    key_data = _read_file(key_path, "private key (opcua.private_key)", MAX_CERT_BYTES)
    try:
        key = serialization.load_pem_private_key(key_data, password=None)
    except TypeError:
        raise BadInput(
            "the private key is encrypted: compd needs it unencrypted (mode 0600)", file=str(key_path)
        ) from None
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
            log.warning(
                "no certificate (%s) in trusted_clients %s: every client is refused", ", ".join(CERT_SUFFIXES), folder
            )
        trusted = frozenset(ders)
    return Material(cert, key, uris[0], passwords, trusted)


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
                digital_signature=True,
                content_commitment=True,
                key_encipherment=True,
                data_encipherment=True,
                key_agreement=False,
                key_cert_sign=True,
                crl_sign=False,
                encipher_only=False,
                decipher_only=False,
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
