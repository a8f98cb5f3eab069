"""The read-only OPC UA server: values, updates, the documented address space, and its security.

One server (module scope) serves the tests that need the default security: Basic256Sha256
SignAndEncrypt only, trusted_clients, one user, no anonymous. The asyncua client is
async: each test runs its own loop with asyncio.run. Everything listens on 127.0.0.1.
"""

from __future__ import annotations

import asyncio
import copy
import os
import socket
import stat
import threading
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
from cryptography import x509
from cryptography.hazmat.primitives import serialization

from compd.config import OpcUaConfig
from compd.errors import BadInput
from compd.plant.opcua import OpcUaServer, generate_certificate

DOC = Path(__file__).resolve().parents[2] / "docs" / "plant.md"
NS_URI = "urn:compd:test"
PASSWORD = "correct horse"
TIMEOUT_S = 30.0  # for a value to appear: generous, never a speed assertion

SNAP: dict[str, Any] = {
    "state": "running",
    "observe": False,
    "written_unix_s": 1795541065.5,
    "word": "0x4512",
    "axes": {
        "x": {"correction_um": -3.25, "target_um": -3.5, "prediction_um": 3.5, "applied_um": -3.0, "enable": True,
              "state": "normal", "byte": "0x12", "word_byte": "low"},
        "z": {"correction_um": 0.0, "target_um": -5.375, "prediction_um": 5.375, "applied_um": None,
              "enable": False, "state": "starting", "byte": "0x45", "word_byte": "high"},
    },
    "signals": {
        "T_spindle": {"value": 22.4, "quality": "good", "age_s": 0.0},
        "T_bed": {"value": None, "quality": "bad", "age_s": 4.0},
        "speed_rpm": {"value": 10000.0, "quality": "stale", "age_s": 2.5},
    },
    "loop": {
        "period_ms": 50.0, "cycles": 12001, "misses": 3,
        "lateness_us": {"p50": 1.0, "p99": 12.5, "p999": 30.0, "max": 44.0},
        "cycle_compute_us": {"p50": 144.0, "p99": 278.0, "max": 1058.9},
    },
    "model": {"kind": "xi_spindle", "file": None, "fit": {"fitted_at": "2026-01-01T00:00:00Z"}},
}

# a signal's quality → the StatusCode of its Value (docs/plant.md, "Status codes")
QUALITY_STATUS = {"good": "Good", "bad": "BadSensorFailure", "stale": "UncertainLastUsableValue",
                  "comms_lost": "BadNoCommunication"}


def expected(snap: dict[str, Any]) -> dict[str, tuple[Any, str]]:
    """Node id → (value, StatusCode name) that a client should read for `snap`."""
    def num(v: Any) -> tuple[Any, str]:
        return (v, "Good") if v is not None else (None, "BadNoData")

    out = {"compd.State": (snap["state"], "Good"), "compd.Observe": (snap["observe"], "Good")}
    for axis, a in snap["axes"].items():
        p = f"compd.Axes.{axis}."
        out[p + "CorrectionUm"] = num(a["correction_um"])
        out[p + "TargetUm"] = num(a["target_um"])
        out[p + "PredictionUm"] = num(a["prediction_um"])
        out[p + "AppliedUm"] = num(a.get("applied_um"))
        out[p + "Word"] = (int(snap["word"], 16), "Good")
        out[p + "Enable"] = (False, "Good") if snap["observe"] else num(a["enable"])
        out[p + "State"] = (a["state"], "Good")
        out[p + "ModelKind"] = (snap["model"]["kind"], "Good")
        out[p + "FitDate"] = (snap["model"]["fit"].get("fitted_at", ""), "Good")
    for name, s in snap["signals"].items():
        status = QUALITY_STATUS[s["quality"]]
        out[f"compd.Signals.{name}.Value"] = (None, status) if status.startswith("Bad") else (s["value"], status)
        out[f"compd.Signals.{name}.Quality"] = (s["quality"], "Good")
    lp = snap["loop"]
    out["compd.Loop.PeriodMs"] = num(lp["period_ms"])
    out["compd.Loop.Cycles"] = (lp["cycles"], "Good")
    out["compd.Loop.Misses"] = (lp["misses"], "Good")
    out["compd.Loop.LatenessP99Us"] = num(lp["lateness_us"]["p99"])
    out["compd.Loop.LatenessMaxUs"] = num(lp["lateness_us"]["max"])
    out["compd.Loop.ComputeP99Us"] = num(lp["cycle_compute_us"]["p99"])
    return out


# ------------------------------------------------------------------ fixtures and helpers


class Pki:
    """Certificates, keys and password files in one folder; the client's as DER bytes
    (bytes, not paths: asyncua would read a path on a worker thread)."""

    def __init__(self, root: Path) -> None:
        self.root = root
        (root / "trusted").mkdir()
        generate_certificate(root / "server.pem", root / "server.key", common_name="compd test",
                             application_uri="urn:compd:test-server", hosts=["127.0.0.1", "localhost"])
        generate_certificate(root / "trusted" / "client.pem", root / "client.key", common_name="scada",
                             application_uri="urn:compd:test-client", hosts=["127.0.0.1"])
        generate_certificate(root / "stranger.pem", root / "stranger.key", common_name="stranger",
                             application_uri="urn:compd:test-stranger", hosts=["127.0.0.1"])
        (root / "alice.password").write_text(PASSWORD + "\n")

    def client(self, name: str) -> tuple[bytes, bytes, str]:
        """A client's certificate and key (DER) and its application URI."""
        cert_file = self.root / ("trusted/client.pem" if name == "client" else f"{name}.pem")
        cert = x509.load_pem_x509_certificate(cert_file.read_bytes())
        key = serialization.load_pem_private_key((self.root / f"{name}.key").read_bytes(), None)
        uri = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        return (
            cert.public_bytes(serialization.Encoding.DER),
            key.private_bytes(serialization.Encoding.DER, serialization.PrivateFormat.PKCS8,
                              serialization.NoEncryption()),
            uri.get_values_for_type(x509.UniformResourceIdentifier)[0],
        )


def config(**changes: Any) -> OpcUaConfig:
    base: dict[str, Any] = dict(
        bind="127.0.0.1", port=0, certificate="server.pem", private_key="server.key",
        trusted_clients="trusted", users={"alice": {"password_file": "alice.password"}},
        namespace_uri=NS_URI,
    )
    return OpcUaConfig(**(base | changes))


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Pki:
    return Pki(tmp_path_factory.mktemp("opcua"))


@pytest.fixture(scope="module")
def served(pki: Pki) -> Any:
    """The default server, started once with SNAP: (server, endpoint URL)."""
    server = OpcUaServer(config(), pki.root)
    url = server.start(copy.deepcopy(SNAP))
    yield server, url
    server.stop()


async def connect(url: str, pki: Pki, *, cert: str | None = "client", user: str | None = "alice",
                  password: str = PASSWORD) -> Client:
    """A connected client: Basic256Sha256 SignAndEncrypt with `cert` (None: no security)."""
    client = Client(url, timeout=TIMEOUT_S)
    if cert is not None:
        cert_der, key_der, uri = pki.client(cert)
        client.application_uri = uri
        await client.set_security(SecurityPolicyBasic256Sha256, cert_der, key_der,
                                  mode=ua.MessageSecurityMode.SignAndEncrypt)
    if user is not None:
        client.set_user(user)
        client.set_password(password)
    await client.connect()
    return client


def run(url: str, pki: Pki, body: Callable[[Client], Awaitable[Any]], **kw: Any) -> Any:
    """Connect, run `body(client)`, disconnect; on a loop of its own."""
    async def main() -> Any:
        client = await connect(url, pki, **kw)
        try:
            return await body(client)
        finally:
            await client.disconnect()

    return asyncio.run(main())


async def read_all(client: Client, node_ids: list[str]) -> dict[str, tuple[Any, str]]:
    idx = await client.get_namespace_index(NS_URI)
    out = {}
    for nid in node_ids:
        dv = await client.get_node(ua.NodeId(nid, idx)).read_data_value(raise_on_bad_status=False)
        code = dv.StatusCode.value if dv.StatusCode is not None else 0
        out[nid] = (dv.Value.Value if dv.Value is not None else None, ua.StatusCode(code).name)
    return out


async def until(read: Callable[[], Awaitable[Any]], want: Any) -> None:
    """Poll `read` until it returns `want`, for TIMEOUT_S at most."""
    deadline = time.monotonic() + TIMEOUT_S
    got = await read()
    while got != want and time.monotonic() < deadline:
        await asyncio.sleep(0.05)
        got = await read()
    assert got == want


# ------------------------------------------------------------------ values


def test_values_are_the_snapshots_and_follow_updates(served: Any, pki: Pki) -> None:
    server, url = served
    first = expected(SNAP)
    new = copy.deepcopy(SNAP)
    new.update(state="stopped", observe=True, word="0x0000")
    new["axes"]["x"].update(correction_um=-3.5, enable=False, state="fault", prediction_um=None)
    new["signals"]["T_bed"].update(value=21.0, quality="good")
    new["signals"]["T_spindle"].update(quality="comms_lost")
    new["loop"].update(cycles=2**40, misses=4)
    new["model"]["fit"] = {}
    second = expected(new)
    assert second["compd.Axes.x.PredictionUm"] == (None, "BadNoData")
    odd = {"state": "running", "axes": {"x": {"correction_um": "12"}}, "signals": None}

    async def body(client: Client) -> None:
        assert await read_all(client, list(first)) == first
        server.update(new)
        await until(lambda: read_all(client, list(second)), second)
        errors = server.get_status()["errors"]
        server.update(odd)  # another shape: what it has is written, the rest is Bad, one error
        assert server.get_status()["errors"] == errors + 1
        await until(lambda: read_all(client, ["compd.State", "compd.Axes.x.CorrectionUm", "compd.Loop.Cycles"]),
                    {"compd.State": ("running", "Good"), "compd.Axes.x.CorrectionUm": (None, "BadNoData"),
                     "compd.Loop.Cycles": (None, "BadNoData")})
        server.update(copy.deepcopy(SNAP))
        await until(lambda: read_all(client, list(first)), first)

    run(url, pki, body)
    status = server.get_status()
    assert status["endpoint"] == url and status["updates"] >= 3
    assert "compd.Axes.x.CorrectionUm" in status["last_error"]


def test_endpoint_is_the_real_port(served: Any) -> None:
    _, url = served
    assert url.startswith("opc.tcp://127.0.0.1:") and url.endswith("/compd/")
    assert int(url.split(":")[2].split("/")[0]) > 0


# ------------------------------------------------------------------ the documented address space


def doc_tables() -> tuple[list[list[str]], dict[str, tuple[str, int]]]:
    """The address-space rows (node id, browse name, data type, unit) and the units table
    (symbol → UNECE code, UnitId) of docs/plant.md."""
    rows, units = [], {}
    for line in DOC.read_text(encoding="utf-8").splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 5 and cells[0].startswith("`compd"):
            rows.append([c.strip("`") for c in cells[:4]])
        elif len(cells) == 3 and cells[2].isdigit():
            units[cells[0]] = (cells[1], int(cells[2]))
    return rows, units


def documented(snap: dict[str, Any]) -> dict[str, tuple[str, str, str]]:
    """Node id → (browse name, data type, unit) for the axes and signals of `snap`."""
    rows, _ = doc_tables()
    out = {}
    for node_id, bname, dtype, unit in rows:
        if "<axis>" in node_id:
            key, names = "<axis>", snap["axes"]
        elif "<signal>" in node_id:
            key, names = "<signal>", snap["signals"]
        else:
            out[node_id] = (bname, dtype, unit)
            continue
        for name in names:
            out[node_id.replace(key, name)] = (bname.replace(key, name), dtype, unit)
    return out


def test_browse_matches_the_documented_address_space(served: Any, pki: Pki) -> None:
    _, url = served
    want = documented(SNAP)
    _, units = doc_tables()
    # compd, State, Observe; Axes, 2 × (folder + 8); Signals, 3 × (folder + 2); Loop + 6
    assert len(want) == 3 + (1 + 2 * 10) + (1 + 3 * 3) + (1 + 6)
    read_only = ua.AccessLevel.CurrentRead.mask

    async def body(client: Client) -> dict[str, tuple[str, str, str]]:
        idx = await client.get_namespace_index(NS_URI)
        top = await client.nodes.objects.get_child(f"{idx}:compd")
        got: dict[str, tuple[str, str, str]] = {}

        async def walk(node: Any, path: str) -> None:
            bname = await node.read_browse_name()
            nid = node.nodeid
            assert (nid.NamespaceIndex, nid.Identifier) == (idx, path)  # node id = browse path
            assert bname.NamespaceIndex == idx
            if await node.read_node_class() == ua.NodeClass.Object:
                assert (await node.read_type_definition()) == ua.NodeId(ua.ObjectIds.FolderType)
                got[path] = (bname.Name, "Folder", "—")
                for child in await node.get_children():
                    await walk(child, f"{path}.{(await child.read_browse_name()).Name}")
                return
            vtype = await node.read_data_type_as_variant_type()
            for attr in (ua.AttributeIds.AccessLevel, ua.AttributeIds.UserAccessLevel):
                assert (await node.read_attribute(attr)).Value.Value == read_only
            unit = "—"
            for prop in await node.get_properties():
                pname = await prop.read_browse_name()
                assert pname == ua.QualifiedName("EngineeringUnits", 0)
                assert prop.nodeid == ua.NodeId(f"{path}.EngineeringUnits", idx)
                eu = await prop.read_value()
                unit = eu.DisplayName.Text
                assert (eu.NamespaceUri, eu.UnitId) == (
                    "http://www.opcfoundation.org/UA/units/un/cefact", units[unit][1])
                assert eu.UnitId == int.from_bytes(units[unit][0].encode(), "big")
            got[path] = (bname.Name, vtype.name, unit)

        await walk(top, "compd")
        return got

    assert run(url, pki, body) == want


# ------------------------------------------------------------------ security


def test_writing_is_refused(served: Any, pki: Pki) -> None:
    _, url = served

    async def body(client: Client) -> None:
        idx = await client.get_namespace_index(NS_URI)
        for nid, value in (("compd.Axes.x.CorrectionUm", 99.0), ("compd.State", "stopped"),
                           ("compd.Observe", True)):
            with pytest.raises(ua.uaerrors.BadUserAccessDenied):
                await client.get_node(ua.NodeId(nid, idx)).write_value(value)
        dv = await client.get_node(ua.NodeId("compd.Axes.x.CorrectionUm", idx)).read_data_value()
        assert dv.Value.Value == SNAP["axes"]["x"]["correction_um"]

    run(url, pki, body)


@pytest.mark.parametrize(
    ("kw", "error"),
    [
        ({"password": "wrong"}, ua.uaerrors.BadUserAccessDenied),
        ({"user": "mallory"}, ua.uaerrors.BadUserAccessDenied),
        ({"user": None}, ua.uaerrors.BadIdentityTokenRejected),  # anonymous
        ({"cert": "stranger"}, ua.uaerrors.BadCertificateUntrusted),  # not in trusted_clients
    ],
    ids=["wrong-password", "unknown-user", "anonymous", "untrusted-certificate"],
)
def test_logins_refused(served: Any, pki: Pki, kw: dict[str, Any], error: type[Exception]) -> None:
    _, url = served
    with pytest.raises(error):
        run(url, pki, lambda client: client.nodes.objects.read_browse_name(), **kw)


def test_unencrypted_session_refused_when_none_is_not_offered(
    served: Any, pki: Pki, monkeypatch: pytest.MonkeyPatch
) -> None:
    _, url = served
    # an ordinary client gives up by itself (no endpoint with security None); a hostile one
    # goes on over the unsecured channel asyncua keeps open for GetEndpoints: compd refuses it
    with pytest.raises(ua.UaError, match="No matching endpoints"):
        run(url, pki, lambda client: client.nodes.objects.read_browse_name(), cert=None)
    monkeypatch.setattr(Client, "find_endpoint", staticmethod(lambda endpoints, mode, uri: endpoints[0]))
    with pytest.raises(ua.uaerrors.BadUserAccessDenied):
        run(url, pki, lambda client: client.nodes.objects.read_browse_name(), cert=None)


def test_anonymous_and_unencrypted_when_allowed_and_stop_twice(pki: Pki) -> None:
    server = OpcUaServer(
        config(anonymous=True, users={}, trusted_clients=None,
               security=["Basic256Sha256_SignAndEncrypt", "None"]),
        pki.root,
    )
    before = set(threading.enumerate())
    url = server.start(copy.deepcopy(SNAP))
    try:
        async def state(client: Client) -> Any:
            idx = await client.get_namespace_index(NS_URI)
            return await client.get_node(ua.NodeId("compd.State", idx)).read_value()

        assert run(url, pki, state, user=None, cert="stranger") == "running"  # any certificate
        assert run(url, pki, state, user=None, cert=None) == "running"
    finally:
        server.stop()
    server.stop()
    assert not set(threading.enumerate()) - before


# ------------------------------------------------------------------ bad input


@pytest.mark.parametrize("key", ["certificate", "private_key", "password_file", "trusted_clients"])
def test_missing_file_is_bad_input_naming_it(pki: Pki, key: str) -> None:
    if key == "password_file":
        cfg = config(users={"alice": {"password_file": "nowhere.password"}})
        missing = "nowhere.password"
    else:
        missing = f"nowhere-{key}"
        cfg = config(**{key: missing})
    server = OpcUaServer(cfg, pki.root)
    with pytest.raises(BadInput) as e:
        server.start(copy.deepcopy(SNAP))
    assert str(pki.root / missing) in str(e.value) and "\n" not in str(e.value)
    server.stop()


def test_port_taken_is_bad_input(pki: Pki) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        server = OpcUaServer(config(port=port), pki.root)
        with pytest.raises(BadInput, match=f"127.0.0.1:{port}"):
            server.start(copy.deepcopy(SNAP))
        server.stop()


def test_generate_certificate(tmp_path: Path) -> None:
    generate_certificate(tmp_path / "c.pem", tmp_path / "k.pem", common_name="compd",
                         application_uri="urn:host:compd", hosts=["cnc-7", "10.0.0.7"], days=30)
    assert stat.S_IMODE(os.stat(tmp_path / "k.pem").st_mode) == 0o600
    cert = x509.load_pem_x509_certificate((tmp_path / "c.pem").read_bytes())
    san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert san.get_values_for_type(x509.UniformResourceIdentifier) == ["urn:host:compd"]
    assert san.get_values_for_type(x509.DNSName) == ["cnc-7"]
    assert [str(a) for a in san.get_values_for_type(x509.IPAddress)] == ["10.0.0.7"]
    assert cert.public_key().key_size == 2048
    assert cert.signature_hash_algorithm is not None and cert.signature_hash_algorithm.name == "sha256"
