// The real Foxglove WebSocket client (@foxglove/ws-protocol's FoxgloveClient over `ws`), driven
// by the lcmx foxglove tests (test/foxglove/server_test.cpp) and the benchmark (bench/foxglove).
//
//   node fg_client.js PLAN.json
//
// PLAN (every key optional but url):
//   url, subprotocol ("foxglove.websocket.v1" | "foxglove.sdk.v1"), timeout_ms (whole run)
//   ca: PATH                           wss:// trusting only this PEM certificate (else any)
//   expect_capability: NAME            wait until a serverInfo lists it (e.g. "time")
//   time_count: N                      wait for N `time` messages, print {"event":"time",...}
//   expect_topics: [topic...]          wait until each is advertised
//   subscribe: [{topic, count}]        subscribe, wait for `count` messages (decoded JSON)
//   publish: [{topic, schemaName, messages: [obj...], period_ms}]   clientPublish
//   call: [{service, request}]         wait for the service, call it, wait for the answer
//   graph_topic: NAME                  subscribe to the connection graph, wait for NAME published
//   dump: PATH                         write {channels, messages: {topic: [first 3 decoded]}}
//   subscribe_all: true                subscribe to every channel advertised (now and later)
//   slow: true                         with subscribe_all: stop reading the socket (never resume),
//                                      after expect_topics are advertised
//   stats_every_ms: N                  print {"stats":{topic:{count, lat_p50_ms...}}} lines
//   run_ms: N                          stay connected this long after the steps (bench)
//   report_timestamps: true            at the end, {"event":"timestamps", topic, min, max, count}
// Prints one JSON line per event worth checking ("serverInfo", "advertised", "message" for the
// first of each topic, "status", "called", "graph") and a last line {"done": true|false,
// "error": ...}. Exit 0 when every step finished in time, 1 otherwise.
"use strict";
const fs = require("fs");
const { FoxgloveClient } = require("@foxglove/ws-protocol");
const WebSocket = require("ws");

const plan = JSON.parse(fs.readFileSync(process.argv[2], "utf8"));
const out = (o) => process.stdout.write(JSON.stringify(o) + "\n");
const deadline = Date.now() + (plan.timeout_ms || 20000);

// wss://: with `ca`, only a server presenting that certificate (for the address in the URL) is
// accepted, as a browser that trusts it would; without, any certificate.
const ws = new WebSocket(plan.url, [plan.subprotocol || FoxgloveClient.SUPPORTED_SUBPROTOCOL],
  plan.ca ? { ca: [fs.readFileSync(plan.ca)], rejectUnauthorized: true } : { rejectUnauthorized: false });
const client = new FoxgloveClient({ ws });
const channels = new Map(); // id -> channel
const byTopic = new Map(); // topic -> [channel]
const subs = new Map(); // subscription id -> channel
const received = new Map(); // topic -> [decoded]
const counts = new Map(); // topic -> count
const lat = new Map(); // topic -> [ms from the message's timestamp to now]
const services = new Map(); // name -> service
const callResults = new Map(); // callId -> result
let graph = null;
let info = null;
const times = { count: 0, first: null, last: null, min: null, max: null, decreasing: 0 };
const stamps = new Map(); // topic -> {min, max, count} of message timestamps (ns, BigInt)
const waiters = [];
const decoder = new TextDecoder();
let paused = false;

function poke() {
  for (let i = waiters.length - 1; i >= 0; --i) {
    if (waiters[i].pred()) {
      const w = waiters.splice(i, 1)[0];
      w.resolve();
    }
  }
}
function until(pred, what) {
  if (pred()) return Promise.resolve();
  return new Promise((resolve, reject) => {
    const left = deadline - Date.now();
    const t = setTimeout(() => reject(new Error("timed out waiting for " + what)), Math.max(left, 0));
    waiters.push({ pred, resolve: () => { clearTimeout(t); resolve(); } });
  });
}

function subscribeChannel(ch) {
  const id = client.subscribe(ch.id);
  subs.set(id, ch);
  return id;
}

client.on("error", (e) => out({ event: "error", message: String(e && e.message ? e.message : e) }));
client.on("serverInfo", (i) => {
  info = i;
  out({ event: "serverInfo", name: i.name, capabilities: i.capabilities, supportedEncodings: i.supportedEncodings,
        subprotocol: ws.protocol });
  poke();
});
client.on("status", (s) => { out({ event: "status", level: s.level, message: s.message, id: s.id }); });
client.on("removeStatus", (s) => { out({ event: "removeStatus", statusIds: s.statusIds }); });
client.on("advertise", (list) => {
  for (const ch of list) {
    channels.set(ch.id, ch);
    if (!byTopic.has(ch.topic)) byTopic.set(ch.topic, []);
    byTopic.get(ch.topic).push(ch);
    out({ event: "advertised", id: ch.id, topic: ch.topic, schemaName: ch.schemaName, encoding: ch.encoding,
          schemaEncoding: ch.schemaEncoding });
    if (plan.subscribe_all) subscribeChannel(ch);
  }
  poke();
});
client.on("unadvertise", (ids) => {
  for (const id of ids) {
    const ch = channels.get(id);
    if (!ch) continue;
    channels.delete(id);
    byTopic.set(ch.topic, (byTopic.get(ch.topic) || []).filter((c) => c.id !== id));
    out({ event: "unadvertised", id, topic: ch.topic });
  }
  poke();
});
client.on("message", ({ subscriptionId, timestamp, data }) => {
  const ch = subs.get(subscriptionId);
  if (!ch) return;
  const n = (counts.get(ch.topic) || 0) + 1;
  counts.set(ch.topic, n);
  const st = stamps.get(ch.topic) || { min: timestamp, max: timestamp, count: 0 };
  if (timestamp < st.min) st.min = timestamp;
  if (timestamp > st.max) st.max = timestamp;
  st.count += 1;
  stamps.set(ch.topic, st);
  const nowNs = BigInt(Date.now()) * 1000000n;
  if (!lat.has(ch.topic)) lat.set(ch.topic, []);
  lat.get(ch.topic).push(Number(nowNs - timestamp) / 1e6);
  if (plan.count_only) { poke(); return; }
  let msg;
  try {
    msg = JSON.parse(decoder.decode(data));
  } catch (e) {
    out({ event: "bad_json", topic: ch.topic, message: String(e) });
    return;
  }
  if (!received.has(ch.topic)) received.set(ch.topic, []);
  const r = received.get(ch.topic);
  if (r.length < 3) r.push(msg);
  if (n === 1) {
    // Big fields shortened for the listing.
    const short = JSON.parse(JSON.stringify(msg, (k, v) => (typeof v === "string" && v.length > 48 ? v.slice(0, 24) + "...(" + v.length + " chars)" : v)));
    out({ event: "message", topic: ch.topic, schemaName: ch.schemaName, timestamp: timestamp.toString(), data: short });
  }
  poke();
});
client.on("advertiseServices", (list) => {
  for (const s of list) {
    services.set(s.name, s);
    out({ event: "service", id: s.id, name: s.name, type: s.type,
          request: s.request && s.request.schemaName, response: s.response && s.response.schemaName });
  }
  poke();
});
client.on("serviceCallResponse", (r) => {
  const body = JSON.parse(decoder.decode(r.data));
  callResults.set(r.callId, { ok: true, body });
  poke();
});
client.on("serviceCallFailure", (r) => {
  callResults.set(r.callId, { ok: false, message: r.message });
  poke();
});
client.on("time", ({ timestamp }) => {
  if (times.count === 0) times.first = timestamp;
  if (times.last !== null && timestamp < times.last) times.decreasing += 1;
  times.last = timestamp;
  if (times.min === null || timestamp < times.min) times.min = timestamp;
  if (times.max === null || timestamp > times.max) times.max = timestamp;
  times.count += 1;
  poke();
});
client.on("connectionGraphUpdate", (g) => {
  graph = g;
  poke();
});

function percentile(a, p) {
  if (a.length === 0) return null;
  const s = [...a].sort((x, y) => x - y);
  return s[Math.min(s.length - 1, Math.floor((p / 100) * s.length))];
}

async function main() {
  await until(() => info !== null, "serverInfo");
  if (plan.expect_capability)
    await until(() => info.capabilities.includes(plan.expect_capability), "capability " + plan.expect_capability);
  for (const t of plan.expect_topics || []) await until(() => (byTopic.get(t) || []).length > 0, "topic " + t);
  if (plan.slow) {
    // Stop reading (once the expected topics are advertised, and subscribed with subscribe_all):
    // the socket's receive buffer fills, then the server's sends wait.
    ws._socket.pause();
    paused = true;
    out({ event: "paused" });
  }
  for (const s of plan.subscribe || []) {
    await until(() => (byTopic.get(s.topic) || []).length > 0, "topic " + s.topic);
    for (const ch of byTopic.get(s.topic)) subscribeChannel(ch);
  }
  for (const s of plan.subscribe || [])
    await until(() => (counts.get(s.topic) || 0) >= (s.count || 1), (s.count || 1) + " messages of " + s.topic);
  for (const p of plan.publish || []) {
    const id = client.advertise({ topic: p.topic, encoding: "json", schemaName: p.schemaName });
    const enc = new TextEncoder();
    for (const m of p.messages) {
      await new Promise((r) => setTimeout(r, p.period_ms || 50)); // pacing a publisher, not a synchronisation
      client.sendMessage(id, enc.encode(JSON.stringify(m)));
    }
    out({ event: "published", topic: p.topic, count: p.messages.length });
  }
  let callId = 1;
  for (const c of plan.call || []) {
    await until(() => services.has(c.service), "service " + c.service);
    const s = services.get(c.service);
    const id = callId++;
    client.sendServiceCallRequest({ serviceId: s.id, callId: id, encoding: "json",
                                    data: new TextEncoder().encode(JSON.stringify(c.request)) });
    await until(() => callResults.has(id), "the answer of " + c.service);
    out({ event: "called", service: c.service, result: callResults.get(id) });
  }
  if (plan.graph_topic) {
    client.subscribeConnectionGraph();
    await until(() => graph && graph.publishedTopics.some((t) => t.name === plan.graph_topic), "graph topic " + plan.graph_topic);
    out({ event: "graph", publishedTopics: graph.publishedTopics.filter((t) => t.name === plan.graph_topic),
          subscribedTopics: graph.subscribedTopics.length, advertisedServices: graph.advertisedServices });
  }
  if (plan.time_count) {
    await until(() => times.count >= plan.time_count, plan.time_count + " time messages");
    out({ event: "time", count: times.count, first: String(times.first), last: String(times.last),
          min: String(times.min), max: String(times.max), decreasing: times.decreasing });
  }
  if (plan.report_timestamps)
    for (const [t, st] of stamps)
      out({ event: "timestamps", topic: t, min: String(st.min), max: String(st.max), count: st.count });
  if (plan.dump) {
    const ms = {};
    for (const [t, r] of received) ms[t] = r;
    fs.writeFileSync(plan.dump, JSON.stringify({ channels: [...channels.values()], messages: ms }));
  }
  if (plan.run_ms) {
    const start = Date.now();
    const every = plan.stats_every_ms || plan.run_ms;
    while (Date.now() - start < plan.run_ms) {
      const c0 = new Map(counts);
      for (const k of lat.keys()) lat.set(k, []);
      const t0 = Date.now();
      await new Promise((r) => setTimeout(r, Math.min(every, plan.run_ms - (Date.now() - start)))); // measuring window
      const dt = (Date.now() - t0) / 1000;
      const st = {};
      for (const [t, n] of counts) st[t] = { rate: (n - (c0.get(t) || 0)) / dt, p50_ms: percentile(lat.get(t) || [], 50),
                                             p99_ms: percentile(lat.get(t) || [], 99) };
      out({ event: "stats", window_s: dt, topics: st });
    }
  }
}

main().then(
  () => { out({ done: true, paused }); client.close(); process.exit(0); },
  (e) => { out({ done: false, error: String(e.message || e) }); try { client.close(); } catch (_) {} process.exit(1); },
);
