// The receive filter (lcmx/udpm/filter.hpp) and the per-channel send counts (publish_counted).
// Groups on lo, each test its own group and port. What the kernel dropped is told apart from
// what user space dropped by the receiving Group's packets_received (datagrams read from the
// socket) against a *witness*: an unfiltered Group on the same group and port, which reads
// every datagram. Once the witness read a datagram, the kernel ran every socket's filter on it
// (it delivers a multicast datagram to all the port's sockets in one pass).
#include <linux/audit.h>
#include <linux/filter.h>
#include <linux/seccomp.h>
#include <sys/prctl.h>
#include <sys/syscall.h>

#include <catch2/catch.hpp>
#include <algorithm>
#include <atomic>
#include <bit>
#include <cstddef>
#include <map>
#include <mutex>
#include <set>
#include <thread>

#include "reassembler.hpp"
#include "socket_filter.hpp"
#include "support.hpp"

using namespace lcmx::udpm;
using namespace lcmx::udpm::test;

namespace filter_test {

std::vector<std::byte> bytes(std::initializer_list<int> v) {
  std::vector<std::byte> out;
  for (int b : v) out.push_back(static_cast<std::byte>(b));
  return out;
}
std::vector<std::byte> bytes(std::string_view s) {
  std::vector<std::byte> out;
  for (char c : s) out.push_back(static_cast<std::byte>(c));
  return out;
}
std::vector<std::byte> concat(std::vector<std::byte> a, const std::vector<std::byte>& b) {
  a.insert(a.end(), b.begin(), b.end());
  return a;
}

std::shared_ptr<const GroupKeys> group_keys(std::vector<GroupKey> k, bool encrypt = false) {
  auto g = std::make_shared<GroupKeys>();
  g->keys = std::move(k);
  g->encrypt = encrypt;
  return g;
}
GroupKey key_of(std::uint8_t fill) {
  std::array<std::uint8_t, kKeySize> b{};
  for (std::size_t i = 0; i < b.size(); ++i) b[i] = static_cast<std::uint8_t>(fill * 7 + i);
  return make_key(b);
}

ReceiveFilter only(std::vector<std::string> channels) {
  ReceiveFilter f;
  f.channels = std::move(channels);
  return f;
}

// A message heard: who sent it, with what sequence number, on which channel.
struct Heard {
  Source source;
  std::uint32_t sequence;
  std::string channel;
  std::size_t size;
  friend bool operator<(const Heard& a, const Heard& b) {
    return std::tie(a.source.address_be, a.source.port_be, a.sequence) <
           std::tie(b.source.address_be, b.source.port_be, b.sequence);
  }
  friend bool operator==(const Heard& a, const Heard& b) {
    return a.source == b.source && a.sequence == b.sequence && a.channel == b.channel && a.size == b.size;
  }
};
Group::Handler into(std::vector<Heard>& out) {
  return [&out](const Message& m) {
    out.push_back(Heard{m.source, m.sequence, std::string(m.channel), m.data.size()});
  };
}
const Group::Handler ignore = [](const Message&) {};

// Reads `witness` until it read `n` datagrams in all (every socket's filter then ran on them).
void witness_reads(Group& witness, std::uint64_t n) {
  REQUIRE(poll_until(witness, ignore, [&] { return witness.counters().packets_received >= n; }));
  REQUIRE(witness.counters().packets_received == n);
}

// True when the socket is readable right now.
bool readable(const Group& g) {
  pollfd p{g.fd(), POLLIN, 0};
  return ::poll(&p, 1, 0) == 1;
}

// Drains everything queued now (the socket is not readable afterwards).
void drain_all(Group& g, std::vector<Heard>& out) {
  for (int guard = 0; guard < 1000 && readable(g); ++guard) g.drain(into(out));
  REQUIRE_FALSE(readable(g));
}

std::vector<Heard> sorted(std::vector<Heard> v) {
  std::sort(v.begin(), v.end());
  return v;
}

}  // namespace filter_test

using namespace filter_test;

// ---------------------------------------------------------------- the rule alone

TEST_CASE("filter: the rule takes exact channel names and the control channel's marks", "[unit][filter]") {
  const Source a{0x0100007f, 0x1111}, b{0x0100007f, 0x2222};
  const auto prefix = bytes({1, 2, 3, 4, 5, 6, 7, 8});
  const auto mark = concat(prefix, bytes({9}));
  const auto not_mark = bytes({1, 2, 3, 4, 5, 6, 7, 9});

  detail::FilterRule all;
  CHECK(all.everything());
  CHECK(all.takes("ANY", {}, a));

  ReceiveFilter f = only({"AB", "POSE", "POSE"});
  detail::FilterRule r(f);
  CHECK_FALSE(r.everything());
  CHECK(r.takes("AB", {}, a));
  CHECK(r.takes("POSE", {}, a));
  for (const char* refused : {"A", "ABC", "", "POS", "POSEX", "pose", "LCMX_BEACON"}) {
    INFO(refused);
    CHECK_FALSE(r.takes(refused, {}, a));
  }

  f.control_channel = "LCMX_BEACON";  // control_all: every datagram of it
  CHECK(detail::FilterRule(f).takes("LCMX_BEACON", {}, a));
  CHECK_FALSE(detail::FilterRule(f).takes("LCMX_BEACONX", prefix, a));
  f.control_all = false;
  f.mark_prefix = prefix;
  detail::FilterRule marks(f);
  CHECK(marks.takes("LCMX_BEACON", mark, a));
  CHECK(marks.takes("LCMX_BEACON", prefix, b));  // exactly the prefix is a mark
  CHECK_FALSE(marks.takes("LCMX_BEACON", not_mark, a));
  CHECK_FALSE(marks.takes("LCMX_BEACON", std::span(prefix).first(7), a));  // too short
  CHECK_FALSE(marks.takes("LCMX_BEACON", {}, a));
  f.mark_sources = std::vector<Source>{a};
  f.channels->push_back("LCMX_BEACON");  // judged apart all the same
  detail::FilterRule from_a(f);
  CHECK(from_a.takes("LCMX_BEACON", mark, a));
  CHECK_FALSE(from_a.takes("LCMX_BEACON", mark, b));
  CHECK_FALSE(from_a.takes("LCMX_BEACON", not_mark, a));
  CHECK(from_a.takes("AB", {}, b));

  // No channels list: every other channel.
  ReceiveFilter g;
  g.control_channel = "C";
  g.control_all = false;
  detail::FilterRule rest(g);
  CHECK(rest.takes("ANY", {}, a));
  CHECK(rest.takes("C", {}, a));  // an empty prefix: every datagram of it is a mark
  CHECK(takes_everything(ReceiveFilter{}));
  CHECK_FALSE(takes_everything(g));
}

TEST_CASE("filter: set_filter refuses bad filters and keeps the one in force", "[integration][filter]") {
  auto g = Group::open(unique_config());
  CHECK(g.filter() == ReceiveFilter{});
  CHECK(g.kernel_filtered());
  const auto good = only({"GOOD"});
  CHECK(g.set_filter(good));
  auto refused = [&](const ReceiveFilter& f) {
    try {
      g.set_filter(f);
    } catch (const Error& e) {
      INFO(e.what());
      CHECK(e.code() == Error::Code::invalid_config);
      CHECK(g.filter() == good);
      return true;
    }
    return false;
  };
  CHECK(refused(only({std::string(64, 'x')})));
  CHECK(refused(only({std::string("A\0B", 3)})));
  ReceiveFilter f;
  f.control_channel = std::string(64, 'c');
  CHECK(refused(f));
  f = ReceiveFilter{};
  f.control_channel = "C";
  f.mark_prefix.assign(kMaxMarkPrefix + 1, std::byte{1});
  CHECK(refused(f));
  f.mark_prefix.resize(kMaxMarkPrefix);
  CHECK(g.set_filter(f));
  CHECK(g.filter() == f);
}

// ---------------------------------------------------------------- the kernel program

TEST_CASE("filter: the kernel program's size and limits", "[unit][filter]") {
  using detail::KernelPart;
  detail::ProgramSpec spec;
  // Nothing to drop: no program at all.
  CHECK(detail::socket_program(spec, ReceiveFilter{}, KernelPart::whole)->empty());
  ReceiveFilter f;
  f.control_channel = "LCMX_BEACON";  // control_all: takes everything
  CHECK(detail::socket_program(spec, f, KernelPart::whole)->empty());
  spec.drop_own = true;
  spec.own_port_be = htons(1234);
  spec.own_addresses = {htonl(INADDR_LOOPBACK)};
  const auto own = detail::socket_program(spec, ReceiveFilter{}, KernelPart::whole);
  REQUIRE(own);
  CHECK(own->size() == 7);

  // How many channels fit 4096 instructions: the documented figures (filter.hpp).
  auto fits = [&](std::size_t n, std::size_t length, bool keyed) {
    ReceiveFilter c;
    c.channels.emplace();
    for (std::size_t i = 0; i < n; ++i) {
      std::string name = std::to_string(i);
      name.insert(0, length - name.size(), 'c');
      c.channels->push_back(name);
    }
    detail::ProgramSpec s = spec;
    if (keyed) s.key_ids = std::vector<std::uint32_t>{1, 2};
    const auto p = detail::socket_program(s, c, KernelPart::whole);
    if (p) CHECK(p->size() <= detail::kMaxInstructions);
    return p.has_value();
  };
  // A channel of n bytes: its length check (2), a compare per 4 bytes of name + NUL (2 each, the
  // last 2-3 bytes taking one or two more), its return.
  CHECK(fits(116, 63, false));
  CHECK_FALSE(fits(117, 63, false));
  CHECK(fits(116, 63, true));  // two key ids: 7 more instructions
  CHECK_FALSE(fits(117, 63, true));
  CHECK(fits(371, 15, false));  // 15 bytes + NUL: 4 words
  CHECK_FALSE(fits(372, 15, false));
  CHECK(fits(371, 12, false));  // 12 bytes + NUL: 3 words and a byte
  CHECK(fits(453, 6, false));   // 6 bytes + NUL: a word, a half-word and a byte
  CHECK_FALSE(fits(454, 6, false));

  ReceiveFilter m;
  m.channels = std::vector<std::string>{};
  m.control_channel = "LCMX_BEACON";
  m.control_all = false;
  m.mark_prefix.assign(8, std::byte{7});
  m.mark_sources.emplace();
  for (std::uint16_t i = 0; i < 813; ++i) m.mark_sources->push_back(Source{htonl(INADDR_LOOPBACK), htons(i)});
  CHECK(detail::socket_program(spec, m, KernelPart::whole));
  m.mark_sources->push_back(Source{htonl(INADDR_LOOPBACK), 1});
  CHECK_FALSE(detail::socket_program(spec, m, KernelPart::whole));
  // What it falls back to: without the sources (marks of any sender), then the own drop.
  CHECK(detail::socket_program(spec, m, KernelPart::without_sources));
  const auto own_only = detail::socket_program(spec, m, KernelPart::own_only);
  REQUIRE(own_only);
  REQUIRE(own_only->size() == own->size());
  CHECK(std::memcmp(own_only->data(), own->data(), own->size() * sizeof(sock_filter)) == 0);
}

TEST_CASE("filter: channels are taken by exact name in the kernel - prefixes, longer names, the NUL",
          "[integration][filter]") {
  const auto cfg = unique_config();
  auto rx = Group::open(cfg);
  auto queued = Group::open(cfg);  // the same rule applied later, in user space
  auto witness = Group::open(cfg);
  RawSender raw(cfg);
  const std::string x63(63, 'X');
  // Sorted, "X" comes after longer names: a datagram of X with an empty payload (10 bytes)
  // is shorter than their compares, which must not end the program (a load past the end drops).
  const std::vector<std::string> taken = {"AB", "POSE", "ABCDEFG", "LCMX_POSE_1", x63, "X", "ABCD"};
  const ReceiveFilter f = only(taken);
  REQUIRE(rx.set_filter(f));
  CHECK(rx.kernel_filtered());
  CHECK(rx.filter() == f);
  const std::vector<std::string> others = {"A",        "ABC",        "ABD",         "AC",          "POS",
                                           "POSEX",    "POSE_",      "pose",        "ABCDEF",      "ABCDEFGH",
                                           "ABCDEFF",  "ABCDE",      "ABC",         "",            "LCMX_POSE_2",
                                           "LCMX_POSE_", "LCMX_POSE_11", "B",       x63.substr(1), x63.substr(1) + "Y",
                                           "XX",       "Y"};
  std::vector<std::string> corpus = taken;
  corpus.insert(corpus.end(), others.begin(), others.end());
  std::vector<Heard> expected;
  std::uint32_t seq = 0;
  std::uint64_t refused = 0;
  for (const std::size_t size : {0, 1, 3, 64}) {
    for (const auto& c : corpus) {
      raw.send(lc02(seq, c, make_payload(seq, size)));
      if (std::find(taken.begin(), taken.end(), c) != taken.end())
        expected.push_back(Heard{raw.source(), seq, c, size});
      else
        ++refused;
      ++seq;
    }
  }
  witness_reads(witness, seq);
  std::vector<Heard> got;
  drain_all(rx, got);
  CHECK(got == expected);
  CHECK(rx.counters().packets_received == expected.size());  // the kernel dropped the rest
  CHECK(rx.counters().filtered_dropped == 0);

  // Queued before the filter: the same verdicts, from user space.
  CHECK(queued.set_filter(f));
  std::vector<Heard> later;
  drain_all(queued, later);
  CHECK(later == expected);
  CHECK(queued.counters().packets_received == seq);
  CHECK(queued.counters().filtered_dropped == refused);

  // Through Groups too (their channels, any payload), and the default filter again.
  auto tx = Group::open(cfg);
  const auto s1 = tx.publish("POSE", make_payload(1, 10));
  tx.publish("POSEX", make_payload(2, 10));
  const auto s3 = tx.publish("X", {});
  witness_reads(witness, seq + 3);
  got.clear();
  drain_all(rx, got);
  CHECK(got == std::vector<Heard>{{tx.local_source(), s1, "POSE", 10}, {tx.local_source(), s3, "X", 0}});
  CHECK(rx.set_filter(ReceiveFilter{}));
  tx.publish("POSEX", make_payload(3, 10));
  witness_reads(witness, seq + 4);
  got.clear();
  drain_all(rx, got);
  REQUIRE(got.size() == 1);
  CHECK(got[0].channel == "POSEX");
}

TEST_CASE("filter: refused datagrams never wake the socket", "[integration][filter]") {
  const auto cfg = unique_config();
  auto rx = Group::open(cfg);
  auto witness = Group::open(cfg);
  auto tx = Group::open(cfg);
  REQUIRE(rx.set_filter(only({"LCMX_WANTED"})));
  constexpr int kRefused = 500;
  for (int i = 0; i < kRefused; ++i) tx.publish(i % 2 ? "LCMX_OTHER" : "LCMX_WANTE", make_payload(i, 100));
  witness_reads(witness, kRefused);
  CHECK_FALSE(readable(rx));  // the kernel queued none of them
  rx.drain(ignore);
  CHECK(rx.counters().packets_received == 0);
  tx.publish("LCMX_WANTED", make_payload(1, 100));
  pollfd p{rx.fd(), POLLIN, 0};
  REQUIRE(::poll(&p, 1, 5000) == 1);
  std::vector<Heard> got;
  drain_all(rx, got);
  REQUIRE(got.size() == 1);
  CHECK(got[0].channel == "LCMX_WANTED");
  CHECK(rx.counters().packets_received == 1);
  CHECK(rx.counters().filtered_dropped == 0);
  CHECK(rx.counters().kernel_dropped == kRefused);  // the socket's drop count (SO_RXQ_OVFL) says so too
}

TEST_CASE("filter: LC03 is always taken, a refused message's fragments are never counted incomplete, a lost "
          "fragment 0 still is",
          "[integration][filter][reassembly]") {
  auto cfg = unique_config();
  cfg.reassembly_timeout = std::chrono::milliseconds(50);
  auto rx = Group::open(cfg);
  auto witness = Group::open(cfg);
  auto tx = Group::open(cfg);
  RawSender raw(cfg);
  REQUIRE(rx.set_filter(only({"BIG"})));
  const auto big = make_payload(1, 200000);
  const std::size_t frags = datagram_count(3, big.size());
  REQUIRE(frags == 4);
  tx.publish("BIG_OTHER", big);
  const auto taken = tx.publish("BIG", big);
  // Fragments that overtook their fragment 0, then it: the same message, dropped with it.
  auto reordered = lc03_message(50, "OTHER", big);
  raw.send(reordered[2]);
  raw.send(reordered[1]);
  raw.send(reordered[0]);
  raw.send(reordered[3]);
  // A message of a channel taken whose fragment 0 never came: real loss.
  auto lost = lc03_message(60, "BIG", big);
  for (std::size_t i = 1; i < lost.size(); ++i) raw.send(lost[i]);
  witness_reads(witness, 2 * frags + 4 + (frags - 1));

  std::vector<Heard> got;
  REQUIRE(poll_until(rx, into(got), [&] { return rx.counters().incomplete_dropped >= 1; }));
  CHECK(got == std::vector<Heard>{{tx.local_source(), taken, "BIG", big.size()}});
  const auto& c = rx.counters();
  CHECK(c.packets_received == 2 * frags + 4 + (frags - 1));  // every LC03 datagram reached the socket
  CHECK(c.fragments_received == c.packets_received);
  CHECK(c.filtered_dropped == frags + 4);
  CHECK(c.incomplete_dropped == 1);  // the lost one alone, expired with (or after) the others
  CHECK(c.malformed_dropped == 0);
  CHECK(c.messages_received == 1);
}

TEST_CASE("filter: changing the filter applies to datagrams queued before", "[integration][filter]") {
  const auto cfg = unique_config();
  auto rx = Group::open(cfg);
  auto witness = Group::open(cfg);
  auto tx = Group::open(cfg);
  RawSender raw(cfg);
  const auto a1 = tx.publish("A", make_payload(1, 10));
  tx.publish("B", make_payload(2, 10));
  witness_reads(witness, 2);
  REQUIRE(rx.set_filter(only({"A"})));  // B was queued already
  const auto b3 = tx.publish("B", make_payload(3, 10));
  const auto a4 = tx.publish("A", make_payload(4, 10));
  witness_reads(witness, 4);
  std::vector<Heard> got;
  drain_all(rx, got);
  // The B sent under the filter {A} was dropped by the kernel; the one queued before, in user space.
  CHECK(got == std::vector<Heard>{{tx.local_source(), a1, "A", 10}, {tx.local_source(), a4, "A", 10}});
  CHECK(rx.counters().filtered_dropped == 1);
  CHECK(rx.counters().packets_received == 3);
  (void)b3;

  // Now A queued, then a filter that refuses it.
  tx.publish("A", make_payload(5, 10));
  witness_reads(witness, 5);
  REQUIRE(rx.set_filter(only({"B"})));
  const auto b6 = tx.publish("B", make_payload(6, 10));
  witness_reads(witness, 6);
  got.clear();
  drain_all(rx, got);
  CHECK(got == std::vector<Heard>{{tx.local_source(), b6, "B", 10}});
  CHECK(rx.counters().filtered_dropped == 2);

  // An LC03 message taken at its fragment 0 and refused by the time it completes.
  const auto big = make_payload(7, 150000);
  const auto frags = lc03_message(90, "B", big);
  raw.send(frags[0]);
  witness_reads(witness, 7);
  REQUIRE(poll_until(rx, into(got), [&] { return rx.counters().fragments_received == 1; }));
  REQUIRE(rx.set_filter(only({"A"})));
  for (std::size_t i = 1; i < frags.size(); ++i) raw.send(frags[i]);
  witness_reads(witness, 6 + frags.size());
  drain_all(rx, got);
  CHECK(got.size() == 1);  // b6 alone
  CHECK(rx.counters().filtered_dropped == 3);
  CHECK(rx.counters().fragments_received == frags.size());
  rx.drain(ignore);
  CHECK(rx.counters().incomplete_dropped == 0);
}

TEST_CASE("filter: the control channel - every datagram, marks only, marks of listed sources only",
          "[integration][filter]") {
  const auto cfg = unique_config();
  const std::string control = "LCMX_BEACON";
  const auto prefix = bytes({0x8a, 0x11, 0x02, 0x33, 0x44, 0x55, 0x66, 0x77});
  struct Case {
    const char* name;
    ReceiveFilter filter;
  };
  std::vector<Case> cases(5);
  cases[0].name = "control_all, channels {DATA}";
  cases[0].filter = only({"DATA"});
  cases[0].filter.control_channel = control;
  cases[1].name = "marks only, every other channel";
  cases[1].filter.control_channel = control;
  cases[1].filter.control_all = false;
  cases[1].filter.mark_prefix = prefix;
  cases[2].name = "marks of A only, channels {DATA, the control channel}";
  cases[2].filter = only({"DATA", control});
  cases[2].filter.control_channel = control;
  cases[2].filter.control_all = false;
  cases[2].filter.mark_prefix = prefix;
  cases[3].name = "every datagram of B (empty prefix), no other channel";
  cases[3].filter = only({});
  cases[3].filter.control_channel = control;
  cases[3].filter.control_all = false;
  cases[4].name = "marks of B, channels {LCMX_BEACONX}";
  cases[4].filter = only({"LCMX_BEACONX"});
  cases[4].filter.control_channel = control;
  cases[4].filter.control_all = false;
  cases[4].filter.mark_prefix = prefix;

  const auto i = GENERATE(0, 1, 2, 3, 4);
  Case& k = cases[static_cast<std::size_t>(i)];
  INFO(k.name);
  auto rx = Group::open(cfg);
  auto queued = Group::open(cfg);
  auto witness = Group::open(cfg);
  auto a = Group::open(cfg);
  auto b = Group::open(cfg);
  if (i == 2) k.filter.mark_sources = std::vector<Source>{a.local_source()};
  if (i == 3 || i == 4) k.filter.mark_sources = std::vector<Source>{b.local_source()};
  REQUIRE(rx.set_filter(k.filter));
  const detail::FilterRule rule(k.filter);

  struct Sent {
    Group* from;
    std::string channel;
    std::vector<std::byte> payload;
  };
  std::vector<Sent> plan;
  for (Group* g : {&a, &b}) {
    plan.push_back({g, control, concat(prefix, bytes("mark"))});
    plan.push_back({g, control, prefix});                                      // exactly the prefix: a mark
    plan.push_back({g, control, std::vector<std::byte>(prefix.begin(), prefix.end() - 1)});  // too short
    plan.push_back({g, control, concat(bytes({0x8a, 0x11, 0x02, 0x33, 0x44, 0x55, 0x66, 0x78}), bytes("x"))});
    plan.push_back({g, control, concat(bytes({0x8b}), std::vector<std::byte>(prefix.begin() + 1, prefix.end()))});
    plan.push_back({g, control, {}});
    plan.push_back({g, control + "X", concat(prefix, bytes("longer name"))});
    plan.push_back({g, "LCMX_BEACO", concat(prefix, bytes("shorter name"))});
    plan.push_back({g, "DATA", bytes("data")});
    plan.push_back({g, "OTHER", bytes("other")});
  }
  std::vector<Heard> expected;
  for (const auto& s : plan) {
    const auto seq = s.from->publish(s.channel, s.payload);
    if (rule.takes(s.channel, s.payload, s.from->local_source()))
      expected.push_back(Heard{s.from->local_source(), seq, s.channel, s.payload.size()});
  }
  // What each case must take, written out (the rule is checked above; this checks the plan).
  const std::size_t want[] = {2 * 7, 2 * 2 + 2 * 4, 1 * 2 + 2, 6, 2 + 2};
  CHECK(expected.size() == want[i]);
  witness_reads(witness, plan.size());
  std::vector<Heard> got;
  drain_all(rx, got);
  CHECK(sorted(got) == sorted(expected));
  CHECK(rx.kernel_filtered());
  CHECK(rx.counters().packets_received == expected.size());  // all refused in the kernel
  CHECK(rx.counters().filtered_dropped == 0);
  // And in user space, for datagrams queued before.
  CHECK(queued.set_filter(k.filter));
  std::vector<Heard> later;
  drain_all(queued, later);
  CHECK(sorted(later) == sorted(expected));
  CHECK(queued.counters().filtered_dropped == plan.size() - expected.size());
}

namespace filter_test {
// An LCM string: big-endian int32 length counting the NUL, the bytes, the NUL.
std::vector<std::byte> lcm_string(std::string_view s) {
  const auto n = static_cast<std::uint32_t>(s.size() + 1);
  auto out = bytes({static_cast<int>(n >> 24), static_cast<int>((n >> 16) & 0xff), static_cast<int>((n >> 8) & 0xff),
                    static_cast<int>(n & 0xff)});
  out = concat(out, bytes(s));
  out.push_back(std::byte{0});
  return out;
}
}  // namespace filter_test

// The data markers of lcmx (lcmx_msgs::marker_t) name their channel: a socket takes only those
// of the channels it reads, whoever sends them (its filter need not know the senders yet).
TEST_CASE("filter: marks naming a channel are taken only for the channels taken - exact names, in the kernel and "
          "in user space",
          "[integration][filter]") {
  const auto cfg = unique_config();
  const std::string control = "LCMX_BEACON";
  const auto prefix = bytes({0x8a, 0x11, 0x02, 0x33, 0x44, 0x55, 0x66, 0x77});
  const auto filler = std::vector<std::byte>(20, std::byte{0x5a});  // version, participant, host
  auto mark = [&](std::vector<std::byte> name) { return concat(concat(prefix, filler), std::move(name)); };
  ReceiveFilter f = only({"DATA", "DATA_2"});
  f.control_channel = control;
  f.control_all = false;
  f.mark_prefix = prefix;
  f.mark_channel_at = 28;
  auto rx = Group::open(cfg);
  auto queued = Group::open(cfg);
  auto witness = Group::open(cfg);
  auto tx = Group::open(cfg);
  REQUIRE(rx.set_filter(f));
  const detail::FilterRule rule(f);
  std::vector<std::pair<std::string, std::vector<std::byte>>> plan = {
      {control, mark(lcm_string("DATA"))},                                  // taken
      {control, concat(mark(lcm_string("DATA_2")), bytes("count"))},        // taken (bytes after it)
      {control, mark(lcm_string("DAT"))},                                   // a prefix of a name
      {control, mark(lcm_string("DATA_"))},                                 // longer than one, shorter than the other
      {control, mark(lcm_string("OTHER"))},
      {control, mark(bytes({0, 0, 0, 5, 'D', 'A', 'T', 'A', 'X'}))},         // no NUL where the length says
      {control, mark(bytes({0, 0, 0, 6, 'D', 'A', 'T', 'A', 0}))},           // the length says one more
      {control, mark(bytes({0, 0, 0, 5, 'D', 'A'}))},                        // cut short
      {control, concat(prefix, lcm_string("DATA"))},                        // the name elsewhere
      {"DATA", bytes("data")},                                              // data of a channel taken
      {"OTHER", bytes("other")}};
  std::vector<Heard> expected;
  for (const auto& [channel, payload] : plan) {
    const auto seq = tx.publish(channel, payload);
    if (rule.takes(channel, payload, tx.local_source())) expected.push_back(Heard{tx.local_source(), seq, channel, payload.size()});
  }
  CHECK(expected.size() == 3);  // the two marks of DATA and DATA_2, and DATA's data
  witness_reads(witness, plan.size());
  std::vector<Heard> got;
  drain_all(rx, got);
  CHECK(sorted(got) == sorted(expected));
  CHECK(rx.kernel_filtered());
  CHECK(rx.counters().packets_received == expected.size());  // the rest refused in the kernel
  CHECK(queued.set_filter(f));
  std::vector<Heard> later;
  drain_all(queued, later);
  CHECK(sorted(later) == sorted(expected));
  CHECK(queued.counters().filtered_dropped == plan.size() - expected.size());
}

TEST_CASE("filter: own datagrams are still dropped with a filter, also one the kernel holds in part",
          "[integration][filter]") {
  auto cfg = unique_config();
  auto witness = Group::open(cfg);
  auto other = Group::open(cfg);
  cfg.receive_own = false;
  auto self = Group::open(cfg);
  REQUIRE(self.set_filter(only({"X"})));
  for (int i = 0; i < 3; ++i) self.publish("X", make_payload(i, 10)), self.publish("Y", make_payload(i, 10));
  const auto x1 = other.publish("X", make_payload(7, 10));
  other.publish("Y", make_payload(8, 10));
  witness_reads(witness, 8);
  std::vector<Heard> got;
  drain_all(self, got);
  CHECK(got == std::vector<Heard>{{other.local_source(), x1, "X", 10}});
  CHECK(self.counters().packets_received == 1);

  // A filter too large for the kernel: its channels are judged in user space, own datagrams
  // still never reach the socket.
  ReceiveFilter large = only({"X"});
  for (int i = 0; i < 200; ++i) large.channels->push_back(std::string(60, 'c') + std::to_string(100 + i));
  CHECK_FALSE(self.set_filter(large));
  CHECK_FALSE(self.kernel_filtered());
  self.publish("X", make_payload(9, 10));
  self.publish("Y", make_payload(10, 10));
  const auto x2 = other.publish("X", make_payload(11, 10));
  other.publish("Y", make_payload(12, 10));
  witness_reads(witness, 12);
  got.clear();
  drain_all(self, got);
  CHECK(got == std::vector<Heard>{{other.local_source(), x2, "X", 10}});
  CHECK(self.counters().packets_received == 1 + 2);  // other's two: the own two never came
  CHECK(self.counters().filtered_dropped == 1);
}

TEST_CASE("filter: a filter too large for BPF falls back honestly - the kernel keeps what it can",
          "[integration][filter]") {
  const auto cfg = unique_config();
  auto rx = Group::open(cfg);
  auto witness = Group::open(cfg);
  auto a = Group::open(cfg);
  auto b = Group::open(cfg);
  const auto prefix = bytes({1, 2, 3, 4, 5, 6, 7, 8});
  ReceiveFilter f = only({"TAKEN"});
  for (int i = 0; i < 200; ++i) f.channels->push_back(std::string(60, 'c') + std::to_string(100 + i));
  f.control_channel = "LCMX_BEACON";
  f.control_all = false;
  f.mark_prefix = prefix;
  CHECK_FALSE(rx.set_filter(f));
  CHECK_FALSE(rx.kernel_filtered());

  std::vector<Heard> expected;
  auto expect = [&](Group& g, const std::string& c, const std::vector<std::byte>& p) {
    expected.push_back(Heard{g.local_source(), g.publish(c, p), c, p.size()});
  };
  for (int i = 0; i < 5; ++i) a.publish("REFUSED", make_payload(i, 10));  // reach the socket
  expect(a, "TAKEN", make_payload(1, 10));
  expect(a, f.channels->back(), make_payload(2, 10));
  for (int i = 0; i < 4; ++i) a.publish("LCMX_BEACON", bytes("not a mark"));  // dropped in the kernel
  expect(a, "LCMX_BEACON", concat(prefix, bytes("!")));
  witness_reads(witness, 12);
  std::vector<Heard> got;
  drain_all(rx, got);
  CHECK(got == expected);
  CHECK(rx.counters().packets_received == 5 + 3);
  CHECK(rx.counters().filtered_dropped == 5);

  // Too many mark sources: marks of any sender pass the kernel, non-marks still do not.
  ReceiveFilter m;
  m.control_channel = "LCMX_BEACON";
  m.control_all = false;
  m.mark_prefix = prefix;
  m.mark_sources.emplace();
  for (std::uint16_t i = 1; i <= 1000; ++i) m.mark_sources->push_back(Source{htonl(0x0a000000u + i), htons(i)});
  m.mark_sources->push_back(a.local_source());
  CHECK_FALSE(rx.set_filter(m));
  expected.clear();
  for (int i = 0; i < 3; ++i) b.publish("LCMX_BEACON", concat(prefix, bytes("b")));  // a mark, not listed
  for (int i = 0; i < 3; ++i) b.publish("LCMX_BEACON", bytes("not a mark"));
  expect(a, "LCMX_BEACON", concat(prefix, bytes("a")));
  expect(b, "OTHER", bytes("any channel"));
  witness_reads(witness, 12 + 8);
  got.clear();
  drain_all(rx, got);
  CHECK(got == expected);
  CHECK(rx.counters().packets_received == 8 + 3 + 2);
  CHECK(rx.counters().filtered_dropped == 5 + 3);

  // A filter that fits again is whole in the kernel.
  m.mark_sources->erase(m.mark_sources->begin(), m.mark_sources->begin() + 900);
  CHECK(rx.set_filter(m));
  CHECK(rx.kernel_filtered());
}

// ---------------------------------------------------------------- keyed groups

TEST_CASE("filter: a keyed authenticated group is filtered in the kernel, unkeyed and wrong-key datagrams still "
          "reach user space, and every change of keys re-derives the program",
          "[integration][filter][keyed]") {
  auto cfg = unique_config();
  const auto k1 = key_of(1), k2 = key_of(2), k3 = key_of(3);
  cfg.keys = group_keys({k1});
  auto rx = Group::open(cfg);
  auto witness = Group::open(cfg);
  auto tx = Group::open(cfg);
  auto plain_cfg = cfg;
  plain_cfg.keys = nullptr;
  auto plain = Group::open(plain_cfg);
  auto wrong_cfg = cfg;
  wrong_cfg.keys = group_keys({k2});
  auto wrong = Group::open(wrong_cfg);
  REQUIRE(rx.set_filter(only({"TAKEN"})));
  CHECK(rx.kernel_filtered());

  for (int i = 0; i < 20; ++i) tx.publish("REFUSED", make_payload(i, 50));
  for (int i = 0; i < 3; ++i) plain.publish("REFUSED", make_payload(i, 50));
  for (int i = 0; i < 2; ++i) wrong.publish("REFUSED", make_payload(i, 50));
  tx.publish("TAKEN", make_payload(1, 50));
  std::uint64_t sent = 26;
  witness_reads(witness, sent);
  std::vector<Heard> got;
  drain_all(rx, got);
  REQUIRE(got.size() == 1);
  CHECK(got[0].channel == "TAKEN");
  auto c = rx.counters();
  CHECK(c.packets_received == 1 + 3 + 2);  // the group's own envelopes of REFUSED: dropped unread
  CHECK(c.unauthenticated_dropped == 3 + 2);
  CHECK(c.filtered_dropped == 0);
  const auto sources = rx.refusals().sources();
  REQUIRE(sources.size() == 1);
  CHECK(sources[0].count == 5);

  auto round = [&](const char* step, std::uint64_t reach) {
    INFO(step);
    const auto before = rx.counters();
    for (int i = 0; i < 10; ++i) tx.publish("REFUSED", make_payload(i, 50));
    tx.publish("TAKEN", make_payload(2, 50));
    sent += 11;
    witness_reads(witness, sent);
    got.clear();
    drain_all(rx, got);
    REQUIRE(got.size() == 1);
    CHECK(got[0].channel == "TAKEN");
    const auto& after = rx.counters();
    CHECK(after.packets_received - before.packets_received == reach);
    CHECK(after.filtered_dropped - before.filtered_dropped == reach - 1);
    CHECK(after.unauthenticated_dropped == before.unauthenticated_dropped);
  };
  // Rotation: the program learns k3's id (without it, k3's envelopes pass the kernel).
  for (Group* g : {&rx, &witness}) g->set_keys(group_keys({k3, k1}));
  tx.set_keys(group_keys({k3}));
  round("rotated to k3", 1);
  CHECK(rx.kernel_filtered());
  // Unkeyed: the LCM datagram is at offset 0 again.
  for (Group* g : {&rx, &witness, &tx}) g->set_keys(nullptr);
  round("unkeyed", 1);
  // Keyed again, encrypted: the kernel cannot see the channel.
  for (Group* g : {&rx, &witness, &tx}) g->set_keys(group_keys({k1}, true));
  CHECK_FALSE(rx.kernel_filtered());
  round("encrypted", 11);
  // Authenticated again.
  for (Group* g : {&rx, &witness, &tx}) g->set_keys(group_keys({k1}));
  CHECK(rx.kernel_filtered());
  round("authenticated", 1);
}

TEST_CASE("filter: a keyed encrypted group is filtered in user space", "[integration][filter][keyed]") {
  auto cfg = unique_config();
  cfg.keys = group_keys({key_of(4)}, true);
  auto rx = Group::open(cfg);
  auto witness = Group::open(cfg);
  auto tx = Group::open(cfg);
  CHECK_FALSE(rx.set_filter(only({"TAKEN"})));
  CHECK_FALSE(rx.kernel_filtered());
  for (int i = 0; i < 10; ++i) tx.publish("REFUSED", make_payload(i, 50));
  const auto big = make_payload(3, 200000);
  tx.publish("REFUSED", big);  // fragments
  const auto s = tx.publish("TAKEN", make_payload(1, 50));
  const auto frags = 10 + 4 + 1;
  witness_reads(witness, frags);
  std::vector<Heard> got;
  drain_all(rx, got);
  CHECK(got == std::vector<Heard>{{tx.local_source(), s, "TAKEN", 50}});
  CHECK(rx.counters().packets_received == frags);
  CHECK(rx.counters().filtered_dropped == 10 + 4);
  CHECK(rx.counters().unauthenticated_dropped == 0);
  // Default filter: the kernel holds it (nothing to hold).
  CHECK(rx.set_filter(ReceiveFilter{}));
}

// ---------------------------------------------------------------- Reassembler, refused messages

TEST_CASE("Reassembler: a refused message's fragments are used up, never counted incomplete", "[unit][filter]") {
  using detail::Reassembler;
  const Source src{0x0100007f, 0x1111};
  auto parsed = [](const std::vector<std::byte>& d) {
    auto p = parse_datagram(d);
    REQUIRE(p);
    return *p;
  };
  Reassembler r({1u << 28, 16, std::chrono::milliseconds(100)});
  const auto t0 = Reassembler::Clock::now();
  const auto m = lc03_message(5, "CAM", make_payload(1, 300000));
  REQUIRE(m.size() == 5);
  // Two fragments overtook fragment 0: dropped with it.
  CHECK_FALSE(r.add(parsed(m[3]), src, t0));
  CHECK_FALSE(r.add(parsed(m[1]), src, t0));
  CHECK(r.refuse(parsed(m[0]), src, t0) == 2);
  CHECK(r.partial_count() == 0);
  CHECK(r.reserved_bytes() == 0);
  CHECK(r.refused_count() == 1);
  CHECK_FALSE(r.refused(parsed(lc03_message(6, "CAM", make_payload(1, 300000))[1]), src, t0));  // another one
  CHECK(r.refused(parsed(m[2]), src, t0));
  CHECK(r.refused(parsed(m[4]), src, t0));
  CHECK(r.refused_count() == 0);  // all came: forgotten
  CHECK_FALSE(r.refused(parsed(m[2]), src, t0));
  CHECK(r.stats().incomplete_dropped == 0);

  // One whose other fragments never come is forgotten after the timeout, silently.
  const auto n = lc03_message(7, "CAM", make_payload(2, 300000));
  CHECK(r.refuse(parsed(n[0]), src, t0) == 0);
  CHECK(r.refused(parsed(n[1]), src, t0));
  r.expire(t0 + std::chrono::milliseconds(50));
  CHECK(r.refused_count() == 1);
  r.expire(t0 + std::chrono::milliseconds(200));
  CHECK(r.refused_count() == 0);
  CHECK(r.stats().incomplete_dropped == 0);

  // Bounded.
  for (std::uint32_t s = 0; s < Reassembler::kMaxRefused + 10; ++s)
    r.refuse(parsed(lc03_message(1000 + s, "CAM", make_payload(2, 100000))[0]), src, t0);
  CHECK(r.refused_count() == Reassembler::kMaxRefused);
}

// ---------------------------------------------------------------- publish_counted

namespace filter_test {

// The marker of these tests: u8 final, u32 count, then per channel u8 length, name, u64 messages.
std::vector<std::byte> encode_counts(std::span<const ChannelCount> counts, bool final = false) {
  std::vector<std::byte> out;
  out.push_back(std::byte{final ? std::uint8_t{1} : std::uint8_t{0}});
  put32(out, static_cast<std::uint32_t>(counts.size()));
  for (const auto& c : counts) {
    out.push_back(static_cast<std::byte>(c.channel.size()));
    put_str(out, c.channel, false);
    put32(out, static_cast<std::uint32_t>(c.messages >> 32));
    put32(out, static_cast<std::uint32_t>(c.messages));
  }
  return out;
}
std::map<std::string, std::uint64_t> decode_counts(std::span<const std::byte> d, bool* final) {
  std::map<std::string, std::uint64_t> out;
  std::size_t at = 1;
  REQUIRE(!d.empty());
  *final = d[0] == std::byte{1};
  auto u8 = [&] {
    REQUIRE(at < d.size());
    return std::to_integer<std::uint8_t>(d[at++]);
  };
  auto u32 = [&] {
    std::uint32_t v = 0;
    for (int i = 0; i < 4; ++i) v = (v << 8) | u8();
    return v;
  };
  const std::uint32_t n = u32();
  for (std::uint32_t i = 0; i < n; ++i) {
    const std::size_t len = u8();
    REQUIRE(at + len <= d.size());
    std::string name(reinterpret_cast<const char*>(d.data() + at), len);
    at += len;
    const std::uint64_t hi = u32();
    out[name] = (hi << 32) | u32();
  }
  REQUIRE(at == d.size());
  return out;
}

// Makes sendmmsg(..., vlen == `vlen`, ...) fail with EPERM on the calling thread only (seccomp;
// the thread keeps it until it ends).
void fail_sendmmsg_of(unsigned vlen) {
  constexpr std::uint32_t arg2 = offsetof(seccomp_data, args) + 2 * sizeof(std::uint64_t) +
                                 (std::endian::native == std::endian::little ? 0 : 4);
  sock_filter code[] = {
      BPF_STMT(BPF_LD | BPF_W | BPF_ABS, offsetof(seccomp_data, nr)),
      BPF_JUMP(BPF_JMP | BPF_JEQ | BPF_K, __NR_sendmmsg, 0, 3),
      BPF_STMT(BPF_LD | BPF_W | BPF_ABS, arg2),
      BPF_JUMP(BPF_JMP | BPF_JEQ | BPF_K, vlen, 0, 1),
      BPF_STMT(BPF_RET | BPF_K, SECCOMP_RET_ERRNO | EPERM),
      BPF_STMT(BPF_RET | BPF_K, SECCOMP_RET_ALLOW),
  };
  sock_fprog prog{static_cast<unsigned short>(std::size(code)), code};
  REQUIRE(::prctl(PR_SET_NO_NEW_PRIVS, 1, 0, 0, 0) == 0);
  REQUIRE(::prctl(PR_SET_SECCOMP, SECCOMP_MODE_FILTER, &prog) == 0);
}

}  // namespace filter_test

TEST_CASE("publish_counted: counts are exact under 4 concurrent publishers, a fragmented message counts once",
          "[integration][filter][counted]") {
  auto cfg = unique_config();
  auto rx = Group::open(cfg);
  cfg.receive_own = false;
  auto tx = Group::open(cfg);
  REQUIRE(rx.set_filter(only({"CH0", "CH1", "CH2", "CH3", "SHARED", "BIG", "MARK"})));
  constexpr int kThreads = 4, kEach = 1500, kMarkers = 300;
  std::atomic<bool> go{false};
  std::atomic<int> running{kThreads};
  std::uint64_t sent[kThreads][3] = {};  // own channel, SHARED, BIG
  Clock::time_point before_last[kThreads];
  std::vector<std::thread> threads;
  for (int t = 0; t < kThreads; ++t)
    threads.emplace_back([&, t] {
      while (!go.load()) std::this_thread::yield();
      const std::string own = "CH" + std::to_string(t);
      for (int i = 0; i < kEach; ++i) {
        if (i == kEach - 1) before_last[t] = Clock::now();
        tx.publish(own, make_payload(static_cast<std::uint32_t>(i), 40));
        ++sent[t][0];
        if (i % 3 == 0) tx.publish("SHARED", make_payload(static_cast<std::uint32_t>(i), 20)), ++sent[t][1];
        if (t == 3 && i % 100 == 0) tx.publish("BIG", make_payload(static_cast<std::uint32_t>(i), 150000)), ++sent[t][2];
        tx.publish("UNREAD", make_payload(static_cast<std::uint32_t>(i), 20));  // counted, filtered away
      }
      running.fetch_sub(1);
    });
  // Markers while they publish, then one at the end.
  std::atomic<int> markers{0};
  std::thread marker([&] {
    while (!go.load()) std::this_thread::yield();
    while (running.load() > 0 && markers.load() < kMarkers) {
      tx.publish_counted("MARK", [](std::span<const ChannelCount> c) { return encode_counts(c); });
      markers.fetch_add(1);
    }
  });

  // Receiver: at every marker, each channel's count must equal what arrived before it.
  std::map<std::string, std::uint64_t> received, last_marker;
  std::size_t checked = 0, mismatches = 0;
  bool final_seen = false;
  std::vector<std::string> report;
  auto on_message = [&](const Message& m) {
    if (m.channel != "MARK") {
      ++received[std::string(m.channel)];
      return;
    }
    bool final = false;
    const auto counts = decode_counts(m.data, &final);
    ++checked;
    for (const auto& [name, n] : received)
      if (!counts.contains(name) || counts.at(name) != n) {
        ++mismatches;
        if (report.size() < 10)
          report.push_back(name + ": marker " + (counts.contains(name) ? std::to_string(counts.at(name)) : "none") +
                           ", received " + std::to_string(n));
      }
    for (const auto& [name, n] : counts)
      if (name != "UNREAD" && !received.contains(name) && n != 0) ++mismatches;
    CHECK_FALSE(counts.contains("MARK"));
    last_marker = counts;
    final_seen = final_seen || final;
  };
  go.store(true);
  const auto deadline = Clock::now() + 30s;
  while (running.load() > 0 && Clock::now() < deadline) rx.poll(50ms, on_message);
  for (auto& th : threads) th.join();
  marker.join();
  tx.publish_counted("MARK", [](std::span<const ChannelCount> c) { return encode_counts(c, true); });
  REQUIRE(poll_until(rx, on_message, [&] { return final_seen; }, 10000ms));
  INFO("first mismatches: " << [&] {
    std::string s;
    for (const auto& r : report) s += r + "; ";
    return s;
  }());
  // No loss on lo (the kernel's drops are the UNREAD datagrams its filter refused): every count
  // must match.
  REQUIRE(rx.counters().kernel_dropped == kThreads * kEach);
  CHECK(rx.counters().incomplete_dropped == 0);
  CHECK(checked >= 2);
  CHECK(mismatches == 0);
  // The final counts are what each thread sent.
  std::uint64_t shared = 0;
  for (int t = 0; t < kThreads; ++t) {
    CHECK(last_marker.at("CH" + std::to_string(t)) == sent[t][0]);
    shared += sent[t][1];
  }
  CHECK(last_marker.at("SHARED") == shared);
  CHECK(last_marker.at("BIG") == sent[3][2]);  // messages, not fragments
  CHECK(last_marker.at("UNREAD") == kThreads * kEach);
  CHECK(received.at("BIG") == sent[3][2]);
  // last_sent: the time of each channel's last message.
  bool times_ok = true;
  tx.publish_counted("MARK", [&](std::span<const ChannelCount> counts) {
    const auto now = Clock::now();
    for (const auto& c : counts) {
      times_ok = times_ok && c.last_sent <= now;
      for (int t = 0; t < kThreads; ++t)
        if (c.channel == "CH" + std::to_string(t)) times_ok = times_ok && c.last_sent >= before_last[t];
    }
    return std::vector<std::byte>{};
  });
  CHECK(times_ok);
  CHECK(tx.counters().uncounted_sent == 0);
}

TEST_CASE("publish_counted: a publish that fails part-way is not counted, a build that throws sends nothing",
          "[integration][filter][counted]") {
  auto cfg = unique_config();
  cfg.reassembly_timeout = std::chrono::milliseconds(50);
  auto rx = Group::open(cfg);
  cfg.receive_own = false;
  auto tx = Group::open(cfg);
  auto counts = [&] {
    std::map<std::string, std::uint64_t> out;
    tx.publish_counted("MARK", [&](std::span<const ChannelCount> c) {
      for (const auto& x : c) out[std::string(x.channel)] = x.messages;
      return std::vector<std::byte>{};
    });
    return out;
  };
  tx.publish("BIG", make_payload(1, 1000));
  // 34 fragments: sendmmsg of 32, then of 2, which fails.
  const auto big = make_payload(2, 33 * kFragmentMaxPayload + 1000);
  REQUIRE(datagram_count(3, big.size()) == 34);
  const auto seq_before = tx.next_sequence();
  const auto packets_before = tx.counters().packets_sent;
  int err = 0;
  std::thread failing([&] {
    fail_sendmmsg_of(2);
    try {
      tx.publish("BIG", big);
    } catch (const Error& e) {
      err = e.sys_errno();
    }
  });
  failing.join();
  CHECK(err == EPERM);
  CHECK(tx.counters().packets_sent - packets_before == 32);  // part of it went out
  CHECK(tx.next_sequence() == seq_before + 1);              // its sequence number is used up
  CHECK(tx.counters().messages_sent == 1);
  CHECK(counts() == std::map<std::string, std::uint64_t>{{"BIG", 1}});
  // The receiver agrees: one BIG message, the partial one never completes.
  std::vector<Heard> got;
  REQUIRE(poll_until(rx, into(got), [&] { return rx.counters().incomplete_dropped == 1 && got.size() >= 2; }));
  CHECK(std::count_if(got.begin(), got.end(), [](const Heard& h) { return h.channel == "BIG"; }) == 1);

  // A build that throws: nothing sent, no sequence number used.
  const auto seq = tx.next_sequence();
  const auto packets = tx.counters().packets_sent;
  CHECK_THROWS_AS(tx.publish_counted("MARK", [](std::span<const ChannelCount>) -> std::vector<std::byte> {
    throw std::runtime_error("no marker");
  }), std::runtime_error);
  CHECK(tx.next_sequence() == seq);
  CHECK(tx.counters().packets_sent == packets);
  // A bad channel is refused before build runs.
  bool built = false;
  CHECK_THROWS_AS(tx.publish_counted(std::string(64, 'm'), [&](std::span<const ChannelCount>) {
    built = true;
    return std::vector<std::byte>{};
  }), Error);
  CHECK_FALSE(built);
  // The markers sent by counts() count on MARK, the ones refused do not.
  tx.publish("OTHER", {});
  const auto c = [&] {
    std::map<std::string, std::uint64_t> out;
    tx.publish_counted("OTHER", [&](std::span<const ChannelCount> s) {
      for (const auto& x : s) out[std::string(x.channel)] = x.messages;
      return std::vector<std::byte>{};
    });
    return out;
  }();
  CHECK(c == std::map<std::string, std::uint64_t>{{"BIG", 1}, {"MARK", 1}});
}

TEST_CASE("publish_counted: counts are kept for the first 4096 channels, the rest counted as uncounted",
          "[integration][filter][counted]") {
  auto cfg = unique_config();
  cfg.receive_own = false;
  cfg.multicast_loop = false;
  auto tx = Group::open(cfg);
  for (std::size_t i = 0; i < Group::kMaxCountedChannels + 3; ++i) tx.publish("C" + std::to_string(i), {});
  tx.publish("C0", {});
  tx.publish("C" + std::to_string(Group::kMaxCountedChannels + 1), {});
  std::size_t n = 0;
  std::uint64_t c0 = 0;
  tx.publish_counted("C1", [&](std::span<const ChannelCount> s) {
    n = s.size();
    for (const auto& x : s)
      if (x.channel == "C0") c0 = x.messages;
    return std::vector<std::byte>{};
  });
  CHECK(n == Group::kMaxCountedChannels - 1);  // C1 itself left out
  CHECK(c0 == 2);
  CHECK(tx.counters().uncounted_sent == 4);
  CHECK(tx.counters().messages_sent == Group::kMaxCountedChannels + 6);
}
