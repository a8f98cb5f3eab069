// Browses and reads compd's OPC UA server with node-opcua (npm node-opcua-client), an OPC UA stack that shares no code with asyncua or compd.
// argv[2]: a JSON file {url, namespaceUri, userName, password, certificateFile, privateKeyFile,
// applicationUri, serverCertificateFile (DER), pkiFolder, longPassword: {userName, password} (a password
// longer than one RSA block once encrypted)}. stdout: one JSON object a line —
// the endpoints with their user token policies, every node under Objects/compd with its
// attributes and properties, and what happened to an anonymous and an unsecured login.
"use strict";
const fs = require("fs");
const {
  OPCUAClient, MessageSecurityMode, SecurityPolicy, UserTokenType, AttributeIds, BrowseDirection, NodeClass,
} = require("node-opcua-client");
const { OPCUACertificateManager } = require("node-opcua-certificate-manager");

const cfg = JSON.parse(fs.readFileSync(process.argv[2], "utf8"));
const out = (obj) => process.stdout.write(JSON.stringify(obj) + "\n");

function plain(v) {
  if (v === null || v === undefined) return null;
  if (typeof v === "bigint") return v.toString();
  if (Buffer.isBuffer(v)) return v.toString("hex");
  if (Array.isArray(v)) return v.map(plain);
  if (typeof v === "object" && typeof v.toJSON === "function") return v.toJSON();
  return v;
}

// a Variant's value as JSON: UInt64 (node-opcua: [high, low]) as a decimal string
function value(variant) {
  if (!variant || variant.value === null || variant.value === undefined) return null;
  if (variant.dataType === 9 /* UInt64 */ && Array.isArray(variant.value)) {
    return ((BigInt(variant.value[0]) << 32n) + BigInt(variant.value[1])).toString();
  }
  return plain(variant.value);
}

function client(mode, policy, manager) {
  return OPCUAClient.create({
    applicationName: "compd-conformance",
    applicationUri: cfg.applicationUri,
    securityMode: mode,
    securityPolicy: policy,
    certificateFile: cfg.certificateFile,
    privateKeyFile: cfg.privateKeyFile,
    clientCertificateManager: manager,
    connectionStrategy: { maxRetry: 0, initialDelay: 100, maxDelay: 200 },
    requestedSessionTimeout: 60000,
    transportTimeout: 30000,
  });
}

async function browse(session, nodeId, referenceTypeId) {
  const r = await session.browse({
    nodeId, browseDirection: BrowseDirection.Forward, referenceTypeId, includeSubtypes: true,
    nodeClassMask: 0, resultMask: 63,
  });
  if (!r.statusCode.isGood()) throw new Error(`browse ${nodeId}: ${r.statusCode.name}`);
  return r.references || [];
}

const names = new Map(); // NodeId text → its BrowseName (types, data types)
async function nameOf(session, nodeId) {
  const key = nodeId.toString();
  if (!names.has(key)) {
    const dv = await session.read({ nodeId, attributeId: AttributeIds.BrowseName });
    names.set(key, dv.value.value ? dv.value.value.name : `?${key}`);
  }
  return names.get(key);
}

async function attributes(session, nodeId, ids) {
  const dvs = await session.read(ids.map((attributeId) => ({ nodeId, attributeId })));
  return dvs;
}

async function describe(session, ref, path) {
  const nodeId = ref.nodeId;
  const node = {
    kind: "node",
    nodeId: nodeId.toString(),
    browsePath: path,
    browseName: ref.browseName.toString(),
    nodeClass: NodeClass[ref.nodeClass],
    typeDefinition: await nameOf(session, ref.typeDefinition),
  };
  const [desc] = await attributes(session, nodeId, [AttributeIds.Description]);
  node.description = desc.value.value ? desc.value.value.text : null;
  if (ref.nodeClass === NodeClass.Object) {
    out(node);
    for (const child of await browse(session, nodeId, "HierarchicalReferences")) {
      await describe(session, child, `${path}/${child.browseName.name}`);
    }
    return;
  }
  const [dt, sampling, access, userAccess, val] = await attributes(session, nodeId, [
    AttributeIds.DataType, AttributeIds.MinimumSamplingInterval, AttributeIds.AccessLevel,
    AttributeIds.UserAccessLevel, AttributeIds.Value,
  ]);
  node.dataType = await nameOf(session, dt.value.value);
  node.minimumSamplingInterval = sampling.value.value;
  node.accessLevel = access.value.value;
  node.userAccessLevel = userAccess.value.value;
  node.statusCode = val.statusCode.name;
  node.value = value(val.value);
  node.properties = {};
  for (const p of await browse(session, nodeId, "HasProperty")) {
    const [pv, pdesc] = await attributes(session, p.nodeId, [AttributeIds.Value, AttributeIds.Description]);
    const v = pv.value.value;
    const prop = {
      nodeId: p.nodeId.toString(),
      typeDefinition: await nameOf(session, p.typeDefinition),
      description: pdesc.value.value ? pdesc.value.value.text : null,
    };
    if (p.browseName.name === "EURange") Object.assign(prop, { low: v.low, high: v.high });
    else if (p.browseName.name === "EngineeringUnits") {
      Object.assign(prop, {
        namespaceUri: v.namespaceUri, unitId: v.unitId,
        displayName: v.displayName.text, unitDescription: v.description.text,
      });
    } else prop.value = plain(v);
    node.properties[p.browseName.name] = prop;
  }
  out(node);
}

// a login that should fail; `insist`: the client adds to the endpoint the token policy the server does
// not offer (node-opcua would give up by itself), so that the server is the one that refuses
async function refused(name, mode, policy, manager, identity, insist) {
  const c = client(mode, policy, manager);
  try {
    await c.connect(cfg.url);
    if (insist) { // node-opcua 2.186's endpoints as GetEndpoints gave them (a private field: pinned version)
      for (const e of c._serverEndpoints) {
        e.userIdentityTokens.push({ policyId: "anonymous", tokenType: identity.type, securityPolicyUri: SecurityPolicy.None });
      }
    }
    const s = await c.createSession(identity);
    await s.close();
    out({ kind: "refused", case: name, insist, refused: false });
  } catch (e) {
    out({ kind: "refused", case: name, insist, refused: true, error: String(e.message || e).split("\n")[0].trim() });
  } finally {
    await c.disconnect();
  }
}

async function main() {
  const manager = new OPCUACertificateManager({ rootFolder: cfg.pkiFolder, automaticallyAcceptUnknownCertificate: false });
  await manager.initialize();
  await manager.trustCertificate(fs.readFileSync(cfg.serverCertificateFile)); // the server's, and only it

  const c = client(MessageSecurityMode.SignAndEncrypt, SecurityPolicy.Basic256Sha256, manager);
  await c.connect(cfg.url);
  let idx = -1;
  try {
    const endpoints = await c.getEndpoints();
    out({
      kind: "endpoints",
      endpoints: endpoints.map((e) => ({
        endpointUrl: e.endpointUrl,
        securityMode: MessageSecurityMode[e.securityMode],
        securityPolicyUri: e.securityPolicyUri,
        userIdentityTokens: e.userIdentityTokens.map((t) => ({
          policyId: t.policyId, tokenType: UserTokenType[t.tokenType], securityPolicyUri: t.securityPolicyUri,
        })),
      })),
    });
    const session = await c.createSession({ type: UserTokenType.UserName, userName: cfg.userName, password: cfg.password });
    try {
      const ns = (await session.read({ nodeId: "ns=0;i=2255", attributeId: AttributeIds.Value })).value.value;
      idx = ns.indexOf(cfg.namespaceUri);
      out({ kind: "namespace", index: idx, uri: cfg.namespaceUri });
      const top = (await browse(session, "ns=0;i=85", "Organizes")).filter(
        (r) => r.browseName.name === "compd" && r.browseName.namespaceIndex === idx);
      if (top.length !== 1) throw new Error(`Objects/compd: ${top.length} nodes`);
      await describe(session, top[0], "Objects/compd");
    } finally {
      await session.close();
    }
  } finally {
    await c.disconnect();
  }
  for (const insist of [false, true]) {
    await refused("anonymous", MessageSecurityMode.SignAndEncrypt, SecurityPolicy.Basic256Sha256, manager,
      { type: UserTokenType.Anonymous }, insist);
  }
  // no endpoint with security None: node-opcua finds none to open a session on (the asyncua tests go
  // on over the unsecured channel anyway: compd refuses the session)
  await refused("security None", MessageSecurityMode.None, SecurityPolicy.None, manager,
    { type: UserTokenType.UserName, userName: cfg.userName, password: cfg.password }, false);
  // a long password: node-opcua encrypts it in more than one RSA block
  const lc = client(MessageSecurityMode.SignAndEncrypt, SecurityPolicy.Basic256Sha256, manager);
  await lc.connect(cfg.url);
  try {
    const s = await lc.createSession({ type: UserTokenType.UserName, ...cfg.longPassword });
    const state = await s.read({ nodeId: `ns=${idx};s=compd.State`, attributeId: AttributeIds.Value });
    out({ kind: "login", userName: cfg.longPassword.userName, passwordBytes: Buffer.byteLength(cfg.longPassword.password), state: state.value.value });
    await s.close();
  } finally {
    await lc.disconnect();
  }
  await manager.dispose();
  out({ kind: "done" });
}

main().then(() => process.exit(0), (e) => {
  process.stderr.write(`opcua_read.js: ${e.stack || e}\n`);
  process.exit(1);
});
