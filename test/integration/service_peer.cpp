// lcmx_service_peer: the other processes of the service tests (test/integration/service_test.cpp,
// test/multihost). Request lcmx_examples.pose_t, response lcmx_examples.bench_t: the response's
// seq is the request's position[0], its data has position[1] bytes of pattern(i, seq).
//
//   server --name N
//     Serves N, prints "READY participant=<id>", then reads commands on stdin:
//       "block"  from now on a request with x < 0 prints "CALLED <x>" and never returns
//       "stats"  prints "STATS requests=<r> failed=<f> probes=<p> refused=<x> clients=<c>"
//                (lcmx::ServerStats)
//       "quit"   (or EOF) prints "SERVED <requests>" and exits 0
//   client --name N --calls K [--size BYTES] [--call-timeout-ms T] [--servers S] [--first X] [--go]
//          [--no-wait] [--async]
//     Waits for a server (for S servers with --servers), prints "CHOSEN participant=<id>" (the
//     server calls go to; --no-wait: neither waits nor prints, e.g. for a server of other
//     types), with --go waits for "go" on stdin, makes K calls (x = X..X+K-1,
//     default X = 0), checks every response's seq and bytes,
//     prints "CALLS ok=<n> failed=<f> wrong=<w> path=<path of the last answer>
//     server=<participant> error=<first error or -> direct=<ClientStats::direct_replies>" and
//     exits 0. Calls are blocking call()s; with --async, call_async() with a callback of its
//     own (which must run on the client's thread: never direct).
//   action-server --name N [--client-timeout-ms T]
//     Serves action N (goal pose_t, feedback pose_t, result bench_t), prints "READY
//     participant=<id>". A goal with x = position[0] >= 0 publishes feedback 1..x, 5 ms apart,
//     and succeeds with seq x; a goal with x < 0 prints "EXECUTING <goal id>" and runs until
//     canceled, then prints "CANCELED <goal id>" and ends canceled (seq x).
//     "quit" (or EOF) prints "ACTIONS accepted=<a> succeeded=<s> canceled=<c> client_gone=<g>".
//   action-client --name N --x X
//     Sends one goal x = X, prints "ACCEPTED <goal id>", waits for its end and prints
//     "OUTCOME state=<state> seq=<result seq or -> feedback=<feedback received>".
// Every run ends by itself after --timeout-ms (exit 3).
#include <CLI/CLI.hpp>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cstdio>
#include <future>
#include <iostream>
#include <optional>
#include <string>
#include <thread>

#include "lcmx/core.hpp"
#include "lcmx_examples/bench_t.hpp"
#include "lcmx_examples/pose_t.hpp"

namespace {

using namespace std::chrono_literals;

void say(const std::string& line) {
  std::printf("%s\n", line.c_str());
  std::fflush(stdout);
}

std::uint8_t pattern(std::size_t i, std::int64_t seq) {
  return static_cast<std::uint8_t>((i * 131u + static_cast<std::uint64_t>(seq) * 7u) & 0xffu);
}

lcmx_examples::bench_t answer(const lcmx_examples::pose_t& p) {
  lcmx_examples::bench_t b;
  b.seq = static_cast<std::int64_t>(p.position[0]);
  b.size = static_cast<std::int32_t>(p.position[1]);
  b.data.resize(static_cast<std::size_t>(b.size));
  for (std::size_t i = 0; i < b.data.size(); ++i) b.data[i] = pattern(i, b.seq);
  return b;
}

int run_server(const std::string& name) {
  auto rt = lcmx::Runtime::create();
  auto node = rt.create_node("service_peer");
  std::atomic<bool> block{false};
  std::atomic<long long> served{0};
  auto server = node.create_service<lcmx_examples::pose_t, lcmx_examples::bench_t>(
      name, [&](const lcmx_examples::pose_t& p) {
        ++served;
        if (p.position[0] < 0 && block.load()) {
          say("CALLED " + std::to_string(static_cast<long long>(p.position[0])));
          for (;;) std::this_thread::sleep_for(1h);  // until killed: "a server dies mid-call"
        }
        return answer(p);
      });
  say("READY participant=" + std::to_string(rt.participant_id()));
  std::string line;
  while (std::getline(std::cin, line)) {
    if (line == "block") {
      block = true;
      say("BLOCKING");
    } else if (line == "stats") {
      const auto st = server.stats();
      say("STATS requests=" + std::to_string(st.requests) + " failed=" + std::to_string(st.failed) +
          " probes=" + std::to_string(st.probes) + " refused=" + std::to_string(st.refused) +
          " clients=" + std::to_string(st.clients));
    } else if (line == "quit") {
      break;
    }
  }
  say("SERVED " + std::to_string(served.load()));
  return 0;
}

int run_client(const std::string& name, int calls, int size, int call_timeout_ms,
               std::size_t servers_wanted, int first, bool go, bool no_wait, bool async) {
  auto rt = lcmx::Runtime::create();
  auto node = rt.create_node("service_peer_client");
  auto client = node.create_client<lcmx_examples::pose_t, lcmx_examples::bench_t>(name);
  if (no_wait) {
    servers_wanted = 0;
  } else if (!client.wait_for_service(20s)) {
    say("CALLS ok=0 failed=" + std::to_string(calls) + " wrong=0 path=- server=0 error=no-server");
    return 0;
  }
  const auto deadline = std::chrono::steady_clock::now() + 20s;
  while (client.servers().size() < servers_wanted && std::chrono::steady_clock::now() < deadline)
    std::this_thread::sleep_for(5ms);  // condition polling with a deadline
  if (!no_wait) say("CHOSEN participant=" + std::to_string(client.servers().front().participant));
  if (go) {
    std::string line;
    while (std::getline(std::cin, line) && line != "go") {
    }
  }
  int ok = 0, failed = 0, wrong = 0;
  std::string first_error = "-", path = "-";
  std::uint64_t server = 0;
  for (int i = first; i < first + calls; ++i) {
    lcmx_examples::pose_t p;
    p.position[0] = i;
    p.position[1] = size;
    const auto timeout = std::chrono::milliseconds(call_timeout_ms);
    using Result = decltype(client)::Result;
    std::optional<Result> got;
    if (async) {
      std::promise<Result> done;
      auto f = done.get_future();
      client.call_async(p, timeout, [&done](Result x) { done.set_value(std::move(x)); });
      got.emplace(f.get());
    } else {
      got.emplace(client.call(p, timeout));
    }
    auto& r = *got;
    if (!r.ok()) {
      ++failed;
      if (first_error == "-") first_error = std::string(lcmx::to_string(r.error())) + ": " + r.message();
      continue;
    }
    const auto& b = r.value();
    bool good = b.seq == i && b.data.size() == static_cast<std::size_t>(size);
    for (std::size_t k = 0; good && k < b.data.size(); ++k) good = b.data[k] == pattern(k, b.seq);
    good ? ++ok : ++wrong;
    path = lcmx::to_string(r.server().path);
    server = r.server().participant;
  }
  say("CALLS ok=" + std::to_string(ok) + " failed=" + std::to_string(failed) +
      " wrong=" + std::to_string(wrong) + " path=" + path + " server=" + std::to_string(server) +
      " error=" + first_error + " direct=" + std::to_string(client.stats().direct_replies));
  return 0;
}

using ActionGoal = lcmx::ActionGoal<lcmx_examples::pose_t, lcmx_examples::pose_t, lcmx_examples::bench_t>;

int run_action_server(const std::string& name, int client_timeout_ms) {
  auto rt = lcmx::Runtime::create();
  auto node = rt.create_node("action_peer");
  lcmx::ActionServerOptions o;
  o.client_timeout = std::chrono::milliseconds(client_timeout_ms);
  auto server = node.create_action_server<lcmx_examples::pose_t, lcmx_examples::pose_t, lcmx_examples::bench_t>(
      name,
      [](ActionGoal& g) {
        const auto x = static_cast<std::int64_t>(g.goal().position[0]);
        lcmx_examples::bench_t result;
        result.seq = x;
        result.size = 0;
        if (x < 0) {
          say("EXECUTING " + g.id());
          g.wait_for_cancel(std::chrono::hours(1));
          say("CANCELED " + g.id());
          g.canceled(result);
          return;
        }
        for (std::int64_t i = 1; i <= x && !g.cancel_requested(); ++i) {
          lcmx_examples::pose_t f;
          f.position[0] = static_cast<double>(i);
          g.publish_feedback(f);
          g.wait_for_cancel(5ms);
        }
        g.succeed(result);
      },
      o);
  say("READY participant=" + std::to_string(rt.participant_id()));
  std::string line;
  while (std::getline(std::cin, line) && line != "quit") {
  }
  const auto st = server.stats();
  say("ACTIONS accepted=" + std::to_string(st.accepted) + " succeeded=" + std::to_string(st.succeeded) +
      " canceled=" + std::to_string(st.canceled) + " client_gone=" + std::to_string(st.client_gone_cancels));
  return 0;
}

int run_action_client(const std::string& name, int x) {
  auto rt = lcmx::Runtime::create();
  auto node = rt.create_node("action_peer_client");
  auto client = node.create_action_client<lcmx_examples::pose_t, lcmx_examples::pose_t, lcmx_examples::bench_t>(name);
  std::atomic<int> feedback{0};
  lcmx_examples::pose_t goal;
  goal.position[0] = x;
  auto sent = client.send_goal(goal, 20s, [&](const lcmx_examples::pose_t&) { ++feedback; });
  if (!sent.ok()) {
    say(std::string("OUTCOME state=error seq=- feedback=0 error=") + lcmx::to_string(sent.error()));
    return 0;
  }
  say("ACCEPTED " + sent.value().id());
  auto outcome = sent.value().wait(50s);
  if (!outcome.ok()) {
    say(std::string("OUTCOME state=error seq=- feedback=0 error=") + lcmx::to_string(outcome.error()));
    return 0;
  }
  const auto& o = outcome.value();
  say(std::string("OUTCOME state=") + lcmx::to_string(o.status.state) +
      " seq=" + (o.result ? std::to_string(o.result->seq) : std::string("-")) +
      " feedback=" + std::to_string(feedback.load()));
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"lcmx_service_peer: a service server or client for the tests"};
  std::string name;
  int calls = 10, size = 16, call_timeout_ms = 5000, timeout_ms = 60000;
  std::size_t servers_wanted = 1;
  int first = 0;
  bool go = false, no_wait = false, async = false;
  app.require_subcommand(1);
  auto* server = app.add_subcommand("server", "serve NAME");
  auto* client = app.add_subcommand("client", "call NAME");
  auto* action_server = app.add_subcommand("action-server", "serve action NAME");
  auto* action_client = app.add_subcommand("action-client", "send one goal to action NAME");
  int client_timeout_ms = 5000, x = 0;
  action_server->add_option("--client-timeout-ms", client_timeout_ms);
  action_client->add_option("--x", x, "the goal's position[0]");
  for (auto* sc : {server, client, action_server, action_client}) {
    sc->add_option("--name", name, "service name")->required();
    sc->add_option("--timeout-ms", timeout_ms, "exit with 3 after this");
  }
  client->add_option("--calls", calls);
  client->add_option("--size", size, "response data bytes");
  client->add_option("--call-timeout-ms", call_timeout_ms);
  client->add_option("--servers", servers_wanted, "wait until this many servers are known");
  client->add_option("--first", first, "x of the first call");
  client->add_flag("--go", go, "wait for \"go\" on stdin before calling");
  client->add_flag("--no-wait", no_wait, "call without waiting for a server");
  client->add_flag("--async", async, "call_async() with a callback instead of call()");
  CLI11_PARSE(app, argc, argv);
  std::thread([timeout_ms] {
    std::this_thread::sleep_for(std::chrono::milliseconds(timeout_ms));
    say("TIMEOUT");
    std::_Exit(3);
  }).detach();
  try {
    if (*server) return run_server(name);
    if (*action_server) return run_action_server(name, client_timeout_ms);
    if (*action_client) return run_action_client(name, x);
    return run_client(name, calls, size, call_timeout_ms, servers_wanted, first, go, no_wait, async);
  } catch (const std::exception& e) {
    say(std::string("FATAL ") + e.what());
    return 1;
  }
}
