// Decodes Sparkplug B payloads with Eclipse Tahu's library (npm sparkplug-payload), not compd's code.
// stdin: one JSON object a line, {"topic": ..., "hex": ...}; stdout: one JSON object a line, the
// topic and the decoded payload (64-bit numbers as strings, bytes as hex).
const readline = require("readline");
const sparkplug = require("sparkplug-payload").get("spBv1.0");

function plain(v) {
  if (v === null || v === undefined) return null;
  if (typeof v === "object" && typeof v.toString === "function" && "low" in v && "high" in v) return v.toString();
  if (Buffer.isBuffer(v) || v instanceof Uint8Array) return Buffer.from(v).toString("hex");
  if (Array.isArray(v)) return v.map(plain);
  if (typeof v === "object") {
    const out = {};
    for (const [k, x] of Object.entries(v)) out[k] = plain(x);
    return out;
  }
  return v;
}

const rl = readline.createInterface({ input: process.stdin });
rl.on("line", (line) => {
  const { topic, hex } = JSON.parse(line);
  try {
    const p = sparkplug.decodePayload(Buffer.from(hex, "hex"));
    process.stdout.write(JSON.stringify({ topic, payload: plain(p) }) + "\n");
  } catch (e) {
    process.stdout.write(JSON.stringify({ topic, error: String(e) }) + "\n");
  }
});
