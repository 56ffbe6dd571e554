// lcmx_bench_service (issue 12): round-trip time of a service call, lcmx vs ZeroMQ REQ/REP,
// on one host and between two emulated hosts, plus calls per second with concurrent clients.
//
//   one host   lcmx service (shm)  |  two lcmx one-way shm messages (ping -> pong)  |
//              ZeroMQ REQ/REP over ipc://  and  tcp://127.0.0.1
//   two hosts  lcmx service (UDP, the vehicle group; a 1 MB response as UDP fragments)  |
//              lcmx service, UDP + bridges (1 MB responses through the Message Bridges)  |
//              lcmx service, bridges only (no vehicle group, `carry`)  |
//              ZeroMQ REQ/REP over TCP on the same link.
//
// Every method runs a server process and a client process (this binary with a hidden --role,
// started as the harness's RoleProcess: report lines on fd 3, the server ends when its command
// fd 4 closes); the client measures each call's round trip with CLOCK_MONOTONIC and reports
// "rtt <case> <p50_us> <p99_us> <n>" and "tput <clients> <calls/s>" lines, which the
// orchestrator turns into one Markdown table with ratios against the peers measured in the same
// run. A request's first 8 bytes say how large the response must be (every server honours it),
// the rest is filler.
#include <signal.h>
#include <spdlog/spdlog.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <map>
#include <mutex>
#include <optional>
#include <sstream>
#include <thread>
#include <zmq.hpp>

#include "harness/options.hpp"
#include "harness/process.hpp"
#include "harness/report.hpp"
#include "harness/stats.hpp"
#include "lcmx/core.hpp"
#ifdef LCMX_BENCH_WITH_NETNS
#include "harness/hosts.hpp"
#endif

namespace {

using namespace std::chrono_literals;
using Clock = std::chrono::steady_clock;
using lcmx::Bytes;

struct Case {
  std::size_t request = 0, response = 0;
  int calls = 0;
};

std::string case_label(const Case& c) {
  return lcmxbench::size_label(c.request) + " / " + lcmxbench::size_label(c.response);
}

// A case's key in the clients' "rtt" lines and in Result::rtt: "<request>:<response>".
std::string case_key(const Case& c) { return std::to_string(c.request) + ":" + std::to_string(c.response); }

Bytes make_request(std::size_t size, std::size_t response) {
  Bytes b(std::max<std::size_t>(size, 8), std::byte{0x5a});
  const std::uint64_t r = response;
  std::memcpy(b.data(), &r, 8);
  return b;
}

std::size_t response_size(std::span<const std::byte> req) {
  std::uint64_t r = 0;
  if (req.size() >= 8) std::memcpy(&r, req.data(), 8);
  return static_cast<std::size_t>(std::min<std::uint64_t>(r, 64u << 20));
}

using lcmxbench::stopped;

// A report line (fd 3) of a role: thread-safe, one write() per line.
void say(const std::string& line) { lcmxbench::report_line(line); }

// ---- servers ----

// Waits until the command fd closes (the orchestrator ends the role) or a stop signal.
void wait_for_end() {
  char c;
  while (!stopped() && ::read(lcmxbench::kCmdFd, &c, 1) > 0) {
  }
}

lcmx::RuntimeOptions runtime_options(const std::string& url, const std::string& vehicle) {
  lcmx::RuntimeOptions o;
  o.discovery_url = url;
  o.vehicle_url = vehicle;
  return o;
}

// Two one-way messages: NAME_PING -> a node of its own in this process -> NAME_PONG of the
// asked size. Not movable (the callback holds `this`).
struct EchoServer {
  lcmx::Node node;
  lcmx::RawPublisher pong;
  Bytes out;
  lcmx::RawSubscriber sub;
  EchoServer(lcmx::Runtime& rt, const std::string& name)
      : node(rt.create_node("bench_echo")), pong(node.advertise_raw(name + "_PONG")) {
    sub = node.subscribe_raw(name + "_PING", [this](const lcmx::RawMessage& m) {
      out.assign(response_size(m.data), std::byte{0xa5});
      std::memcpy(out.data(), m.data.data(), std::min<std::size_t>(8, out.size()));  // echo the tag
      pong.publish(out);
    });
  }
  EchoServer(const EchoServer&) = delete;
  EchoServer& operator=(const EchoServer&) = delete;
};

int server_echo(const std::string& url, const std::string& name) {
  auto rt = lcmx::Runtime::create(runtime_options(url, ""));
  EchoServer echo(rt, name);
  say("ready");
  wait_for_end();
  return 0;
}

// A ZeroMQ REP socket bound to `endpoint`, answering every request with a response of the size
// it asks for on a thread of its own, until destroyed (which shuts its context down and joins).
class RepServer {
 public:
  explicit RepServer(const std::string& endpoint) : rep_(ctx_, zmq::socket_type::rep) {
    rep_.bind(endpoint);
    thread_ = std::thread([this] {
      try {
        for (;;) {
          zmq::message_t req;
          if (!rep_.recv(req, zmq::recv_flags::none)) continue;
          zmq::message_t resp(response_size({static_cast<const std::byte*>(req.data()), req.size()}));
          std::memset(resp.data(), 0xa5, resp.size());
          rep_.send(resp, zmq::send_flags::none);
        }
      } catch (const zmq::error_t& e) {
        if (e.num() != ETERM) say(std::string("error REP socket: ") + e.what());
      }
    });
  }
  RepServer(const RepServer&) = delete;
  RepServer& operator=(const RepServer&) = delete;
  ~RepServer() {
    ctx_.shutdown();  // the thread's recv/send end with ETERM
    thread_.join();
  }

 private:
  zmq::context_t ctx_{1};
  zmq::socket_t rep_;
  std::thread thread_;
};

int server_zmq(const std::string& endpoint) {
  RepServer rep(endpoint);
  say("ready");
  wait_for_end();
  return 0;
}

// The lcmx server (its response written in place: shared memory for shm clients) and, with
// --interleave, in the same process a ZeroMQ REP socket on `endpoint` or an echo (`echo_name`:
// its channels' prefix), so that one client process can alternate between them call by call.
int server_lcmx(const std::string& url, const std::string& vehicle, const std::string& name,
                const std::string& endpoint, const std::string& echo_name) {
  auto rt = lcmx::Runtime::create(runtime_options(url, vehicle));
  auto node = rt.create_node("bench_server");
  auto s = node.create_service_raw(name, [](std::span<const std::byte> req, lcmx::ResponseWriter& out) {
    auto b = out.allocate(response_size(req));
    std::memset(b.data(), 0xa5, b.size());
  });
  std::optional<EchoServer> echo;
  if (!echo_name.empty()) echo.emplace(rt, echo_name);
  std::optional<RepServer> rep;
  if (!endpoint.empty()) rep.emplace(endpoint);
  say("ready");
  wait_for_end();
  return 0;
}

// ---- clients ----

struct Rtts {
  std::vector<double> us;
};

// "<kind> <case> <p50_us> <p99_us> <n>" (kind: rtt, or rtt-peer for --interleave's peer).
void report_rtt(const Case& c, const Rtts& r, const char* kind = "rtt") {
  const auto st = lcmxbench::stats_of(r.us);
  std::ostringstream o;
  o << kind << " " << case_key(c) << " " << st.p50 << " " << st.p99 << " " << r.us.size();
  say(o.str());
}

// Calls `call(request, response)` once per iteration; returns false to stop on an error.
using CallFn = std::function<bool(const Bytes& request)>;

void measure(const std::vector<Case>& cases, const CallFn& call) {
  for (const auto& c : cases) {
    const auto req = make_request(c.request, c.response);
    for (int i = 0; i < std::max(10, c.calls / 10); ++i)  // warm-up (segments grow, caches)
      if (!call(req)) return say("error warm-up call failed for " + case_label(c));
    Rtts r;
    r.us.reserve(static_cast<std::size_t>(c.calls));
    for (int i = 0; i < c.calls; ++i) {
      const auto t0 = Clock::now();
      if (!call(req)) return say("error call failed for " + case_label(c));
      r.us.push_back(std::chrono::duration<double, std::micro>(Clock::now() - t0).count());
    }
    report_rtt(c, r);
  }
}

// --interleave: two ways of calling, in turn call by call (a first in even calls, b first in
// odd ones), so that both see the same moments of the machine; prints "rtt" lines for `a` and
// "rtt-peer" lines for `b`.
void measure_pair(const std::vector<Case>& cases, const CallFn& a, const CallFn& b) {
  for (const auto& c : cases) {
    const auto req = make_request(c.request, c.response);
    for (int i = 0; i < std::max(10, c.calls / 10); ++i)
      if (!a(req) || !b(req)) return say("error warm-up call failed for " + case_label(c));
    Rtts ra, rb;
    for (int i = 0; i < c.calls; ++i) {
      for (int k = 0; k < 2; ++k) {
        const bool first_a = i % 2 == 0;
        const bool use_a = (k == 0) == first_a;
        const auto t0 = Clock::now();
        if (!(use_a ? a : b)(req)) return say("error call failed for " + case_label(c));
        (use_a ? ra : rb).us.push_back(std::chrono::duration<double, std::micro>(Clock::now() - t0).count());
      }
    }
    report_rtt(c, ra);
    report_rtt(c, rb, "rtt-peer");
  }
}

// A ZeroMQ REQ socket connected to `endpoint` (no linger, 10 s receive timeout).
zmq::socket_t req_socket(zmq::context_t& ctx, const std::string& endpoint) {
  zmq::socket_t s(ctx, zmq::socket_type::req);
  s.set(zmq::sockopt::linger, 0);
  s.set(zmq::sockopt::rcvtimeo, 10000);
  s.connect(endpoint);
  return s;
}

// One REQ/REP call on `s`; false on a timeout.
bool zmq_call(zmq::socket_t& s, const Bytes& req) {
  s.send(zmq::buffer(req.data(), req.size()), zmq::send_flags::none);
  zmq::message_t resp;
  return s.recv(resp, zmq::recv_flags::none).has_value();
}

// `clients` threads call back to back for `seconds`; prints "tput <clients> <calls/s>".
void throughput(int clients, double seconds, const std::function<CallFn(int)>& make) {
  std::atomic<long long> total{0};
  std::atomic<bool> failed{false};
  std::vector<std::thread> threads;
  const auto end = Clock::now() + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(seconds));
  const auto t0 = Clock::now();
  for (int i = 0; i < clients; ++i)
    threads.emplace_back([&, i] {
      auto call = make(i);
      const auto req = make_request(1024, 1024);
      long long n = 0;
      while (Clock::now() < end && !failed.load()) {
        if (!call(req)) {
          failed = true;
          break;
        }
        ++n;
      }
      total += n;
    });
  for (auto& t : threads) t.join();
  const double s = std::chrono::duration<double>(Clock::now() - t0).count();
  if (failed) return say("error a throughput call failed");
  say("tput " + std::to_string(clients) + " " + std::to_string(static_cast<double>(total.load()) / s));
}

// The client side of EchoServer, on a node of its own. A call publishes a ping and waits for a
// pong newer than it, counting them (one at a time: no overlap). Not movable.
struct EchoClient {
  lcmx::Node node;
  lcmx::RawPublisher ping;
  std::mutex mu;
  std::condition_variable cv;
  std::uint64_t pongs = 0, seen = 0;  // guarded by mu
  lcmx::RawSubscriber sub;
  EchoClient(lcmx::Runtime& rt, const std::string& name)
      : node(rt.create_node("bench_echo_client")), ping(node.advertise_raw(name + "_PING")) {
    sub = node.subscribe_raw(name + "_PONG", [this](const lcmx::RawMessage&) {
      std::lock_guard lock(mu);
      ++pongs;
      cv.notify_all();
    });
  }
  EchoClient(const EchoClient&) = delete;
  EchoClient& operator=(const EchoClient&) = delete;
  bool wait_ready() { return ping.wait_for_subscribers(1, 20s) && sub.wait_for_publishers(1, 20s); }
  bool call(const Bytes& req) {
    ping.publish(req);
    std::unique_lock lock(mu);
    const bool ok = cv.wait_for(lock, 10s, [&] { return pongs > seen; });
    seen = pongs;
    return ok;
  }
};

// With `endpoint` or `echo_name` (--interleave), a ZeroMQ REQ socket to it or an EchoClient
// too, and the two alternate call by call (measure_pair: "rtt" lines for lcmx, "rtt-peer" for
// the other).
int client_lcmx(const std::string& url, const std::string& vehicle, const std::string& name,
                const std::vector<Case>& cases, int clients, double seconds, bool settle_bridge,
                const std::string& endpoint, const std::string& echo_name) {
  auto rt = lcmx::Runtime::create(runtime_options(url, vehicle));
  // --settle-bridge: measure the settled state of "UDP + bridges", where this client's reply
  // channel is matched with this host's bridge republisher before it turns large (bridges
  // serve and offer small topics too, docs/bridge.md). A reply that turns large before that
  // is lost (docs/services.md "Known limits"); in a running system the bridges settle within
  // a few heartbeats of a client's start, the benchmark's first calls come sooner.
  std::mutex mu;
  std::condition_variable cv;
  bool bridged = false;
  if (settle_bridge)
    rt.on_event([&](const lcmx::Event& e) {
      const std::string suffix = "(bridge)";
      if (e.kind != lcmx::Event::Kind::publisher_matched || e.channel.rfind(name + "/rp/", 0) != 0 ||
          e.message.size() < suffix.size() || e.message.compare(e.message.size() - suffix.size(), suffix.size(), suffix) != 0)
        return;
      std::lock_guard lock(mu);
      bridged = true;
      cv.notify_all();
    });
  auto node = rt.create_node("bench_client");
  auto client = node.create_client_raw(name);
  if (!client.wait_for_service(20s)) return say("error no server"), 1;
  if (settle_bridge) {
    std::unique_lock lock(mu);
    if (!cv.wait_for(lock, 20s, [&] { return bridged; }))
      return say("error the reply channel was not matched through the bridges within 20 s"), 1;
  }
  std::string path = lcmx::to_string(client.servers().front().path);
  say("note path " + path);
  // The zero-copy form (RawClient::call_retained): the server writes its response in place
  // and the client reads it where it arrived, as ZeroMQ's REQ socket hands over the message it
  // received. call() would add a copy of the response into a byte vector (~15-20 µs per MB).
  const CallFn call = [&](const Bytes& req) {
    auto r = client.call_retained(req, 10s);
    if (!r.ok()) say("error " + r.message());
    return r.ok();
  };
  if (!echo_name.empty()) {
    EchoClient echo(rt, echo_name);
    if (!echo.wait_ready()) return say("error no echo"), 1;
    measure_pair(cases, call, [&](const Bytes& req) { return echo.call(req); });
  } else if (endpoint.empty()) {
    measure(cases, call);
  } else {
    zmq::context_t ctx(1);
    auto sock = req_socket(ctx, endpoint);
    measure_pair(cases, call, [&](const Bytes& req) { return zmq_call(sock, req); });
  }
  if (clients > 0) {
    std::vector<lcmx::RawClient> cs;
    for (int i = 0; i < clients; ++i) {
      cs.push_back(node.create_client_raw(name));
      if (!cs.back().wait_for_service(20s)) return say("error no server"), 1;
    }
    throughput(clients, seconds, [&](int i) -> CallFn {
      return [&, i](const Bytes& req) {
        auto r = cs[static_cast<std::size_t>(i)].call_retained(req, 10s);
        if (!r.ok()) say(std::string("error ") + lcmx::to_string(r.error()) + ": " + r.message());
        return r.ok();
      };
    });
  }
  return 0;
}

int client_echo(const std::string& url, const std::string& name, const std::vector<Case>& cases) {
  auto rt = lcmx::Runtime::create(runtime_options(url, ""));
  EchoClient echo(rt, name);
  if (!echo.wait_ready()) return say("error no echo"), 1;
  say("note path shm");
  measure(cases, [&](const Bytes& req) { return echo.call(req); });
  return 0;
}

int client_zmq(const std::string& endpoint, const std::vector<Case>& cases, int clients, double seconds) {
  zmq::context_t ctx(1);
  auto sock = req_socket(ctx, endpoint);
  say("note path " + endpoint.substr(0, endpoint.find(':')));
  measure(cases, [&](const Bytes& req) { return zmq_call(sock, req); });
  if (clients > 0) {
    std::vector<zmq::socket_t> socks;
    for (int i = 0; i < clients; ++i) socks.push_back(req_socket(ctx, endpoint));
    throughput(clients, seconds, [&](int i) -> CallFn {
      return [&, i](const Bytes& req) { return zmq_call(socks[static_cast<std::size_t>(i)], req); };
    });
  }
  return 0;
}

// ---- orchestrator ----

#ifdef LCMX_BENCH_WITH_NETNS
// Reads `c`'s lines until one contains `needle` (returned); nullopt at the deadline or EOF.
std::optional<std::string> line_with(lcmx::test::Child& c, const std::string& needle, std::chrono::milliseconds timeout) {
  const auto deadline = Clock::now() + timeout;
  while (auto line = c.read_line(deadline))
    if (line->find(needle) != std::string::npos) return line;
  return std::nullopt;
}
#endif

struct Result {
  std::string method, path;
  std::map<std::string, std::pair<double, double>> rtt;  // "req:resp" -> p50, p99
  std::map<std::string, std::pair<double, double>> peer_rtt;  // --interleave: ZeroMQ's, same calls
  double tput = 0;
  std::string error;
};

// Runs the server role, then the client role; collects the client's lines. A role runs in
// network namespace `*_ns` (-1: ours) and, with `*_cpu` >= 0, on that CPU only (--pin split).
Result run_method(const std::string& method, const std::vector<std::string>& server_args,
                  const std::vector<std::string>& client_args, int server_ns = -1, int client_ns = -1,
                  int server_cpu = -1, int client_cpu = -1) {
  Result res;
  res.method = method;
  const auto exe = lcmxbench::self_exe();
  auto argv = [&](const std::vector<std::string>& args) {
    std::vector<std::string> a{exe};
    a.insert(a.end(), args.begin(), args.end());
    return a;
  };
  lcmxbench::RoleProcess server("server", argv(server_args), server_cpu, server_ns);
  if (!lcmxbench::pump_until({&server.out()}, lcmxbench::now_ns() + 20'000'000'000LL,
                             [&] { return server.out().has("ready"); }) ||
      !server.out().has("ready")) {
    res.error = "the server did not start";
  } else {
    lcmxbench::RoleProcess client("client", argv(client_args), client_cpu, client_ns);
    client.close_commands();
    lcmxbench::pump_until({&client.out()}, lcmxbench::now_ns() + 180'000'000'000LL, [] { return false; });
    client.reap(5000);
    for (const auto& l : client.lines()) {
      std::istringstream in(l);
      std::string kind;
      in >> kind;
      if (kind == "rtt" || kind == "rtt-peer") {
        std::string c;
        double p50 = 0, p99 = 0;
        in >> c >> p50 >> p99;
        (kind == "rtt" ? res.rtt : res.peer_rtt)[c] = {p50, p99};
      } else if (kind == "tput") {
        int n = 0;
        in >> n >> res.tput;
      } else if (kind == "note") {
        std::string what;
        in >> what >> res.path;
      } else if (kind == "error" && res.error.empty()) {
        res.error = l.substr(6);
      }
    }
    if (client.lines().empty() && res.error.empty()) res.error = "the client printed nothing";
  }
  server.close_commands();  // the server's command fd closes: it exits
  server.reap(5000);
  return res;
}

// --interleave: the peer's row of an interleaved run (its "rtt-peer" lines).
Result peer_of(const Result& r, const std::string& method, const std::string& path) {
  Result p;
  p.method = method;
  p.path = path;
  p.rtt = r.peer_rtt;
  p.error = r.error;
  return p;
}

std::string fmt(double v) {
  char b[32];
  std::snprintf(b, sizeof b, v < 10 ? "%.1f" : "%.0f", v);
  return b;
}

std::string ratio(double a, double b) { return a <= 0 || b <= 0 ? "-" : lcmxbench::fmt_ratio(a / b); }

std::string table(const std::string& title, const std::vector<Result>& rs, const std::vector<Case>& cases,
                  const Result& reference, const std::string& ref_name) {
  std::ostringstream o;
  o << "### " << title << "\n\n| method | path |";
  for (const auto& c : cases) o << " " << case_label(c) << " p50 µs | p99 µs | p50 vs " << ref_name << " |";
  o << " calls/s (8 clients, 1 KB) |\n|---|---|";
  for (std::size_t i = 0; i < cases.size(); ++i) o << "---:|---:|---:|";
  o << "---:|\n";
  for (const auto& r : rs) {
    o << "| " << r.method << " | " << (r.path.empty() ? "-" : r.path) << " |";
    for (const auto& c : cases) {
      const auto key = case_key(c);
      auto it = r.rtt.find(key);
      auto ref = reference.rtt.find(key);
      if (it == r.rtt.end()) {
        o << " - | - | - |";
        continue;
      }
      o << " " << fmt(it->second.first) << " | " << fmt(it->second.second) << " | "
        << (ref == reference.rtt.end() ? "-" : ratio(it->second.first, ref->second.first)) << " |";
    }
    o << " " << (r.tput > 0 ? fmt(r.tput) : "-") << " |";
    if (!r.error.empty()) o << " FAILED: " << r.error;
    o << "\n";
  }
  return o.str();
}

using lcmxbench::median;

// One row from several rounds of a method: the median of the rounds' p50s and of their p99s
// per case (rounds that failed are left out; the first error is kept).
Result median_of(const std::vector<Result>& rounds) {
  Result out = rounds.front();
  out.rtt.clear();
  std::map<std::string, std::pair<std::vector<double>, std::vector<double>>> all;
  std::vector<double> tputs;
  for (const auto& r : rounds) {
    if (out.error.empty() && !r.error.empty()) out.error = r.error;
    if (out.path.empty()) out.path = r.path;
    for (const auto& [k, v] : r.rtt) {
      all[k].first.push_back(v.first);
      all[k].second.push_back(v.second);
    }
    if (r.tput > 0) tputs.push_back(r.tput);
  }
  for (auto& [k, v] : all) out.rtt[k] = {median(v.first), median(v.second)};
  out.tput = median(tputs);
  return out;
}

// The p50 of `r` over that of `ref` for case `key`; 0 when either is missing.
double p50_ratio(const Result& r, const Result& ref, const std::string& key) {
  auto a = r.rtt.find(key), b = ref.rtt.find(key);
  if (a == r.rtt.end() || b == ref.rtt.end() || a->second.first <= 0 || b->second.first <= 0) return 0;
  return a->second.first / b->second.first;
}

// The median over rounds of each round's p50 ratio (runs[i] against ref[i]); 0 if none.
double median_round_ratio(const std::vector<Result>& runs, const std::vector<Result>& ref, const std::string& key) {
  std::vector<double> rs;
  for (std::size_t i = 0; i < runs.size() && i < ref.size(); ++i)
    if (const double x = p50_ratio(runs[i], ref[i], key); x > 0) rs.push_back(x);
  return median(rs);
}

// "method, case: per-round p50 ratios against the reference of the same round ...; median".
std::string per_round_ratios(const std::vector<Result>& runs, const std::vector<Result>& ref,
                             const std::vector<Case>& cases) {
  std::ostringstream o;
  for (const auto& c : cases) {
    const auto key = case_key(c);
    std::string list;
    for (std::size_t i = 0; i < runs.size() && i < ref.size(); ++i) {
      const double x = p50_ratio(runs[i], ref[i], key);
      list += (list.empty() ? "" : ", ") + (x > 0 ? ratio(x, 1.0) : std::string("-"));
    }
    const double m = median_round_ratio(runs, ref, key);
    o << "- " << runs.front().method << ", " << case_label(c) << ": per-round p50 vs ZeroMQ tcp " << list
      << "; median " << (m > 0 ? ratio(m, 1.0) : std::string("-")) << "\n";
  }
  return o.str();
}

using lcmxbench::ratio_target;

std::string cases_arg(const std::vector<Case>& cases) {
  std::string s;
  for (const auto& c : cases)
    s += (s.empty() ? "" : ",") + case_key(c) + ":" + std::to_string(c.calls);
  return s;
}

std::vector<Case> parse_cases(const std::string& text) {
  std::vector<Case> out;
  std::istringstream in(text);
  std::string item;
  while (std::getline(in, item, ',')) {
    Case c;
    if (std::sscanf(item.c_str(), "%zu:%zu:%d", &c.request, &c.response, &c.calls) != 3)
      throw std::invalid_argument("bad case '" + item + "'");
    out.push_back(c);
  }
  return out;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "lcmx_bench_service: service round trip (p50/p99) and calls/s, lcmx vs ZeroMQ REQ/REP and two lcmx\n"
      "one-way shm messages, on one host and (root) between two emulated hosts. Markdown on stdout."};
  std::string role, url, vehicle, name, endpoint, cases_text, markdown, pin = "none";
  lcmxbench::LinkOptions link;  // two hosts: not shaped, cubic
  int calls = 2000, big_calls = 200, clients = 8, rounds = 1;
  double seconds = 3;
  bool no_hosts = false, settle_bridge = false, interleave = false;
  app.add_option("--calls", calls, "measured calls of 1 KB / 1 KB")->check(CLI::PositiveNumber)->capture_default_str();
  app.add_option("--big-calls", big_calls, "measured calls of 1 KB / 1 MB")->check(CLI::PositiveNumber)->capture_default_str();
  app.add_option("--clients", clients, "concurrent clients for calls/s (0: skip)")->check(CLI::Range(0, 64))->capture_default_str();
  app.add_option("--seconds", seconds, "duration of the calls/s run")->check(CLI::Range(0.5, 60.0))->capture_default_str();
  app.add_flag("--no-hosts", no_hosts, "skip the two-host part (it needs root for network namespaces)");
  app.add_option("--rounds", rounds, "two hosts: run every method this many times, in turn; tables show medians")
      ->check(CLI::Range(1, 20))
      ->capture_default_str();
  app.add_flag("--interleave", interleave,
               "one client process (and one server process) alternating the lcmx service and its peer call by "
               "call, so both see the same moments of the machine: on one host against two one-way shm messages "
               "and against ZeroMQ REQ/REP ipc (no calls/s), between hosts only \"UDP + bridges\" against ZeroMQ "
               "REQ/REP tcp");
  app.add_option("--markdown", markdown, "also write the tables to this file");
  app.add_option("--link-rate", link.rate,
                 "two hosts: shape the link to this tc rate (e.g. 10gbit, the vehicle's 10 GbE; a tbf qdisc at "
                 "each sender, as lcmx_bench_bridge --link-rate); \"\" = not rate-limited (a veth: memory speed)")
      ->capture_default_str();
  app.add_option("--tcp-congestion", link.tcp_congestion,
                 "two hosts: their TCP congestion control (Linux's default cubic; \"\" = this machine's, e.g. "
                 "bbr, whose pacing slows 1 MB bursts; bench/README.md)")
      ->capture_default_str();
  lcmxbench::add_pin_option(app, pin, {"none", "split"},
                            "two hosts: none, or split: host A's processes (client, its bridge) on CPU 0, host B's "
                            "(server, its bridge) on CPU 1, as if each host had its own CPU (bench/README.md)");
  // The children.
  lcmxbench::add_hidden(app, "--role", role);
  lcmxbench::add_hidden(app, "--url", url);
  lcmxbench::add_hidden(app, "--vehicle", vehicle);
  lcmxbench::add_hidden(app, "--name", name);
  lcmxbench::add_hidden(app, "--endpoint", endpoint);
  std::string echo_name;
  lcmxbench::add_hidden(app, "--echo", echo_name);
  lcmxbench::add_hidden(app, "--cases", cases_text);
  app.add_flag("--settle-bridge", settle_bridge)->group("");
  CLI11_PARSE(app, argc, argv);
  spdlog::set_level(spdlog::level::warn);
  lcmxbench::on_stop_signals(lcmxbench::OnStop::flag);  // the roles too: a server ends on SIGINT/SIGTERM

  try {
    if (!role.empty()) {
      lcmxbench::log_to_stderr(role);  // fd 3 is the report; stdout is the orchestrator's
      const auto cs = cases_text.empty() ? std::vector<Case>{} : parse_cases(cases_text);
      if (role == "server-lcmx") return server_lcmx(url, vehicle, name, endpoint, echo_name);
      if (role == "server-echo") return server_echo(url, name);
      if (role == "server-zmq") return server_zmq(endpoint);
      if (role == "client-lcmx")
        return client_lcmx(url, vehicle, name, cs, clients, seconds, settle_bridge, endpoint, echo_name);
      if (role == "client-echo") return client_echo(url, name, cs);
      if (role == "client-zmq") return client_zmq(endpoint, cs, clients, seconds);
      std::cerr << "unknown role " << role << "\n";
      return 2;
    }
  } catch (const std::exception& e) {
    say(std::string("error ") + e.what());
    return 1;
  }

  const char* const program = "lcmx_bench_service";
  if (pin == "split")
    if (const auto why = lcmxbench::split_unavailable()) return lcmxbench::bad_options(program, *why);
#ifdef LCMX_BENCH_WITH_NETNS
  if (const auto why = lcmxbench::bad_link_options(link)) return lcmxbench::bad_options(program, *why);
#endif
  const std::vector<Case> cases{{1024, 1024, calls}, {1024, 1u << 20, big_calls}};
  const std::string tag = std::to_string(::getpid());
  const std::string url1 = "udpm://239.255.79." + std::to_string(1 + ::getpid() % 250) + ":" +
                           std::to_string(21000 + ::getpid() % 20000) + "?ttl=0&iface=lo";
  const std::string cs = cases_arg(cases);
  const std::string n_clients = std::to_string(clients), secs = std::to_string(seconds);
  std::ostringstream md;
  md << "## lcmx_bench_service\n\n";

  // The service's rows the one-host targets compare (the same row unless --interleave, where
  // each comparison is its own run).
  Result svc_vs_echo, echo, svc_vs_zi, zi;
  const std::string ipc = "ipc:///tmp/lcmx_bench_service_" + tag;
  if (interleave) {
    std::cerr << "one host: lcmx service and two one-way lcmx shm messages, interleaved\n";
    svc_vs_echo = run_method("lcmx service, interleaved",
                             {"--role", "server-lcmx", "--url", url1, "--name", "svcb_" + tag, "--echo", "SVCB_" + tag},
                             {"--role", "client-lcmx", "--url", url1, "--name", "svcb_" + tag, "--echo", "SVCB_" + tag,
                              "--cases", cs, "--clients", "0"});
    echo = peer_of(svc_vs_echo, "2 x lcmx one-way, interleaved", "shm");
    std::cerr << "one host: lcmx service and ZeroMQ REQ/REP ipc, interleaved\n";
    svc_vs_zi = run_method("lcmx service, interleaved",
                           {"--role", "server-lcmx", "--url", url1, "--name", "svcb_" + tag, "--endpoint", ipc},
                           {"--role", "client-lcmx", "--url", url1, "--name", "svcb_" + tag, "--endpoint", ipc,
                            "--cases", cs, "--clients", "0"});
    zi = peer_of(svc_vs_zi, "ZeroMQ REQ/REP, interleaved", "ipc");
    ::unlink(("/tmp/lcmx_bench_service_" + tag).c_str());
    md << table("One host, interleaved with two one-way shm messages", {svc_vs_echo, echo}, cases, echo, "2 x one-way")
       << "\n";
    md << table("One host, interleaved with ZeroMQ REQ/REP ipc", {svc_vs_zi, zi}, cases, zi, "ZeroMQ ipc") << "\n";
  } else {
    std::cerr << "one host: lcmx service\n";
    auto lx = run_method("lcmx service", {"--role", "server-lcmx", "--url", url1, "--name", "svcb_" + tag},
                         {"--role", "client-lcmx", "--url", url1, "--name", "svcb_" + tag, "--cases", cs,
                          "--clients", n_clients, "--seconds", secs});
    std::cerr << "one host: two one-way lcmx shm messages\n";
    echo = run_method("2 x lcmx one-way", {"--role", "server-echo", "--url", url1, "--name", "SVCB_" + tag},
                      {"--role", "client-echo", "--url", url1, "--name", "SVCB_" + tag, "--cases", cs});
    std::cerr << "one host: ZeroMQ REQ/REP ipc\n";
    zi = run_method("ZeroMQ REQ/REP", {"--role", "server-zmq", "--endpoint", ipc},
                    {"--role", "client-zmq", "--endpoint", ipc, "--cases", cs, "--clients", n_clients, "--seconds", secs});
    ::unlink(("/tmp/lcmx_bench_service_" + tag).c_str());
    const std::string tcp = "tcp://127.0.0.1:" + std::to_string(41000 + ::getpid() % 20000);
    std::cerr << "one host: ZeroMQ REQ/REP tcp\n";
    auto zt = run_method("ZeroMQ REQ/REP", {"--role", "server-zmq", "--endpoint", tcp},
                         {"--role", "client-zmq", "--endpoint", tcp, "--cases", cs, "--clients", n_clients, "--seconds", secs});
    md << table("One host (ratios against ZeroMQ ipc)", {lx, echo, zi, zt}, cases, zi, "ZeroMQ ipc") << "\n";
    md << table("One host (ratios against two one-way shm messages)", {lx, echo}, cases, echo, "2 x one-way") << "\n";
    svc_vs_echo = svc_vs_zi = lx;
  }
  // Issue 12's targets, checked after the tables (the ratios are p50 against p50; two hosts:
  // the median of the rounds' ratios).
  std::string targets;
  for (const auto& c : cases) {
    const auto key = case_key(c);
    targets += ratio_target("one host, " + case_label(c) + ": service ≤ 1.5x two one-way shm messages",
                           p50_ratio(svc_vs_echo, echo, key), 1.5, false);
    targets += ratio_target("one host, " + case_label(c) + ": service faster than ZeroMQ REQ/REP ipc",
                           p50_ratio(svc_vs_zi, zi, key), 1.0, true);
  }

#ifdef LCMX_BENCH_WITH_NETNS
  if (!no_hosts && !stopped()) {
    if (const auto why = lcmxbench::hosts_unavailable()) {
      md << "Two hosts: skipped (" << why->substr(why->find(": ") + 2) << ")\n";
    } else {
      auto emu = lcmxbench::emulate_hosts(link);
      // --pin split: host A (index 0: the clients, bridge svcA) on CPU 0, host B (index 1: the
      // servers, bridge svcB) on CPU 1. The orchestrator (this process) stays unpinned.
      const int cpu_a = pin == "split" ? 0 : -1, cpu_b = pin == "split" ? 1 : -1;
      const std::string local = "udpm://239.255.78.1:7667?ttl=0";
      const std::string veh = "udpm://239.255.78.2:7668?ttl=1&iface=eth";
      auto udp_row = [&] {
        std::cerr << "two hosts: lcmx service\n";
        return run_method("lcmx service", {"--role", "server-lcmx", "--url", local, "--vehicle", veh, "--name", "svcb"},
                          {"--role", "client-lcmx", "--url", local, "--vehicle", veh, "--name", "svcb", "--cases", cs,
                           "--clients", n_clients, "--seconds", secs},
                          emu.ns_fd(1), emu.ns_fd(0), cpu_b, cpu_a);
      };
#ifdef LCMX_BENCH_LCMX_TOOL
      // Through the Message Bridges, a bridge on each host. Two set-ups:
      //  - "UDP + bridges" (the designed one, DESIGN.md "Delivery"): a vehicle group too, so
      //    requests and 1 KB responses cross over UDP and the reply channel turns large at the
      //    first 1 MB response, which the bridges then carry. Checked: bridge B (the server's
      //    host) must report at least the measured 1 MB responses as sent, else the row fails.
      //  - "bridges only": no vehicle group; the bridges carry the service's channels from the
      //    start (`carry`, docs/services.md "Known limits"), so every call takes four
      //    shared-memory/bridge hops.
      //  - with `zmq_endpoint` (--interleave): the server process also answers ZeroMQ REQ/REP there
      //    and the client alternates lcmx and ZeroMQ calls (Result::peer_rtt: ZeroMQ's).
      auto bridged = [&](const std::string& method, const std::string& local_b, const std::string& veh_b,
                         const std::string& svc, int hosts_id, const std::string& zmq_endpoint) {
        Result r;
        r.method = method;
        try {
          const std::string dir = "/tmp/lcmx_bench_service_" + tag + "_" + std::to_string(hosts_id);
          std::filesystem::create_directories(dir);
          struct RemoveDir {  // the configs go on every path out, a failed set-up too
            std::string path;
            ~RemoveDir() {
              std::error_code ec;
              std::filesystem::remove_all(path, ec);
            }
          } remove_dir{dir};
          const std::string body = (veh_b.empty() ? "carry = [\"" + svc + "/*\"]\n" : std::string()) +
                                   "\n[[channel]]\nname = \"all\"\nport = 7702\ntopics = [\"*\"]\n";
          const std::string config_a = lcmxbench::write_bridge_config(emu, 0, dir, "svc", body);
          const std::string config_b = lcmxbench::write_bridge_config(emu, 1, dir, "svc", body);
          lcmx::test::Env env{{"LCMX_DISCOVERY_URL", local_b}, {"SPDLOG_LEVEL", "info"}};
          if (!veh_b.empty()) env.push_back({"LCMX_VEHICLE_URL", veh_b});
          // The bridge logs on stderr and prints only its ready line on stdout; its log lines
          // ("link eth ... is up", the counters at "stopping") are read here: stderr goes to the
          // same pipe.
          auto merged = [](std::vector<std::string> argv) {
            argv.insert(argv.begin(), {"/bin/sh", "-c", "exec \"$@\" 2>&1", "sh"});
            return argv;
          };
          std::vector<lcmx::test::Child> bridges;
          bridges.push_back(emu.spawn(0, merged(lcmxbench::taskset(cpu_a, {LCMX_BENCH_LCMX_TOOL, "bridge", "--config", config_a})), env));
          bridges.push_back(emu.spawn(1, merged(lcmxbench::taskset(cpu_b, {LCMX_BENCH_LCMX_TOOL, "bridge", "--config", config_b})), env));
          // Ready, then linked to the other (its log line "bridge svcA: link eth to svcB ... is up").
          for (const char* n : {"A", "B"}) {
            auto& br = bridges[n[0] == 'A' ? 0 : 1];
            if (!br.expect(std::string("bridge svc") + n + ": ready", std::chrono::milliseconds(10000)))
              throw std::runtime_error(std::string("bridge svc") + n + " did not start");
            if (!line_with(br, std::string("bridge svc") + n + ": link eth", std::chrono::milliseconds(10000)))
              throw std::runtime_error(std::string("bridge svc") + n + " did not link to the other host");
          }
          std::cerr << "two hosts: " << method << "\n";
          std::vector<std::string> server{"--role", "server-lcmx", "--url", local_b, "--name", svc};
          std::vector<std::string> client{"--role", "client-lcmx", "--url", local_b, "--name", svc, "--cases", cs,
                                          "--clients", zmq_endpoint.empty() ? n_clients : "0", "--seconds", secs};
          if (!zmq_endpoint.empty()) {
            server.insert(server.end(), {"--endpoint", zmq_endpoint});
            client.insert(client.end(), {"--endpoint", zmq_endpoint});
          }
          if (!veh_b.empty()) {
            server.insert(server.end(), {"--vehicle", veh_b});
            client.insert(client.end(), {"--vehicle", veh_b, "--settle-bridge"});
          }
          r = run_method(method, server, client, emu.ns_fd(1), emu.ns_fd(0), cpu_b, cpu_a);
          for (auto& br : bridges) br.kill(SIGTERM);
          // "[time] [info] bridge svcB: stopping; local messages sent zero-copy Z, copied C; ..."
          const auto line = line_with(bridges[1], "bridge svcB: stopping", std::chrono::milliseconds(5000));
          long long zc = -1, copied = -1;
          if (line)
            std::sscanf(line->c_str() + line->find("bridge svcB"),
                        "bridge svcB: stopping; local messages sent zero-copy %lld, copied %lld", &zc, &copied);
          for (auto& br : bridges) br.wait(std::chrono::milliseconds(5000));
          if (!veh_b.empty() && r.error.empty() && (zc < 0 || zc + copied < big_calls))
            r.error = zc < 0 ? std::string("bridge B did not report what it sent")
                             : "bridge B sent " + std::to_string(zc + copied) + " messages, fewer than the " +
                                   std::to_string(big_calls) + " measured 1 MB responses";
          if (!veh_b.empty() && r.path == "udp") r.path = "udp, 1 MB replies: bridge";
        } catch (const std::exception& e) {
          r.error = e.what();
        }
        return r;
      };
#endif
      const std::string tcp2 = "tcp://" + emu.address(1, "eth") + ":5599";
      auto zmq_row = [&] {
        std::cerr << "two hosts: ZeroMQ REQ/REP tcp\n";
        return run_method("ZeroMQ REQ/REP", {"--role", "server-zmq", "--endpoint", tcp2},
                          {"--role", "client-zmq", "--endpoint", tcp2, "--cases", cs, "--clients", n_clients,
                           "--seconds", secs},
                          emu.ns_fd(1), emu.ns_fd(0), cpu_b, cpu_a);
      };
      // --rounds: every method once per round, in turn, so that the machine's drift between
      // runs (ZeroMQ's own 1 MB time varies 3x from run to run here) falls on all alike.
      std::vector<std::vector<Result>> runs(4);  // udp, UDP + bridges, bridges only, ZeroMQ
      for (int round = 0; round < rounds && !stopped(); ++round) {
        if (rounds > 1) std::cerr << "two hosts: round " << round + 1 << " of " << rounds << "\n";
#ifdef LCMX_BENCH_LCMX_TOOL
        if (interleave) {
          // One client process alternating lcmx and ZeroMQ calls: the ZeroMQ row is its peer_rtt.
          auto r = bridged("lcmx service (UDP + bridges), interleaved", "udpm://239.255.78.5:7671?ttl=0",
                           "udpm://239.255.78.6:7672?ttl=1&iface=eth", "svcbv", 1, tcp2);
          auto z = peer_of(r, "ZeroMQ REQ/REP, interleaved", "tcp");
          runs[1].push_back(std::move(r));
          runs[3].push_back(std::move(z));
          continue;
        }
#endif
        runs[0].push_back(udp_row());
#ifdef LCMX_BENCH_LCMX_TOOL
        runs[1].push_back(bridged("lcmx service (UDP + bridges)", "udpm://239.255.78.5:7671?ttl=0",
                                  "udpm://239.255.78.6:7672?ttl=1&iface=eth", "svcbv", 1, ""));
        runs[2].push_back(bridged("lcmx service (bridges only)", "udpm://239.255.78.3:7669?ttl=0", "", "svcbb", 2, ""));
#endif
        runs[3].push_back(zmq_row());
      }
      std::vector<Result> rows;
      for (const auto& r : runs)
        if (!r.empty()) rows.push_back(median_of(r));
      const std::string cc = lcmxbench::tcp_congestion_of(emu, 0);
      md << table("Two emulated hosts, one veth link " +
                      (link.rate.empty() ? std::string("(not rate-limited)") : "shaped to " + link.rate + " (tc tbf)") +
                      ", TCP congestion control " + cc +
                      (pin == "split" ? ", host A on CPU 0 and host B on CPU 1 (--pin split)" : "") +
                      " (ratios against ZeroMQ tcp)" +
                      (rounds > 1 ? " — medians of " + std::to_string(rounds) + " rounds" : std::string()),
                  rows, cases, rows.back(), "ZeroMQ tcp")
         << "\n";
      if (rounds > 1)
        for (std::size_t m = 0; m + 1 < runs.size(); ++m)
          if (!runs[m].empty()) md << per_round_ratios(runs[m], runs[3], cases) << "\n";
      for (std::size_t m = 0; m + 1 < runs.size(); ++m) {
        if (runs[m].empty()) continue;
        for (const auto& c : cases) {
          const auto key = case_key(c);
          targets += ratio_target("two hosts" + std::string(pin == "split" ? " (split)" : "") +
                                   (link.rate.empty() ? std::string() : ", link " + link.rate) + ", " + case_label(c) +
                                     ": " + runs[m].front().method + " ≤ 1.2x ZeroMQ REQ/REP tcp",
                                 median_round_ratio(runs[m], runs[3], key), 1.2, false);
        }
      }
    }
  }
#else
  (void)no_hosts;
  (void)rounds;
  (void)interleave;
  (void)link;
  md << "Two hosts: not built (needs lcmx::test_netns, LCMX_BUILD_TESTS=ON)\n";
#endif
  md << "### Targets (issue 12)\n\n" << targets
     << "- (between hosts the designed set-up is \"UDP + bridges\": small messages over UDP, 1 MB through the "
        "bridges; the other rows are for comparison. One host without --interleave: single runs, whose wake-up "
        "placement on a 2-vCPU machine moves a 1 KB call by 2-3x (bench/README.md \"The cross-vCPU wake-up\"); "
        "--interleave compares call by call. The 1 KB / 1 MB "
        "call between hosts and why: docs/services.md \"A CPU per host\")\n";
  return lcmxbench::print_report(program, md.str(), markdown) ? 0 : 1;
}
