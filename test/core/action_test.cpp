// Actions inside one process (the intra-process path): goal, feedback, result, cancel, the
// states, concurrent goals, rejection, a failing execute, a late client, cancel races, the
// envelopes against lcm-gen. Other paths: test/integration/service_test.cpp (shm, SIGKILL of
// server and client mid-goal), test/multihost/service_multihost_test.cpp (UDP).
#include <atomic>
#include <catch2/catch.hpp>
#include <condition_variable>
#include <future>
#include <mutex>
#include <thread>

#include <iostream>

#include "core_support.hpp"
#include "lcmx/core.hpp"
#include "lcmx_examples/bench_t.hpp"
#include "lcmx_examples/pose_t.hpp"

namespace {

using namespace std::chrono_literals;
using lcmx::GoalState;
using lcmx::core_test::eventually;
using lcmx::core_test::Gate;
using lcmx::core_test::pose;
using lcmx::core_test::test_options;
using Pose = lcmx_examples::pose_t;
using Bench = lcmx_examples::bench_t;
using Goal = lcmx::ActionGoal<Pose, Pose, Bench>;

Bench bench(std::int64_t seq) {
  Bench b;
  b.seq = seq;
  b.size = 0;
  return b;
}


}  // namespace

TEST_CASE("action: goal, feedback in order, result, states", "[action]") {
  auto rt = lcmx::Runtime::create(test_options());
  auto sn = rt.create_node("server");
  auto cn = rt.create_node("client");
  auto server = sn.create_action_server<Pose, Pose, Bench>("act_basic", [](Goal& g) {
    const int n = static_cast<int>(g.goal().position[0]);
    for (int i = 1; i <= n; ++i) g.publish_feedback(pose(i));
    g.succeed(bench(n * 10));
  });
  auto client = cn.create_action_client<Pose, Pose, Bench>("act_basic");
  REQUIRE(client.wait_for_server(5s));

  std::mutex mu;
  std::vector<double> feedback;
  auto sent = client.send_goal(pose(5), 2s, [&](const Pose& f) {
    std::lock_guard lock(mu);
    feedback.push_back(f.position[0]);
  });
  REQUIRE(sent.ok());
  const auto goal = sent.value();
  CHECK(goal.accepted());
  CHECK(goal.id().size() == 32);
  const auto outcome = goal.wait(5s);
  REQUIRE(outcome.ok());
  CHECK(outcome.value().status.state == GoalState::succeeded);
  REQUIRE(outcome.value().result.has_value());
  CHECK(outcome.value().result->seq == 50);
  CHECK(goal.status().state == GoalState::succeeded);
  // Feedback travels on its own topic and may trail the end, but wait() delivers it all, in
  // order, before it reports the end (and no callback runs after).
  {
    std::lock_guard lock(mu);
    CHECK(feedback == std::vector<double>{1, 2, 3, 4, 5});
  }
  const auto st = server.stats();
  CHECK(st.accepted == 1);
  CHECK(st.succeeded == 1);
  CHECK(st.executing == 0);
  REQUIRE(server.goals().size() == 1);
  CHECK(server.goals()[0].state == GoalState::succeeded);
}

TEST_CASE("action: executing and canceling are seen, cancel ends a goal canceled", "[action]") {
  auto rt = lcmx::Runtime::create(test_options());
  auto node = rt.create_node("n");
  std::atomic<bool> saw_cancel{false};
  auto server = node.create_action_server<Pose, Pose, Bench>("act_cancel", [&](Goal& g) {
    // Works until canceled (bounded: 10 s), then acknowledges.
    if (g.wait_for_cancel(10s)) {
      saw_cancel = true;
      g.canceled(bench(-1));
    } else {
      g.abort(bench(0), "never canceled");
    }
  });
  auto client = node.create_action_client<Pose, Pose, Bench>("act_cancel");
  auto goal = client.send_goal(pose(1), 2s).value();
  REQUIRE(goal.accepted());
  REQUIRE(eventually([&] { return goal.status().state == GoalState::executing; }));
  const auto c = goal.cancel(2s);
  REQUIRE(c.ok());
  // The reply is the state at the server when the cancel arrived: canceling, or already canceled.
  CHECK((c.value().state == GoalState::canceling || c.value().state == GoalState::canceled));
  const auto outcome = goal.wait(5s);
  REQUIRE(outcome.ok());
  CHECK(outcome.value().status.state == GoalState::canceled);
  REQUIRE(outcome.value().result.has_value());
  CHECK(outcome.value().result->seq == -1);
  CHECK(saw_cancel);
  CHECK(server.stats().canceled == 1);
  CHECK(server.stats().cancel_requests == 1);
}

TEST_CASE("action: a cancel that arrives after success changes nothing", "[action]") {
  auto rt = lcmx::Runtime::create(test_options());
  auto node = rt.create_node("n");
  auto server = node.create_action_server<Pose, Pose, Bench>("act_race", [](Goal& g) { g.succeed(bench(7)); });
  auto client = node.create_action_client<Pose, Pose, Bench>("act_race");
  for (int i = 0; i < 20; ++i) {
    auto goal = client.send_goal(pose(i), 2s).value();
    REQUIRE(goal.accepted());
    // Races the end of execute: either the goal was still live (then execute ignored the
    // request and succeeded anyway) or it had ended: the reply says how.
    const auto c = goal.cancel(2s);
    REQUIRE(c.ok());
    CHECK((c.value().state == GoalState::succeeded || c.value().state == GoalState::canceling ||
           c.value().state == GoalState::accepted || c.value().state == GoalState::executing));
    const auto outcome = goal.wait(5s);
    REQUIRE(outcome.ok());
    CHECK(outcome.value().status.state == GoalState::succeeded);
    CHECK(outcome.value().result->seq == 7);
    // Asking again after the end: still succeeded, never canceled.
    const auto again = goal.cancel(2s);
    REQUIRE(again.ok());
    CHECK(again.value().state == GoalState::succeeded);
  }
  CHECK(server.stats().succeeded == 20);
  CHECK(server.stats().canceled == 0);
}

TEST_CASE("action: concurrent goals run at once, max_goals rejects the rest", "[action]") {
  auto rt = lcmx::Runtime::create(test_options());
  auto node = rt.create_node("n");
  Gate gate;
  lcmx::ActionServerOptions o;
  o.max_goals = 3;
  auto server = node.create_action_server<Pose, Pose, Bench>(
      "act_many",
      [&](Goal& g) {
        gate.wait();
        g.succeed(bench(static_cast<std::int64_t>(g.goal().position[0])));
      },
      o);
  auto client = node.create_action_client<Pose, Pose, Bench>("act_many");
  std::vector<lcmx::ClientGoal<Bench>> goals;
  for (int i = 0; i < 3; ++i) {
    goals.push_back(client.send_goal(pose(i), 2s).value());
    REQUIRE(goals.back().accepted());
  }
  REQUIRE(gate.wait_arrived(3));  // three execute functions at once
  auto fourth = client.send_goal(pose(3), 2s);
  REQUIRE(fourth.ok());
  CHECK_FALSE(fourth.value().accepted());
  CHECK(fourth.value().message().find("busy") != std::string::npos);
  CHECK(fourth.value().wait(1s).value().status.state == GoalState::rejected);
  gate.release();
  for (int i = 0; i < 3; ++i) {
    const auto outcome = goals[static_cast<std::size_t>(i)].wait(5s);
    REQUIRE(outcome.ok());
    CHECK(outcome.value().result->seq == i);
  }
  CHECK(server.stats().rejected == 1);
}

TEST_CASE("action: the accept function rejects with a reason, execute that throws aborts", "[action]") {
  auto rt = lcmx::Runtime::create(test_options());
  auto node = rt.create_node("n");
  auto server = node.create_action_server<Pose, Pose, Bench>(
      "act_reject",
      [](Goal& g) {
        if (g.goal().position[0] > 5) throw std::runtime_error("too far");
        // Returns without ending the goal.
      },
      [](const Pose& p) { return p.position[0] < 0 ? std::string("negative goals are refused") : std::string(); });
  auto client = node.create_action_client<Pose, Pose, Bench>("act_reject");
  auto rejected = client.send_goal(pose(-1), 2s).value();
  CHECK_FALSE(rejected.accepted());
  CHECK(rejected.message() == "negative goals are refused");

  auto thrown = client.send_goal(pose(9), 2s).value().wait(5s);
  REQUIRE(thrown.ok());
  CHECK(thrown.value().status.state == GoalState::aborted);
  CHECK(thrown.value().status.message == "execute threw: too far");
  CHECK_FALSE(thrown.value().result.has_value());

  auto silent = client.send_goal(pose(1), 2s).value().wait(5s);
  REQUIRE(silent.ok());
  CHECK(silent.value().status.state == GoalState::aborted);
  CHECK(silent.value().status.message == "execute returned without ending the goal");
  CHECK(server.stats().aborted == 2);
  CHECK(server.stats().rejected == 1);
}

TEST_CASE("action: a late client learns live goals from the status and fetches a result by id", "[action]") {
  auto rt = lcmx::Runtime::create(test_options());
  auto node = rt.create_node("n");
  Gate gate;
  lcmx::ActionServerOptions o;
  o.status_period = 50ms;
  auto server = node.create_action_server<Pose, Pose, Bench>(
      "act_late",
      [&](Goal& g) {
        gate.wait();
        g.succeed(bench(42));
      },
      o);
  auto first = node.create_action_client<Pose, Pose, Bench>("act_late");
  auto goal = first.send_goal(pose(1), 2s).value();
  REQUIRE(gate.wait_arrived(1));
  // A client made after the goal was sent hears its state from the re-announced status...
  auto late = node.create_action_client<Pose, Pose, Bench>("act_late");
  REQUIRE(eventually([&] { return late.status(goal.id()).state == GoalState::executing; }));
  // ...can wait for it and get the result, and cancel it if it wanted to.
  auto handle = late.goal(goal.id());
  auto waiting = std::async(std::launch::async, [&] { return handle.wait(5s); });
  gate.release();
  const auto outcome = waiting.get();
  REQUIRE(outcome.ok());
  CHECK(outcome.value().status.state == GoalState::succeeded);
  CHECK(outcome.value().result->seq == 42);
  // An id nobody announced is an error, not a hang.
  const auto unknown = late.goal("00000000000000000000000000000001").wait(200ms);
  CHECK_FALSE(unknown.ok());
  CHECK(unknown.error() == lcmx::CallErrc::no_server);
}

TEST_CASE("action: type mismatch, raw clients and servers, bad names", "[action]") {
  auto rt = lcmx::Runtime::create(test_options());
  auto node = rt.create_node("n");
  auto server = node.create_action_server<Pose, Pose, Bench>("act_types", [](Goal& g) { g.succeed(bench(3)); });
  auto wrong = node.create_action_client<Bench, Pose, Bench>("act_types");
  const auto r = wrong.send_goal(bench(1), 2s);
  REQUIRE_FALSE(r.ok());
  CHECK(r.error() == lcmx::CallErrc::type_mismatch);
  CHECK(r.message().find("pose_t") != std::string::npos);
  CHECK(r.message().find("bench_t (") != std::string::npos);

  // A raw client talks to the typed server with encoded bytes.
  auto raw = node.create_action_client_raw("act_types");
  const Pose p = pose(2);
  lcmx::Bytes b(static_cast<std::size_t>(p.getEncodedSize()));
  p.encode(b.data(), 0, static_cast<int>(b.size()));
  auto out = raw.send_goal(b, 2s).value().wait(5s);
  REQUIRE(out.ok());
  CHECK(out.value().status.state == GoalState::succeeded);
  Bench decoded;
  REQUIRE(out.value().result.has_value());
  REQUIRE(decoded.decode(out.value().result->data(), 0, static_cast<int>(out.value().result->size())) > 0);
  CHECK(decoded.seq == 3);
  // ...and a raw server gets a raw goal's bytes as sent, and undecodable goals are bad requests.
  auto raw_server = node.create_action_server_raw("act_raw", [](lcmx::RawActionGoal& g) {
    g.publish_feedback(g.goal());
    g.finish(GoalState::succeeded, g.goal(), "");
  });
  const lcmx::Bytes bytes{std::byte{1}, std::byte{2}, std::byte{3}};
  auto raw2 = node.create_action_client_raw("act_raw");
  auto echoed = raw2.send_goal(bytes, 2s).value().wait(5s);
  REQUIRE(echoed.ok());
  CHECK(*echoed.value().result == bytes);
  auto garbage = raw.send_goal(bytes, 2s);
  REQUIRE_FALSE(garbage.ok());
  CHECK(garbage.error() == lcmx::CallErrc::bad_request);

  auto long_name = [&] { node.create_action_server<Pose, Pose, Bench>(std::string(37, 'a'), [](Goal&) {}); };
  auto empty_name = [&] { node.create_action_client<Pose, Pose, Bench>(""); };
  CHECK_THROWS_AS(long_name(), lcmx::Error);
  CHECK_THROWS_AS(empty_name(), lcmx::Error);
  CHECK_THROWS_AS(node.create_action_server_raw("act_empty", nullptr), lcmx::Error);
}

TEST_CASE("action: ending a goal twice or with a live state throws, destroying the server cancels live goals", "[action]") {
  auto rt = lcmx::Runtime::create(test_options());
  auto node = rt.create_node("n");
  std::atomic<int> second_end_threw{0}, bad_state_threw{0};
  std::atomic<bool> canceled_on_close{false};
  auto server = node.create_action_server<Pose, Pose, Bench>("act_close", [&](Goal& g) {
    if (g.goal().position[0] == 1) {
      try {
        g.raw().finish(GoalState::executing, {}, "");
      } catch (const lcmx::Error&) {
        ++bad_state_threw;
      }
      g.succeed(bench(1));
      try {
        g.succeed(bench(2));
      } catch (const lcmx::Error&) {
        ++second_end_threw;
      }
      return;
    }
    if (g.wait_for_cancel(10s)) {
      canceled_on_close = true;
      g.canceled(bench(0));
    }
  });
  auto client = node.create_action_client<Pose, Pose, Bench>("act_close");
  auto once = client.send_goal(pose(1), 2s).value().wait(5s);
  REQUIRE(once.ok());
  CHECK(once.value().result->seq == 1);
  // execute goes on after its first end (the client may hear the end first).
  CHECK(eventually([&] { return second_end_threw == 1; }));
  CHECK(bad_state_threw == 1);

  auto live = client.send_goal(pose(2), 2s).value();
  REQUIRE(eventually([&] { return live.status().state == GoalState::executing; }));
  server.reset();  // returns once execute returned
  CHECK(canceled_on_close);
  // The client hears the end (canceled, in the final status) or, if the server's services were
  // gone first, that the server went away: never a hang.
  const auto outcome = live.wait(5s);
  REQUIRE(outcome.ok());
  CHECK((outcome.value().status.state == GoalState::canceled || outcome.value().status.state == GoalState::lost));
}

TEST_CASE("action: the tutorial of README.md and docs/actions.md runs as written", "[action]") {
  auto rt = lcmx::Runtime::create(test_options());
  auto node = rt.create_node("driver");
  // Copied from README.md ("Actions in a dozen lines"); keep the three in step.
  using Pose = lcmx_examples::pose_t;
  using Result = lcmx_examples::bench_t;
  auto server = node.create_action_server<Pose, Pose, Result>(  // goal, feedback, result types
      "drive", [](lcmx::ActionGoal<Pose, Pose, Result>& g) {    // a thread of its own per goal
        for (int i = 1; i <= 10; ++i) {
          if (g.wait_for_cancel(std::chrono::milliseconds(10))) return g.canceled(Result{});
          Pose progress{};
          progress.position[0] = i;
          g.publish_feedback(progress);
        }
        Result done{};
        done.seq = 10;
        g.succeed(done);  // or g.abort(result, "why")
      });
  auto client = node.create_action_client<Pose, Pose, Result>("drive");
  auto goal = client.send_goal(Pose{}, std::chrono::seconds(2),
                               [](const Pose& f) { std::cout << "at " << f.position[0] << "\n"; }).value();
  auto outcome = goal.wait(std::chrono::seconds(30));  // the end, after all feedback
  if (outcome) std::cout << lcmx::to_string(outcome.value().status.state) << " " << outcome.value().result->seq << "\n";
  REQUIRE(outcome.ok());
  CHECK(outcome.value().status.state == GoalState::succeeded);
  CHECK(outcome.value().result->seq == 10);
  CHECK(server.stats().succeeded == 1);
}
