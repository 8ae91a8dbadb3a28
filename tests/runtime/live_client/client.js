// Test tool: a Foxglove WebSocket protocol client (Foxglove's @foxglove/ws-protocol) that subscribes to
// every channel a server advertises and decodes each message with Foxglove's ROS 2 CDR reader.
//   node client.js URL [--seconds S] [--until TOPIC,TOPIC...]   -> one JSON report on stdout
//   node client.js URL --stuck                                   subscribes, then never reads again
// Report: {"channels": {topic: {schemaName, encoding, schemaEncoding}}, "topics": {topic: {count,
// first, last}}} where first / last are the decoded messages (arrays as {len, head}, bigints as strings).
"use strict";
const { FoxgloveClient } = require("@foxglove/ws-protocol");
const { parse } = require("@foxglove/rosmsg");
const { MessageReader } = require("@foxglove/rosmsg2-serialization");
const WebSocket = require("ws");

const args = process.argv.slice(2);
const url = args[0];
const opt = (name, dflt) => { const i = args.indexOf(name); return i >= 0 ? args[i + 1] : dflt; };
const seconds = Number(opt("--seconds", "20"));
const until = (opt("--until", "") || "").split(",").filter(Boolean);
const stuck = args.includes("--stuck");

function plain(v) {
  if (typeof v === "bigint") return v.toString();
  if (ArrayBuffer.isView(v) || Array.isArray(v)) {
    const head = Array.from(v.slice(0, 4), plain);
    return { len: v.length, head };
  }
  if (v && typeof v === "object") {
    const o = {};
    for (const [k, x] of Object.entries(v)) o[k] = plain(x);
    return o;
  }
  if (typeof v === "number" && !Number.isFinite(v)) return String(v);
  return v;
}

const ws = new WebSocket(url, [opt("--subprotocol", "foxglove.sdk.v1")]);
const client = new FoxgloveClient({ ws });
const channels = {}, readerOf = new Map(), topicOf = new Map(), report = {};
let subscribed = 0, done = false;

function finish(code) {
  if (done) return;
  done = true;
  process.stdout.write(JSON.stringify({ channels, topics: report }) + "\n");
  try { client.close(); } catch (e) { /* closing anyway */ }
  process.exit(code);
}

client.on("error", (e) => { process.stderr.write(`client error: ${e && e.message}\n`); });
client.on("close", () => { if (stuck) process.stdout.write("closed\n"); else finish(0); });
client.on("advertise", (chans) => {
  for (const ch of chans) {
    channels[ch.topic] = { schemaName: ch.schemaName, encoding: ch.encoding, schemaEncoding: ch.schemaEncoding };
    if (ch.encoding !== "cdr" || ch.schemaEncoding !== "ros2msg") continue;
    const sid = client.subscribe(ch.id);
    readerOf.set(sid, new MessageReader(parse(ch.schema, { ros2: true })));
    topicOf.set(sid, ch.topic);
    subscribed += 1;
  }
  if (!stuck && subscribed > 0) process.stderr.write("subscribed\n");
  if (stuck && subscribed > 0) {
    // stop reading: the TCP receive window fills and the server must cope with a client that never reads
    setTimeout(() => { ws._socket.pause(); process.stdout.write("stuck\n"); }, 200);
  }
});
client.on("message", ({ subscriptionId, timestamp, data }) => {
  if (stuck) return;
  const topic = topicOf.get(subscriptionId);
  const msg = readerOf.get(subscriptionId).readMessage(data);
  const r = report[topic] || (report[topic] = { count: 0, first: null, last: null, log_time: null });
  r.count += 1;
  if (r.first === null) r.first = plain(msg);
  r.last = plain(msg);
  r.log_time = timestamp.toString();
  if (until.length && until.every((t) => report[t])) finish(0);
});

if (!stuck) setTimeout(() => finish(until.length ? 3 : 0), seconds * 1000);
else setInterval(() => {}, 1000); // stay connected (and not reading) until killed
