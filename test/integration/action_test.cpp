// Actions across processes on one host (shared memory): goal, feedback, result and cancel
// both ways; a server SIGKILLed mid-goal (its client reports the goal lost at once); a client
// SIGKILLed mid-goal (the server cancels its goal after client_timeout, not before). The peers
// are lcmx_service_peer's action roles (service_peer.cpp).
#include "lcmx/core.hpp"
#include "lcmx_examples/bench_t.hpp"
#include "lcmx_examples/pose_t.hpp"
#include "support.hpp"

using namespace lcmx::it;
using Pose = lcmx_examples::pose_t;
using Bench = lcmx_examples::bench_t;
using lcmx::GoalState;

namespace {

Pose goal(double x) {
  Pose p;
  p.position[0] = x;
  return p;
}

}  // namespace

TEST_CASE("action across processes: a client here, a server there, over shared memory", "[integration][action]") {
  Session s(136);
  const auto name = unique_channel("ACT", 136);
  auto& server = s.spawn({LCMX_SERVICE_PEER, "action-server", "--name", name, "--timeout-ms", "60000"});
  REQUIRE(server.expect("READY"));
  auto rt = lcmx::Runtime::create();
  auto node = rt.create_node("client");
  auto client = node.create_action_client<Pose, Pose, Bench>(name);
  REQUIRE(client.wait_for_server(10000ms));
  REQUIRE(client.servers().size() == 1);
  CHECK(client.servers()[0].path == lcmx::Path::shm);

  std::atomic<int> feedback{0};
  auto g = client.send_goal(goal(20), 5000ms, [&](const Pose& f) { CHECK(f.position[0] == ++feedback); });
  REQUIRE(g.ok());
  REQUIRE(g.value().accepted());
  const auto outcome = g.value().wait(10000ms);
  REQUIRE(outcome.ok());
  CHECK(outcome.value().status.state == GoalState::succeeded);
  REQUIRE(outcome.value().result.has_value());
  CHECK(outcome.value().result->seq == 20);
  CHECK(feedback == 20);

  // A goal that runs until canceled: the cancel reaches the other process and ends it canceled.
  auto live = client.send_goal(goal(-1), 5000ms).value();
  REQUIRE(server.expect("EXECUTING " + live.id()));
  REQUIRE(wait_until([&] { return live.status().state == GoalState::executing; }, 5000ms));
  const auto c = live.cancel(5000ms);
  REQUIRE(c.ok());
  REQUIRE(server.expect("CANCELED " + live.id()));
  const auto ended = live.wait(10000ms);
  REQUIRE(ended.ok());
  CHECK(ended.value().status.state == GoalState::canceled);
  CHECK(ended.value().result->seq == -1);

  server.send("quit");
  const auto summary = server.expect("ACTIONS");
  REQUIRE(summary);
  const auto kv = parse_kv(*summary);
  CHECK(kv.at("accepted") == "2");
  CHECK(kv.at("succeeded") == "1");
  CHECK(kv.at("canceled") == "1");
}

TEST_CASE("action across processes: the server is SIGKILLed mid-goal: the client reports the goal lost at once",
          "[integration][action]") {
  Session s(137);
  const auto name = unique_channel("ACT", 137);
  auto& server = s.spawn({LCMX_SERVICE_PEER, "action-server", "--name", name, "--timeout-ms", "60000"});
  REQUIRE(server.expect("READY"));
  auto rt = lcmx::Runtime::create();
  auto node = rt.create_node("client");
  auto client = node.create_action_client<Pose, Pose, Bench>(name);
  auto live = client.send_goal(goal(-1), 10000ms).value();
  REQUIRE(live.accepted());
  REQUIRE(server.expect("EXECUTING " + live.id()));
  const auto killed = Clock::now();
  server.kill9();
  const auto outcome = live.wait(10000ms);
  const auto took = std::chrono::duration_cast<ms>(Clock::now() - killed);
  INFO("the client reported the end " << took.count() << " ms after the SIGKILL");
  REQUIRE(outcome.ok());
  CHECK(outcome.value().status.state == GoalState::lost);
  CHECK(outcome.value().status.message.find("went away") != std::string::npos);
  CHECK_FALSE(outcome.value().result.has_value());
  CHECK(took < 1000ms);  // a local death is noticed at once (pidfd), not after the lease
  // A cancel of a lost goal says so instead of waiting for a server that is gone.
  const auto c = live.cancel(1000ms);
  REQUIRE_FALSE(c.ok());
  CHECK(c.error() == lcmx::CallErrc::server_gone);
}

TEST_CASE("action across processes: the client is SIGKILLed mid-goal: the server cancels its goal after client_timeout",
          "[integration][action]") {
  Session s(138);
  const auto name = unique_channel("ACT", 138);
  auto rt = lcmx::Runtime::create();
  auto node = rt.create_node("server");
  std::atomic<bool> canceled{false};
  lcmx::ActionServerOptions o;
  o.client_timeout = 600ms;
  auto server = node.create_action_server<Pose, Pose, Bench>(
      name,
      [&](lcmx::ActionGoal<Pose, Pose, Bench>& g) {
        if (g.wait_for_cancel(30s)) canceled = true;
        Bench b;
        b.seq = -1;
        b.size = 0;
        g.canceled(b);
      },
      o);
  auto& client = s.spawn({LCMX_SERVICE_PEER, "action-client", "--name", name, "--x", "-1", "--timeout-ms", "60000"});
  const auto accepted = client.expect("ACCEPTED");
  REQUIRE(accepted);
  const std::string id = accepted->substr(9);
  REQUIRE(wait_until([&] { return server.stats().executing == 1; }, 5000ms));
  const auto killed = Clock::now();
  client.kill9();
  REQUIRE(wait_until([&] { return canceled.load(); }, 10000ms));
  const auto took = std::chrono::duration_cast<ms>(Clock::now() - killed);
  INFO("canceled " << took.count() << " ms after the client's SIGKILL (client_timeout 600 ms)");
  CHECK(took >= 600ms);   // not before the timeout
  CHECK(took < 3000ms);   // the death is noticed at once; the timeout is all the delay
  REQUIRE(wait_until([&] { return server.stats().canceled == 1; }, 5000ms));
  CHECK(server.stats().client_gone_cancels == 1);
  const auto goals = server.goals();
  REQUIRE(goals.size() == 1);
  CHECK(goals[0].goal_id == id);
  CHECK(goals[0].state == GoalState::canceled);
  CHECK(goals[0].message == "canceled: the client went away");
}

#ifdef LCMX_TOOL
TEST_CASE("lcmx actions and lcmx action send against a server process, Ctrl-C cancels", "[integration][action]") {
  Session s(139);
  const auto name = unique_channel("ACT", 139);
  auto& server = s.spawn({LCMX_SERVICE_PEER, "action-server", "--name", name, "--timeout-ms", "60000"});
  REQUIRE(server.expect("READY"));
  const std::string types = LCMX_LCMTYPES_DIR;

  auto list = s.run({LCMX_TOOL, "actions", "--json", "--types", types});
  INFO(list.out);
  REQUIRE(list.rc == 0);
  const auto j = json_line(list.out);
  CHECK(j.find("\"name\":\"" + name + "\"") != std::string::npos);
  CHECK(j.find("\"goal_type\":\"lcmx_examples.pose_t\"") != std::string::npos);
  CHECK(j.find("\"feedback_type\":\"lcmx_examples.pose_t\"") != std::string::npos);
  CHECK(j.find("\"result_type\":\"lcmx_examples.bench_t\"") != std::string::npos);
  CHECK(j.find("\"process\":\"lcmx_service_pe\"") != std::string::npos);

  // A goal that succeeds: feedback lines, the result, the end; exit 0.
  auto send = s.run({LCMX_TOOL, "action", "send", name, "{\"position\": [3, 0, 0]}", "--types", types, "--json"},
                    {}, 20000ms);
  INFO(send.out);
  REQUIRE(send.rc == 0);
  std::size_t feedback = 0;
  for (auto at = send.out.find("{\"feedback\":"); at != std::string::npos; at = send.out.find("{\"feedback\":", at + 1))
    ++feedback;
  CHECK(feedback == 3);
  CHECK(send.out.find("\"seq\":3") != std::string::npos);
  CHECK(send.out.find("\"state\":\"succeeded\"") != std::string::npos);

  // A goal that runs until canceled: Ctrl-C cancels it, the tool waits for the end, exit 130.
  auto& tool = s.spawn({LCMX_TOOL, "action", "send", name, "{\"position\": [-1, 0, 0]}", "--types", types});
  const auto accepted = tool.expect("goal ");
  REQUIRE(accepted);
  CHECK(accepted->find("accepted") != std::string::npos);
  REQUIRE(server.expect("EXECUTING"));
  tool.signal(SIGINT);
  REQUIRE(server.expect("CANCELED"));
  CHECK(tool.wait(10000ms) == 130);
  CHECK(tool.output().find("canceled: canceled by a client") != std::string::npos);

  auto text = s.run({LCMX_TOOL, "actions", "--types", types});
  INFO(text.out);
  REQUIRE(text.rc == 0);
  CHECK(text.out.find(name + "  goal lcmx_examples.pose_t, feedback lcmx_examples.pose_t, result lcmx_examples.bench_t") !=
        std::string::npos);
  CHECK(text.out.find("  succeeded") != std::string::npos);
  CHECK(text.out.find("  canceled  (canceled by a client)") != std::string::npos);

  // Clear errors: a field that does not exist, no server, bad hex.
  auto bad = s.run({LCMX_TOOL, "action", "send", name, "{\"positon\": [1]}", "--types", types});
  CHECK(bad.rc == 1);
  CHECK(bad.out.find("positon: no such field") != std::string::npos);
  auto none = s.run({LCMX_TOOL, "action", "send", name + "_nobody", "{}", "--find-timeout", "0.3"});
  CHECK(none.rc == 1);
  CHECK(none.out.find("no server of action") != std::string::npos);
  auto hex = s.run({LCMX_TOOL, "action", "send", name, "--hex", "abc"});
  CHECK(hex.rc == 2);
  auto both = s.run({LCMX_TOOL, "action", "send", name, "{}", "--hex", "00"});  // JSON and hex: which one?
  CHECK(both.rc == 2);
  CHECK(both.out.find("excludes") != std::string::npos);
  auto usage = s.run({LCMX_TOOL, "action"});
  CHECK(usage.rc != 0);
  server.send("quit");
  CHECK(server.wait() == 0);
}
#endif
