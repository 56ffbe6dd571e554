// Trust in services and actions (issue 34 item 4, docs/services.md "Trust"): a server makes
// nothing for a request before it is checked and keeps a bounded number of clients; a client
// takes a reply, and an action client a goal's status, only from the server its call went to.
// The attacker is another participant: a process forked before this one creates its Runtime,
// on the same discovery group (so it reaches us over shared memory), driven through pipes.
#include <poll.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <atomic>
#include <catch2/catch.hpp>
#include <condition_variable>
#include <functional>
#include <mutex>
#include <optional>
#include <random>

#include "core_support.hpp"
#include "lcmx/core.hpp"
#include "lcmx_examples/bench_t.hpp"
#include "lcmx_examples/pose_t.hpp"
#include "lcmx_msgs/action_status_t.hpp"
#include "lcmx_msgs/service_reply_t.hpp"
#include "lcmx_msgs/service_request_t.hpp"

namespace {

using namespace std::chrono_literals;
using lcmx::core_test::eventually;
using lcmx::core_test::Gate;
using lcmx::core_test::pose;
using Pose = lcmx_examples::pose_t;
using Bench = lcmx_examples::bench_t;

constexpr auto kTrustWait = 15000ms;  // every wait's deadline here

// The attacker: `body` runs in a child process with its own Runtime on options `o`; it
// reports progress with report(c) and may wait for the parent's go with wait_go().
// Destroying the handle tells the child to end (EOF on its pipe) and reaps it.
struct Attacker {
  struct Pipes {
    int cmd = -1, report = -1;
    void report_char(char c) const {
      if (::write(report, &c, 1) != 1) _exit(3);
    }
    // Blocks until the parent writes (or closes its end).
    void wait_go() const {
      char c;
      [[maybe_unused]] auto n = ::read(cmd, &c, 1);
    }
  };
  pid_t pid = -1;
  int cmd = -1, report = -1;

  Attacker(const lcmx::RuntimeOptions& o, std::function<void(lcmx::Runtime&, const Pipes&)> body) {
    int c[2], r[2];
    REQUIRE(::pipe(c) == 0);
    REQUIRE(::pipe(r) == 0);
    pid = ::fork();
    REQUIRE(pid >= 0);
    if (pid == 0) {
      ::close(c[1]);
      ::close(r[0]);
      ::alarm(60);  // watchdog
      int code = 0;
      try {
        auto rt = lcmx::Runtime::create(o);
        body(rt, Pipes{c[0], r[1]});
        Pipes{c[0], r[1]}.wait_go();  // until the parent is done
      } catch (...) {
        code = 4;
      }
      _exit(code);
    }
    ::close(c[0]);
    ::close(r[1]);
    cmd = c[1];
    report = r[0];
  }
  // Waits for the child to report `want`; false on a deadline, another character or EOF.
  bool reported(char want, std::chrono::milliseconds deadline = kTrustWait) const {
    pollfd p{report, POLLIN, 0};
    if (::poll(&p, 1, static_cast<int>(deadline.count())) != 1) return false;
    char c = 0;
    return ::read(report, &c, 1) == 1 && c == want;
  }
  void go() const {
    const char c = 'g';
    [[maybe_unused]] auto n = ::write(cmd, &c, 1);
  }
  ~Attacker() {
    ::close(cmd);
    int status = 0;
    for (int i = 0; i < 500 && ::waitpid(pid, &status, WNOHANG) == 0; ++i) ::usleep(10000);
    if (::waitpid(pid, &status, WNOHANG) == 0) {
      ::kill(pid, SIGKILL);
      ::waitpid(pid, &status, 0);
    }
    ::close(report);
  }
};

// Shared options of the attacker and this process: one group, a lease that outlasts pauses.
lcmx::RuntimeOptions trust_options() {
  auto o = lcmx::core_test::test_options();
  o.lease = 2000ms;
  return o;
}

Bench trust_bench(std::int64_t seq) {
  Bench b{};
  b.seq = seq;
  b.size = 0;
  return b;
}

template <class T>
std::vector<std::byte> trust_encoded(const T& m) {
  std::vector<std::byte> b(static_cast<std::size_t>(m.getEncodedSize()));
  m.encode(b.data(), 0, static_cast<int>(b.size()));
  return b;
}

}  // namespace

TEST_CASE("service trust: a reply forged by another participant is ignored, the server's is taken",
          "[service][trust]") {
  const auto o = trust_options();
  // The attacker listens to the requests, and answers the first call on its client's reply
  // channel as if it were the server (its participant and id copied from the request).
  Attacker forger(o, [](lcmx::Runtime& rt, const Attacker::Pipes& pipes) {
    auto node = rt.create_node("forger");
    std::mutex mu;
    std::condition_variable cv;
    std::optional<lcmx_msgs::service_request_t> call;
    bool probed = false;
    auto tap = node.subscribe<lcmx_msgs::service_request_t>("svc_forge/rq", [&](const lcmx_msgs::service_request_t& r) {
      std::lock_guard lock(mu);
      if (r.request_id == 0) probed = true;
      if (r.request_id != 0 && !call) call = r;
      cv.notify_all();
    });
    pipes.report_char('r');
    std::unique_lock lock(mu);
    // The client probes every subscriber of its request channel, us too: from then on we get
    // its calls.
    if (!cv.wait_for(lock, kTrustWait, [&] { return probed; })) _exit(7);
    pipes.report_char('p');
    if (!cv.wait_for(lock, kTrustWait, [&] { return call.has_value(); })) _exit(5);
    auto pub = node.advertise_raw(call->reply_channel, lcmx_msgs::service_reply_t::getTypeName(),
                                  lcmx_msgs::service_reply_t::getHash());
    if (!pub.wait_for_subscribers(1, kTrustWait)) _exit(6);
    lcmx_msgs::service_reply_t r{};
    r.client_id = call->client_id;
    r.request_id = call->request_id;
    r.server_participant = call->server_participant;
    r.server_id = call->server_id;
    r.request_fingerprint = Pose::getHash();
    r.response_fingerprint = Bench::getHash();
    r.request_type = "pose_t";
    r.response_type = "bench_t";
    r.status = lcmx_msgs::service_reply_t::OK;
    const auto payload = trust_encoded(trust_bench(666));
    r.payload.assign(reinterpret_cast<const std::uint8_t*>(payload.data()),
                     reinterpret_cast<const std::uint8_t*>(payload.data()) + payload.size());
    r.size = static_cast<std::int32_t>(r.payload.size());
    pub.publish(trust_encoded(r));
    pipes.report_char('s');
  });
  REQUIRE(forger.reported('r'));

  auto rt = lcmx::Runtime::create(o);
  auto node = rt.create_node("n");
  Gate gate;  // the server answers only once the forged reply was seen
  auto server = node.create_service<Pose, Bench>("svc_forge", [&](const Pose& p) {
    gate.wait();
    return trust_bench(static_cast<std::int64_t>(p.position[0]));
  });
  auto client = node.create_client<Pose, Bench>("svc_forge");
  REQUIRE(client.wait_for_service(kTrustWait));
  REQUIRE(forger.reported('p'));  // it hears our requests
  auto reply = client.call_async(pose(42), kTrustWait);
  REQUIRE(forger.reported('s'));
  // The forged reply arrives (over shared memory, from the attacker's participant) and is
  // counted, not taken.
  CHECK(eventually([&] { return client.stats().foreign_replies >= 1; }, kTrustWait));
  CHECK(reply.wait_for(0s) == std::future_status::timeout);
  gate.release();
  auto r = reply.get();
  REQUIRE(r.ok());
  CHECK(r.value().seq == 42);
  CHECK(client.stats().foreign_replies == 1);
}

TEST_CASE("service trust: requests with random client ids make no reply channel", "[service][trust]") {
  const auto o = trust_options();
  constexpr int kRequests = 200;
  // The attacker publishes probes (and calls) for random client ids on the request channel:
  // half naming itself as the client's participant, half another participant. It subscribes
  // to none of their reply channels.
  Attacker flood(o, [&](lcmx::Runtime& rt, const Attacker::Pipes& pipes) {
    auto node = rt.create_node("flood");
    lcmx::PublisherOptions po;
    po.shm_slots = 2 * kRequests;  // the server may read them all late: none is lapped
    auto pub = node.advertise_raw("svc_flood/rq", lcmx_msgs::service_request_t::getTypeName(),
                                  lcmx_msgs::service_request_t::getHash(), po);
    if (!pub.wait_for_subscribers(1, kTrustWait)) _exit(5);
    std::mt19937_64 rng(7);
    for (int i = 0; i < kRequests; ++i) {
      lcmx_msgs::service_request_t q{};
      q.client_id = static_cast<std::int64_t>(rng() | 1);
      q.request_id = i % 2;  // probes and calls
      q.client_participant = i % 4 < 2 ? static_cast<std::int64_t>(rt.participant_id())
                                       : static_cast<std::int64_t>(rng() | 1);
      q.reply_channel = fmt::format("svc_flood/rp/{:016x}", static_cast<std::uint64_t>(q.client_id));
      q.size = 0;
      pub.publish(trust_encoded(q));
    }
    pipes.report_char('s');
  });

  auto rt = lcmx::Runtime::create(o);
  auto node = rt.create_node("n");
  std::atomic<int> executed{0};
  auto server = node.create_service<Pose, Bench>("svc_flood", [&](const Pose&) {
    ++executed;
    return trust_bench(0);
  });
  REQUIRE(flood.reported('s'));
  CHECK(eventually([&] { return server.stats().refused >= kRequests; }, kTrustWait));
  const auto st = server.stats();
  CHECK(st.clients == 0);  // no publisher, no /dev/shm segment, no endpoint in our beacons
  CHECK(st.probes == 0);
  CHECK(st.requests == 0);
  CHECK(executed == 0);
  // A real client is still served.
  auto client = node.create_client<Pose, Bench>("svc_flood");
  REQUIRE(client.wait_for_service(kTrustWait));
  CHECK(client.call(pose(1), kTrustWait).ok());
  CHECK(server.stats().clients == 1);
}

TEST_CASE("service trust: a server keeps a reply channel for at most 256 clients", "[service][trust]") {
  auto rt = lcmx::Runtime::create(lcmx::core_test::test_options());
  auto node = rt.create_node("n");
  auto server = node.create_service_raw("svc_many", [](std::span<const std::byte>) { return lcmx::Bytes{}; });
  // 264 would-be clients in this process, each subscribed to its reply channel, probing.
  constexpr int kClients = 264;
  std::vector<lcmx::RawSubscriber> subs;
  auto pub = node.advertise_raw("svc_many/rq", lcmx_msgs::service_request_t::getTypeName(),
                                lcmx_msgs::service_request_t::getHash());
  REQUIRE(pub.wait_for_subscribers(1, kTrustWait));
  for (int i = 0; i < kClients; ++i) {
    const auto id = static_cast<std::uint64_t>(0x1000 + i);
    const auto channel = fmt::format("svc_many/rp/{:016x}", id);
    subs.push_back(node.subscribe_raw(channel, lcmx_msgs::service_reply_t::getTypeName(),
                                      lcmx_msgs::service_reply_t::getHash(), [](const lcmx::RawMessage&) {}));
    lcmx_msgs::service_request_t q{};
    q.client_id = static_cast<std::int64_t>(id);
    q.client_participant = static_cast<std::int64_t>(rt.participant_id());
    q.reply_channel = channel;
    pub.publish(trust_encoded(q));
    // One at a time: the request subscriber's queue is not what is tested.
    REQUIRE(eventually([&] {
      const auto s = server.stats();
      return s.probes + s.refused == static_cast<std::uint64_t>(i + 1);
    }, kTrustWait));
  }
  const auto st = server.stats();
  CHECK(st.clients == 256);
  CHECK(st.probes == 256);
  CHECK(st.refused == kClients - 256);
  // A client gone (its reply channel unsubscribed) makes room for a new one.
  subs.front().reset();
  lcmx_msgs::service_request_t q{};
  q.client_id = 0x1000 + kClients;
  q.client_participant = static_cast<std::int64_t>(rt.participant_id());
  q.reply_channel = fmt::format("svc_many/rp/{:016x}", static_cast<std::uint64_t>(q.client_id));
  auto last = node.subscribe_raw(q.reply_channel, lcmx_msgs::service_reply_t::getTypeName(),
                                 lcmx_msgs::service_reply_t::getHash(), [](const lcmx::RawMessage&) {});
  pub.publish(trust_encoded(q));
  CHECK(eventually([&] { return server.stats().probes == 257; }, kTrustWait));
  CHECK(server.stats().clients == 256);
}

TEST_CASE("action trust: a status forged by another participant cannot end a goal", "[action][trust]") {
  const auto o = trust_options();
  constexpr int kForged = 40;
  // The attacker hears the server's status, then publishes statuses that name the same server
  // (participant and ids copied) and say every goal succeeded.
  Attacker forger(o, [&](lcmx::Runtime& rt, const Attacker::Pipes& pipes) {
    auto node = rt.create_node("forger");
    std::mutex mu;
    std::condition_variable cv;
    std::optional<lcmx_msgs::action_status_t> heard;
    auto tap = node.subscribe<lcmx_msgs::action_status_t>("act_forge/status", [&](const lcmx_msgs::action_status_t& s) {
      std::lock_guard lock(mu);
      if (!s.goals.empty() && s.goals[0].message != "forged" && !heard) heard = s;
      cv.notify_all();
    });
    pipes.report_char('r');
    lcmx_msgs::action_status_t forged;
    {
      std::unique_lock lock(mu);
      if (!cv.wait_for(lock, kTrustWait, [&] { return heard.has_value(); })) _exit(5);
      forged = *heard;
    }
    for (auto& g : forged.goals) {
      g.state = lcmx_msgs::action_goal_status_t::SUCCEEDED;
      g.message = "forged";
    }
    lcmx::PublisherOptions po;
    po.shm_slots = 2 * kForged;  // none lapped before the client and the parent's tap read it
    auto pub = node.advertise<lcmx_msgs::action_status_t>("act_forge/status", po);
    // The client's subscriber, the parent's tap and our own tap.
    if (!pub.wait_for_subscribers(3, kTrustWait)) _exit(6);
    for (int i = 0; i < kForged; ++i) pub.publish(forged);
    pipes.report_char('s');
  });
  REQUIRE(forger.reported('r'));

  auto rt = lcmx::Runtime::create(o);
  auto sn = rt.create_node("server");
  auto cn = rt.create_node("client");
  auto tn = rt.create_node("tap");
  Gate gate;
  lcmx::ActionServerOptions so;
  so.status_period = 100ms;
  auto server = sn.create_action_server<Pose, Pose, Bench>(
      "act_forge",
      [&](lcmx::ActionGoal<Pose, Pose, Bench>& g) {
        gate.wait();
        g.succeed(trust_bench(7));
      },
      so);
  std::atomic<int> forged_seen{0};
  auto tap = tn.subscribe<lcmx_msgs::action_status_t>("act_forge/status", [&](const lcmx_msgs::action_status_t& s) {
    if (!s.goals.empty() && s.goals[0].message == "forged") ++forged_seen;
  });
  auto client = cn.create_action_client<Pose, Pose, Bench>("act_forge");
  REQUIRE(client.wait_for_server(kTrustWait));
  auto sent = client.send_goal(pose(1), kTrustWait);
  REQUIRE(sent.ok());
  const auto goal = sent.value();
  REQUIRE(gate.wait_arrived(1));
  REQUIRE(forger.reported('s'));
  REQUIRE(eventually([&] { return forged_seen.load() >= kForged; }, kTrustWait));
  // The client hears the same statuses as the tap (on its own thread) and takes none of them:
  // its goal stays executing (a window for the client's thread; no state change expected).
  CHECK_FALSE(eventually([&] { return goal.status().state != lcmx::GoalState::executing; }, 500ms));
  CHECK(goal.status().state == lcmx::GoalState::executing);
  gate.release();
  auto outcome = goal.wait(kTrustWait);
  REQUIRE(outcome.ok());
  CHECK(outcome.value().status.state == lcmx::GoalState::succeeded);
  CHECK(outcome.value().status.message != "forged");
  REQUIRE(outcome.value().result.has_value());
  CHECK(outcome.value().result->seq == 7);
}
