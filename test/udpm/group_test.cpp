// Group on lo in this network namespace: every test has its own group and port.
#include <catch2/catch.hpp>
#include <set>
#include <thread>

#include "support.hpp"

using namespace lcmx::udpm;
using namespace lcmx::udpm::test;

namespace {
struct Got {
  std::string channel;
  std::vector<std::byte> data;
  Source source;
  std::uint32_t sequence;
};
Group::Handler collect(std::vector<Got>& out) {
  return [&out](const Message& m) {
    out.push_back(Got{std::string(m.channel), {m.data.begin(), m.data.end()}, m.source, m.sequence});
  };
}
Error::Code open_error(const GroupConfig& cfg) {
  try {
    Group::open(cfg);
  } catch (const Error& e) {
    INFO(e.what());
    return e.code();
  }
  FAIL("Group::open did not throw");
  return Error::Code::system;
}
}  // namespace

TEST_CASE("Group::open reports bad configurations", "[integration][group]") {
  auto cfg = unique_config();
  SECTION("not multicast") {
    cfg.address = "127.0.0.1";
    CHECK(open_error(cfg) == Error::Code::invalid_config);
  }
  SECTION("not an address") {
    cfg.address = "239.1.2";
    CHECK(open_error(cfg) == Error::Code::invalid_config);
  }
  SECTION("port 0, ttl, buffer") {
    cfg.port = 0;
    CHECK(open_error(cfg) == Error::Code::invalid_config);
    cfg = unique_config();
    cfg.ttl = 256;
    CHECK(open_error(cfg) == Error::Code::invalid_config);
    cfg = unique_config();
    cfg.recv_buffer_bytes = -1;
    CHECK(open_error(cfg) == Error::Code::invalid_config);
  }
  SECTION("missing interface") {
    cfg.interface = "lcmx_nope0";
    CHECK(open_error(cfg) == Error::Code::no_such_interface);
  }
}

TEST_CASE("Group round-trips small and fragmented messages in order on lo", "[integration][group]") {
  const auto cfg = unique_config();
  auto rx = Group::open(cfg);
  auto tx = Group::open(cfg);
  CHECK(rx.fd() >= 0);
  CHECK(rx.effective_recv_buffer() >= cfg.recv_buffer_bytes);  // root: SO_RCVBUFFORCE
  CHECK(tx.local_source().address_be == htonl(INADDR_LOOPBACK));
  CHECK(tx.local_source().port_be != 0);
  CHECK_FALSE(tx.local_source() == rx.local_source());

  // sizes around the LC02/LC03 boundary, an empty message and 1 MB
  const std::string channel = "LCMX_ROUNDTRIP";
  const std::size_t boundary = kShortMessageMaxSize - channel.size() - 1;
  const std::vector<std::size_t> sizes = {0, 1, 100, 1400, boundary, boundary + 1, 65487, 200000, 1000000, 7};
  for (std::uint32_t i = 0; i < sizes.size(); ++i) tx.publish(channel, make_payload(i, sizes[i]));

  std::vector<Got> got;
  REQUIRE(poll_until(rx, collect(got), [&] { return got.size() >= sizes.size(); }));
  REQUIRE(got.size() == sizes.size());
  for (std::uint32_t i = 0; i < sizes.size(); ++i) {
    INFO("message " << i << " of " << sizes[i] << " bytes");
    CHECK(got[i].channel == channel);
    CHECK(got[i].data.size() == sizes[i]);
    CHECK(got[i].sequence == i);
    CHECK(got[i].source == tx.local_source());
    if (sizes[i] >= 4) CHECK(payload_index(got[i].data) == i);
    CHECK(payload_ok(got[i].data));
  }
  const auto& rc = rx.counters();
  CHECK(rc.messages_received == sizes.size());
  CHECK(rc.malformed_dropped == 0);
  CHECK(rc.incomplete_dropped == 0);
  std::size_t datagrams = 0, fragments = 0;
  for (auto s : sizes) {
    const auto n = datagram_count(channel.size(), s);
    datagrams += n;
    fragments += n > 1 ? n : 0;
  }
  CHECK(rc.packets_received == datagrams);
  CHECK(rc.fragments_received == fragments);
  const auto& tc = tx.counters();
  CHECK(tc.messages_sent == sizes.size());
  CHECK(tc.packets_sent == datagrams);
  // the sender hears itself too (multicast loop) and can tell by local_source()
  std::size_t own = 0;
  poll_until(tx, [&](const Message& m) { own += m.source == tx.local_source(); }, [&] { return own >= sizes.size(); });
  CHECK(own == sizes.size());
}

TEST_CASE("receive_own = false: the kernel drops the Group's own datagrams, others still hear them",
          "[integration][group]") {
  auto cfg = unique_config();
  auto rx = Group::open(cfg);
  cfg.receive_own = false;
  auto tx = Group::open(cfg);
  const std::string channel = "LCMX_OWN";
  tx.publish(channel, make_payload(0, 100));
  tx.publish(channel, make_payload(1, 200000));  // LC03 fragments
  std::vector<Got> got;
  REQUIRE(poll_until(rx, collect(got), [&] { return got.size() >= 2; }));
  // Every socket's copy of tx's datagrams was queued (or filtered) when rx got its copy, so
  // once tx hears rx's marker it would have heard its own messages before it.
  rx.publish(channel, make_payload(2, 10));
  std::vector<Got> own;
  REQUIRE(poll_until(tx, collect(own), [&] { return !own.empty(); }));
  tx.poll(0ms, collect(own));
  REQUIRE(own.size() == 1);
  CHECK(own[0].source == rx.local_source());
  CHECK(tx.counters().packets_received == 1);
  CHECK(tx.counters().malformed_dropped == 0);
}

TEST_CASE("Group::publish rejects bad channels and oversize payloads", "[integration][group]") {
  auto g = Group::open(unique_config());
  const std::byte b[1] = {};
  auto code = [&](auto&& f) {
    try {
      f();
    } catch (const Error& e) {
      return e.code();
    }
    return Error::Code::system;
  };
  CHECK(code([&] { g.publish(std::string(64, 'c'), b); }) == Error::Code::channel_too_long);
  CHECK(code([&] { g.publish(std::string_view("A\0B", 3), b); }) == Error::Code::invalid_channel);
  // A view larger than kMaxMessageSize; publish must refuse before reading it.
  CHECK(code([&] { g.publish("BIG", std::span<const std::byte>(b, kMaxMessageSize + 1)); }) ==
        Error::Code::message_too_large);
  CHECK_NOTHROW(g.publish(std::string(63, 'c'), b));
  CHECK(g.counters().messages_sent == 1);
}

TEST_CASE("A missing fragment drops only that message", "[integration][group][reassembly]") {
  auto cfg = unique_config();
  cfg.reassembly_timeout = std::chrono::milliseconds(50);
  auto rx = Group::open(cfg);
  RawSender raw(cfg);

  const auto a = make_payload(1, 300000);
  const auto b = make_payload(2, 300000);
  auto fa = lc03_message(100, "INJECT", a);
  const auto fb = lc03_message(101, "INJECT", b);
  REQUIRE(fa.size() == 5);
  fa.erase(fa.begin() + 2);  // lose one fragment of message A
  for (const auto& d : fa) raw.send(d);
  raw.send(lc02(102, "INJECT", make_payload(3, 10)));
  for (const auto& d : fb) raw.send(d);
  raw.send(lc02(103, "INJECT", make_payload(4, 10)));
  // garbage in between is counted and ignored
  raw.send(lc02(104, std::string(70, 'x'), make_payload(0, 100)));  // channel too long
  raw.send(lc03(105, 10, 20, 1, 2, std::nullopt, make_payload(0, 5)));

  std::vector<Got> got;
  REQUIRE(poll_until(rx, collect(got), [&] { return got.size() >= 3; }));
  // A partial message expires after reassembly_timeout without new fragments.
  REQUIRE(poll_until(rx, collect(got), [&] { return rx.counters().incomplete_dropped >= 1; }));
  REQUIRE(got.size() == 3);
  CHECK(got[0].sequence == 102);
  CHECK(got[1].sequence == 101);
  CHECK(got[1].data == b);
  CHECK(got[2].sequence == 103);
  for (const auto& g : got) CHECK(g.source == raw.source());
  const auto& c = rx.counters();
  CHECK(c.incomplete_dropped == 1);
  CHECK(c.malformed_dropped == 2);
  CHECK(c.messages_received == 3);
  CHECK(c.fragments_received == 4 + 5);
}

TEST_CASE("publish is thread-safe and keeps each message's fragments together", "[integration][group]") {
  const auto cfg = unique_config();
  auto rx = Group::open(cfg);
  auto tx = Group::open(cfg);
  constexpr int kThreads = 3, kEach = 10;
  std::vector<std::thread> threads;
  for (int t = 0; t < kThreads; ++t)
    threads.emplace_back([&tx, t] {
      for (int i = 0; i < kEach; ++i) {
        const auto idx = static_cast<std::uint32_t>(t * 100 + i);
        tx.publish("T" + std::to_string(t), make_payload(idx, i % 2 ? 70000 : 500));
      }
    });
  std::vector<Got> got;
  // Receive while the publishers run.
  const bool all = poll_until(rx, collect(got), [&] { return got.size() >= kThreads * kEach; }, 10000ms);
  for (auto& th : threads) th.join();
  REQUIRE(all);
  std::set<std::uint32_t> sequences;
  int next[kThreads] = {};
  for (const auto& g : got) {
    CHECK(payload_ok(g.data));
    sequences.insert(g.sequence);
    const int t = g.channel[1] - '0';
    CHECK(payload_index(g.data) == static_cast<std::uint32_t>(t * 100 + next[t]++));  // per-thread order
  }
  CHECK(sequences.size() == kThreads * kEach);  // no sequence number used twice
  CHECK(rx.counters().incomplete_dropped == 0);
}

TEST_CASE("Groups on other groups or ports do not hear each other", "[integration][group]") {
  auto a = unique_config("a");
  auto b = unique_config("b");
  b.port = a.port;  // same port, other group: IP_MULTICAST_ALL=0 keeps them apart
  auto ga = Group::open(a);
  auto gb = Group::open(b);
  gb.publish("B", make_payload(1, 10));
  ga.publish("A", make_payload(2, 10));
  std::vector<Got> got_a;
  REQUIRE(poll_until(ga, collect(got_a), [&] { return !got_a.empty(); }));
  std::vector<Got> got_b;
  REQUIRE(poll_until(gb, collect(got_b), [&] { return !got_b.empty(); }));
  // Drain whatever else is there (nothing should be).
  ga.poll(50ms, collect(got_a));
  gb.poll(50ms, collect(got_b));
  REQUIRE(got_a.size() == 1);
  REQUIRE(got_b.size() == 1);
  CHECK(got_a[0].channel == "A");
  CHECK(got_b[0].channel == "B");
}

TEST_CASE("drain resumes after a throwing callback without losing datagrams", "[integration][group]") {
  const auto cfg = unique_config();
  auto rx = Group::open(cfg);
  auto tx = Group::open(cfg);
  for (std::uint32_t i = 0; i < 5; ++i) tx.publish("R", make_payload(i, 20));
  std::vector<std::uint32_t> seen;
  bool thrown = false;
  auto handler = [&](const Message& m) {
    seen.push_back(m.sequence);
    if (m.sequence == 1 && !thrown) {
      thrown = true;
      throw std::runtime_error("callback failed");
    }
  };
  const auto deadline = Clock::now() + 5s;
  while (seen.size() < 5 && Clock::now() < deadline) {
    try {
      rx.poll(100ms, handler);
    } catch (const std::runtime_error&) {
    }
  }
  CHECK(thrown);
  CHECK(seen == std::vector<std::uint32_t>{0, 1, 2, 3, 4});
}

TEST_CASE("A message whose source and sequence were delivered already is dropped - also fragmented",
          "[integration][group][dedupe]") {
  auto cfg = unique_config();
  auto rx = Group::open(cfg);
  RawSender raw(cfg);
  const auto big = make_payload(7, 100000);
  const auto frags = lc03_message(20, "DUP", big);
  // 10, 11, 10 again, 12, 11 again (out of order), the fragmented 20 twice, 13; then a sender
  // far behind (a restart on the same port: sequence starts over) is delivered.
  raw.send(lc02(10, "DUP", make_payload(10, 10)));
  raw.send(lc02(11, "DUP", make_payload(11, 10)));
  raw.send(lc02(10, "DUP", make_payload(10, 10)));
  raw.send(lc02(12, "DUP", make_payload(12, 10)));
  raw.send(lc02(11, "DUP", make_payload(11, 10)));
  for (int twice = 0; twice < 2; ++twice)
    for (const auto& d : frags) raw.send(d);
  raw.send(lc02(13, "DUP", make_payload(13, 10)));
  raw.send(lc02(100000, "DUP", make_payload(14, 10)));
  raw.send(lc02(0, "DUP", make_payload(15, 10)));
  std::vector<Got> got;
  REQUIRE(poll_until(rx, collect(got), [&] { return rx.counters().duplicates_dropped >= 3 && got.size() >= 7; }));
  std::vector<std::uint32_t> seqs;
  for (const auto& g : got) seqs.push_back(g.sequence);
  CHECK(seqs == std::vector<std::uint32_t>{10, 11, 12, 20, 13, 100000, 0});
  CHECK(got[3].data == big);
  CHECK(rx.counters().duplicates_dropped == 3);
  CHECK(rx.counters().messages_received == 7);
}

TEST_CASE("lost_before counts the sequence numbers a source skipped, and a reassembled message comes with its buffer",
          "[integration][group][loss]") {
  auto cfg = unique_config();
  auto rx = Group::open(cfg);
  RawSender raw(cfg);
  const auto big = make_payload(9, 100000);
  raw.send(lc02(10, "LOSS", make_payload(10, 10)));
  raw.send(lc02(11, "LOSS", make_payload(11, 10)));
  raw.send(lc02(14, "LOSS", make_payload(14, 10)));              // 12 and 13 lost
  for (const auto& d : lc03_message(20, "LOSS", big)) raw.send(d);  // 15..19 lost
  raw.send(lc02(21, "LOSS", make_payload(21, 10)));
  raw.send(lc02(21 + 70000, "LOSS", make_payload(22, 10)));  // a jump this far: a restart, not loss
  raw.send(lc02(3, "LOSS", make_payload(23, 10)));           // far behind: a restart too
  raw.send(lc02(5, "LOSS", make_payload(24, 10)));           // 4 lost
  struct Seen {
    std::uint32_t sequence, lost;
    bool buffer;
    std::vector<std::byte> data;
  };
  std::vector<Seen> got;
  REQUIRE(poll_until(
      rx,
      [&](const Message& m) {
        got.push_back({m.sequence, m.lost_before, m.buffer != nullptr, {m.data.begin(), m.data.end()}});
        if (m.buffer) CHECK(m.data.data() == m.buffer.get());  // the message is the buffer
      },
      [&] { return got.size() >= 8; }));
  REQUIRE(got.size() == 8);
  std::vector<std::uint32_t> seqs, lost;
  for (const auto& g : got) seqs.push_back(g.sequence), lost.push_back(g.lost);
  CHECK(seqs == std::vector<std::uint32_t>{10, 11, 14, 20, 21, 21 + 70000, 3, 5});
  CHECK(lost == std::vector<std::uint32_t>{0, 0, 2, 5, 0, 0, 0, 1});
  CHECK(got[3].buffer);
  CHECK(got[3].data == big);
  for (std::size_t i = 0; i < got.size(); ++i)
    if (i != 3) CHECK_FALSE(got[i].buffer);
}
