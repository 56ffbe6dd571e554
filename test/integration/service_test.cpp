// Services across processes on one host (shared memory): calls both ways, a 1 MB response,
// a server SIGKILLed mid-call (fail-over to the other server, or server_gone), many client
// processes and two servers. The peers are lcmx_service_peer (service_peer.cpp).
#include <fstream>
#include <future>
#include <iterator>
#include <thread>

#include "lcmx/core.hpp"
#include "lcmx_examples/bench_t.hpp"
#include "lcmx_examples/pose_t.hpp"
#include "containers.hpp"
#include "support.hpp"

using namespace lcmx::it;
using Pose = lcmx_examples::pose_t;
using Bench = lcmx_examples::bench_t;

namespace {

Child& server_peer(Session& s, const std::string& name) {
  return s.spawn({LCMX_SERVICE_PEER, "server", "--name", name, "--timeout-ms", "60000"});
}

std::uint64_t participant_of(const std::string& ready_line) {
  return std::stoull(parse_kv(ready_line).at("participant"));
}

Pose request(double x, double size) {
  Pose p;
  p.position[0] = x;
  p.position[1] = size;
  return p;
}

// The state letter of /proc/<pid>/stat ('R', 'S', 'T' for stopped, ...), '?' if unreadable.
char process_state(pid_t pid) {
  std::ifstream f("/proc/" + std::to_string(pid) + "/stat");
  std::string stat((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
  const auto close = stat.rfind(')');
  return close == std::string::npos || close + 2 >= stat.size() ? '?' : stat[close + 2];
}

bool content_ok(const Bench& b) {
  for (std::size_t i = 0; i < b.data.size(); ++i)
    if (b.data[i] != static_cast<std::uint8_t>((i * 131u + static_cast<std::uint64_t>(b.seq) * 7u) & 0xffu))
      return false;
  return true;
}

// What lcmx_service_peer's server answers (content_ok checks it): seq = x, position[1] bytes.
Bench answer(const Pose& p) {
  Bench b;
  b.seq = static_cast<std::int64_t>(p.position[0]);
  b.size = static_cast<std::int32_t>(p.position[1]);
  b.data.resize(static_cast<std::size_t>(b.size));
  for (std::size_t i = 0; i < b.data.size(); ++i)
    b.data[i] = static_cast<std::uint8_t>((i * 131u + static_cast<std::uint64_t>(b.seq) * 7u) & 0xffu);
  return b;
}

}  // namespace

TEST_CASE("service across processes: a client here, a server there, over shared memory",
          "[integration][service]") {
  Session s(130);
  const auto name = unique_channel("SVC", 130);
  auto& server = server_peer(s, name);
  auto ready = server.expect("READY");
  REQUIRE(ready);
  auto rt = lcmx::Runtime::create();
  auto node = rt.create_node("client");
  auto client = node.create_client<Pose, Bench>(name);
  REQUIRE(client.wait_for_service(10000ms));
  REQUIRE(client.servers().size() == 1);
  CHECK(client.servers()[0].participant == participant_of(*ready));
  CHECK(client.servers()[0].path == lcmx::Path::shm);
  for (int i = 0; i < 100; ++i) {
    auto r = client.call(request(i, 32), 5000ms);
    REQUIRE(r.ok());
    CHECK(r.value().seq == i);
    CHECK(content_ok(r.value()));
  }
  auto big = client.call(request(7, 1 << 20), 10000ms);  // a 1 MB response
  REQUIRE(big.ok());
  CHECK(big.value().data.size() == (1u << 20));
  CHECK(content_ok(big.value()));
  server.send("quit");
  REQUIRE(server.expect("SERVED"));
  CHECK(server.wait() == 0);
}

// A server that is a neighbour (a container with its own /dev/shm, sharing the network): the
// calls go over UDP on the host-local group. A blocking call (call(), the future call_async)
// completes on the thread that receives its reply (ClientStats::direct_replies), sparing the
// hand-over through the client's thread; a call_async with a callback of its own never does:
// the callback runs on the client's thread.
TEST_CASE("service to a neighbour over UDP: blocking calls complete where the reply is received, a callback on the client's thread",
          "[integration][service][containers]") {
  if (!can_unshare()) {
    LCMX_SKIP("cannot create mount namespaces here");
  }
  Session s(147);
  const auto name = unique_channel("SVC_NEIGHBOUR", 147);
  auto& server = s.spawn(in_container({"--mount", "--propagation", "private"}, true, LCMX_SERVICE_PEER,
                                      {"server", "--name", name}));
  REQUIRE(server.expect("READY"));
  auto rt = lcmx::Runtime::create();
  auto node = rt.create_node("client");
  auto client = node.create_client<Pose, Bench>(name);
  REQUIRE(client.wait_for_service(10000ms));
  REQUIRE(client.servers().size() == 1);
  REQUIRE(client.servers()[0].path == lcmx::Path::udp);
  const auto before = client.stats().direct_replies;  // none yet: probes' answers never count
  CHECK(before == 0);
  for (int i = 0; i < 50; ++i) {
    auto r = client.call(request(i, 64), 5000ms);
    REQUIRE(r.ok());
    CHECK(r.value().seq == i);
    CHECK(content_ok(r.value()));
    CHECK(r.server().path == lcmx::Path::udp);
  }
  CHECK(client.stats().direct_replies == 50);
  auto f = client.call_async(request(50, 64), 5000ms);  // the future form: a hand-over too
  auto fr = f.get();
  REQUIRE(fr.ok());
  CHECK(fr.value().seq == 50);
  CHECK(client.stats().direct_replies == 51);
  std::promise<bool> done;
  auto got = done.get_future();
  client.call_async(request(51, 64), 5000ms, [&done](lcmx::Client<Pose, Bench>::Result r) {
    done.set_value(r.ok() && r.value().seq == 51 && content_ok(r.value()));
  });
  CHECK(got.get());
  CHECK(client.stats().direct_replies == 51);  // the callback's call went through the client's thread
  CHECK(client.stats().replies == 52);
  CHECK(client.stats().late_replies == 0);
  server.send("quit");
  auto served = server.expect("SERVED");
  REQUIRE(served);
  CHECK(*served == "SERVED 52");
  CHECK(server.wait() == 0);
}

// A burst from one client: more calls at once than the request ring has slots (8). Each is
// answered once; none is lost to a ring the server had not read yet (the client keeps at
// most 6 in flight, the rest wait their turn).
TEST_CASE("service across processes: a burst of 40 calls at once from one client, each answered",
          "[integration][service]") {
  Session s(143);
  const auto name = unique_channel("SVC", 143);
  auto& server = server_peer(s, name);
  REQUIRE(server.expect("READY"));
  auto rt = lcmx::Runtime::create();
  auto node = rt.create_node("client");
  auto client = node.create_client<Pose, Bench>(name);
  REQUIRE(client.wait_for_service(10000ms));
  std::vector<std::future<lcmx::Client<Pose, Bench>::Result>> calls;
  for (int i = 0; i < 40; ++i) calls.push_back(client.call_async(request(i, 100), 10000ms));
  std::vector<std::thread> threads;  // and 16 threads calling at once
  std::atomic<int> thread_ok{0};
  for (int t = 0; t < 16; ++t)
    threads.emplace_back([&, t] {
      auto r = client.call(request(100 + t, 100), 10000ms);
      if (r.ok() && r.value().seq == 100 + t && content_ok(r.value())) ++thread_ok;
    });
  int ok = 0;
  for (int i = 0; i < 40; ++i) {
    auto r = calls[static_cast<std::size_t>(i)].get();
    INFO("call " << i << ": " << lcmx::to_string(r.error()) << ": " << r.message());
    CHECK(r.ok());
    if (r.ok() && r.value().seq == i && content_ok(r.value())) ++ok;
  }
  for (auto& t : threads) t.join();
  CHECK(ok == 40);
  CHECK(thread_ok == 16);
  CHECK(client.stats().timeouts == 0);
  CHECK(client.stats().pending == 0);
  server.send("quit");
  REQUIRE(server.expect("SERVED"));
  CHECK(server.wait() == 0);
}

// A client process that called once and exited: within kClientGone (10 s) and the next
// housekeeping pass the server forgets it and releases its reply publisher (8 slots of its
// largest response), even though no other client ever comes.
TEST_CASE("service across processes: a server forgets a client that exited, with no new client coming",
          "[integration][service]") {
  Session s(144);
  const auto name = unique_channel("SVC", 144);
  auto rt = lcmx::Runtime::create();
  auto node = rt.create_node("server");
  auto server = node.create_service<Pose, Bench>(name, [](const Pose& p) { return answer(p); });
  auto& client = s.spawn({LCMX_SERVICE_PEER, "client", "--name", name, "--calls", "1", "--size",
                          std::to_string(1 << 20), "--timeout-ms", "30000"});
  auto line = client.expect("CALLS", 30000ms);
  REQUIRE(line);
  CHECK(parse_kv(*line).at("ok") == "1");
  CHECK(client.wait() == 0);
  CHECK(server.stats().clients == 1);
  const auto segments = shm_segments_of(::getpid()).size();  // the reply publisher's among them
  CHECK(wait_until([&] { return server.stats().clients == 0; }, 20000ms));
  CHECK(wait_until([&] { return shm_segments_of(::getpid()).size() < segments; }, 5000ms));
}

TEST_CASE("service across processes: a server here, clients in other processes",
          "[integration][service]") {
  Session s(131);
  const auto name = unique_channel("SVC", 131);
  auto rt = lcmx::Runtime::create();
  auto node = rt.create_node("server");
  std::atomic<int> served{0};
  auto server = node.create_service<Pose, Bench>(name, [&](const Pose& p) {
    ++served;
    return answer(p);
  });
  std::vector<Child*> clients;
  for (int i = 0; i < 3; ++i)
    clients.push_back(&s.spawn({LCMX_SERVICE_PEER, "client", "--name", name, "--calls", "200",
                                "--size", "100", "--timeout-ms", "60000"}));
  for (auto* c : clients) {
    auto line = c->expect("CALLS", 30000ms);
    REQUIRE(line);
    const auto kv = parse_kv(*line);
    INFO(*line);
    CHECK(kv.at("ok") == "200");
    CHECK(kv.at("wrong") == "0");
    CHECK(kv.at("path") == "shm");
    CHECK(c->wait() == 0);
  }
  CHECK(served == 600);
  CHECK(server.stats().requests == 600);
}

TEST_CASE("service across processes: the server is SIGKILLed mid-call: the call fails over",
          "[integration][service]") {
  Session s(132);
  const auto name = unique_channel("SVC", 132);
  auto& a = server_peer(s, name);
  auto& b = server_peer(s, name);
  auto ra = a.expect("READY"), rb = b.expect("READY");
  REQUIRE(ra);
  REQUIRE(rb);
  auto rt = lcmx::Runtime::create();
  auto node = rt.create_node("client");
  auto client = node.create_client<Pose, Bench>(name);
  REQUIRE(wait_until([&] { return client.servers().size() == 2; }, 10000ms));
  // The server calls go to (same path: the lower participant id) is told to hang on x < 0.
  const auto chosen = client.servers()[0].participant;
  Child& victim = chosen == participant_of(*ra) ? a : b;
  Child& other = &victim == &a ? b : a;
  const auto other_participant = participant_of(&other == &a ? *ra : *rb);
  victim.send("block");
  REQUIRE(victim.expect("BLOCKING"));

  auto f = client.call_async(request(-5, 10), 10000ms);
  REQUIRE(victim.expect("CALLED -5"));
  const auto killed = Clock::now();
  victim.kill9();
  REQUIRE(f.wait_for(8000ms) == std::future_status::ready);
  const auto took = std::chrono::duration_cast<ms>(Clock::now() - killed);
  auto r = f.get();
  INFO("answered " << took.count() << " ms after the SIGKILL");
  REQUIRE(r.ok());
  CHECK(r.value().seq == -5);
  CHECK(r.server().participant == other_participant);
  CHECK(client.stats().failovers == 1);
  CHECK(took < 1000ms);  // a local death is noticed at once (pidfd), not after the lease

  SECTION("and with no server left, a call in flight ends with server_gone") {
    other.send("block");
    REQUIRE(other.expect("BLOCKING"));
    auto f2 = client.call_async(request(-6, 10), 10000ms);
    REQUIRE(other.expect("CALLED -6"));
    other.kill9();
    REQUIRE(f2.wait_for(8000ms) == std::future_status::ready);
    auto r2 = f2.get();
    REQUIRE_FALSE(r2.ok());
    CHECK(r2.error() == lcmx::CallErrc::server_gone);
  }
}

TEST_CASE("service across processes: many client processes, two servers, each call once",
          "[integration][service]") {
  Session s(133, 60000ms);
  const auto name = unique_channel("SVC", 133);
  auto& a = server_peer(s, name);
  auto& b = server_peer(s, name);
  REQUIRE(a.expect("READY"));
  REQUIRE(b.expect("READY"));
  constexpr int kClients = 4, kCalls = 150;
  std::vector<Child*> clients;
  for (int i = 0; i < kClients; ++i)
    clients.push_back(&s.spawn({LCMX_SERVICE_PEER, "client", "--name", name, "--calls",
                                std::to_string(kCalls), "--size", "64", "--servers", "2",
                                "--timeout-ms", "60000"}));
  std::set<std::string> servers_used;
  for (auto* c : clients) {
    auto line = c->expect("CALLS", 40000ms);
    REQUIRE(line);
    INFO(*line);
    const auto kv = parse_kv(*line);
    CHECK(kv.at("ok") == std::to_string(kCalls));
    CHECK(kv.at("wrong") == "0");
    servers_used.insert(kv.at("server"));
  }
  CHECK(servers_used.size() == 1);  // every client chose the same server (stable choice)
  a.send("quit");
  b.send("quit");
  auto sa = a.expect("SERVED"), sb = b.expect("SERVED");
  REQUIRE(sa);
  REQUIRE(sb);
  // Every call executed exactly once, by one server (probes are not counted as requests).
  const long long na = std::stoll(sa->substr(7)), nb = std::stoll(sb->substr(7));
  CHECK(na + nb == kClients * kCalls);
  CHECK((na == 0 || nb == 0));
}

#ifdef LCMX_TOOL
TEST_CASE("lcmx services and lcmx call against a server process", "[integration][service]") {
  Session s(134);
  const auto name = unique_channel("SVC", 134);
  auto& server = server_peer(s, name);
  REQUIRE(server.expect("READY"));
  const std::string types = LCMX_LCMTYPES_DIR;

  auto list = s.run({LCMX_TOOL, "services", "--json", "--types", types});
  REQUIRE(list.rc == 0);
  const auto j = json_line(list.out);
  INFO(list.out);
  CHECK(j.find("\"name\":\"" + name + "\"") != std::string::npos);
  CHECK(j.find("\"request_type\":\"lcmx_examples.pose_t\"") != std::string::npos);
  CHECK(j.find("\"response_type\":\"lcmx_examples.bench_t\"") != std::string::npos);
  CHECK(j.find("\"process\":\"lcmx_service_pe\"") != std::string::npos);

  auto text = s.run({LCMX_TOOL, "services", "--types", types});
  REQUIRE(text.rc == 0);
  CHECK(text.out.find(name + "  lcmx_examples.pose_t -> lcmx_examples.bench_t") != std::string::npos);

  auto call = s.run({LCMX_TOOL, "call", name, "{\"position\": [12, 4, 0]}", "--types", types, "--json"});
  INFO(call.out);
  REQUIRE(call.rc == 0);
  CHECK(call.out.find("\"seq\":12") != std::string::npos);
  CHECK(call.out.find("\"size\":4") != std::string::npos);

  auto human = s.run({LCMX_TOOL, "call", name, "{\"position\": [13, 2, 0]}", "--types", types});
  REQUIRE(human.rc == 0);
  CHECK(human.out.find("seq: 13") != std::string::npos);

  // Clear errors: a field that does not exist, no type path, no server, bad hex.
  auto bad = s.run({LCMX_TOOL, "call", name, "{\"positon\": [1]}", "--types", types});
  CHECK(bad.rc == 1);
  CHECK(bad.out.find("positon: no such field") != std::string::npos);
  auto no_types = s.run({LCMX_TOOL, "call", name, "{}"}, {"LCMX_TYPES_PATH"});
  CHECK(no_types.rc == 1);
  CHECK(no_types.out.find("not in the type path") != std::string::npos);
  auto both = s.run({LCMX_TOOL, "call", name, "{}", "--hex", "00"});  // JSON and hex: which one?
  CHECK(both.rc == 2);
  CHECK(both.out.find("excludes") != std::string::npos);
  auto none = s.run({LCMX_TOOL, "call", name + "_nobody", "{}", "--timeout", "0.3"});
  CHECK(none.rc == 1);
  CHECK(none.out.find("no server of") != std::string::npos);
  auto hex = s.run({LCMX_TOOL, "call", name, "--hex", "abc"});
  CHECK(hex.rc == 2);
  server.send("quit");
  CHECK(server.wait() == 0);
}
#endif

TEST_CASE("service across processes: a SIGSTOPped server: a call times out, past the lease the call in flight ends server_gone, after SIGCONT it answers again",
          "[integration][service]") {
  Session s(135);
  const auto name = unique_channel("SVC", 135);
  auto& server = server_peer(s, name);
  REQUIRE(server.expect("READY"));
  auto rt = lcmx::Runtime::create();
  auto node = rt.create_node("client");
  auto client = node.create_client<Pose, Bench>(name);
  REQUIRE(client.wait_for_service(10000ms));
  REQUIRE(client.call(request(1, 8), 5000ms).ok());
  server.signal(SIGSTOP);  // a debugger's breakpoint: alive, silent, beyond its lease
  // Every thread of it stopped (state T), not just signalled: a running thread finishes its
  // time slice first.
  REQUIRE(wait_until([&] { return process_state(server.pid()) == 'T'; }, 5000ms));
  auto r = client.call(request(2, 8), 300ms);
  REQUIRE_FALSE(r.ok());
  CHECK(r.error() == lcmx::CallErrc::timeout);
  CHECK(client.stats().pending == 0);  // the timed-out call is forgotten, not leaked
  // Stopped past its lease (600 ms here): the server is gone for the client, so a call in
  // flight ends with server_gone (no other server), before its own 3 s timeout.
  auto f = client.call_async(request(3, 8), 3000ms);
  REQUIRE(f.wait_for(5000ms) == std::future_status::ready);
  auto gone = f.get();
  CHECK(gone.error() == lcmx::CallErrc::server_gone);
  CHECK(client.servers().empty());
  server.signal(SIGCONT);
  // Back: it beacons again, answers a probe, and a new call (which waits for a server within
  // its timeout) is answered as before.
  auto again = client.call(request(4, 8), 5000ms);
  INFO(lcmx::to_string(again.error()) << ": " << again.message());
  REQUIRE(again.ok());
  CHECK(again.value().seq == 4);
  CHECK(client.stats().pending == 0);
}

TEST_CASE("service across processes: call_retained keeps a 1 MB response in its shared-memory slot, valid while held",
          "[integration][service]") {
  Session s(142);
  const auto name = unique_channel("SVC_RETAIN", 142);
  auto& server = server_peer(s, name);
  REQUIRE(server.expect("READY"));
  auto rt = lcmx::Runtime::create();
  auto node = rt.create_node("client");
  auto client = node.create_client_raw(name);  // raw bytes: it takes the server's types
  REQUIRE(client.wait_for_service(10000ms));
  REQUIRE(client.servers().at(0).path == lcmx::Path::shm);
  auto call = [&](double x, double size) {
    const Pose p = request(x, size);
    lcmx::Bytes req(static_cast<std::size_t>(p.getEncodedSize()));
    p.encode(req.data(), 0, static_cast<int>(req.size()));
    return client.call_retained(req, 10000ms);
  };
  auto decoded = [](const lcmx::RetainedBytes& r) {
    Bench b;
    REQUIRE(b.decode(r.data.data(), 0, static_cast<int>(r.data.size())) == static_cast<int>(r.data.size()));
    return b;
  };
  // Held responses stay intact while later calls answer through the same reply publisher:
  // their slots stay pinned. Beyond shm::Reader::kMaxDetached held at once they are copies.
  std::vector<lcmx::RetainedBytes> held;
  for (int i = 0; i < lcmx::shm::Reader::kMaxDetached + 2; ++i) {
    auto r = call(i, 1 << 20);
    REQUIRE(r.ok());
    INFO("response " << i);
    CHECK(r.value().zero_copy == (i < lcmx::shm::Reader::kMaxDetached));
    held.push_back(std::move(r).value());
  }
  for (int i = 0; i < 20; ++i) REQUIRE(call(100 + i, 1 << 20).ok());  // the ring goes round
  for (std::size_t i = 0; i < held.size(); ++i) {
    const Bench b = decoded(held[i]);
    INFO("held response " << i);
    CHECK(b.seq == static_cast<std::int64_t>(i));
    CHECK(b.data.size() == (1u << 20));
    CHECK(content_ok(b));
  }
  held.clear();  // releases the pins: zero-copy again
  auto again = call(7, 4096);
  REQUIRE(again.ok());
  CHECK(again.value().zero_copy);
  CHECK(content_ok(decoded(again.value())));
  // Errors are the same as call()'s.
  auto unknown = node.create_client_raw(name + "_none");
  auto none = unknown.call_retained({}, 300ms);
  CHECK_FALSE(none.ok());
  CHECK(none.error() == lcmx::CallErrc::no_server);
  server.send("quit");
  REQUIRE(server.expect("SERVED"));
  CHECK(server.wait() == 0);
}
