"""The read-only OPC UA server: values, updates, the documented address space, its security, and asyncua's log lines.

The address space as documented: types, units, ranges, descriptions, sampling interval.

One server (module scope) serves the tests that need the default security: Basic256Sha256
SignAndEncrypt only, trusted_clients, one user, no anonymous. The asyncua client is
async: each test runs its own loop with asyncio.run. Everything listens on 127.0.0.1.
"""

from __future__ import annotations

import asyncio
import copy
import logging
import math
import os
import socket
import stat
import threading
import time
from collections.abc import Awaitable, Callable
from datetime import UTC
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256, SecurityPolicyNone
from cryptography import x509
from cryptography.hazmat.primitives import serialization

from compd.core.config import GuardConfig, OpcUaConfig
from compd.core.errors import BadInput
from compd.plant.material import generate_certificate
from compd.plant.opcua import OpcUaServer

DOC = Path(__file__).resolve().parents[2] / "docs" / "plant.md"
NS_URI = "urn:compd:test"
PASSWORD = "correct horse"
TIMEOUT_S = 30.0  # for a value to appear: generous, never a speed assertion
PERIOD_S = 0.5  # opcua.period_s: every variable's MinimumSamplingInterval is 500 ms
# the config's guard: its clamps and signal limits are the EURanges (x has a clamp of its own, z the default)
GUARD = GuardConfig(
    max_abs_um=40.0, axes={"x": {"max_abs_um": 20.0}}, signals={"T_spindle": {"min": 10.0, "max": 60.0}}
)

SNAP: dict[str, Any] = {
    "state": "running",
    "observe": False,
    "written_unix_s": 1795541065.5,
    "word": "0x4512",
    "axes": {
        "x": {
            "correction_um": -3.25,
            "target_um": -3.5,
            "prediction_um": 3.5,
            "commanded_um": -3.25,
            "applied_um": -3.0,
            "enable": True,
            "state": "normal",
            "inhibit": None,
            "saturated": False,
            "byte": "0x12",
            "word_byte": "low",
        },
        "z": {
            "correction_um": 0.0,
            "target_um": -5.375,
            "prediction_um": 5.375,
            "commanded_um": None,
            "applied_um": None,
            "enable": False,
            "state": "starting",
            "inhibit": "waiting for reference",
            "saturated": True,
            "byte": "0x45",
            "word_byte": "high",
        },
    },
    "signals": {
        "T_spindle": {"value": 22.4, "quality": "good", "age_s": 0.0},
        "T_bed": {"value": None, "quality": "bad", "age_s": 4.0},
        "speed_rpm": {"value": 10000.0, "quality": "stale", "age_s": 2.5},
        "coolant": {"value": 3.0, "quality": "good", "age_s": 0.0},  # its name says no unit
    },
    "loop": {
        "period_ms": 50.0,
        "cycles": 12001,
        "misses": 3,
        "skipped": 1,
        "lateness_us": {"p50": 1.0, "p99": 12.5, "p999": 30.0, "max": 44.0},
        "cycle_compute_us": {"p50": 144.0, "p99": 278.0, "max": 1058.9},
    },
    "model": {"kind": "xi_spindle", "file": None, "fit": {"fitted_at": "2026-01-01T00:00:00Z"}},
    "sink": {"link": "up"},
    "saturations": 7,
}

# a signal's quality → the StatusCode of its Value (docs/plant.md, "Status codes")
QUALITY_STATUS = {
    "good": "Good",
    "bad": "BadSensorFailure",
    "stale": "UncertainLastUsableValue",
    "comms_lost": "BadNoCommunication",
}


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
        out[p + "CommandedUm"] = num(a.get("commanded_um"))
        out[p + "Inhibit"] = (a["inhibit"] or "", "Good")  # no hold: the empty string
        out[p + "Saturated"] = (a["saturated"], "Good")
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
    out["compd.Loop.Skipped"] = (lp["skipped"], "Good")
    out["compd.Loop.Link"] = (snap["sink"]["link"], "Good")
    out["compd.Loop.Saturations"] = (snap["saturations"], "Good")
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
        generate_certificate(
            root / "server.pem",
            root / "server.key",
            common_name="compd test",
            application_uri="urn:compd:test-server",
            hosts=["127.0.0.1", "localhost"],
        )
        generate_certificate(
            root / "trusted" / "client.pem",
            root / "client.key",
            common_name="scada",
            application_uri="urn:compd:test-client",
            hosts=["127.0.0.1"],
        )
        generate_certificate(
            root / "stranger.pem",
            root / "stranger.key",
            common_name="stranger",
            application_uri="urn:compd:test-stranger",
            hosts=["127.0.0.1"],
        )
        (root / "alice.password").write_text(PASSWORD + "\n")

    def client(self, name: str) -> tuple[bytes, bytes, str]:
        """A client's certificate and key (DER) and its application URI."""
        cert_file = self.root / ("trusted/client.pem" if name == "client" else f"{name}.pem")
        cert = x509.load_pem_x509_certificate(cert_file.read_bytes())
        key = serialization.load_pem_private_key((self.root / f"{name}.key").read_bytes(), None)
        uri = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        return (
            cert.public_bytes(serialization.Encoding.DER),
            key.private_bytes(
                serialization.Encoding.DER, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
            ),
            uri.get_values_for_type(x509.UniformResourceIdentifier)[0],
        )


def config(**changes: Any) -> OpcUaConfig:
    base: dict[str, Any] = dict(
        bind="127.0.0.1",
        port=0,
        certificate="server.pem",
        private_key="server.key",
        trusted_clients="trusted",
        users={"alice": {"password_file": "alice.password"}},
        namespace_uri=NS_URI,
        period_s=PERIOD_S,
    )
    return OpcUaConfig(**(base | changes))


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Pki:
    return Pki(tmp_path_factory.mktemp("opcua"))


@pytest.fixture(scope="module")
def served(pki: Pki) -> Any:
    """The default server, started once with SNAP: (server, endpoint URL)."""
    server = OpcUaServer(config(), pki.root, GUARD)
    url = server.start(copy.deepcopy(SNAP))
    yield server, url
    server.stop()


async def connect(
    url: str, pki: Pki, *, cert: str | None = "client", user: str | None = "alice", password: str = PASSWORD
) -> Client:
    """A connected client: Basic256Sha256 SignAndEncrypt with `cert` (None: no security)."""
    client = Client(url, timeout=TIMEOUT_S)
    if cert is not None:
        cert_der, key_der, uri = pki.client(cert)
        client.application_uri = uri
        await client.set_security(
            SecurityPolicyBasic256Sha256, cert_der, key_der, mode=ua.MessageSecurityMode.SignAndEncrypt
        )
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
        await until(
            lambda: read_all(client, ["compd.State", "compd.Axes.x.CorrectionUm", "compd.Loop.Cycles"]),
            {
                "compd.State": ("running", "Good"),
                "compd.Axes.x.CorrectionUm": (None, "BadNoData"),
                "compd.Loop.Cycles": (None, "BadNoData"),
            },
        )
        server.update(copy.deepcopy(SNAP))
        await until(lambda: read_all(client, list(first)), first)

    run(url, pki, body)
    status = server.get_status()
    assert status["endpoint"] == url and status["updates"] >= 3
    assert "compd.Axes.x.CorrectionUm" in status["last_error"]


def test_a_stale_cycle_s_values_are_its_last_usable_ones(served: Any, pki: Pki) -> None:
    """The states say `stale` (Good: composed now); every other value is the record's last,
    Uncertain_LastUsableValue stamped when the cycle wrote it; a Bad one stays Bad."""
    from compd.service.status import mark_stale

    server, url = served
    stale = copy.deepcopy(SNAP)
    mark_stale(stale)
    stale["record_age_s"] = 3.0
    nodes = [
        "compd.State",
        "compd.Axes.x.State",
        "compd.Axes.x.CorrectionUm",
        "compd.Axes.x.Enable",
        "compd.Signals.T_spindle.Value",
        "compd.Signals.T_bed.Value",
        "compd.Loop.Cycles",
    ]
    want = {
        "compd.State": ("stale", "Good"),
        "compd.Axes.x.State": ("stale", "Good"),
        "compd.Axes.x.CorrectionUm": (-3.25, "UncertainLastUsableValue"),
        "compd.Axes.x.Enable": (None, "BadNoData"),  # not confirmed at the machine
        "compd.Signals.T_spindle.Value": (22.4, "UncertainLastUsableValue"),
        "compd.Signals.T_bed.Value": (None, "BadSensorFailure"),
        "compd.Loop.Cycles": (12001, "UncertainLastUsableValue"),
    }

    async def body(client: Client) -> Any:
        server.update(stale)
        await until(lambda: read_all(client, nodes), want)
        idx = await client.get_namespace_index(NS_URI)
        stamps = [
            (await client.get_node(ua.NodeId(n, idx)).read_data_value(raise_on_bad_status=False)).SourceTimestamp
            for n in ("compd.Axes.x.CorrectionUm", "compd.State")
        ]
        server.update(copy.deepcopy(SNAP))
        await until(lambda: read_all(client, ["compd.State"]), {"compd.State": ("running", "Good")})
        return stamps

    recorded, state = (t if t.tzinfo else t.replace(tzinfo=UTC) for t in run(url, pki, body))
    assert state.timestamp() == SNAP["written_unix_s"]
    assert recorded.timestamp() == SNAP["written_unix_s"] - 3.0  # when the cycle last wrote its record


def test_endpoint_is_the_real_port(served: Any) -> None:
    _, url = served
    assert url.startswith("opc.tcp://127.0.0.1:") and url.endswith("/compd/")
    assert int(url.split(":")[2].split("/")[0]) > 0


# ------------------------------------------------------------------ the documented address space


def _cells(line: str) -> list[str]:
    return [c.strip() for c in line.strip().strip("|").split("|")]


def doc_tables() -> tuple[list[list[str]], dict[str, tuple[str, int, str]], list[list[str]]]:
    """From docs/plant.md: the address-space rows (node id, browse name, type, data type, unit,
    EURange), the units table (symbol → UNECE code, UnitId, description) and the signal units table
    (name pattern, unit, EURange)."""
    rows, units, signal_rows = [], {}, []
    for line in DOC.read_text(encoding="utf-8").splitlines():
        cells = _cells(line)
        if len(cells) == 7 and cells[0].startswith("`compd"):
            rows.append([c.strip("`") for c in cells[:6]])
        elif len(cells) == 4 and cells[2].isdigit():
            units[cells[0]] = (cells[1], int(cells[2]), cells[3])
        elif len(cells) == 4 and " … " in cells[2] and (cells[0].startswith("`") or cells[0] == "any other"):
            signal_rows.append(cells[:3])
    return rows, units, signal_rows


def _doc_range(text: str) -> tuple[float, float]:
    low, high = text.split(" … ")
    return float(low), float(high)


def expected_range(node_id: str, cell: str) -> tuple[float, float] | None:
    """The EURange a node should have: from GUARD (± clamp, signal limits) or the documented numbers."""
    if cell == "—":
        return None
    if cell == "± clamp":
        axis = node_id.split(".")[2]
        clamp = GUARD.axes[axis].max_abs_um if axis in GUARD.axes else GUARD.max_abs_um
        return (-clamp, clamp)
    if cell == "limits, else by name":
        name = node_id.split(".")[2]
        if name in GUARD.signals:
            return (GUARD.signals[name].min, GUARD.signals[name].max)
        _, _, signal_rows = doc_tables()
        return _doc_range(_signal_row(signal_rows, name)[2])
    return _doc_range(cell)


def _signal_row(signal_rows: list[list[str]], name: str) -> list[str]:
    """The signal units table's row for a signal name (`T_…`, `…_c`, …, else `any other`)."""
    for row in signal_rows:
        for pattern in row[0].replace("`", "").split(", "):
            if (pattern.endswith("…") and name.startswith(pattern[:-1])) or (
                pattern.startswith("…") and name.lower().endswith(pattern[1:])
            ):
                return row
    return next(row for row in signal_rows if row[0] == "any other")


def documented(snap: dict[str, Any]) -> dict[str, tuple[str, str, str, str, tuple[float, float] | None]]:
    """Node id → (browse name, type, data type, unit, EURange) for the axes and signals of `snap`."""
    rows, _, signal_rows = doc_tables()
    out = {}
    for node_id, bname, ntype, dtype, unit, eu_range in rows:
        if "<axis>" in node_id:
            key, names = "<axis>", snap["axes"]
        elif "<signal>" in node_id:
            key, names = "<signal>", snap["signals"]
        else:
            out[node_id] = (bname, ntype, dtype, unit, expected_range(node_id, eu_range))
            continue
        for name in names:
            nid = node_id.replace(key, name)
            u = _signal_row(signal_rows, name)[1] if unit == "by name" else unit
            out[nid] = (bname.replace(key, name), ntype, dtype, u, expected_range(nid, eu_range))
    return out


def test_browse_matches_the_documented_address_space(served: Any, pki: Pki) -> None:
    """Every node browsed: node id = browse path, its type definition, data type, unit and EURange as
    documented; a Description that is not its browse name; MinimumSamplingInterval = period_s."""
    _, url = served
    want = documented(SNAP)
    _, units, _ = doc_tables()
    # compd, State, Observe; Axes, 2 × (folder + 12); Signals, 4 × (folder + 2); Loop + 9
    assert len(want) == 3 + (1 + 2 * 13) + (1 + 4 * 3) + (1 + 9)
    read_only = ua.AccessLevel.CurrentRead.mask
    type_names = {
        ua.NodeId(ua.ObjectIds.FolderType): "Folder",
        ua.NodeId(ua.ObjectIds.AnalogItemType): "AnalogItemType",
        ua.NodeId(ua.ObjectIds.BaseDataVariableType): "BaseDataVariableType",
    }

    async def body(client: Client) -> tuple[dict[str, Any], dict[str, str]]:
        idx = await client.get_namespace_index(NS_URI)
        top = await client.nodes.objects.get_child(f"{idx}:compd")
        got: dict[str, Any] = {}
        descriptions: dict[str, str] = {}

        async def walk(node: Any, path: str) -> None:
            bname = await node.read_browse_name()
            nid = node.nodeid
            assert (nid.NamespaceIndex, nid.Identifier) == (idx, path)  # node id = browse path
            assert bname.NamespaceIndex == idx
            description = (await node.read_description()).Text
            assert description and description != bname.Name, (path, description)
            descriptions[path] = description
            ntype = type_names[await node.read_type_definition()]
            if await node.read_node_class() == ua.NodeClass.Object:
                got[path] = (bname.Name, ntype, "—", "—", None)
                for child in await node.get_children():
                    await walk(child, f"{path}.{(await child.read_browse_name()).Name}")
                return
            vtype = await node.read_data_type_as_variant_type()
            for attr in (ua.AttributeIds.AccessLevel, ua.AttributeIds.UserAccessLevel):
                assert (await node.read_attribute(attr)).Value.Value == read_only
            sampling = await node.read_attribute(ua.AttributeIds.MinimumSamplingInterval)
            assert sampling.Value.Value == PERIOD_S * 1000.0
            props = {(await p.read_browse_name()).Name: p for p in await node.get_properties()}
            unit, eu_range = "—", None
            if ntype == "AnalogItemType":
                assert "EURange" in props, path
            assert set(props) <= {"EURange", "EngineeringUnits"}, (path, set(props))
            for name, prop in props.items():
                assert await prop.read_browse_name() == ua.QualifiedName(name, 0)
                assert prop.nodeid == ua.NodeId(f"{path}.{name}", idx)
                assert await prop.read_type_definition() == ua.NodeId(ua.ObjectIds.PropertyType)
                assert (await prop.read_description()).Text
                value = await prop.read_value()
                if name == "EURange":
                    eu_range = (value.Low, value.High)
                else:
                    unit = value.DisplayName.Text
                    assert (value.NamespaceUri, value.UnitId, value.Description.Text) == (
                        "http://www.opcfoundation.org/UA/units/un/cefact",
                        units[unit][1],
                        units[unit][2],
                    )
                    assert value.UnitId == int.from_bytes(units[unit][0].encode(), "big")
            got[path] = (bname.Name, ntype, vtype.name, unit, eu_range)

        await walk(top, "compd")
        return got, descriptions

    got, descriptions = run(url, pki, body)
    assert got == want
    # a field of the status record is described by its meaning there (one text: status-fields.md, OPC UA)
    from compd.cycle.statusblock import AXIS, LOOP, SIGNAL

    meaning = {f.key: f.meaning for f in AXIS} | {"signal." + f.key: f.meaning for f in SIGNAL}
    assert descriptions["compd.Axes.z.CorrectionUm"] == meaning["correction_um"]
    assert descriptions["compd.Axes.z.PredictionUm"] == meaning["prediction_um"].replace("null", "Bad_NoData")
    assert descriptions["compd.Signals.speed_rpm.Value"].startswith(meaning["signal.value"])
    assert descriptions["compd.Loop.Misses"] == next(f.meaning for f in LOOP if f.key == "misses")


def test_the_documented_units_and_signal_ranges_are_the_servers() -> None:
    """docs/plant.md's units and signal-range tables against compd.plant.opcua's (and every unit's
    UnitId computed as Part 8 says)."""
    from compd.cycle.statusblock import signal_unit
    from compd.plant.opcua import MICROMETRE, MICROSECOND, MILLISECOND, SIGNAL_RANGES, SIGNAL_UNITS

    _, units, signal_rows = doc_tables()
    served_units = {u.symbol: u for u in (MICROMETRE, MILLISECOND, MICROSECOND, *SIGNAL_UNITS.values())}
    assert {s: (u.unece, u.unit_id, u.description) for s, u in served_units.items()} == units
    assert all(unit_id == int.from_bytes(code.encode(), "big") for code, unit_id, _ in units.values())
    assert len(signal_rows) == len(SIGNAL_RANGES)
    for pattern, unit, eu_range in signal_rows:
        name = "x" if pattern == "any other" else pattern.replace("`", "").split(", ")[0].replace("…", "x")
        code_unit = signal_unit(name)
        assert (SIGNAL_UNITS[code_unit].symbol if code_unit else "—") == unit, pattern
        assert SIGNAL_RANGES[code_unit][:2] == _doc_range(eu_range), pattern


# ------------------------------------------------------------------ security


def test_writing_is_refused(served: Any, pki: Pki) -> None:
    _, url = served

    async def body(client: Client) -> None:
        idx = await client.get_namespace_index(NS_URI)
        for nid, value in (("compd.Axes.x.CorrectionUm", 99.0), ("compd.State", "stopped"), ("compd.Observe", True)):
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
    # it even encrypts the password as the token policy asks, with the server certificate's key
    server_der = x509.load_pem_x509_certificate((pki.root / "server.pem").read_bytes()).public_bytes(
        serialization.Encoding.DER
    )
    encrypt = Client._encrypt_password

    def with_the_servers_key(self: Client, password: str, policy_uri: str) -> tuple[bytes, str]:
        self.security_policy.peer_certificate = server_der
        return encrypt(self, password, policy_uri)

    monkeypatch.setattr(Client, "_encrypt_password", with_the_servers_key)
    with pytest.raises(ua.uaerrors.BadUserAccessDenied):
        run(url, pki, lambda client: client.nodes.objects.read_browse_name(), cert=None)


def test_every_endpoint_asks_for_an_encrypted_password(pki: Pki, monkeypatch: pytest.MonkeyPatch) -> None:
    """The UserName token policy of every endpoint (SignAndEncrypt, Sign, None) carries Basic256Sha256:
    the password is encrypted with the server's key on each; one sent unencrypted is refused."""
    server = OpcUaServer(
        config(security=["Basic256Sha256_SignAndEncrypt", "Basic256Sha256_Sign", "None"]), pki.root, GUARD
    )
    url = server.start(copy.deepcopy(SNAP))
    try:

        async def endpoints() -> list[Any]:
            return await Client(url, timeout=TIMEOUT_S).connect_and_get_server_endpoints()

        policies = {}
        for edp in asyncio.run(endpoints()):
            tokens = {t.TokenType: t for t in edp.UserIdentityTokens}
            assert set(tokens) == {ua.UserTokenType.UserName}  # no anonymous: anonymous is false
            policies[(edp.SecurityPolicyUri.rsplit("#", 1)[1], edp.SecurityMode.name)] = tokens[
                ua.UserTokenType.UserName
            ].SecurityPolicyUri
        assert policies == {
            ("Basic256Sha256", "SignAndEncrypt"): SecurityPolicyBasic256Sha256.URI,
            ("Basic256Sha256", "Sign"): SecurityPolicyBasic256Sha256.URI,
            ("None", "None_"): SecurityPolicyBasic256Sha256.URI,
        }

        async def state(client: Client) -> Any:
            idx = await client.get_namespace_index(NS_URI)
            return await client.get_node(ua.NodeId("compd.State", idx)).read_value()

        assert run(url, pki, state) == "running"  # SignAndEncrypt, the password encrypted again
        assert run(url, pki, state, cert=None) == "running"  # None offered: the password still encrypted
        # a password encrypted with another session's nonce (a replayed token) is refused
        encrypt = Client._encrypt_password

        def with_another_nonce(self: Client, password: str, policy_uri: str) -> tuple[bytes, str]:
            self._server_nonce = bytes(32)
            return encrypt(self, password, policy_uri)

        with monkeypatch.context() as m:
            m.setattr(Client, "_encrypt_password", with_another_nonce)
            with pytest.raises(ua.uaerrors.BadIdentityTokenInvalid):
                run(url, pki, state)
        # a client that sends the password as it is (as for a token policy None) is refused
        monkeypatch.setattr(
            Client,
            "server_policy",
            lambda self, token_type: ua.UserTokenPolicy(
                PolicyId="username", TokenType=token_type, SecurityPolicyUri=SecurityPolicyNone.URI
            ),
        )
        with pytest.raises(ua.uaerrors.BadIdentityTokenInvalid):
            run(url, pki, state)
    finally:
        server.stop()


def test_anonymous_and_unencrypted_when_allowed_and_stop_twice(pki: Pki) -> None:
    server = OpcUaServer(
        config(anonymous=True, users={}, trusted_clients=None, security=["Basic256Sha256_SignAndEncrypt", "None"]),
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
    generate_certificate(
        tmp_path / "c.pem",
        tmp_path / "k.pem",
        common_name="compd",
        application_uri="urn:host:compd",
        hosts=["cnc-7", "10.0.0.7"],
        days=30,
    )
    assert stat.S_IMODE(os.stat(tmp_path / "k.pem").st_mode) == 0o600
    cert = x509.load_pem_x509_certificate((tmp_path / "c.pem").read_bytes())
    san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert san.get_values_for_type(x509.UniformResourceIdentifier) == ["urn:host:compd"]
    assert san.get_values_for_type(x509.DNSName) == ["cnc-7"]
    assert [str(a) for a in san.get_values_for_type(x509.IPAddress)] == ["10.0.0.7"]
    assert cert.public_key().key_size == 2048
    assert cert.signature_hash_algorithm is not None and cert.signature_hash_algorithm.name == "sha256"


# ------------------------------------------------------------------ asyncua's log


class _Keep(logging.Handler):
    def __init__(self) -> None:
        super().__init__()
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


def test_asyncua_log_lines_become_rate_limited_compd_events() -> None:
    """A record of asyncua's becomes one compd event: INFO at debug, ERROR at warning, a repeat
    within the window counted into the next line, at most STACK_LINES_PER_WINDOW lines a window."""
    from compd.plant.opcua import STACK_EVENT, STACK_LINES_PER_WINDOW, STACK_WINDOW_S, _StackEvents
    from compd.service.logsetup import KeyValueFormatter

    now = [1000.0]
    events = _StackEvents(clock=lambda: now[0])
    keep = _Keep()
    events.out = logging.getLogger("test_opcua.events")
    events.out.propagate, events.out.level = False, logging.DEBUG
    events.out.addHandler(keep)
    stack = logging.getLogger("test_opcua.asyncua.server.uaprocessor")
    stack.propagate, stack.level = False, logging.DEBUG
    stack.addHandler(events)
    try:
        stack.info("process message %s", 1)
        for _ in range(5):
            stack.error("sending service fault response: %s (%s)", "denied", "BadUserAccessDenied")
        assert [(r.levelno, r.event, r.stack_level, r.getMessage()) for r in keep.records] == [
            (logging.DEBUG, STACK_EVENT, "info", "asyncua: process message 1"),
            (
                logging.WARNING,
                STACK_EVENT,
                "error",
                "asyncua: sending service fault response: denied (BadUserAccessDenied)",
            ),
        ]
        assert keep.records[1].stack_logger == stack.name and not hasattr(keep.records[1], "repeated")
        now[0] += STACK_WINDOW_S
        stack.error("sending service fault response: %s (%s)", "other", "BadNodeIdUnknown")
        assert keep.records[-1].repeated == 4  # the 4 held back, counted into the next line
        line = KeyValueFormatter(journal=True).format(keep.records[-1])
        assert line.startswith("<4>level=warning event=opcua_stack ") and "repeated=4" in line, line
        try:
            raise KeyError("x")
        except KeyError:
            stack.exception("Error while processing message")
        assert keep.records[-1].error == "KeyError: 'x'" and keep.records[-1].exc_info is None
        # a flood of distinct messages: at most STACK_LINES_PER_WINDOW lines a window, the rest counted
        now[0] += STACK_WINDOW_S
        before = len(keep.records)
        for i in range(STACK_LINES_PER_WINDOW + 7):
            stack.warning(f"message {i}")
        assert len(keep.records) - before == STACK_LINES_PER_WINDOW
        now[0] += STACK_WINDOW_S
        stack.warning("after the flood")
        assert keep.records[-1].dropped == 7
    finally:
        stack.removeHandler(events)
        events.out.removeHandler(keep)


def test_the_servers_asyncua_lines_reach_compd_as_events(
    served: Any, pki: Pki, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """asyncua's loggers do not propagate (no raw line; pytest alone attaches its own capture to
    them): the fault a refused login answers reaches compd's log as one opcua_stack event per window."""
    from compd.plant import opcua

    stack = logging.getLogger("asyncua")
    assert stack.propagate is False and opcua._STACK_HANDLER in stack.handlers
    assert stack.level == logging.WARNING  # compd logs info: asyncua's INFO (each request) is not even made
    monkeypatch.setattr(opcua._STACK_HANDLER, "_seen", {})  # what earlier tests logged is not a repeat here
    monkeypatch.setattr(opcua._STACK_HANDLER, "_window", (-math.inf, 0))
    _, url = served
    with caplog.at_level(logging.WARNING, logger="compd"):
        for _ in range(2):
            with pytest.raises(ua.uaerrors.BadUserAccessDenied):
                run(url, pki, lambda client: client.nodes.objects.read_browse_name(), password="wrong")
    faults = [r for r in caplog.records if r.name == "compd.opcua.stack" and "service fault" in r.getMessage()]
    assert len(faults) == 1, [r.getMessage() for r in faults]
    assert (faults[0].levelno, faults[0].event, faults[0].stack_logger) == (
        logging.WARNING,
        opcua.STACK_EVENT,
        "asyncua.server.uaprocessor",
    )
