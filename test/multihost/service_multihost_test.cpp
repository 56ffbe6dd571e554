// Services between emulated hosts (the vehicle group, UDP): calls from another host and from
// the server's own host, a response too large for one datagram, and a server on another host
// SIGKILLed mid-call (noticed within the lease; the call fails over to the server that is
// left). Peers: lcmx_service_peer (test/integration/service_peer.cpp). The Message Bridge
// carrying a 6 MB response: test/bridge/bridge_test.cpp.
#include "lcmx/test/catch_netns.hpp"
#include "multihost.hpp"

using namespace lcmx::mh;
using lcmx::it::parse_kv;

namespace {

Child& service_peer(Hosts& h, int host, std::vector<std::string> args) {
  args.insert(args.begin(), LCMX_SERVICE_PEER);
  args.insert(args.end(), {"--timeout-ms", "45000"});
  return h.spawn(host, std::move(args), h.lcmx_env({"SPDLOG_LEVEL=warn"}));
}

}  // namespace

TEST_CASE("service across hosts: a client on another host calls over UDP, one on the server's host over shm",
          "[multihost][service]") {
  LCMX_REQUIRE_NETNS();
  Hosts h(2, 70);
  const auto name = h.channel("SVC");
  auto& server = service_peer(h, 1, {"server", "--name", name});
  REQUIRE(server.expect("READY"));
  auto& remote = service_peer(h, 0, {"client", "--name", name, "--calls", "100", "--size", "300"});
  auto& local = service_peer(h, 1, {"client", "--name", name, "--calls", "100", "--size", "300"});
  // A response of 200 KB: more than one datagram (fragments, as no bridge runs here).
  auto& big = service_peer(h, 0, {"client", "--name", name, "--calls", "5", "--size", "200000"});
  // call_async with a callback of its own: the callback runs on the client's thread.
  auto& async = service_peer(h, 0, {"client", "--name", name, "--calls", "20", "--size", "300", "--async"});
  for (auto* c : {&remote, &local, &big, &async}) {
    auto line = c->expect("CALLS", 30000ms);
    INFO(c->output());
    REQUIRE(line);
    const auto kv = parse_kv(*line);
    CHECK(kv.at("failed") == "0");
    CHECK(kv.at("wrong") == "0");
    CHECK(kv.at("path") == (c == &local ? "shm" : "udp"));
    // Blocking calls answered over UDP complete where the reply is received (no hand-over
    // through the client's thread); over shm, and for a user's callback, never.
    CHECK(kv.at("direct") == (c == &remote ? "100" : c == &big ? "5" : "0"));
    CHECK(c->wait() == 0);
  }
  server.send("quit");
  auto served = server.expect("SERVED");
  REQUIRE(served);
  CHECK(*served == "SERVED 225");
}

TEST_CASE("service across hosts: the server on another host is SIGKILLed mid-call, the call fails over",
          "[multihost][service]") {
  LCMX_REQUIRE_NETNS();
  Hosts h(2, 71);
  const auto name = h.channel("SVC");
  // Two servers on host 1, the client on host 0: nothing but the lease (800 ms here) tells the
  // client that the chosen one died.
  auto& a = service_peer(h, 1, {"server", "--name", name});
  auto& b = service_peer(h, 1, {"server", "--name", name});
  auto ra = a.expect("READY"), rb = b.expect("READY");
  REQUIRE(ra);
  REQUIRE(rb);
  auto& client = service_peer(h, 0, {"client", "--name", name, "--calls", "3", "--size", "10", "--servers", "2",
                                     "--first", "-1", "--call-timeout-ms", "10000", "--go"});
  auto chosen = client.expect("CHOSEN", 20000ms);
  REQUIRE(chosen);
  const auto who = parse_kv(*chosen).at("participant");
  Child& victim = parse_kv(*ra).at("participant") == who ? a : b;
  Child& other = &victim == &a ? b : a;
  victim.send("block");
  REQUIRE(victim.expect("BLOCKING"));
  client.send("go");
  REQUIRE(victim.expect("CALLED -1", 20000ms));  // the first call (x = -1) hangs there
  victim.kill9();
  auto line = client.expect("CALLS", 20000ms);
  INFO(client.output());
  REQUIRE(line);
  const auto kv = parse_kv(*line);
  CHECK(kv.at("ok") == "3");  // x = -1 answered by the other server after the fail-over
  CHECK(kv.at("wrong") == "0");
  CHECK(kv.at("path") == "udp");
  CHECK(kv.at("server") != who);
  other.send("quit");
  auto served = other.expect("SERVED");
  REQUIRE(served);
  CHECK(*served == "SERVED 3");
}

TEST_CASE("action across hosts: goal, feedback and result over UDP, a server SIGKILLed mid-goal is reported lost within the lease",
          "[multihost][action]") {
  LCMX_REQUIRE_NETNS();
  Hosts h(2, 72);
  const auto name = h.channel("ACT");
  auto& server = service_peer(h, 1, {"action-server", "--name", name});
  REQUIRE(server.expect("READY"));
  auto& done = service_peer(h, 0, {"action-client", "--name", name, "--x", "20"});
  auto outcome = done.expect("OUTCOME", 30000ms);
  INFO(done.output());
  REQUIRE(outcome);
  auto kv = parse_kv(*outcome);
  CHECK(kv.at("state") == "succeeded");
  CHECK(kv.at("seq") == "20");
  CHECK(kv.at("feedback") == "20");  // every feedback, before the end

  auto& live = service_peer(h, 0, {"action-client", "--name", name, "--x", "-1"});
  const bool accepted = static_cast<bool>(live.expect("ACCEPTED", 20000ms));
  INFO("second client:\n" << live.output() << "\nserver:\n" << server.output());
  REQUIRE(accepted);
  REQUIRE(server.expect("EXECUTING", 20000ms));
  const auto killed = Clock::now();
  server.kill9();
  outcome = live.expect("OUTCOME", 20000ms);
  const auto took = std::chrono::duration_cast<ms>(Clock::now() - killed);
  INFO(live.output() << "\nreported " << took.count() << " ms after the SIGKILL");
  REQUIRE(outcome);
  kv = parse_kv(*outcome);
  CHECK(kv.at("state") == "lost");
  CHECK(took < 5000ms);  // the lease (800 ms here), not the goal's 50 s wait
}
