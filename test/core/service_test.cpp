// Services inside one process (the intra-process path): calls, errors, several servers,
// fail-over, timeouts, and the envelopes' layout against lcm-gen's code.
// Other paths: test/integration/service_test.cpp (shm), test/multihost (UDP, bridge).
#include <sched.h>
#include <sys/mount.h>
#include <sys/wait.h>
#include <unistd.h>

#include <atomic>
#include <catch2/catch.hpp>
#include <condition_variable>
#include <future>
#include <mutex>
#include <thread>

#include "core_support.hpp"
#include "lcmx/core.hpp"
#include "lcmx/core/service.hpp"
#include "lcmx_examples/bench_t.hpp"
#include "lcmx_examples/pose_t.hpp"
#include "lcmx_msgs/service_reply_t.hpp"
#include "lcmx_msgs/service_request_t.hpp"

namespace {

using namespace std::chrono_literals;
using lcmx::core_test::eventually;
using lcmx::core_test::Gate;
using lcmx::core_test::manual;
using lcmx::core_test::pose;
using lcmx::core_test::test_options;
using Pose = lcmx_examples::pose_t;
using Bench = lcmx_examples::bench_t;


// Answers a pose with a bench_t whose seq is the pose's x and whose data has `size` bytes.
Bench answer(const Pose& p, std::int32_t size = 3) {
  Bench b;
  b.seq = static_cast<std::int64_t>(p.position[0]);
  b.size = size;
  b.data.assign(static_cast<std::size_t>(size), static_cast<std::uint8_t>(b.seq & 0xff));
  return b;
}


}  // namespace

TEST_CASE("service: a typed call in one process, sync, future and callback", "[service]") {
  auto rt = lcmx::Runtime::create(test_options());
  auto sn = rt.create_node("server");
  auto cn = rt.create_node("client");
  auto server = sn.create_service<Pose, Bench>("svc_basic", [](const Pose& p) { return answer(p); });
  auto client = cn.create_client<Pose, Bench>("svc_basic");

  REQUIRE(client.wait_for_service(5s));
  const auto servers = client.servers();
  REQUIRE(servers.size() == 1);
  CHECK(servers[0].participant == rt.participant_id());
  CHECK(servers[0].path == lcmx::Path::intra);

  auto r = client.call(pose(7), 2s);
  REQUIRE(r.ok());
  CHECK(r.value().seq == 7);
  CHECK(r.value().data.size() == 3);
  CHECK(r.server().path == lcmx::Path::intra);

  auto f = client.call_async(pose(8), 2s);
  REQUIRE(f.wait_for(5s) == std::future_status::ready);
  CHECK(f.get().value().seq == 8);

  std::promise<std::int64_t> got;
  client.call_async(pose(9), 2s, [&](lcmx::CallResult<Bench> res) { got.set_value(res.value().seq); });
  auto gf = got.get_future();
  REQUIRE(gf.wait_for(5s) == std::future_status::ready);
  CHECK(gf.get() == 9);

  const auto cs = client.stats();
  CHECK(cs.calls == 3);
  CHECK(cs.replies == 3);
  CHECK(cs.pending == 0);
  CHECK(server.stats().requests == 3);
  CHECK(server.stats().clients == 1);
}

// A full /dev/shm (a container's small tmpfs): the reply cannot be loaned. The call fails
// handler_failed, and the message says the server, not its handler, failed. In a child with
// a private 1 MiB tmpfs on /dev/shm (skipped where mount namespaces are not allowed).
TEST_CASE("service: a response the server cannot fit in /dev/shm says the server failed, not the handler",
          "[service][tmpfs]") {
  const pid_t pid = ::fork();
  REQUIRE(pid >= 0);
  if (pid == 0) {
    if (::unshare(CLONE_NEWNS) != 0 || ::mount(nullptr, "/", nullptr, MS_REC | MS_PRIVATE, nullptr) != 0 ||
        ::mount("tmpfs", "/dev/shm", "tmpfs", MS_NOSUID | MS_NODEV, "size=1m") != 0)
      ::_exit(96);
    int rc = 10;
    try {
      auto rt = lcmx::Runtime::create(test_options());
      auto sn = rt.create_node("server");
      auto cn = rt.create_node("client");
      auto server = sn.create_service<Pose, Bench>("svc_fullshm", [](const Pose& p) { return answer(p, 2 << 20); });
      auto client = cn.create_client<Pose, Bench>("svc_fullshm");
      if (!client.wait_for_service(5s)) ::_exit(11);
      auto r = client.call(pose(1), 5s);
      if (r.ok()) ::_exit(12);
      if (r.error() != lcmx::CallErrc::handler_failed) ::_exit(13);
      if (r.message().find("the server could not reserve shared memory for its response (its handler did not "
                           "fail)") == std::string::npos)
        ::_exit(14);
      auto small = sn.create_service<Pose, Bench>("svc_fullshm_small", [](const Pose& p) { return answer(p); });
      auto small_client = cn.create_client<Pose, Bench>("svc_fullshm_small");
      if (!small_client.wait_for_service(5s) || !small_client.call(pose(2), 5s).ok()) ::_exit(15);
      rc = 0;
    } catch (...) {
      rc = 16;
    }
    ::_exit(rc);
  }
  int st = 0;
  REQUIRE(::waitpid(pid, &st, 0) == pid);
  REQUIRE(WIFEXITED(st));
  if (WEXITSTATUS(st) == 96) {
    WARN("cannot mount a private tmpfs on /dev/shm: skipped");
    return;
  }
  CHECK(WEXITSTATUS(st) == 0);
}

TEST_CASE("service: call() before any server finds it once it appears (no lost first call)",
          "[service]") {
  auto rt = lcmx::Runtime::create(test_options());
  auto cn = rt.create_node("client");
  auto client = cn.create_client<Pose, Bench>("svc_late");
  auto f = client.call_async(pose(3), 5s);  // no server yet: waits for one
  auto sn = rt.create_node("server");
  auto server = sn.create_service<Pose, Bench>("svc_late", [](const Pose& p) { return answer(p); });
  REQUIRE(f.wait_for(10s) == std::future_status::ready);
  auto r = f.get();
  REQUIRE(r.ok());
  CHECK(r.value().seq == 3);
}

TEST_CASE("service: errors are results: no server, timeout, handler threw, type mismatch",
          "[service]") {
  auto rt = lcmx::Runtime::create(test_options());
  auto sn = rt.create_node("server");
  auto cn = rt.create_node("client");

  SECTION("no server") {
    auto client = cn.create_client<Pose, Bench>("svc_none");
    CHECK_FALSE(client.wait_for_service(100ms));
    auto r = client.call(pose(1), 150ms);
    REQUIRE_FALSE(r.ok());
    CHECK(r.error() == lcmx::CallErrc::no_server);
    CHECK(r.message().find("svc_none") != std::string::npos);
    CHECK_THROWS_AS(r.value(), lcmx::CallError);
    CHECK(client.stats().pending == 0);
  }
  SECTION("timeout: the pending call is removed and a late reply dropped") {
    Gate gate;
    auto server = sn.create_service<Pose, Bench>("svc_slow", [&](const Pose& p) {
      gate.wait();
      return answer(p);
    });
    auto client = cn.create_client<Pose, Bench>("svc_slow");
    REQUIRE(client.wait_for_service(5s));
    auto r = client.call(pose(1), 100ms);
    REQUIRE_FALSE(r.ok());
    CHECK(r.error() == lcmx::CallErrc::timeout);
    CHECK(client.stats().pending == 0);
    CHECK(client.stats().timeouts == 1);
    gate.release();
    CHECK(eventually([&] { return client.stats().late_replies == 1; }));
    auto r2 = client.call(pose(2), 5s);  // the server still works
    REQUIRE(r2.ok());
    CHECK(r2.value().seq == 2);
  }
  SECTION("the handler throws") {
    auto server = sn.create_service<Pose, Bench>("svc_throw", [](const Pose& p) -> Bench {
      if (p.position[0] < 0) throw std::runtime_error("negative x is not allowed");
      return answer(p);
    });
    auto client = cn.create_client<Pose, Bench>("svc_throw");
    auto r = client.call(pose(-1), 5s);
    REQUIRE_FALSE(r.ok());
    CHECK(r.error() == lcmx::CallErrc::handler_failed);
    CHECK(r.message().find("negative x is not allowed") != std::string::npos);
    CHECK(client.call(pose(4), 5s).value().seq == 4);  // the server lives on
    CHECK(server.stats().failed == 1);
  }
  SECTION("type mismatch: reported with both sides' types, at once") {
    auto server = sn.create_service<Pose, Pose>("svc_types", [](const Pose& p) { return p; });
    auto client = cn.create_client<Pose, Bench>("svc_types");
    CHECK_FALSE(client.wait_for_service(300ms));  // a server of other types does not count
    auto r = client.call(pose(1), 300ms);
    REQUIRE_FALSE(r.ok());
    CHECK(r.error() == lcmx::CallErrc::type_mismatch);
    CHECK(r.message().find("pose_t") != std::string::npos);
    // A raw client takes any type.
    auto raw = cn.create_client_raw("svc_types");
    Pose p = pose(5);
    lcmx::Bytes req(static_cast<std::size_t>(p.getEncodedSize()));
    p.encode(req.data(), 0, static_cast<int>(req.size()));
    auto rr = raw.call(req, 5s);
    REQUIRE(rr.ok());
    Pose back;
    REQUIRE(back.decode(rr.value().data(), 0, static_cast<int>(rr.value().size())) > 0);
    CHECK(back.position[0] == 5);
  }
  SECTION("a request that does not decode") {
    auto server = sn.create_service<Pose, Bench>("svc_bad", [](const Pose& p) { return answer(p); });
    auto raw = cn.create_client_raw("svc_bad");
    const lcmx::Bytes junk(5, std::byte{0x42});
    auto r = raw.call(junk, 5s);
    REQUIRE_FALSE(r.ok());
    CHECK(r.error() == lcmx::CallErrc::bad_request);
  }
}

TEST_CASE("service: a raw server and client", "[service]") {
  auto rt = lcmx::Runtime::create(test_options());
  auto sn = rt.create_node("server");
  auto server = sn.create_service_raw("svc_raw", [](std::span<const std::byte> in) {
    lcmx::Bytes out(in.rbegin(), in.rend());
    return out;
  });
  auto client = sn.create_client_raw("svc_raw");  // a client on the server's own node: no deadlock
  const lcmx::Bytes req{std::byte{1}, std::byte{2}, std::byte{3}};
  auto r = client.call(req, 5s);
  REQUIRE(r.ok());
  CHECK(r.value() == lcmx::Bytes{std::byte{3}, std::byte{2}, std::byte{1}});
  auto empty = client.call({}, 5s);
  REQUIRE(empty.ok());
  CHECK(empty.value().empty());
  // The zero-copy form: in one process the reply's own buffer, valid after the call.
  auto retained = client.call_retained(req, 5s);
  REQUIRE(retained.ok());
  CHECK(retained.value().zero_copy);
  CHECK(lcmx::Bytes(retained.value().data.begin(), retained.value().data.end()) ==
        lcmx::Bytes{std::byte{3}, std::byte{2}, std::byte{1}});
  auto retained_empty = client.call_retained({}, 5s);
  REQUIRE(retained_empty.ok());
  CHECK(retained_empty.value().data.empty());

  // A handler that writes its response in place; one that writes nothing answers empty.
  auto in_place = sn.create_service_raw("svc_raw2", [](std::span<const std::byte> in, lcmx::ResponseWriter& out) {
    if (in.empty()) return;
    auto b = out.allocate(in.size() * 2);
    std::copy(in.begin(), in.end(), b.begin());
    std::copy(in.begin(), in.end(), b.begin() + static_cast<std::ptrdiff_t>(in.size()));
  });
  auto c2 = sn.create_client_raw("svc_raw2");
  auto r2 = c2.call(req, 5s);
  REQUIRE(r2.ok());
  CHECK(r2.value() == lcmx::Bytes{std::byte{1}, std::byte{2}, std::byte{3}, std::byte{1}, std::byte{2}, std::byte{3}});
  auto r3 = c2.call({}, 5s);
  REQUIRE(r3.ok());
  CHECK(r3.value().empty());
}

TEST_CASE("service: a blocking call from inside a callback of the client's node", "[service]") {
  auto rt = lcmx::Runtime::create(test_options());
  auto sn = rt.create_node("server");
  auto cn = rt.create_node("client");
  auto server = sn.create_service<Pose, Bench>("svc_nested", [](const Pose& p) { return answer(p); });
  auto client = cn.create_client<Pose, Bench>("svc_nested");
  std::promise<std::int64_t> got;
  auto pub = sn.advertise<Pose>("SVC_NESTED_TICK");
  auto sub = cn.subscribe<Pose>("SVC_NESTED_TICK", [&](const Pose& p) {
    got.set_value(client.call(p, 5s).value().seq);  // replies come on the client's own thread
  });
  REQUIRE(pub.wait_for_subscribers(1, 5s));
  pub.publish(pose(11));
  auto f = got.get_future();
  REQUIRE(f.wait_for(10s) == std::future_status::ready);
  CHECK(f.get() == 11);
}

TEST_CASE("service: many clients, two servers: each call executed once, replies to the asker only",
          "[service]") {
  auto rt = lcmx::Runtime::create(test_options());
  auto n1 = rt.create_node("server1");
  auto n2 = rt.create_node("server2");
  std::atomic<int> executed{0};
  auto handler = [&](const Pose& p) {
    ++executed;
    return answer(p);
  };
  auto s1 = n1.create_service<Pose, Bench>("svc_many", handler);
  auto s2 = n2.create_service<Pose, Bench>("svc_many", handler);
  constexpr int kClients = 8, kCalls = 50;
  std::vector<lcmx::Node> nodes;
  std::vector<lcmx::Client<Pose, Bench>> clients;
  for (int i = 0; i < kClients; ++i) {
    nodes.push_back(rt.create_node("client" + std::to_string(i)));
    clients.push_back(nodes.back().create_client<Pose, Bench>("svc_many"));
  }
  for (auto& c : clients) REQUIRE(c.wait_for_service(5s));
  // Every client eventually knows both servers, and they all choose the same one.
  for (auto& c : clients) REQUIRE(eventually([&] { return c.servers().size() == 2; }));
  const auto chosen = clients[0].servers()[0];
  for (auto& c : clients) CHECK(c.servers()[0].id == chosen.id);

  std::vector<std::thread> threads;
  std::atomic<int> wrong{0}, failed{0};
  for (int i = 0; i < kClients; ++i)
    threads.emplace_back([&, i] {
      for (int k = 0; k < kCalls; ++k) {
        const int x = i * 1000 + k;
        auto r = clients[static_cast<std::size_t>(i)].call(pose(x), 5s);
        if (!r.ok()) ++failed;
        else if (r.value().seq != x || r.server().id != chosen.id) ++wrong;
      }
    });
  for (auto& t : threads) t.join();
  CHECK(failed == 0);
  CHECK(wrong == 0);
  CHECK(executed == kClients * kCalls);
  CHECK(s1.stats().requests + s2.stats().requests == kClients * kCalls);
  CHECK((s1.stats().requests == 0 || s2.stats().requests == 0));  // one server took them all
  for (auto& c : clients) {
    CHECK(c.stats().late_replies == 0);
    CHECK(c.stats().replies == kCalls);
  }
}

TEST_CASE("service: a call fails over when its server goes before answering", "[service]") {
  auto rt = lcmx::Runtime::create(test_options());
  // Server A runs on a manual node: it answers probes while the test spins it, then stops
  // answering; it is the one calls go to (created first: the lower server id).
  auto na = rt.create_node("serverA", manual());
  auto nb = rt.create_node("serverB");
  auto cn = rt.create_node("client");
  std::atomic<int> a_calls{0};
  auto a = std::make_unique<lcmx::Service>(
      na.create_service<Pose, Bench>("svc_failover", [&](const Pose& p) {
        ++a_calls;
        return answer(p);
      }));
  auto b = nb.create_service<Pose, Bench>("svc_failover", [](const Pose& p) { return answer(p, 5); });
  auto client = cn.create_client<Pose, Bench>("svc_failover");
  REQUIRE(eventually([&] {
    na.spin_once(1ms);
    return client.servers().size() == 2;
  }));
  REQUIRE(client.servers()[0].id < client.servers()[1].id);  // same path: the lower id first
  auto f = client.call_async(pose(21), 5s);  // goes to A, which does not run now
  a.reset();                                 // A goes away before answering
  REQUIRE(f.wait_for(10s) == std::future_status::ready);
  auto r = f.get();
  REQUIRE(r.ok());
  CHECK(r.value().size == 5);  // B answered
  CHECK(a_calls == 0);
  CHECK(client.stats().failovers == 1);

  SECTION("and fails with server_gone when no other server is left") {
    Gate gate;
    auto nc = rt.create_node("serverC", manual());
    auto c = std::make_unique<lcmx::Service>(
        nc.create_service<Pose, Bench>("svc_gone", [](const Pose& p) { return answer(p); }));
    auto client2 = cn.create_client<Pose, Bench>("svc_gone");
    REQUIRE(eventually([&] {
      nc.spin_once(1ms);
      return client2.servers().size() == 1;
    }));
    auto f2 = client2.call_async(pose(1), 5s);
    c.reset();
    REQUIRE(f2.wait_for(10s) == std::future_status::ready);
    auto r2 = f2.get();
    REQUIRE_FALSE(r2.ok());
    CHECK(r2.error() == lcmx::CallErrc::server_gone);
  }
}

TEST_CASE("service: bad names are errors, and closing a client ends its calls", "[service]") {
  auto rt = lcmx::Runtime::create(test_options());
  auto n = rt.create_node("n");
  CHECK_THROWS_AS(n.create_client_raw(""), lcmx::Error);
  CHECK_THROWS_AS(n.create_client_raw(std::string(44, 'x')), lcmx::Error);
  CHECK_NOTHROW(n.create_client_raw(std::string(43, 'x')));
  CHECK_THROWS_AS(n.create_service_raw("ok", std::function<lcmx::Bytes(std::span<const std::byte>)>{}), lcmx::Error);
  CHECK_THROWS_AS((n.create_service<Pose, Bench>("ok", std::function<Bench(const Pose&)>{})), lcmx::Error);

  auto client = n.create_client<Pose, Bench>("svc_closed");
  auto f = client.call_async(pose(1), 10s);
  client.reset();
  REQUIRE(f.wait_for(5s) == std::future_status::ready);
  CHECK(f.get().error() == lcmx::CallErrc::shutdown);
}

TEST_CASE("service: the envelopes decode with lcm-gen's code (stock tools read them)", "[service]") {
  auto rt = lcmx::Runtime::create(test_options());
  auto n = rt.create_node("n");
  auto tap = rt.create_node("tap");
  std::mutex mu;
  std::vector<lcmx_msgs::service_request_t> requests;
  std::vector<lcmx_msgs::service_reply_t> replies;
  auto rq = tap.subscribe<lcmx_msgs::service_request_t>(
      "svc_wire/rq", [&](const lcmx_msgs::service_request_t& m) {
        std::lock_guard lock(mu);
        requests.push_back(m);
      });
  auto rp = tap.subscribe_channels(
      [](const std::string& c) { return c.rfind("svc_wire/rp/", 0) == 0; },
      [&](const lcmx::RawMessage& m) {
        lcmx_msgs::service_reply_t r;
        if (r.decode(m.data.data(), 0, static_cast<int>(m.data.size())) < 0) return;
        std::lock_guard lock(mu);
        replies.push_back(r);
      });
  auto server = n.create_service<Pose, Bench>("svc_wire", [](const Pose& p) { return answer(p, 4); });
  auto client = n.create_client<Pose, Bench>("svc_wire");
  REQUIRE(client.wait_for_service(5s));
  REQUIRE(eventually([&] {
    std::lock_guard lock(mu);
    return !replies.empty();  // the tap saw a probe's answer: it is subscribed to the channel
  }));
  REQUIRE(client.call(pose(42), 5s).ok());
  REQUIRE(eventually([&] {
    std::lock_guard lock(mu);
    return std::any_of(replies.begin(), replies.end(), [](auto& r) { return r.request_id != 0; }) &&
           std::any_of(requests.begin(), requests.end(), [](auto& r) { return r.request_id != 0; });
  }));
  std::lock_guard lock(mu);
  const auto& req = *std::find_if(requests.begin(), requests.end(), [](auto& r) { return r.request_id != 0; });
  CHECK(req.client_participant == static_cast<std::int64_t>(rt.participant_id()));
  CHECK(req.request_fingerprint == Pose::getHash());
  CHECK(req.response_fingerprint == Bench::getHash());
  CHECK(req.server_participant == static_cast<std::int64_t>(rt.participant_id()));
  CHECK(req.reply_channel.rfind("svc_wire/rp/", 0) == 0);
  CHECK(req.reply_channel.size() == std::string("svc_wire/rp/").size() + 16);
  Pose p;
  REQUIRE(req.size == static_cast<std::int32_t>(req.payload.size()));
  REQUIRE(p.decode(req.payload.data(), 0, req.size) > 0);
  CHECK(p.position[0] == 42);

  const auto& rep = *std::find_if(replies.begin(), replies.end(), [](auto& r) { return r.request_id != 0; });
  CHECK(rep.request_id == req.request_id);
  CHECK(rep.client_id == req.client_id);
  CHECK(rep.server_id == req.server_id);
  CHECK(rep.status == lcmx_msgs::service_reply_t::OK);
  CHECK(rep.request_type.find("pose_t") != std::string::npos);
  CHECK(rep.response_type.find("bench_t") != std::string::npos);
  Bench b;
  REQUIRE(b.decode(rep.payload.data(), 0, rep.size) > 0);
  CHECK(b.seq == 42);
  CHECK(b.size == 4);
}
