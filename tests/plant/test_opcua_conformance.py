"""compd's OPC UA server browsed and read by node-opcua, an independent client.

node-opcua comes from npm, unpacked into build/ by the Makefile. Basic256Sha256 SignAndEncrypt with a trusted client
certificate and a user name; every node's type, units, range, description, sampling interval and value as
documented; anonymous and unsecured logins refused.
"""

from __future__ import annotations

import copy
import json
import os
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest
from cryptography import x509
from cryptography.hazmat.primitives import serialization

from compd.plant.opcua import OpcUaServer
from tests.conftest import ROOT

from .test_opcua import GUARD, NS_URI, PASSWORD, PERIOD_S, SNAP, Pki, config, documented, expected

NODE_OPCUA = ROOT / "build" / "tools" / "node-opcua" / "node_modules"
READER = Path(__file__).with_name("opcua_read.js")
BASIC256SHA256 = "http://opcfoundation.org/UA/SecurityPolicy#Basic256Sha256"
UNITS_NAMESPACE = "http://www.opcfoundation.org/UA/units/un/cefact"
LONG_PASSWORD = "Kennwort-ü-" * 30  # 360 bytes: encrypted in two RSA-2048 blocks
CLIENT_TIMEOUT_S = 180  # node-opcua's start and ~150 reads: seconds; generous for a loaded box


def _node_opcua(pki: Pki, url: str) -> list[dict[str, Any]]:
    node = shutil.which("node")
    assert node, "no node: Node.js runs node-opcua"
    assert (NODE_OPCUA / "node-opcua-client").is_dir(), (
        "no node-opcua: `make build/tools/node-opcua/node_modules/node-opcua-client/package.json`"
    )
    server_der = x509.load_pem_x509_certificate((pki.root / "server.pem").read_bytes()).public_bytes(
        serialization.Encoding.DER
    )
    (pki.root / "server.der").write_bytes(server_der)
    args = {
        "url": url,
        "namespaceUri": NS_URI,
        "userName": "alice",
        "password": PASSWORD,
        "certificateFile": str(pki.root / "trusted" / "client.pem"),
        "privateKeyFile": str(pki.root / "client.key"),
        "applicationUri": pki.client("client")[2],
        "serverCertificateFile": str(pki.root / "server.der"),
        "pkiFolder": str(pki.root / "node-pki"),
        "longPassword": {"userName": "bob", "password": LONG_PASSWORD},
    }
    (pki.root / "reader.json").write_text(json.dumps(args))
    env = {**os.environ, "NODE_PATH": str(NODE_OPCUA), "HOME": str(pki.root)}  # what node-opcua keeps in ~ stays here
    r = subprocess.run(
        [node, str(READER), str(pki.root / "reader.json")],
        capture_output=True,
        text=True,
        timeout=CLIENT_TIMEOUT_S,
        env=env,
        cwd=pki.root,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    lines = [json.loads(ln) for ln in r.stdout.splitlines() if ln.startswith("{")]
    assert lines and lines[-1] == {"kind": "done"}, r.stdout[-2000:] + r.stderr[-2000:]
    return lines


def _version() -> str:
    return json.loads((NODE_OPCUA / "node-opcua-client" / "package.json").read_text())["version"]


def _fmt(x: float) -> str:
    return f"{x:g}"


@pytest.fixture(scope="module")
def read_by_node_opcua(tmp_path_factory: pytest.TempPathFactory) -> list[dict[str, Any]]:
    pki = Pki(tmp_path_factory.mktemp("opcua-conformance"))
    (pki.root / "bob.password").write_text(LONG_PASSWORD + "\n")
    users = {"alice": {"password_file": "alice.password"}, "bob": {"password_file": "bob.password"}}
    server = OpcUaServer(config(users=users), pki.root, GUARD)
    try:
        url = server.start(copy.deepcopy(SNAP))
        assert url.startswith("opc.tcp://127.0.0.1:")
        return _node_opcua(pki, url)
    finally:
        server.stop()


def test_node_opcua_sees_the_documented_address_space(read_by_node_opcua: list[dict[str, Any]]) -> None:
    lines = read_by_node_opcua
    idx = next(ln for ln in lines if ln["kind"] == "namespace")["index"]
    assert idx > 0
    nodes = {ln["nodeId"]: ln for ln in lines if ln["kind"] == "node"}
    want = documented(SNAP)
    values = expected(SNAP)
    print(f"\nnode-opcua-client {_version()} over Basic256Sha256 SignAndEncrypt, user alice; {len(nodes)} nodes:")
    assert {nid.removeprefix(f"ns={idx};s=") for nid in nodes} == set(want)
    for nid, n in nodes.items():
        key = nid.removeprefix(f"ns={idx};s=")
        bname, ntype, dtype, unit, eu_range = want[key]
        assert n["browsePath"] == "Objects/" + key.replace(".", "/")  # node id = browse path
        assert (n["browseName"], n["typeDefinition"]) == (
            f"{idx}:{bname}",
            "FolderType" if ntype == "Folder" else ntype,
        )
        assert n["description"] and n["description"] != bname, key
        if n["nodeClass"] == "Object":
            print(f"  {key:34} {n['typeDefinition']:21} | {n['description']}")
            continue
        props = n["properties"]
        assert n["dataType"] == dtype and n["minimumSamplingInterval"] == PERIOD_S * 1000.0
        assert n["accessLevel"] == n["userAccessLevel"] == 1  # CurrentRead only
        assert set(props) <= {"EngineeringUnits", "EURange"}
        eu = props.get("EngineeringUnits")
        rng = props.get("EURange")
        assert (eu["displayName"] if eu else "—") == unit, key
        assert ((rng["low"], rng["high"]) if rng else None) == eu_range, key
        if eu:
            assert eu["namespaceUri"] == UNITS_NAMESPACE and eu["typeDefinition"] == "PropertyType"
            assert eu["unitId"] > 0 and eu["unitDescription"]
        if rng:
            assert rng["typeDefinition"] == "PropertyType" and rng["description"]
        want_value, want_status = values[key]
        got = int(n["value"]) if dtype == "UInt64" and n["value"] is not None else n["value"]
        assert (got, n["statusCode"]) == (want_value, want_status), key
        units = f"{eu['displayName']} (UnitId {eu['unitId']})" if eu else "—"
        ranges = f"{_fmt(rng['low'])} … {_fmt(rng['high'])}" if rng else "—"
        print(
            f"  {key:34} {n['typeDefinition']:21} {dtype:7} {units:22} {ranges:22}"
            f" {n['minimumSamplingInterval']:g} ms = {got!r} {n['statusCode']} | {n['description']}"
        )


def test_node_opcua_sees_an_encrypted_password_policy_and_is_refused_without_it(
    read_by_node_opcua: list[dict[str, Any]],
) -> None:
    lines = read_by_node_opcua
    endpoints = next(ln for ln in lines if ln["kind"] == "endpoints")["endpoints"]
    assert [(e["securityMode"], e["securityPolicyUri"]) for e in endpoints] == [("SignAndEncrypt", BASIC256SHA256)]
    for e in endpoints:
        tokens = {t["tokenType"]: t for t in e["userIdentityTokens"]}
        print(
            f"\nendpoint {e['endpointUrl']} {e['securityMode']} {e['securityPolicyUri']}: "
            + ", ".join(f"{t['tokenType']} ({t['policyId']}) {t['securityPolicyUri']}" for t in tokens.values())
        )
        assert set(tokens) == {"UserName"}  # no Anonymous token policy
        assert tokens["UserName"]["securityPolicyUri"] == BASIC256SHA256
    refusals = {(ln["case"], ln["insist"]): ln for ln in lines if ln["kind"] == "refused"}
    for (case, insist), r in refusals.items():
        print(f"{case}{' (the client insists)' if insist else ''}: refused={r['refused']} ({r.get('error')})")
    assert set(refusals) == {("anonymous", False), ("anonymous", True), ("security None", False)}
    assert all(r["refused"] for r in refusals.values())
    # node-opcua gives up by itself: the endpoints offer neither; insisting, the server refuses
    assert "ANONYMOUS" in refusals["anonymous", False]["error"]
    assert "BadIdentityTokenRejected" in refusals["anonymous", True]["error"]
    assert "securityMode = None" in refusals["security None", False]["error"]
    login = next(ln for ln in lines if ln["kind"] == "login")
    print(f"user {login['userName']} with a {login['passwordBytes']}-byte password: compd.State = {login['state']!r}")
    assert login == {
        "kind": "login",
        "userName": "bob",
        "passwordBytes": len(LONG_PASSWORD.encode()),
        "state": "running",
    }
